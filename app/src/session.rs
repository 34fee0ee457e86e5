//! The printer as both builds run it: one session takes console and file
//! lines, plans them ([`Printer`]), generates their steps ([`ProfileMotion`]) and
//! hands them to the MCU role, runs homing moves against its endstops,
//! carries out heater and fan commands and waits for heaters.
//!
//! The MCU role is behind [`Mcu`]: the board implements it with its
//! stepper and heater interrupts (a wait sleeps until an interrupt has
//! run), the host build in virtual time (a wait runs the next timer event).
//! Everything a user can observe is decided here, once, for both.

use crate::filament::{FilamentEvent, FilamentSensors};
use crate::heaters::{ThermalCommand, Wait};
use crate::idle_timeout::{self, IdleState, IdleTimeout, ToolheadState};
use crate::line::command_word;
use crate::printer::{LineError, Printer};
use crate::secondary::thermal::Reading;
use crate::text::{ErrorText, error_text};
use crate::tmc::{HomingDrivers, Tmc, TmcLink};
use core::cell::RefCell;
use core::fmt::{self, Write};
use core::mem::MaybeUninit;
use core::ptr::addr_of_mut;
use onechip_config::decimal::Fixed;
use onechip_planner::gcode;
use onechip_planner::machine::{MAX_STEPPERS, Machine};
use onechip_planner::move_sink::{ExtruderStepperMotion, MoveSink, TrapqMove};
use onechip_planner::move_sink::{HomingEnd, HomingMove};
use onechip_sched::clock::widen;
use onechip_sched::endstop::Endstop;
use onechip_sched::engine::Full;
use onechip_sched::shutdown::Shutdown;
use onechip_sched::step_command::StepCommand;
use onechip_stepgen::motion::{HomingStop, StepSink};
use onechip_stepgen::profile::ProfileMotion;

/// The board's profile: queue sizes, step clock, step accuracy and line
/// length, shared by the firmware and (by default) the host build.
pub mod profile {
    /// Lookahead capacity, in moves: more than the 0.25 s lazy-flush
    /// window of 1 ms segments, so long runs of tiny moves are released
    /// lazily (about 117 KB of RAM).
    pub const LOOKAHEAD: usize = 384;
    pub use onechip_stepgen::profile::{COMPRESS_QUEUE, MOTION_QUEUE};
    /// The step timer's clock (TIM5 on the STM32H723: APB1 timers at
    /// twice the 130 MHz bus clock), Hz.
    pub const STEP_CLOCK_HZ: f64 = 260_000_000.0;
    /// Step time error allowed to compression, s (Klipper's 25 µs).
    pub const MAX_STEP_ERROR: f64 = 0.000_025;
    /// Longest console or file line accepted, in bytes.
    pub const MAX_LINE: usize = 256;
}

/// Longest a heater may take to reach its target in M109/M190, s.
pub const MAX_HEAT_WAIT: f64 = 1800.0;
/// Time between temperature reports while waiting for a heater, s
/// (Klipper's).
pub const HEAT_REPORT_TIME: f64 = 1.0;
/// Time between `echo:busy: processing` lines while a console line waits
/// (homing, M400, a full step queue), s (Marlin's host keepalive).
pub const BUSY_TIME: f64 = 2.0;
/// Marlin's host keepalive line: the line is still running.
pub const BUSY_LINE: &str = "echo:busy: processing";

