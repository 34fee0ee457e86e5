//! The secondary MCUs of a printer: their steppers' commands go to the
//! real boards (or peers) instead of the main MCU's engine, each in that
//! MCU's clock, within its move queue, and their faults stop the printer.
//! A homing move whose steppers or endstop are on secondaries runs across
//! the MCUs with trsync ([`super::homing::Homing`], the main MCU one of
//! them): each secondary gets one more trsync for it (`config_trsync`
//! after klippy's config), its steppers are tied to it, and an endstop on
//! it is armed there.
//!
//! Fans, output pins and stepper enable pins on a secondary are driven
//! there as klippy drives them ([`RemoteOutput`]): the MCU role's io runs
//! the fans and pins as for the main MCU, and each update it queues for an
//! output on a secondary goes out as `queue_digital_out` (a hardware PWM
//! channel: `queue_pwm_out`, scaled by the MCU's PWM_MAX) on that MCU's
//! clock (its level inverted on the host for a `!` pin, as klippy does);
//! an enable pin goes active with its stepper's first step and inactive
//! at M84/M18. A shutdown is the MCU's own: `emergency_stop` puts every
//! output at its configured shutdown value.
//!
//! A heater on a secondary (its sensor and output there) is run by the MCU
//! role's heater control as the main MCU's are: its sensor is sampled
//! there ([`super::thermal`]: `query_analog_in` after the config phase),
//! its reports come back as readings ([`Secondaries::take_reading`]), and
//! the PWM updates the control queues go out as the fans' do.

use super::homing::{Homing, TrsyncState};
use super::remote_output::{RemoteDrive, RemoteEnable, RemoteOutput, level, pwm_max};
use super::sent_steps::{SentCommand, SentSteps, each_step};
use super::thermal::{self, Reading, RemoteInput, SpiBytes, SpiResult};
use super::{
    ConnectError, FetchRoom, Heard, Links, McuError, Secondary, SecondaryLink, Start, Text,
    clock_freq, command, text,
};
use crate::heaters::{INPUTS, InputQuery, LinearConversion, McuSetup, OUTPUTS, full_scale};
use crate::mcu_config::{ConfigTarget, Oids, pin_ref, reader_oid, write_config};
use crate::setup::PrinterSetup;
use crate::step_pulse::pulse_ticks;
use core::cell::Cell;
use core::mem::MaybeUninit;
use core::ptr::addr_of_mut;
use heapless::binary_heap::{BinaryHeap, Min};
use onechip_planner::machine::{MAX_STEPPERS, Machine};
use onechip_planner::mcu_section::{MAX_SECONDARIES, RestartMethod};
use onechip_protocol::dictionary::Dictionary;
use onechip_protocol::transport::LinkStats;
use onechip_sched::engine::Full;
use onechip_sched::outputs::OutputKind;
use onechip_sched::shutdown::Shutdown;
use onechip_sched::step_command::StepCommand;
use onechip_secondary_mcu::connection::OUTBOX;
use onechip_secondary_mcu::step_commands::StepCommandEncoder;
use onechip_secondary_mcu::trsync::reason;

/// Seconds between two re-fits of the steppers' clock lines (klippy
/// re-fits from its once-a-second stats).
const CALIBRATE_PERIOD: f64 = 1.0;
/// How long a secondary may take to connect, s.
const CONNECT_TIMEOUT: f64 = 15.0;
/// How far ahead of now a software PWM output's start value is queued
/// after the config phase, s (klippy's 0.2 s for its init command).
const START_LEAD: f64 = 0.200;
/// How long before its stepper's first step an enable pin goes active, s.
const ENABLE_LEAD: f64 = 0.001;
/// How far ahead of now an output update on a secondary must be when it
/// is queued, s: the MCU role's io may queue one for now (klippy's are
/// at least PIN_MIN_TIME ahead, or at the end of the queued moves), but
/// it must reach the MCU before its clock.
const OUTPUT_LEAD: f64 = 0.050;
/// Step commands of one MCU tracked until they have run: at most this
/// many wait in its move queue (the Linux MCU's queue is far longer, an
/// AVR's shorter), `min(move_count, MOVE_SLOTS)` less its outputs' slots.
pub const MOVE_SLOTS: usize = 512;
/// Responses kept from one service round, for a `stepper_position` asked.
const RESPONSES: usize = 8;

/// The move queue slots an MCU with objects `oids` keeps for its outputs:
/// one for each enable pin (steppers may share one), heater, fan and pin
/// output.
fn reserved_slots(oids: &Oids) -> usize {
    let enables = || oids.enables.iter().flatten();
    let distinct = (enables().enumerate())
        .filter(|&(i, oid)| enables().take(i).all(|other| other != oid))
        .count();
    let heaters = oids.heaters.iter().filter(|h| h.1.is_some()).count();
    distinct + heaters + oids.outputs.iter().flatten().count()
}

/// One connected secondary and its move queue.
struct Attached<L> {
    mcu: Secondary<L>,
    /// End clocks of the `queue_step`s the MCU may still hold, soonest
    /// first: at most its room.
    slots: BinaryHeap<u64, Min, MOVE_SLOTS>,
    /// The trsync its steppers and endstop use while homing.
    trsync: u8,
    /// How it is reset (its `restart_method`).
    restart: RestartMethod,
    /// Move queue slots kept for its outputs, one each (klippy's
    /// `request_move_queue_slot`).
    reserved: usize,
}

impl<L> Attached<L> {
    /// Step commands it may hold at once.
    fn room(&self) -> usize {
        usize::from(self.mcu.move_count)
            .saturating_sub(self.reserved)
            .min(MOVE_SLOTS)
    }
}

/// A rail's endstop on a secondary.
#[derive(Debug, Clone, Copy)]
struct RemoteEndstop {
    /// Its MCU (index into `attached`).
    mcu: usize,
    /// Its oid.
    oid: u8,
    /// Its pin is inverted (`!`): it reads 0 when pressed.
    inverted: bool,
}

/// A homing across the main MCU and some secondaries.
struct ActiveHoming {
    homing: Homing,
    /// The secondaries taking part (indices into `attached`, ascending).
    members: heapless::Vec<usize, MAX_SECONDARIES>,
    /// The endstop, if on a secondary: its MCU (index into `attached`)
    /// and oid.
    endstop: Option<(usize, u8)>,
    /// The trigger was taken by the session.
    taken: bool,
}

/// A stepper on a secondary.
struct Route {
    /// Its MCU (index into `attached`).
    mcu: usize,
    /// Its oid there.
    oid: u8,
    encoder: StepCommandEncoder<'static>,
}

/// Every secondary of the printer, at most `N` (at most
/// [`MAX_SECONDARIES`]). Large (tens of KB: each MCU's record of its move
/// queue, each stepper's encoder and steps sent), so it is made once and
/// connected in place: a firmware keeps it in a static.
pub struct Secondaries<L, const N: usize> {
    /// Each `[mcu NAME]`'s name, in printer.cfg's order, as
    /// [`Self::connect`] kept them.
    names: heapless::Vec<&'static str, N>,
    /// The secondaries connected, in the order of `names` (all of them
    /// unless the last connect or restart failed).
    attached: heapless::Vec<Attached<L>, N>,
    /// For each stepper on a secondary: where, and its encoder.
    routes: [Option<Route>; MAX_STEPPERS],
    /// What each stepper on a secondary was sent.
    sent: [SentSteps; MAX_STEPPERS],
    /// Each stepper's direction pin is inverted (`!`).
    dir_inverted: [bool; MAX_STEPPERS],
    /// Each rail's endstop, if on a secondary.
    endstops: [Option<RemoteEndstop>; MAX_STEPPERS],
    /// The homing running across MCUs, if one is.
    homing: Option<ActiveHoming>,
    /// Homings ended by a communication timeout.
    homing_timeouts: usize,
    /// Main clock, Hz (host time is the main clock in seconds).
    freq: f64,
    next_calibrate: f64,
    failure: Option<Shutdown>,
    /// `emergency_stop` went to every secondary.
    stopped: bool,
    /// The `stepper_position` answers the last [`Self::service`] heard:
    /// the MCU's index, the oid and the position.
    positions: heapless::Vec<(usize, u8, i64), RESPONSES>,
    /// Each stepper's step pulse, s (for configuring them again).
    pulses: [f64; MAX_STEPPERS],
    /// The main MCU's internal temperature sensor calibration (for the
    /// io setups computed here).
    mcu_sensor: LinearConversion,
    /// The MCU role's io outputs (by index) that are on a secondary, and
    /// each one's full scale in the io (0: steady on/off).
    outputs: [Option<(RemoteOutput, u32)>; OUTPUTS],
    /// The enable pins on secondaries.
    enables: heapless::Vec<RemoteEnable, MAX_STEPPERS>,
    /// Each stepper's enable pin (index into `enables`), if on a
    /// secondary, and whether the stepper is enabled.
    stepper_enables: [Option<(usize, bool)>; MAX_STEPPERS],
    /// The heaters' and temperature sensors' ADC inputs on secondaries.
    inputs: heapless::Vec<RemoteInput, INPUTS>,
    /// Their readings heard and not taken yet (the oldest dropped if the
    /// MCU role does not take them).
    readings: heapless::Deque<Reading, 32>,
    /// Room for the dictionary fetch while one connects.
    fetch_room: FetchRoom,
}

impl<L: SecondaryLink, const N: usize> Secondaries<L, N> {
    /// No secondaries yet, on a main clock of `freq` Hz whose internal
    /// temperature sensor is calibrated as `mcu_sensor` ([`Self::init_in`]
    /// through the stack).
    pub fn new(freq: f64, mcu_sensor: LinearConversion) -> Self {
        let mut slot = MaybeUninit::uninit();
        Self::init_in(&mut slot, freq, mcu_sensor);
        // SAFETY: `init_in` initialised it.
        unsafe { slot.assume_init() }
    }

    /// [`Self::new`] built in place in `slot` (a static of the firmware):
    /// it is too large to pass through a microcontroller's stack.
    pub fn init_in(
        slot: &mut MaybeUninit<Self>,
        freq: f64,
        mcu_sensor: LinearConversion,
    ) -> &mut Self {
        const {
            assert!(
                N <= MAX_SECONDARIES,
                "trsync homing spans at most MAX_SECONDARIES"
            )
        };
        let p = slot.as_mut_ptr();
        // SAFETY: `p` is valid for writes; every field is written exactly
        // once (the arrays element by element, not through the stack)
        // before the slot is taken as initialised.
        unsafe {
            addr_of_mut!((*p).names).write(heapless::Vec::new());
            addr_of_mut!((*p).attached).write(heapless::Vec::new());
            let routes = &mut *addr_of_mut!((*p).routes)
                .cast::<[MaybeUninit<Option<Route>>; MAX_STEPPERS]>();
            routes.iter_mut().for_each(|r| _ = r.write(None));
            let sent =
                &mut *addr_of_mut!((*p).sent).cast::<[MaybeUninit<SentSteps>; MAX_STEPPERS]>();
            sent.iter_mut()
                .for_each(|s| _ = s.write(SentSteps::default()));
            addr_of_mut!((*p).dir_inverted).write([false; MAX_STEPPERS]);
            addr_of_mut!((*p).endstops).write([None; MAX_STEPPERS]);
            addr_of_mut!((*p).homing).write(None);
            addr_of_mut!((*p).homing_timeouts).write(0);
            addr_of_mut!((*p).freq).write(freq);
            addr_of_mut!((*p).next_calibrate).write(0.0);
            addr_of_mut!((*p).failure).write(None);
            addr_of_mut!((*p).stopped).write(false);
            addr_of_mut!((*p).positions).write(heapless::Vec::new());
            addr_of_mut!((*p).pulses).write([0.0; MAX_STEPPERS]);
            addr_of_mut!((*p).mcu_sensor).write(mcu_sensor);
            addr_of_mut!((*p).outputs).write([const { None }; OUTPUTS]);
            addr_of_mut!((*p).enables).write(heapless::Vec::new());
            addr_of_mut!((*p).stepper_enables).write([None; MAX_STEPPERS]);
            addr_of_mut!((*p).inputs).write(heapless::Vec::new());
            addr_of_mut!((*p).readings).write(heapless::Deque::new());
            // `fetch_room` is MaybeUninit: nothing to write.
            slot.assume_init_mut()
        }
    }