/// The MCU role as the session drives it: the stepper engine with its
/// endstop check, and the heaters' io.
pub trait Mcu {
    /// The 64-bit step clock now, ticks.
    fn now(&mut self) -> u64;
    /// Queues `cmd` for stepper `stepper`, its first step at 64-bit clock
    /// `clock`; [`Full`] while that stepper's outbox is full.
    fn push(&mut self, stepper: usize, cmd: StepCommand, clock: u64) -> Result<(), Full>;
    /// Sleeps until the MCU role has made progress (a timer event ran: a
    /// step, an endstop reading, a heater event) or the clock reached
    /// `until`; may return early. Never spins.
    fn wait(&mut self, until: u64);
    /// Arms the endstop read on stepper `stepper`'s pins, besides those
    /// armed already (up to `onechip_sched::engine::WATCHES`); its trigger
    /// stops the steppers in `stops` (bit `i`: stepper `i`) at once, and
    /// they drop the steps that come until their step clock is reset.
    fn watch_endstop(&mut self, stepper: usize, endstop: Endstop, stops: u32);
    /// Disarms every armed endstop.
    fn stop_watching(&mut self);
    /// An endstop trigger not yet taken: the stepper whose pins read that
    /// endstop (as armed) and the trigger's 32-bit clock.
    fn take_trigger(&mut self) -> Option<(usize, u32)>;
    /// Another MCU's endstop ended the homing move (its trsync trigger,
    /// relayed by the host): the steppers in `stops` (bit `i`: stepper
    /// `i`) stop at once, their queued commands dropped until their step
    /// clock is reset, as Klipper's `trsync_trigger` stops them. No fault;
    /// a watched endstop stays armed.
    fn stop_steppers(&mut self, stops: u32);
    /// True if the trigger just taken ([`Self::take_trigger`]) ended a
    /// homing across MCUs by a communication timeout (the relayed trsync
    /// reports stopped; Klipper's `REASON_COMMS_TIMEOUT`) rather than an
    /// endstop. False by default (no other MCU).
    fn homing_comms_timeout(&mut self) -> bool {
        false
    }
    /// How far stepper `stepper` moved after 64-bit clock `clock` (a
    /// homing trigger) until it stopped, in steps (+1 per positive step):
    /// klippy's halt position less its trigger position. A homing across
    /// MCUs stops a stepper when the trigger reaches its MCU. 0 by
    /// default: an MCU alone stops its steppers at its trigger.
    fn moved_since(&mut self, stepper: usize, clock: u64) -> i64 {
        let _ = (stepper, clock);
        0
    }
    /// Carries out a heater or fan command now.
    fn thermal(&mut self, command: ThermalCommand);
    /// True while `wait` is not over: a heater still reaching its target,
    /// or a temperature outside a range.
    fn thermal_waiting(&mut self, wait: Wait) -> bool;
    /// Writes the temperature report (`T:… /… B:… /…`), no line end.
    fn report_temperatures(&mut self, out: &mut dyn Write) -> fmt::Result;
    /// Why the MCU role shut down, if it did.
    fn shutdown_reason(&mut self) -> Option<Shutdown>;
    /// True while stepper `stepper`'s endstop reads pressed (M119; the
    /// probe's input is the slot after the steppers, see
    /// `Machine::probe_slot`).
    fn endstop_triggered(&mut self, stepper: usize) -> bool;
    /// The probe's control pin (a BLTouch's servo) takes `pulse_width` s
    /// pulses every 20 ms (0: off) from 64-bit clock `clock` on. Ignored
    /// by default (no servo output).
    fn probe_servo(&mut self, clock: u64, pulse_width: f64) {
        let _ = (clock, pulse_width);
    }
    /// Shuts down for `reason` (M112: [`Shutdown::EmergencyStop`]): every
    /// stepper stops and every heater goes off at once, and the MCU role
    /// stays shut down.
    fn shutdown(&mut self, reason: Shutdown);
    /// True if the extruder is hot enough to extrude
    /// ([`crate::heaters::Heaters::can_extrude`]).
    fn can_extrude(&mut self) -> bool;
    /// True while filament switch sensor `sensor` (in
    /// `Machine::accessories` order) reads filament present.
    fn filament_present(&mut self, sensor: usize) -> bool;
    /// Steppers on another MCU (a secondary board) count steps on its
    /// clock: `set(stepper, offset, freq)` gives each one's line from print
    /// time `t` (s) to its clock, `(t - offset) × freq`, re-fitted as its
    /// clock drifts, for moves queued up to `print_time` (s). None by
    /// default.
    fn stepper_clocks(&mut self, print_time: f64, set: &mut dyn FnMut(usize, f64, f64)) {
        let _ = (print_time, set);
    }
    /// A move was planned (toolhead, or extruder if `extruder`); for
    /// simulators that report the plan.
    fn planned(&mut self, m: &TrapqMove, extruder: bool) {
        let _ = (m, extruder);
    }
    /// The wires to the TMC drivers, if this MCU drives them (none by
    /// default: the drivers keep their power-on settings).
    fn tmc_link(&mut self) -> Option<&mut dyn TmcLink> {
        None
    }
    /// The next update the io queued for one of its outputs, if this MCU
    /// role hands them on to another MCU (some outputs may be there):
    /// the output (the io's order), the 64-bit clock, the value. None by
    /// default: every output is here.
    fn take_queued_output(&mut self) -> Option<(usize, u64, u32)> {
        None
    }
    /// A reading of an io input sampled on another MCU (a thermistor on a
    /// secondary): the heater control and temperature sensors take it as
    /// one of their own. Ignored by default.
    fn remote_reading(&mut self, reading: Reading) {
        let _ = reading;
    }
    /// For simulators that report: `cmd` for stepper `stepper`, its first
    /// step at 64-bit `clock` on that MCU's clock, went to another MCU.
    fn sent_elsewhere(&mut self, stepper: usize, cmd: StepCommand, clock: u64) {
        let _ = (stepper, cmd, clock);
    }
    /// For simulators that report: another MCU's trigger ended a homing
    /// across MCUs at this MCU's 64-bit `clock`, homing stepper
    /// `stepper`'s rail.
    fn triggered_elsewhere(&mut self, stepper: usize, clock: u64) {
        let _ = (stepper, clock);
    }
}

/// How the session keeps print time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Timing {
    /// As a printer: an idle toolhead's next move starts from the MCU's
    /// clock now, and M109/M190 wait for their heater.
    RealTime,
    /// As klippy's batch mode (to compare with its output): print time
    /// counts from the start and heater waits take no time.
    Batch,
}

/// The session's side of the MCU role's stepper engine: its clock, what
/// homing needs to know of the machine, and the homing move being watched.
#[derive(Debug, Clone, Copy)]
struct EngineLink {
    /// Step clock, Hz.
    freq: f64,
    /// Axes (0 = X) whose rail has an endstop pin (a delta: towers).
    endstops: [bool; 3],
    /// A delta: the endstops are the towers' (named a, b, c).
    towers: bool,
    /// The motion steppers (bit `i`: stepper `i`): a trigger stops them all.
    rails: u32,
    /// For each axis, its extra steppers with an endstop of their own
    /// (bit `i`: stepper `i`): each stops itself alone, as a delta's
    /// tower, and the rail's own endstop stops the rest.
    own_endstops: [u32; 3],
    /// The finest of their step distances, mm.
    finest_step: f64,
    /// The engine slot of the probe's input, if there is a probe.
    probe_slot: Option<usize>,
    /// Z homes on the probe (`probe:z_virtual_endstop`).
    z_on_probe: bool,
    /// The start clock of the homing move whose endstops are watched.
    watching: Option<u64>,
    /// The watched endstops not yet triggered (bit `i`: engine slot `i`).
    pending: u32,
    /// The clock of the homing move's last trigger so far, ticks.
    last_trigger: Option<u64>,
    /// How far each motion stepper moved past its trigger before it
    /// stopped, steps (see [`Mcu::moved_since`]).
    overshoot: [i64; 3],
    /// The endstop inputs read real switches. False in a simulation
    /// without them (klippy's batch mode): a homing move that runs to its
    /// end is then taken as triggered there, not as an error.
    endstops_modelled: bool,
    /// When the running line next reports that it is busy (clock).
    busy_at: u64,
}