    /// Connects every `[mcu NAME]` of `setup`'s printer over `links` and
    /// configures its steppers (with their step pulses); `keep(name)`
    /// gives each MCU's name as long as the printer runs (the config's
    /// own if it lives that long). `now` is host time (s) on the main
    /// clock. One holding another config is reset and configured anew, as
    /// klippy's automated firmware restart. Made for one connect: a
    /// printer connects again with [`Self::restart`].
    pub fn connect<'m, O: Links<Link = L>>(
        &mut self,
        setup: &PrinterSetup<'m>,
        keep: &dyn Fn(&'m str) -> &'static str,
        links: &mut O,
        now: &dyn Fn() -> f64,
    ) -> Result<(), McuError> {
        let machine = setup.machine();
        for (p, stepper) in self.pulses.iter_mut().zip(setup.steppers()) {
            *p = stepper.step_pulse;
        }
        self.names.clear();
        for secondary in &machine.secondaries {
            if self.names.push(keep(secondary.name)).is_err() {
                let error = ConnectError::Unsupported(text(format_args!(
                    "more than {N} secondary MCUs on this board"
                )));
                return Err(McuError::new(
                    keep(secondary.name),
                    secondary.serial_at,
                    error,
                ));
            }
        }
        self.connect_all(machine, &mut |_| Start::Fresh, links, now)
    }

    /// FIRMWARE_RESTART: every secondary connected is reset as its
    /// `restart_method` says, then each is connected over `links` and
    /// configured again (one reset and still configured is `Failed
    /// automated reset of MCU 'NAME'`; one that was not connected is
    /// connected as at start); what the steppers were sent counts from
    /// there, as their MCU positions do. On an error the printer has no
    /// homing and only the secondaries connected before the error (the
    /// failing one too if its link was up): the caller shuts the printer
    /// down with it ([`Self::fail`]).
    pub fn restart<O: Links<Link = L>>(
        &mut self,
        machine: &Machine<'_>,
        links: &mut O,
        now: &dyn Fn() -> f64,
    ) -> Result<(), ConnectError> {
        self.homing = None;
        let mut reset: heapless::Vec<&'static str, N> = heapless::Vec::new();
        for a in &mut self.attached {
            a.mcu.reset(a.restart, now)?;
            let _ = reset.push(a.mcu.name);
        }
        let mut start = |name| {
            if reset.contains(&name) {
                Start::Restarted
            } else {
                Start::Fresh
            }
        };
        let connected = self.connect_all(machine, &mut start, links, now);
        connected.map_err(|e| e.error)
    }

    /// The printer stays shut down for `reason` (a secondary that could
    /// not be brought back), whatever stopped it before: no homing goes
    /// on.
    pub fn fail(&mut self, reason: Shutdown) {
        self.failure = Some(reason);
        self.homing = None;
    }

    /// Connects and configures each of `machine.secondaries` anew (named
    /// `self.names`), `start(name)` telling whether it was just reset,
    /// after dropping what the secondaries held before (their links
    /// first, which frees them to be opened again).
    #[allow(clippy::too_many_lines)]
    fn connect_all<O: Links<Link = L>>(
        &mut self,
        machine: &Machine<'_>,
        start: &mut dyn FnMut(&'static str) -> Start,
        links: &mut O,
        now: &dyn Fn() -> f64,
    ) -> Result<(), McuError> {
        self.attached.clear();
        self.routes.iter_mut().for_each(|r| *r = None);
        self.sent.iter_mut().for_each(|s| *s = SentSteps::default());
        for (inverted, s) in self.dir_inverted.iter_mut().zip(&machine.steppers) {
            *inverted = pin_ref(s.dir_pin).inverted;
        }
        self.endstops = [None; MAX_STEPPERS];
        self.homing = None;
        self.next_calibrate = 0.0;
        self.failure = None;
        self.stopped = false;
        self.positions.clear();
        self.outputs.iter_mut().for_each(|o| *o = None);
        self.enables.clear();
        self.stepper_enables = [None; MAX_STEPPERS];
        self.inputs.clear();
        self.readings.clear();
        let (freq, mcu_sensor, pulses) = (self.freq, self.mcu_sensor, self.pulses);
        // The io's outputs, at the main clock.
        let io = McuSetup::new(machine, freq, 0, mcu_sensor, 0);
        for (k, secondary) in machine.secondaries.iter().enumerate() {
            let name = self.names.get(k).copied().unwrap_or("?");
            let error = |error| McuError::new(name, secondary.serial_at, error);
            let unsupported = |why: Text| error(ConnectError::Unsupported(why));
            // The config depends on the MCU's clock (step pulses in its
            // ticks) and PWM_MAX, which identify tells; its object ids
            // are kept.
            let oids = Cell::new(Oids::default());
            let config = |dict: &Dictionary<'_>, out: &mut dyn FnMut(&str)| {
                let mcu_freq = clock_freq(dict);
                let spi_bus = thermal::default_spi_bus(dict);
                let target = ConfigTarget {
                    mcu: secondary.name,
                    pwm_max: pwm_max(dict).unwrap_or(0),
                    spi_bus: &spi_bus,
                };
                let setup = McuSetup::new(machine, mcu_freq, 0, mcu_sensor, 0);
                let ticks = |i: usize| pulse_ticks(pulses[i], mcu_freq);
                let o = write_config(machine, &setup, target, &ticks, &mut |_| {});
                // One more object: the trsync for homing moves.
                let mut first = true;
                write_config(machine, &setup, target, &ticks, &mut |l| {
                    if core::mem::take(&mut first) {
                        out(&command(format_args!(
                            "allocate_oids count={}",
                            u16::from(o.count) + 1
                        )));
                    } else {
                        out(l);
                    }
                });
                out(&command(format_args!("config_trsync oid={}", o.count)));
                oids.set(o);
            };
            let serial = (secondary.serial, secondary.baud);
            let how = match start(name) {
                Start::Fresh => (Start::Fresh, Some(secondary.restart_method)),
                start @ Start::Restarted => (start, None),
            };
            let k = self.attached.len();
            // Built in place, in `attached`'s next slot (as many slots as
            // names).
            let Some(slot) = self.attached.spare_capacity_mut().first_mut() else {
                return Err(unsupported(text(format_args!(
                    "more than {N} secondary MCUs"
                ))));
            };
            let p = slot.as_mut_ptr();
            // SAFETY: `p` is valid for writes. The MCU is written by
            // `connect_in` (which leaves it empty on an error), then each
            // other field once; only then is the slot counted in.
            unsafe {
                let mcu = &mut *addr_of_mut!((*p).mcu).cast::<MaybeUninit<Secondary<L>>>();
                let rooms = (mcu, &mut self.fetch_room);
                Secondary::connect_in(
                    rooms,
                    name,
                    serial,
                    links,
                    &config,
                    now,
                    CONNECT_TIMEOUT,
                    how,
                )
                .map_err(error)?;
                addr_of_mut!((*p).slots).write(BinaryHeap::new());
                addr_of_mut!((*p).trsync).write(oids.get().count);
                addr_of_mut!((*p).restart).write(secondary.restart_method);
                addr_of_mut!((*p).reserved).write(reserved_slots(&oids.get()));
                self.attached.set_len(k + 1);
            }
            let oids = oids.get();
            let mcu = &mut self.attached[k].mcu;
            let dict = mcu.dictionary();
            let sync = mcu.connection().clock().copied();
            let start = sync.map_or(0, |s| s.clock_at(now() + START_LEAD));
            self.add_outputs(machine, &io, &oids, k, start)
                .map_err(unsupported)?;
            self.add_inputs(machine, &oids, k, now())
                .map_err(unsupported)?;
            for (i, oid) in oids.steppers.iter().enumerate() {
                let Some(oid) = *oid else { continue };
                let encoder = StepCommandEncoder::new(dict, oid, self.dir_inverted[i])
                    .map_err(|e| error(ConnectError::Dictionary(text(format_args!("{e}")))))?;
                self.routes[i] = Some(Route {
                    mcu: k,
                    oid,
                    encoder,
                });
            }
            for (i, endstop) in oids.endstops.iter().enumerate() {
                let (Some((oid, _)), Some(pin)) = (
                    *endstop,
                    machine.steppers.get(i).and_then(|s| s.endstop_pin),
                ) else {
                    continue;
                };
                self.endstops[i] = Some(RemoteEndstop {
                    mcu: k,
                    oid,
                    inverted: pin_ref(pin).inverted,
                });
            }
        }
        Ok(())
    }

    /// Takes the fan, pin and enable outputs of MCU `k` (index into
    /// `attached`), whose object ids are `oids`; `io` is the MCU role's io
    /// at the main clock. A software PWM output gets its start value at
    /// clock `start` (that MCU's), as klippy's init command; a hardware
    /// PWM or steady output only if the MCU kept its config (klippy's
    /// restart commands: a new config holds it). An MCU without a usable PWM_MAX
    /// is refused if it has a hardware PWM output.
    fn add_outputs(
        &mut self,
        machine: &Machine<'_>,
        io: &McuSetup<'_>,
        oids: &Oids,
        k: usize,
        start: u64,
    ) -> Result<(), Text> {
        let Some(Attached { mcu, .. }) = self.attached.get(k) else {
            return Ok(());
        };
        let (name, kept) = (mcu.name, mcu.config_kept);
        let pwm_max = pwm_max(mcu.dictionary());
        let there = McuSetup::new(machine, mcu.clock_freq(), 0, self.mcu_sensor, 0);
        // The heaters' outputs first (io order), then the fans' and pins'.
        let heaters = oids.heaters.iter().take(machine.heaters.len());
        let heater_oids = heaters.map(|h| h.1);
        let output_oids = oids.outputs.iter().skip(machine.heaters.len()).copied();
        for (index, oid) in heater_oids.chain(output_oids).enumerate() {
            let (Some(oid), Some((pin, config)), Some((_, here))) =
                (oid, io.outputs.get(index), there.outputs.get(index))
            else {
                continue;
            };
            let (drive, queue_start) = match here.kind {
                OutputKind::Digital { cycle_ticks: 0 } => (RemoteDrive::Steady, false),
                OutputKind::Digital { cycle_ticks } => (RemoteDrive::SoftPwm { cycle_ticks }, true),
                OutputKind::HardPwm { .. } => {
                    let pwm_max = pwm_max.ok_or_else(|| {
                        text(format_args!(
                            "MCU '{name}' has no usable PWM_MAX for hardware_pwm pin '{pin}'"
                        ))
                    })?;
                    (RemoteDrive::HardPwm { pwm_max }, kept)
                }
            };
            let inverted = pin_ref(pin).inverted;
            let mut output = RemoteOutput::new(k, oid, drive, inverted);
            let full = full_scale(config.kind);
            if queue_start {
                output.queue(start, level(config.value, full));
            }
            if kept && drive == RemoteDrive::Steady {
                self.restart_level(k, oid, (config.value != 0) != inverted);
            }
            if let Some(slot) = self.outputs.get_mut(index) {
                *slot = Some((output, full));
            }
        }
        for (i, oid) in oids.enables.iter().enumerate() {
            let (Some(oid), Some(pin)) = (*oid, machine.steppers.get(i).and_then(|s| s.enable_pin))
            else {
                continue;
            };
            let shared =
                (self.enables.iter()).position(|e| e.output.mcu == k && e.output.oid == oid);
            let e = match shared {
                Some(e) => e,
                None => {
                    if kept {
                        // Inactive.
                        self.restart_level(k, oid, pin_ref(pin).inverted);
                    }
                    let enable = RemoteEnable {
                        output: RemoteOutput::new(
                            k,
                            oid,
                            RemoteDrive::Steady,
                            pin_ref(pin).inverted,
                        ),
                        count: 0,
                    };
                    // One per stepper at most.
                    let _ = self.enables.push(enable);
                    self.enables.len() - 1
                }
            };
            self.stepper_enables[i] = Some((e, false));
        }
        Ok(())
    }