impl EngineLink {
    fn new(machine: &Machine<'_>, freq: f64) -> Self {
        let rails = machine.motion_steppers();
        let mut link = Self {
            freq,
            endstops: [false; 3],
            towers: machine.travel.delta_homing().is_some(),
            rails: (1 << rails) - 1,
            own_endstops: [0; 3],
            finest_step: f64::INFINITY,
            probe_slot: machine.probe_slot(),
            z_on_probe: machine.homes_on_probe(2),
            watching: None,
            pending: 0,
            last_trigger: None,
            overshoot: [0; 3],
            endstops_modelled: true,
            busy_at: u64::MAX,
        };
        for (i, stepper) in machine.steppers.iter().take(rails).enumerate() {
            link.finest_step = link.finest_step.min(stepper.step_dist);
            let Some(axis) = machine.rail_of(i).filter(|&a| a < 3) else {
                continue;
            };
            if i == axis {
                link.endstops[axis] = stepper.endstop_pin.is_some();
                continue;
            }
            // An extra stepper: its own endstop, unless it names the
            // rail's pin or the probe's.
            let rail_pin = machine.steppers[axis].endstop_pin;
            let own = stepper.endstop_pin.filter(|pin| {
                !crate::probe::is_virtual_endstop(pin)
                    && rail_pin.is_none_or(|rail| !crate::pin_check::same_pin(pin, rail))
            });
            if own.is_some() {
                link.own_endstops[axis] |= 1 << i;
            }
        }
        link
    }

    /// The engine's step sink, through `mcu`; busy lines go to `out`.
    fn steps<'m, M: ?Sized>(
        &'m mut self,
        mcu: &'m mut M,
        out: &'m mut dyn Write,
    ) -> EngineSteps<'m, M> {
        EngineSteps {
            mcu,
            link: self,
            out,
            drivers: None,
        }
    }

    /// The engine slots (bit `i`: stepper `i`) whose endstops `homing`
    /// watches, and for each the steppers its trigger stops; `watch` is
    /// called for each.
    fn watches(&self, homing: &HomingMove, mut watch: impl FnMut(usize, u32)) {
        if homing.towers {
            for (k, _) in self.endstops.iter().enumerate().filter(|e| *e.1) {
                watch(k, 1 << k);
            }
            return;
        }
        let slot = self.endstop_slot(homing.axis, homing.probe);
        let own = match self.own_endstops.get(homing.axis) {
            Some(&own) if slot == homing.axis => own,
            _ => 0,
        };
        watch(slot, self.rails & !own);
        for k in (0..32).filter(|k| own & (1 << k) != 0) {
            watch(k, 1 << k);
        }
    }

    /// The steppers the trigger of engine slot `slot` stops while
    /// `homing` runs (bit `i`: stepper `i`; none for a slot not watched).
    fn stops_of(&self, homing: &HomingMove, slot: usize) -> u32 {
        let mut stops = 0;
        self.watches(homing, |s, of| {
            if s == slot {
                stops = of;
            }
        });
        stops
    }

    /// The engine slots whose endstops `homing` watches (bit `i`: slot
    /// `i`).
    fn watched(&self, homing: &HomingMove) -> u32 {
        let mut slots = 0;
        self.watches(homing, |slot, _| {
            slots |= 1u32.checked_shl(slot as u32).unwrap_or(0)
        });
        slots
    }

    /// A line starts at clock `now`: it reports busy from [`BUSY_TIME`]
    /// on while it waits.
    fn line_starts(&mut self, now: u64) {
        self.busy_at = now + (BUSY_TIME * self.freq) as u64;
    }

    /// The engine slot whose endstop input axis `axis` homes on.
    fn endstop_slot(&self, axis: usize, probe: bool) -> usize {
        match self.probe_slot {
            Some(slot) if probe || (axis == 2 && self.z_on_probe) => slot,
            _ => axis,
        }
    }

    /// Writes the busy line to `out` if it is due at clock `now`.
    fn keepalive(&mut self, now: u64, out: &mut dyn Write) {
        if now >= self.busy_at {
            let _ = writeln!(out, "{BUSY_LINE}");
            self.busy_at = now + (BUSY_TIME * self.freq) as u64;
        }
    }
}

/// One writer shared by the planner's replies and the step sink's busy
/// lines; each write borrows it only while it writes.
struct SharedOut<'o, W>(&'o RefCell<&'o mut W>);

impl<W: Write> Write for SharedOut<'_, W> {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        self.0.borrow_mut().write_str(s)
    }
}

/// A writer that drops what it is given (no console to keep alive).
struct Discard;

impl Write for Discard {
    fn write_str(&mut self, _: &str) -> fmt::Result {
        Ok(())
    }
}

/// Counts of what was planned.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Planned {
    /// Toolhead (XYZ) moves.
    pub toolhead_moves: usize,
    /// Extruder moves.
    pub extruder_moves: usize,
    /// Highest cruise speed, mm/s.
    pub peak_velocity: f64,
}

/// Why a line could not run (besides the printer's own errors).
#[derive(Debug)]
enum SessionError<'l> {
    /// Homing needs every axis' endstop: without one, a homing move would
    /// run its whole length into the frame.
    NoEndstops,
    /// A heater did not settle in time.
    HeatTimeout,
    /// The MCU role shut down: nothing moves or heats until a restart.
    Shutdown(Shutdown),
    /// The printer refused the command.
    Command(LineError<'l>),
}

impl fmt::Display for SessionError<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::NoEndstops => f.write_str(
                "G28: an axis has no endstop_pin; set the position with SET_KINEMATIC_POSITION",
            ),
            Self::HeatTimeout => write!(
                f,
                "heater did not reach its target within {} s",
                Fixed(MAX_HEAT_WAIT, 0)
            ),
            Self::Shutdown(reason) => write!(f, "MCU shutdown: {reason}"),
            Self::Command(e) => e.fmt(f),
        }
    }
}

/// One printer: G-code lines in, steps and heater commands to the MCU
/// role, replies out. `L` moves of lookahead, motion queues of `N`
/// segments, compressors of `Q` steps.
pub struct Session<'a, const L: usize> {
    /// Step accuracy, ticks.
    max_error: f64,
    printer: Printer<'a, L>,
    motion: ProfileMotion,
    engine: EngineLink,
    timing: Timing,
    planned: Planned,
    /// Time spent waiting for heaters, s.
    heat_wait: f64,
    /// Klipper's idle timeout.
    idle: IdleTimeout<'a>,
    /// When the first move since the toolhead was idle was queued (clock):
    /// the priming timer runs.
    priming_since: Option<u64>,
    /// The filament switch sensors.
    filament: FilamentSensors<'a>,
    /// The TMC drivers.
    tmc: Tmc<'a>,
    /// The idle timeout's state the TMC drivers last followed.
    tmc_state: IdleState,
}