    /// Puts steady output `oid` of MCU `k`, which kept its config, back at
    /// its start level `high` (klippy's restart command for its
    /// `MCU_digital_out`: `update_digital_out`). Not sent if the outbox
    /// is full (it has room for the start-up).
    fn restart_level(&mut self, k: usize, oid: u8, high: bool) {
        let line = command(format_args!(
            "update_digital_out oid={oid} value={}",
            u8::from(high)
        ));
        let _ = self.attached[k].mcu.connection().send_text(&line, 0);
    }

    /// Starts reading the heaters' and temperature sensors' inputs on MCU
    /// `k` (index into `attached`), whose object ids are `oids`, as
    /// klippy's init commands do at host time `now` (s): an ADC channel's
    /// sampling, an SPI chip's start-up bytes and reads. An MCU without a
    /// usable ADC_MAX is refused if it has an ADC input.
    fn add_inputs(
        &mut self,
        machine: &Machine<'_>,
        oids: &Oids,
        k: usize,
        now: f64,
    ) -> Result<(), Text> {
        // Io inputs: the heaters', then the temperature sensors'.
        let readers = (0..INPUTS).filter_map(|i| Some((i, reader_oid(oids, machine, i)?)));
        let mut readers = readers.peekable();
        let Some(Attached { mcu, .. }) = self.attached.get_mut(k) else {
            return Ok(());
        };
        if readers.peek().is_none() {
            return Ok(());
        }
        let dict = mcu.dictionary();
        let name = mcu.name;
        // Readings of an SPI chip need no ADC_MAX (nor does its range).
        let adc_max = thermal::adc_max(dict);
        let setup = McuSetup::new(
            machine,
            mcu.clock_freq(),
            adc_max.unwrap_or(1),
            self.mcu_sensor,
            0,
        );
        let Some(sync) = mcu.connection().clock().copied() else {
            return Err(text(format_args!("MCU '{name}': no clock")));
        };
        for (h, oid) in readers {
            let clock = thermal::query_slot(&sync, oid, now);
            let (commands, input) = match (setup.inputs.get(h).map(|(_, q)| q), oids.spi[h]) {
                (Some(InputQuery::Spi(query)), Some(spi)) => (
                    thermal::spi_query_commands(spi, oid, query, clock),
                    RemoteInput::spi(k, (spi, oid), h, query),
                ),
                (Some(InputQuery::Adc(query)), None) => {
                    let adc_max = adc_max
                        .ok_or_else(|| text(format_args!("MCU '{name}' has no usable ADC_MAX")))?;
                    let command = thermal::query_command(dict, oid, query, clock);
                    (
                        [command].into_iter().collect(),
                        RemoteInput::new(k, oid, h, query, adc_max),
                    )
                }
                _ => continue,
            };
            for command in &commands {
                let sent = mcu.connection().send_text(command, 0);
                sent.map_err(|_| text(format_args!("MCU '{name}': {command} not sent")))?;
            }
            // At most INPUTS inputs in the io.
            let _ = self.inputs.push(input);
        }
        Ok(())
    }

    /// The next reading of the sensor inputs (ADC channels, SPI chips) on
    /// secondaries heard and not taken yet, oldest first.
    pub fn take_reading(&mut self) -> Option<Reading> {
        self.readings.pop_front()
    }

    /// The MCU role's io queued `value` for output `index` at main clock
    /// `clock` (ticks, 64-bit) at host time `now` (s): if the output is on
    /// a secondary, the update goes there at that time on its clock, or
    /// [`OUTPUT_LEAD`] from now if that is later (and the updates after it
    /// as late, while it is still to come).
    pub fn queue_output(&mut self, index: usize, clock: u64, value: u32, now: f64) {
        let Some(Some((output, full))) = self.outputs.get_mut(index) else {
            return;
        };
        let Some(sync) = self.attached[output.mcu].mcu.connection().clock() else {
            return;
        };
        let wanted = clock as f64 / self.freq;
        let late = (now + OUTPUT_LEAD - wanted).max(0.0);
        output.delay = if output.last_at > now {
            late.max(output.delay)
        } else {
            late
        };
        output.last_at = wanted + output.delay;
        output.queue(sync.clock_at(output.last_at), level(value, *full));
    }

    /// Stepper `stepper` (on any MCU) steps from host time `at` (s) on:
    /// its enable pin, if on a secondary, goes active [`ENABLE_LEAD`]
    /// before, if it was not (klippy enables a stepper with its first
    /// move).
    pub fn enable_for(&mut self, stepper: usize, at: f64) {
        let Some(Some((e, enabled))) = self.stepper_enables.get_mut(stepper) else {
            return;
        };
        if core::mem::replace(enabled, true) {
            return;
        }
        let Some(enable) = self.enables.get_mut(*e) else {
            return;
        };
        enable.count += 1;
        let conn = self.attached[enable.output.mcu].mcu.connection();
        if let (1, Some(sync)) = (enable.count, conn.clock()) {
            enable.output.queue(sync.clock_at(at - ENABLE_LEAD), 1.0);
        }
    }

    /// M84/M18 (or the idle timeout's): every enable pin on a secondary
    /// goes inactive at host time `at` (s), as klippy's motor off.
    pub fn motors_off(&mut self, at: f64) {
        for (e, enabled) in self.stepper_enables.iter_mut().flatten() {
            *enabled = false;
            let Some(enable) = self.enables.get_mut(*e) else {
                continue;
            };
            if enable.count == 0 {
                continue;
            }
            enable.count = 0;
            let conn = self.attached[enable.output.mcu].mcu.connection();
            if let Some(sync) = conn.clock() {
                enable.output.queue(sync.clock_at(at), 0.0);
            }
        }
    }

    /// Sends each output's next update once the one before it has taken
    /// effect on its MCU (host time `now`, s), at least [`OUTPUT_LEAD`]
    /// ahead of the MCU's clock (one that waited for an update at the
    /// same clock would come too late); after a shutdown none.
    fn send_outputs(&mut self, now: f64) {
        let stopped = self.stopped || self.failure.is_some();
        let outputs = (self.outputs.iter_mut().flatten()).map(|(o, _)| o);
        for output in outputs.chain(self.enables.iter_mut().map(|e| &mut e.output)) {
            if stopped {
                output.pending.clear();
                continue;
            }
            let conn = self.attached[output.mcu].mcu.connection();
            let Some(sync) = conn.clock() else {
                continue;
            };
            let mcu_now = sync.clock_at(now);
            let soonest = sync.clock_at(now + OUTPUT_LEAD);
            while mcu_now >= output.last_clock
                && let Some(&(clock, level)) = output.pending.front()
                && conn.queued() + 1 < OUTBOX
            {
                let clock = clock.max(soonest);
                let _ = conn.send_text(&output.update(clock, level), 0);
                output.last_clock = clock;
                output.pending.pop_front();
            }
        }
    }

    /// True if stepper `stepper` is on a secondary.
    pub fn routes(&self, stepper: usize) -> bool {
        self.routes.get(stepper).is_some_and(Option::is_some)
    }

    /// What stepper `stepper` was sent (nothing if it is not on a
    /// secondary).
    pub fn sent(&self, stepper: usize) -> Option<&SentSteps> {
        self.routes(stepper)
            .then(|| self.sent.get(stepper))
            .flatten()
    }

    /// Queues a step command for a stepper on a secondary, `clock` (its
    /// first step, on that MCU's clock) 64-bit. A `queue_step` waits for
    /// a free slot of the MCU's move queue: it goes out once the oldest
    /// command it displaces has run.
    pub fn push(&mut self, stepper: usize, cmd: StepCommand, clock: u64) -> Result<(), Full> {
        let Some(Some(route)) = self.routes.get(stepper) else {
            return Ok(());
        };
        let attached = &mut self.attached[route.mcu];
        let conn = attached.mcu.connection();
        if conn.queued() + 1 >= OUTBOX {
            return Err(Full);
        }
        let mut bytes = [0u8; 32];
        let Ok(len) = route.encoder.encode(&cmd, &mut bytes) else {
            return Ok(());
        };
        let mut min_clock = 0;
        let sent = &mut self.sent[stepper];
        match cmd {
            StepCommand::Steps {
                interval,
                count,
                add,
            } => {
                if attached.slots.len() >= attached.room() {
                    min_clock = attached.slots.pop().unwrap_or(0);
                }
                let mut last = clock;
                each_step(clock, interval, count, add, |at| last = at);
                // Room for it: one was just taken if it was full.
                let _ = attached.slots.push(last);
                sent.sent(SentCommand {
                    clock,
                    interval,
                    count,
                    add,
                    forward: sent.forward,
                });
            }
            StepCommand::Dir(forward) => sent.forward = forward,
            StepCommand::ResetClock(_) => {}
        }
        let conn = attached.mcu.connection();
        let _ = conn.send(&bytes[..len], min_clock);
        let at = conn.clock().map(|sync| sync.time_at(clock));
        if let (StepCommand::Steps { .. }, Some(at)) = (cmd, at) {
            self.enable_for(stepper, at);
        }
        Ok(())
    }