/// The session with the board's queue sizes.
pub type BoardSession<'a> = Session<'a, { profile::LOOKAHEAD }>;

/// The session as the console drives it, the MCU role and the replies
/// behind `dyn`: the console's code is one for every session, and a
/// session's is compiled where its type becomes this trait object (the
/// board's in this crate, for size: [`BoardSession::console`]).
pub trait ConsoleSession<'a> {
    /// [`Session::run`].
    fn run(&mut self, text: &str, mcu: &mut dyn Mcu, out: &mut dyn Write) -> Result<(), ErrorText>;
    /// [`Session::idle`].
    fn idle(&mut self, mcu: &mut dyn Mcu, out: &mut dyn Write);
    /// [`Session::filament_event`].
    fn filament_event(&mut self, mcu: &mut dyn Mcu, printing: bool) -> Option<FilamentEvent<'a>>;
}

impl<'a, const L: usize> ConsoleSession<'a> for Session<'a, L> {
    fn run(
        &mut self,
        text: &str,
        mcu: &mut dyn Mcu,
        mut out: &mut dyn Write,
    ) -> Result<(), ErrorText> {
        Session::run(self, text, mcu, &mut out)
    }

    fn idle(&mut self, mcu: &mut dyn Mcu, mut out: &mut dyn Write) {
        Session::idle(self, mcu, &mut out);
    }

    fn filament_event(&mut self, mcu: &mut dyn Mcu, printing: bool) -> Option<FilamentEvent<'a>> {
        Session::filament_event(self, mcu, printing)
    }
}

impl<'a> BoardSession<'a> {
    /// The session for the console (the board's, QEMU's), its code
    /// compiled here (for size, as this crate) rather than in the
    /// firmware crate that calls it.
    // Not inlined: the coercion, and with it the session's code, stays
    // in this crate.
    #[inline(never)]
    pub fn console(&mut self) -> &mut dyn ConsoleSession<'a> {
        self
    }

    /// [`Session::init_in`] with the board's queue sizes, compiled here
    /// (for size, as this crate) rather than in the firmware crate that
    /// calls it: it runs once at start-up.
    pub fn init_board_in<'s>(
        slot: &'s mut MaybeUninit<Self>,
        machine: &Machine<'a>,
        freq: f64,
        max_error: f64,
        start: u64,
    ) -> &'s mut Self {
        Self::init_in(slot, machine, freq, max_error, start)
    }
}

impl<'a, const L: usize> Session<'a, L> {
    /// A session for `machine` on a step clock of `freq` Hz, steps within
    /// `max_error` s, print time starting at clock `start` (ticks).
    pub fn new(machine: &Machine<'a>, freq: f64, max_error: f64, start: u64) -> Self {
        let mut slot = MaybeUninit::uninit();
        Self::init_in(&mut slot, machine, freq, max_error, start);
        // SAFETY: `init_in` initialised it.
        unsafe { slot.assume_init() }
    }

    /// [`Self::new`] built in place in `slot`: the lookahead and the motion
    /// queues are far too large to pass through a microcontroller's stack.
    pub fn init_in<'s>(
        slot: &'s mut MaybeUninit<Self>,
        machine: &Machine<'a>,
        freq: f64,
        max_error: f64,
        start: u64,
    ) -> &'s mut Self {
        let p = slot.as_mut_ptr();
        // SAFETY: `p` is valid for writes; every field is written exactly
        // once (the printer and the motion in place, not through the stack)
        // before the slot is taken as initialised.
        unsafe {
            let printer = &mut *addr_of_mut!((*p).printer).cast::<MaybeUninit<Printer<'a, L>>>();
            Printer::init_in(printer, machine).set_time_origin(start as f64 / freq);
            ProfileMotion::init_in(
                &mut *addr_of_mut!((*p).motion).cast(),
                machine,
                freq,
                (max_error * freq) as u32,
                [0.0; 3],
            );
            addr_of_mut!((*p).engine).write(EngineLink::new(machine, freq));
            addr_of_mut!((*p).max_error).write(max_error);
            addr_of_mut!((*p).timing).write(Timing::RealTime);
            addr_of_mut!((*p).planned).write(Planned::default());
            addr_of_mut!((*p).heat_wait).write(0.0);
            addr_of_mut!((*p).idle).write(IdleTimeout::new(&machine.idle_timeout));
            addr_of_mut!((*p).priming_since).write(None);
            let sensors = &machine.accessories.filament_sensors;
            addr_of_mut!((*p).filament).write(FilamentSensors::new(sensors, start as f64 / freq));
            addr_of_mut!((*p).tmc).write(Tmc::new(machine));
            addr_of_mut!((*p).tmc_state).write(IdleState::Idle);
            slot.assume_init_mut()
        }
    }

    /// Sets how print time is kept (default: [`Timing::RealTime`]).
    pub fn set_timing(&mut self, timing: Timing) {
        self.timing = timing;
    }

    /// Whether the endstop inputs read real switches (default: true).
    /// False for a simulation without them, as klippy's batch mode: a
    /// homing move that runs its whole length is then not the error
    /// "No trigger on ... after full movement".
    pub fn set_endstops_modelled(&mut self, modelled: bool) {
        self.engine.endstops_modelled = modelled;
    }

    /// Starts afresh after a shutdown (FIRMWARE_RESTART, M999), as if just
    /// built for `machine` at clock `start`: nothing planned or queued, at
    /// rest at position 0, everything homed again before use.
    pub fn restart(&mut self, machine: &Machine<'a>, start: u64) {
        let (freq, max_error, timing) = (self.engine.freq, self.max_error, self.timing);
        let modelled = self.engine.endstops_modelled;
        // SAFETY: a `MaybeUninit<Self>` has the layout of `Self`; the old
        // value is overwritten without being dropped (nothing in it owns
        // a resource), every field is written by `init_in`.
        let slot = unsafe { &mut *(self as *mut Self).cast::<MaybeUninit<Self>>() };
        let session = Self::init_in(slot, machine, freq, max_error, start);
        session.set_timing(timing);
        session.set_endstops_modelled(modelled);
    }

    /// Runs one line of G-code (without line number or checksum); replies
    /// other than `ok` go to `out`, and while the line waits (homing, M400,
    /// a full step queue) `echo:busy: processing` every [`BUSY_TIME`].
    pub fn run(
        &mut self,
        text: &str,
        mcu: &mut (impl Mcu + ?Sized),
        out: &mut impl Write,
    ) -> Result<(), ErrorText> {
        if let Some(reason) = mcu.shutdown_reason() {
            return Err(error_text(&SessionError::Shutdown(reason)));
        }
        let word = command_word(text.as_bytes());
        if !self.engine.endstops.iter().all(|&e| e) && word.eq_ignore_ascii_case(b"G28") {
            return Err(error_text(&SessionError::NoEndstops));
        }
        // Klipper's batch mode never refuses a cold extrusion.
        let can_extrude = self.timing == Timing::Batch || mcu.can_extrude();
        self.printer.set_can_extrude(can_extrude);
        self.anchor(mcu);
        if word.eq_ignore_ascii_case(b"M119") || word.eq_ignore_ascii_case(b"QUERY_ENDSTOPS") {
            self.query_endstops(mcu, out);
            return Ok(());
        }
        if let Some(slot) = self.engine.probe_slot
            && word.eq_ignore_ascii_case(b"QUERY_PROBE")
        {
            // Read once the queued moves have run (Klipper queries at the
            // last move's time).
            self.run("M400", mcu, out)?;
            crate::probe::query(mcu.endstop_triggered(slot), out);
            return Ok(());
        }
        let now = mcu.now() as f64 / self.engine.freq;
        self.printer.set_probe_now(now);
        let line = gcode::parse(text)
            .map_err(|e| error_text(&SessionError::Command(LineError::from(e))))?;
        match self.filament.command(&line, out) {
            Ok(true) => return Ok(()),
            Ok(false) => {}
            Err(e) => return Err(error_text(&e)),
        }
        match self.idle.command(&line, now, out) {
            Ok(true) => return Ok(()),
            Ok(false) => {}
            Err(e) => return Err(error_text(&e)),
        }
        self.tmc_poll(mcu, out);
        if self.tmc.writes_after_moves(&line) && mcu.tmc_link().is_some() {
            self.run("M400", mcu, out)?;
        }
        if let Some(link) = mcu.tmc_link()
            && let Some(result) = self.tmc.command(&line, link, out)
        {
            return result;
        }
        self.engine.line_starts(mcu.now());
        let was_idle = self.printer.is_idle();
        let result = self.with_planning(mcu, out, |printer, planning, out| {
            printer
                .execute(&line, planning, out)
                .map_err(|e| error_text(&SessionError::Command(e)))
        });
        // A driver that could not be set up for a homing move on its stall
        // fails the line, as in Klipper.
        let result = match self.tmc.take_homing_failure() {
            Some(failure) => result.and(Err(failure)),
            None => result,
        };
        if was_idle && !self.printer.is_idle() && !self.printer.is_flowing() {
            // The first move since idle: the priming timer starts.
            self.priming_since = Some(mcu.now());
        }
        let thermal = self.thermal(mcu, out);
        if self.timing == Timing::RealTime {
            if result.is_ok() && word.eq_ignore_ascii_case(b"M400") {
                self.wait_moves_done(mcu, out);
            }
            if idle_timeout::is_activity(&line) {
                let now = mcu.now() as f64 / self.engine.freq;
                self.idle.note_activity(now, self.printer.print_time());
                self.tmc_follow_idle(mcu, out);
            }
        }
        result.and(thermal)
    }

    /// M119, QUERY_ENDSTOPS: each axis' endstop as Klipper reports it
    /// (`x:open y:open z:TRIGGERED`).
    fn query_endstops(&mut self, mcu: &mut (impl Mcu + ?Sized), out: &mut impl Write) {
        let mut sep = "";
        let names = if self.engine.towers {
            ["a", "b", "c"]
        } else {
            ["x", "y", "z"]
        };
        let state = |mcu: &mut _, slot| {
            if Mcu::endstop_triggered(mcu, slot) {
                "TRIGGERED"
            } else {
                "open"
            }
        };
        for (axis, name) in names.iter().enumerate() {
            if self.engine.endstops[axis] {
                let slot = self.engine.endstop_slot(axis, false);
                let _ = write!(out, "{sep}{name}:{}", state(mcu, slot));
                sep = " ";
            }
            // The rail's extra steppers with endstops of their own
            // (`[stepper_z1]`: z1), numbered in order.
            let own = self.engine.own_endstops.get(axis).copied().unwrap_or(0);
            for (n, slot) in (0..32).filter(|k| own & (1 << k) != 0).enumerate() {
                let _ = write!(out, "{sep}{name}{}:{}", n + 1, state(mcu, slot));
                sep = " ";
            }
        }
        let _ = writeln!(out);
    }

    /// M400: waits until every queued step has run.
    fn wait_moves_done(&mut self, mcu: &mut (impl Mcu + ?Sized), out: &mut impl Write) {
        let mut steps = self.engine.steps(mcu, out);
        self.motion.settle_into(&mut steps);
        let end = (self.printer.print_time().max(0.0) * self.engine.freq) as u64;
        loop {
            let now = mcu.now();
            if now >= end || mcu.shutdown_reason().is_some() {
                return;
            }
            self.engine.keepalive(now, out);
            mcu.wait(end);
        }
    }

    /// Carries out the heater and fan commands of the line just run.
    fn thermal(
        &mut self,
        mcu: &mut (impl Mcu + ?Sized),
        out: &mut impl Write,
    ) -> Result<(), ErrorText> {
        while let Some(command) = self.printer.take_thermal() {
            match command {
                ThermalCommand::Report => {
                    let _ = mcu.report_temperatures(out);
                    let _ = out.write_char('\n');
                }
                ThermalCommand::Target {
                    heater, wait: true, ..
                } => {
                    mcu.thermal(command);
                    if self.timing == Timing::RealTime {
                        self.wait_for(Wait::Settled(heater), mcu, out)?;
                    }
                }
                ThermalCommand::Wait(wait) => {
                    if self.timing == Timing::RealTime {
                        self.wait_for(wait, mcu, out)?;
                    }
                }
                _ => mcu.thermal(command),
            }
        }
        Ok(())
    }

    /// Waits until `wait` is over (or the MCU shut down), once every
    /// queued move has run, reporting temperatures every second as
    /// Klipper does; the next move starts after the wait.
    fn wait_for<M: Mcu + ?Sized>(
        &mut self,
        wait: Wait,
        mcu: &mut M,
        out: &mut impl Write,
    ) -> Result<(), ErrorText> {
        let busy = |mcu: &mut M| mcu.shutdown_reason().is_none() && mcu.thermal_waiting(wait);
        if !busy(mcu) {
            return Ok(());
        }
        let freq = self.engine.freq;
        let clock = |t: f64| (t.max(0.0) * freq) as u64;
        self.motion.settle_into(&mut self.engine.steps(mcu, out));
        let start = mcu.now();
        let report_every = clock(HEAT_REPORT_TIME);
        let deadline = start + clock(MAX_HEAT_WAIT);
        let mut next_report = start + report_every;
        while busy(mcu) {
            let now = mcu.now();
            if now >= deadline {
                return Err(error_text(&SessionError::HeatTimeout));
            }
            if now >= next_report {
                let _ = mcu.report_temperatures(out);
                let _ = out.write_char('\n');
                next_report += report_every;
            }
            mcu.wait(next_report);
        }
        let end = mcu.now();
        self.heat_wait += end.saturating_sub(start) as f64 / freq;
        self.printer.hold_until(end as f64 / freq);
        Ok(())
    }

    /// To call between lines, as real time runs (the board's thread code
    /// between console lines; every 10 ms is often enough): Klipper's
    /// timers. The priming timer releases the moves queued since the
    /// toolhead was idle [`crate::printer::PRIMING_TIME`] after the first
    /// of them; the flush timer flushes the lookahead when the moves sent
    /// are about to run out; once nothing is queued every step goes out;
    /// and the idle timeout runs.
    pub fn idle(&mut self, mcu: &mut (impl Mcu + ?Sized), out: &mut impl Write) {
        if self.timing != Timing::RealTime {
            return;
        }
        let clock = mcu.now();
        let now = clock as f64 / self.engine.freq;
        let priming_ticks = (crate::printer::PRIMING_TIME * self.engine.freq) as u64;
        let priming = self
            .priming_since
            .is_some_and(|since| clock.saturating_sub(since) >= priming_ticks);
        if !self.printer.is_idle() {
            // Moves wait to be released: from now at the earliest. (An idle
            // toolhead's print time stays where its last move ended.)
            self.anchor(mcu);
        }
        self.with_planning(mcu, &mut Discard, |printer, planning, _| {
            if priming {
                printer.priming_timeout(planning);
            }
            printer.flush_if_low(now, planning);
        });
        if self.printer.is_idle() || self.printer.is_flowing() {
            self.priming_since = None;
        }
        if self.printer.is_idle() {
            // Nothing more is coming for now: every step of the motion
            // queued goes out, so it runs to its end (klippy's background
            // flush).
            self.motion
                .settle_into(&mut self.engine.steps(mcu, &mut Discard));
        }
        self.idle_timeout(mcu, out);
        self.tmc_poll(mcu, out);
    }

    /// The TMC drivers' start-up writes and periodic check.
    fn tmc_poll(&mut self, mcu: &mut (impl Mcu + ?Sized), out: &mut impl Write) {
        if self.tmc.is_empty() {
            return;
        }
        let now = mcu.now() as f64 / self.engine.freq;
        if let Some(link) = mcu.tmc_link()
            && let Err(e) = self.tmc.poll(link, now, out)
        {
            // As Klipper's periodic check: the printer shuts down.
            let _ = writeln!(out, "!! {e}");
            mcu.shutdown(Shutdown::TmcError);
        }
    }

    /// The TMC drivers follow the idle timeout's state as Klipper's do
    /// (a TMC2660's idle_current_percent: its run current while Printing,
    /// that share of it once Ready); a driver that cannot be reached shuts
    /// the printer down.
    fn tmc_follow_idle(&mut self, mcu: &mut (impl Mcu + ?Sized), out: &mut impl Write) {
        let state = self.idle.state();
        if state == self.tmc_state {
            return;
        }
        self.tmc_state = state;
        let printing = match state {
            IdleState::Printing => true,
            IdleState::Ready => false,
            IdleState::Idle => return,
        };
        if let Some(link) = mcu.tmc_link()
            && let Err(e) = self.tmc.follow_motion(link, printing)
        {
            let _ = writeln!(out, "!! {e}");
            mcu.shutdown(Shutdown::TmcError);
        }
    }

    /// The TMC drivers (their registers as last written).
    pub fn tmc(&self) -> &Tmc<'a> {
        &self.tmc
    }

    /// Reads the filament switch sensors (between lines, as
    /// [`Self::idle`]); `printing`: a print from the card runs. The event
    /// a change causes, for the console to act on (pause, G-code).
    pub fn filament_event(
        &mut self,
        mcu: &mut (impl Mcu + ?Sized),
        printing: bool,
    ) -> Option<FilamentEvent<'a>> {
        if self.filament.is_empty() {
            return None;
        }
        let now = mcu.now() as f64 / self.engine.freq;
        let printing = printing || !self.printer.is_idle();
        self.filament
            .poll(now, |i| mcu.filament_present(i), printing)
    }

    /// Klipper's priming timeout, now: the moves queued since the toolhead
    /// was idle are planned and released (for replaying klippy's batch
    /// mode, which decides it from its own speed).
    pub fn prime(&mut self, mcu: &mut (impl Mcu + ?Sized)) {
        self.with_planning(mcu, &mut Discard, |printer, planning, _| {
            printer.priming_timeout(planning)
        });
    }

    /// In real time, until moves flow, their print time starts from the
    /// MCU's clock now (as klippy fixes it when it releases the first
    /// moves, not when they are queued).
    fn anchor(&mut self, mcu: &mut (impl Mcu + ?Sized)) {
        if self.timing == Timing::RealTime && !self.printer.is_flowing() {
            let now = mcu.now() as f64 / self.engine.freq;
            self.printer.set_time_origin(now);
        }
    }

    /// Klipper's idle timeout: once nothing has moved for its timeout, its
    /// G-code runs (by default: heaters off, motors off).
    fn idle_timeout(&mut self, mcu: &mut (impl Mcu + ?Sized), out: &mut impl Write) {
        let now = mcu.now() as f64 / self.engine.freq;
        let toolhead = ToolheadState {
            print_time: self.printer.print_time(),
            lookahead_empty: self.printer.is_idle(),
        };
        let gcode = self.idle.poll(now, toolhead);
        self.tmc_follow_idle(mcu, out);
        let Some(gcode) = gcode else {
            return;
        };
        let mut ok = true;
        for line in gcode.lines() {
            if let Err(e) = self.run(line, mcu, out) {
                let _ = writeln!(out, "!! {e}");
                ok = false;
            }
        }
        let now = mcu.now() as f64 / self.engine.freq;
        self.idle.idle_gcode_done(now, ok);
    }

    /// The end of the input: every queued move is planned and its steps
    /// sent (after klippy's 0.5 s dwell).
    pub fn finish(&mut self, mcu: &mut (impl Mcu + ?Sized)) {
        self.with_planning(mcu, &mut Discard, |printer, planning, _| {
            printer.finish(planning)
        });
        self.motion
            .finish_into(&mut self.engine.steps(mcu, &mut Discard));
    }

    /// Runs `f` on the printer with the planning sink and `out`, then
    /// generates steps as far as the plan is final (busy lines to `out`
    /// while waiting); returns what `f` returned.
    fn with_planning<M: Mcu + ?Sized, W: Write, R>(
        &mut self,
        mcu: &mut M,
        out: &mut W,
        f: impl FnOnce(&mut Printer<'a, L>, &mut Planning<'_, '_, M>, &mut SharedOut<'_, W>) -> R,
    ) -> R {
        let motion = &mut self.motion;
        mcu.stepper_clocks(self.printer.print_time(), &mut |i, offset, freq| {
            motion.set_clock(i, offset, freq);
        });
        // The step sink writes busy lines between the replies `f` writes.
        let out = RefCell::new(out);
        let mut sink_out = SharedOut(&out);
        // Only an MCU with wires to the drivers sets them up for homing
        // (without, the drivers' code is left out of the build).
        let wired = mcu.tmc_link().is_some();
        let mut steps = self.engine.steps(mcu, &mut sink_out);
        if wired {
            steps.drivers = Some(&mut self.tmc);
        }
        let result = f(
            &mut self.printer,
            &mut Planning {
                motion: &mut self.motion,
                steps: &mut steps,
                planned: &mut self.planned,
            },
            &mut SharedOut(&out),
        );
        self.motion.generate_into(f64::INFINITY, &mut steps);
        if self.timing == Timing::RealTime {
            // Klippy in real time restarts after what it generated; its
            // batch mode, which the golden runs replay, generates later.
            self.printer
                .note_steps_generated(self.motion.generated_until());
        }
        result
    }

    /// The printer (G-code state and toolhead).
    pub fn printer(&mut self) -> &mut Printer<'a, L> {
        &mut self.printer
    }

    /// What has been planned so far.
    pub fn planned(&self) -> Planned {
        self.planned
    }

    /// Time spent waiting for heaters so far, s.
    pub fn heat_wait(&self) -> f64 {
        self.heat_wait
    }

    /// Print time before which every step has gone to the MCU, s.
    pub fn sent_until(&self) -> f64 {
        self.motion.sent_until()
    }

    /// Why step generation stopped, if it did (the printer must stop).
    pub fn motion_error(&self) -> Option<onechip_stepgen::motion::MotionError> {
        self.motion.error()
    }
}