    /// Runs every link's I/O at host time `now` (s): sends what is due,
    /// takes what arrived; a secondary's shutdown or silence becomes the
    /// printer's shutdown. While a homing runs across MCUs its trsync
    /// reports are relayed; `stop_main(stops)` stops the main MCU's
    /// steppers when another MCU triggered (or the reports stopped).
    pub fn service(&mut self, now: f64, stop_main: &mut dyn FnMut(u32)) {
        self.positions.clear();
        let mut states = heapless::Vec::<(usize, TrsyncState), 16>::new();
        for (k, a) in self.attached.iter_mut().enumerate() {
            let name = a.mcu.name;
            let lost = Shutdown::LostCommunication { mcu: name };
            let mut failure = None;
            let (inputs, readings, positions) =
                (&self.inputs, &mut self.readings, &mut self.positions);
            let sync = a.mcu.connection().clock().copied();
            // SPI chips' faults to clear: bus object, bytes.
            let mut clears = heapless::Vec::<(u8, SpiBytes), 2>::new();
            let io = a.mcu.service(&|| now, 0.0, &mut |h| match h {
                Heard::Shutdown(reason) => {
                    failure = Some(Shutdown::Secondary { mcu: name, reason });
                }
                Heard::Failed(_) => failure = Some(lost),
                Heard::Response(msg) => {
                    let spi = (inputs.iter().filter(|i| i.mcu == k))
                        .find_map(|i| i.spi_result(msg, sync.as_ref()?));
                    if let Some(SpiResult::Reading(reading)) = spi {
                        if readings.is_full() {
                            readings.pop_front();
                        }
                        let _ = readings.push_back(reading);
                    } else if let Some(SpiResult::Fault(clear)) = spi {
                        // At most one a round per chip; more wait for
                        // the next fault.
                        if let Some(clear) = clear {
                            let _ = clears.push(clear);
                        }
                    } else if let Some(state) = TrsyncState::from_message(msg) {
                        if states.is_full() {
                            states.remove(0);
                        }
                        let _ = states.push((k, state));
                    } else if msg.message.name() == "stepper_position"
                        && let (Some(oid), Some(pos)) = (msg.int("oid"), msg.int("pos"))
                    {
                        if positions.is_full() {
                            positions.remove(0);
                        }
                        let _ = positions.push((k, oid as u8, pos));
                    }
                }
                Heard::Analog(report) => {
                    let input = inputs.iter().find(|i| i.mcu == k && i.oid == report.oid);
                    if let (Some(input), Some(sync)) = (input, sync.as_ref()) {
                        for reading in input.readings(&report, sync) {
                            if readings.is_full() {
                                readings.pop_front();
                            }
                            let _ = readings.push_back(reading);
                        }
                    }
                }
            });
            if io.is_err() {
                failure.get_or_insert(lost);
            }
            for line in clears.iter().filter_map(|(spi, bytes)| bytes.send(*spi)) {
                // Not sent (the outbox is full): the next fault asks again.
                let _ = a.mcu.connection().send_text(&line, 0);
            }
            if self.failure.is_none() && failure.is_some() {
                self.failure = failure;
            }
        }
        self.send_outputs(now);
        if let Some(h) = &mut self.homing {
            let mut mcus = members(&mut self.attached, &h.members);
            for (k, state) in states {
                if let Some(i) = h.members.iter().position(|&m| m == k) {
                    let _ = h.homing.on_state(&mut mcus, i, state, now, stop_main);
                }
            }
            let _ = h.homing.main_news(&mut mcus, now, stop_main);
        }
    }

    /// How far stepper `stepper`, on a secondary, moved after host time
    /// `at` (s, a homing's trigger) before it stopped, in steps (+1
    /// forward): as klippy, its position asked of the MCU
    /// (`stepper_get_position`) less its position at the trigger by the
    /// steps sent. None if it is not on a secondary, or its MCU did not
    /// answer within a second (`now`: host time, s; `wait(s)` sleeps up
    /// to `s` s between two services of the links).
    pub fn moved_since(
        &mut self,
        stepper: usize,
        at: f64,
        now: &dyn Fn() -> f64,
        wait: &mut dyn FnMut(f64),
    ) -> Option<i64> {
        let Some(Some(route)) = self.routes.get(stepper) else {
            return None;
        };
        let (k, oid) = (route.mcu, route.oid);
        let a = self.attached.get_mut(k)?;
        let trigger = a.mcu.connection().clock()?.clock_at(at);
        let ask = command(format_args!("stepper_get_position oid={oid}"));
        a.mcu.connection().send_text(&ask, 0).ok()?;
        let deadline = now() + 1.0;
        while now() < deadline && self.failure.is_none() {
            self.service(now(), &mut |_| {});
            let answer = self.positions.iter().find(|p| p.0 == k && p.1 == oid);
            if let Some(&(_, _, pos)) = answer {
                // The MCU counts by its direction pin's level.
                let inverted = self.dir_inverted.get(stepper).copied().unwrap_or(false);
                let halt = if inverted { -pos } else { pos };
                let sent = self.sent.get_mut(stepper)?;
                let moved = halt - sent.position_at(trigger);
                sent.halted_at(halt);
                return Some(moved);
            }
            wait(0.001);
        }
        None
    }

    /// Starts a homing across MCUs at host time `start` (s) if stepper
    /// `endstop_of`'s endstop or any stepper in `stops` (bit `i`: stepper
    /// `i`) is on a secondary: each secondary taking part gets its trsync
    /// started and its steppers tied to it, the endstop (if on one) is
    /// armed there with `sampling` (`endstop_home`'s `(sample_ticks,
    /// sample_count, rest_ticks)` in main clock ticks). Returns the steppers
    /// in `stops` on the main MCU and whether the main MCU's own endstop
    /// is the one; None if no secondary takes part (the main MCU homes
    /// alone), or the homing could not be started.
    pub fn start_homing(
        &mut self,
        endstop_of: usize,
        sampling: (u32, u8, u32),
        stops: u32,
        start: f64,
    ) -> Option<(u32, bool)> {
        self.homing = None;
        let remote = self.endstops.get(endstop_of).copied().flatten();
        let stopping = |i: usize| i < 32 && stops & (1 << i) != 0;
        let routed = (self.routes.iter().enumerate())
            .filter(|(i, r)| *i < 32 && r.is_some())
            .fold(0u32, |m, (i, _)| m | 1 << i);
        let main_stops = stops & !routed;
        // Ascending, as `members` gives them.
        let taking_part: heapless::Vec<usize, MAX_SECONDARIES> = (0..self.attached.len())
            .filter(|&k| {
                remote.is_some_and(|e| e.mcu == k)
                    || (self.routes.iter().enumerate())
                        .any(|(i, r)| stopping(i) && r.as_ref().is_some_and(|r| r.mcu == k))
            })
            .collect();
        if taking_part.is_empty() {
            return None;
        }
        let main_takes_part = main_stops != 0 || remote.is_none();
        let mut trsyncs = heapless::Vec::<u8, MAX_SECONDARIES>::new();
        let mut steppers: [heapless::Vec<u8, MAX_STEPPERS>; MAX_SECONDARIES] =
            core::array::from_fn(|_| heapless::Vec::new());
        for (m, &k) in taking_part.iter().enumerate() {
            let _ = trsyncs.push(self.attached[k].trsync);
            let on_k = (self.routes.iter().enumerate())
                .filter(|(i, _)| *i < 32 && stops & (1 << i) != 0)
                .filter_map(|(_, r)| r.as_ref().filter(|r| r.mcu == k));
            steppers[m].extend(on_k.map(|r| r.oid));
        }
        let freq = self.freq;
        let steppers: heapless::Vec<&[u8], MAX_SECONDARIES> = steppers
            .iter()
            .take(taking_part.len())
            .map(|s| s.as_slice())
            .collect();
        let main = main_takes_part.then_some((main_stops, freq));
        let mut mcus = members(&mut self.attached, &taking_part);
        let homing = Homing::start_with_main(&mut mcus, &trsyncs, &steppers, main, start);
        drop(mcus);
        let homing = homing.ok()?;
        let mut endstop = None;
        if let Some(e) = remote {
            let a = &mut self.attached[e.mcu];
            let sync = *a.mcu.connection().clock()?;
            let ticks =
                |main_ticks: u32| (f64::from(main_ticks) / freq * sync.mcu_freq()).max(1.0) as u32;
            let (sample_ticks, sample_count, rest_ticks) = sampling;
            let home = command(format_args!(
                "endstop_home oid={} clock={} sample_ticks={} sample_count={sample_count} rest_ticks={} pin_value={} trsync_oid={} trigger_reason={}",
                e.oid,
                sync.clock_at(start) & 0xffff_ffff,
                ticks(sample_ticks),
                ticks(rest_ticks),
                u8::from(!e.inverted),
                a.trsync,
                reason::ENDSTOP_HIT
            ));
            a.mcu.connection().send_text(&home, 0).ok()?;
            endstop = Some((e.mcu, e.oid));
        }
        self.homing = Some(ActiveHoming {
            homing,
            members: taking_part,
            endstop,
            taken: false,
        });
        Some((main_stops, remote.is_none()))
    }