/// The planner's sink: moves into step generation, counted.
struct Planning<'p, 'm, M: ?Sized> {
    motion: &'p mut ProfileMotion,
    steps: &'p mut EngineSteps<'m, M>,
    planned: &'p mut Planned,
}

impl<M: Mcu + ?Sized> MoveSink for Planning<'_, '_, M> {
    fn toolhead(&mut self, m: &TrapqMove) {
        self.planned.toolhead_moves += 1;
        self.planned.peak_velocity = self.planned.peak_velocity.max(m.cruise_v);
        self.steps.mcu.planned(m, false);
        self.motion.moves(self.steps).toolhead(m);
    }

    fn extruder(&mut self, m: &TrapqMove) {
        self.planned.extruder_moves += 1;
        self.steps.mcu.planned(m, true);
        self.motion.moves(self.steps).extruder(m);
    }

    fn set_position(&mut self, pos: [f64; 3]) {
        self.motion.moves(self.steps).set_position(pos);
    }

    fn extruder_stepper(
        &mut self,
        stepper: usize,
        motion: &ExtruderStepperMotion,
        position: Option<f64>,
    ) {
        (self.motion.moves(self.steps)).extruder_stepper(stepper, motion, position);
    }

    fn homing_move_end(&mut self, homing: &HomingMove) -> HomingEnd {
        self.motion.moves(self.steps).homing_move_end(homing)
    }

    fn probe_pin(&mut self, print_time: f64, pulse_width: f64) {
        let clock = (print_time.max(0.0) * self.steps.link.freq) as u64;
        self.steps.mcu.probe_servo(clock, pulse_width);
    }

    fn probe_reads(&mut self, from: f64, until: f64, triggered: bool) -> (bool, f64) {
        // Every step of the moves before goes to the MCU, which then runs
        // past them.
        self.motion.settle(&mut *self.steps);
        let steps = &mut *self.steps;
        // Without switches (klippy's batch mode) every check passes.
        let Some(slot) = steps
            .link
            .probe_slot
            .filter(|_| steps.link.endstops_modelled)
        else {
            return (true, from);
        };
        let freq = steps.link.freq;
        let clock = |t: f64| (t.max(0.0) * freq) as u64;
        let (from, until) = (clock(from), clock(until));
        loop {
            let now = steps.mcu.now();
            let ended = now as f64 / freq;
            if steps.mcu.shutdown_reason().is_some() {
                return (false, ended);
            }
            if now >= from && steps.mcu.endstop_triggered(slot) == triggered {
                return (true, ended);
            }
            if now >= until {
                return (false, ended);
            }
            steps.link.keepalive(now, steps.out);
            steps.mcu.wait(if now < from { from } else { until });
        }
    }
}