    /// True while a homing runs across MCUs.
    pub fn is_homing(&self) -> bool {
        self.homing.is_some()
    }

    /// The main MCU's endstop triggered at host time `at` (s): every
    /// secondary of the homing is triggered.
    pub fn main_triggered(&mut self, at: f64, now: f64) {
        let Some(h) = &mut self.homing else { return };
        let mut mcus = members(&mut self.attached, &h.members);
        let _ = h.homing.main_triggered(&mut mcus, at, now);
    }

    /// The homing's trigger (host time, s, and `trsync::reason`), once,
    /// when one came.
    pub fn take_homing_trigger(&mut self) -> Option<(f64, u8)> {
        let h = self.homing.as_mut()?;
        if h.taken {
            return None;
        }
        let trigger = h.homing.triggered()?;
        h.taken = true;
        if trigger.1 == reason::COMMS_TIMEOUT {
            self.homing_timeouts += 1;
        }
        Some(trigger)
    }

    /// Homings ended by a communication timeout so far.
    pub fn homing_timeouts(&self) -> usize {
        self.homing_timeouts
    }

    /// Ends the homing at host time `now` (s): the secondaries' trsyncs
    /// not triggered yet are, and an endstop on a secondary is disarmed.
    pub fn end_homing(&mut self, now: f64) {
        let Some(mut h) = self.homing.take() else {
            return;
        };
        let _ = h
            .homing
            .finish(&mut members(&mut self.attached, &h.members), now);
        if let Some((k, oid)) = h.endstop {
            let disarm = command(format_args!(
                "endstop_home oid={oid} clock=0 sample_ticks=0 sample_count=0 rest_ticks=0 pin_value=0 trsync_oid=0 trigger_reason=0"
            ));
            let _ = self.attached[k].mcu.connection().send_text(&disarm, 0);
        }
    }

    /// A secondary's fault, if one stopped the printer.
    pub fn failure(&self) -> Option<Shutdown> {
        self.failure
    }

    /// Each secondary's name and link counters (retransmissions, bytes).
    pub fn links(&self) -> impl Iterator<Item = (&'static str, LinkStats)> + '_ {
        self.attached
            .iter()
            .map(|a| (a.mcu.name, a.mcu.link_stats()))
    }

    /// Every secondary stops at once (`emergency_stop`), as klippy does
    /// when the printer shuts down.
    pub fn emergency_stop(&mut self, now: f64) {
        if core::mem::replace(&mut self.stopped, true) {
            return;
        }
        for a in &mut self.attached {
            let _ = a.mcu.connection().send_text("emergency_stop", 0);
        }
        self.homing = None;
        self.service(now, &mut |_| {});
    }

    /// Re-fits each secondary stepper's clock line for moves queued up to
    /// `print_time` (s), at most once a [`CALIBRATE_PERIOD`] of host time
    /// `now` (s): `set(stepper, offset, freq)`.
    pub fn calibrate(&mut self, print_time: f64, now: f64, set: &mut dyn FnMut(usize, f64, f64)) {
        if now < self.next_calibrate {
            return;
        }
        self.next_calibrate = now + CALIBRATE_PERIOD;
        let mut lines = [None; N];
        for (line, a) in lines.iter_mut().zip(&mut self.attached) {
            *line = (a.mcu.connection().clock_mut()).map(|c| c.calibrate(print_time, now));
        }
        for (stepper, route) in self.routes.iter().enumerate() {
            if let Some(route) = route
                && let Some(Some((offset, freq))) = lines.get(route.mcu)
            {
                set(stepper, *offset, *freq);
            }
        }
    }

    /// Main clock, Hz.
    pub fn freq(&self) -> f64 {
        self.freq
    }
}

/// The secondaries among `attached` whose indices are `members` (a
/// homing's), in order.
fn members<'a, L>(
    attached: &'a mut [Attached<L>],
    members: &[usize],
) -> heapless::Vec<&'a mut Secondary<L>, MAX_SECONDARIES> {
    let chosen = (attached.iter_mut().enumerate()).filter(|(k, _)| members.contains(k));
    chosen.map(|(_, a)| &mut a.mcu).collect()
}