/// Step commands into the MCU role's engine, waiting (asleep) while a
/// stepper's outbox is full; homing moves run against the endstops.
struct EngineSteps<'m, M: ?Sized> {
    mcu: &'m mut M,
    link: &'m mut EngineLink,
    /// Where busy lines go.
    out: &'m mut dyn Write,
    /// The TMC drivers, told of homing moves (sensorless homing).
    drivers: Option<&'m mut dyn HomingDrivers>,
}

/// Tells `drivers` (through `mcu`'s wires to them) that a homing move
/// watching the endstops of engine slots `slots` begins (`begin`) or
/// ends.
fn tell_drivers(
    drivers: &mut Option<&mut dyn HomingDrivers>,
    mcu: &mut (impl Mcu + ?Sized),
    slots: u32,
    begin: bool,
) {
    if let (Some(drivers), Some(tmc)) = (drivers.as_deref_mut(), mcu.tmc_link()) {
        if begin {
            drivers.homing_move_begin(tmc, slots);
        } else {
            drivers.homing_move_end(tmc, slots);
        }
    }
}

impl<M: Mcu + ?Sized> StepSink for EngineSteps<'_, M> {
    fn command(&mut self, index: usize, cmd: StepCommand, clock: u64) {
        while self.mcu.push(index, cmd, clock).is_err() {
            if self.mcu.shutdown_reason().is_some() {
                return;
            }
            // The engine makes room as its steps run.
            self.link.keepalive(self.mcu.now(), self.out);
            self.mcu.wait(u64::MAX);
        }
    }

    /// Watches the homed axis' endstop (a delta: each tower's) from the
    /// move's start and waits until the steps sent so far have run or
    /// every endstop triggered (an axis' trigger stops every motion
    /// stepper at once; a tower's stops its own stepper, the others go
    /// on).
    fn home(
        &mut self,
        homing: &HomingMove,
        start_clock: u64,
        until_clock: u64,
    ) -> Option<HomingStop> {
        let link = &mut *self.link;
        if link.watching != Some(start_clock) {
            let endstop = Endstop::for_homing(
                start_clock as u32,
                link.freq,
                homing.speed,
                link.finest_step,
            );
            link.last_trigger = None;
            link.overshoot = [0; 3];
            link.pending = link.watched(homing);
            // Drivers homing on their stall detect it from now on (before
            // the endstops are armed, as Klipper).
            tell_drivers(&mut self.drivers, self.mcu, link.pending, true);
            let mcu = &mut *self.mcu;
            link.watches(homing, |slot, stops| {
                mcu.watch_endstop(slot, endstop, stops)
            });
            link.watching = Some(start_clock);
        }
        let stop = |clock, untriggered, moved: [i64; 3]| {
            let mut overshoot = [0; MAX_STEPPERS];
            overshoot[..3].copy_from_slice(&moved);
            HomingStop {
                clock,
                overshoot,
                stopped: true,
                untriggered,
                comms_timeout: false,
            }
        };
        let shutdown = loop {
            while let Some((slot, trigger)) = self.mcu.take_trigger() {
                // The 64-bit clock of the trigger, which lies before now.
                let clock = widen(trigger, self.mcu.now());
                if self.mcu.homing_comms_timeout() {
                    // Every MCU stopped by itself: the homing is over.
                    link.watching = None;
                    return Some(HomingStop {
                        comms_timeout: true,
                        ..stop(clock, None, [0; 3])
                    });
                }
                // How far the motion steppers this trigger stopped went
                // past it (on another MCU than the endstop's, until the
                // trigger reached theirs), as klippy's halt positions.
                let stopped = link.stops_of(homing, slot);
                for k in (0..3).filter(|k| stopped & (1 << k) != 0) {
                    link.overshoot[k] = self.mcu.moved_since(k, clock);
                }
                link.last_trigger = Some(link.last_trigger.map_or(clock, |t| t.max(clock)));
                link.pending &= !(1u32.checked_shl(slot as u32).unwrap_or(0));
                if link.pending == 0 {
                    link.watching = None;
                    tell_drivers(&mut self.drivers, self.mcu, link.watched(homing), false);
                    let moved = link.overshoot;
                    return Some(stop(link.last_trigger.unwrap_or(clock), None, moved));
                }
            }
            let now = self.mcu.now();
            let shutdown = self.mcu.shutdown_reason().is_some();
            if now >= until_clock || shutdown {
                break shutdown;
            }
            link.keepalive(now, self.out);
            self.mcu.wait(until_clock);
        };
        let end_clock = (homing.end_time.max(0.0) * link.freq) as u64;
        if until_clock >= end_clock {
            // The whole move ran with an endstop untriggered.
            self.mcu.stop_watching();
            link.watching = None;
            tell_drivers(&mut self.drivers, self.mcu, link.watched(homing), false);
            // (After a shutdown the shutdown is the error.)
            let untriggered = (link.endstops_modelled && link.pending != 0 && !shutdown)
                .then(|| link.pending.trailing_zeros() as usize);
            if link.last_trigger.is_some() {
                // Some steppers stopped at their trigger: all restart at
                // the move's end.
                let moved = link.overshoot;
                return Some(stop(until_clock.max(end_clock), untriggered, moved));
            }
            if untriggered.is_some() {
                return Some(HomingStop {
                    stopped: false,
                    ..stop(until_clock, untriggered, [0; 3])
                });
            }
        }
        None
    }
}
