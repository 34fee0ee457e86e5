//! The printer as both boards run it: G-code lines in, planned moves and
//! heater/fan commands out.
//!
//! Holds the toolhead (with a lookahead of `N` moves) and the G-code state;
//! each parsed line is executed, and replies follow Klipper's console
//! conventions (`!! ` for errors, `// ` for information). Heater and fan
//! G-codes (M104, M109, M140, M190, M106, M107, M105,
//! SET_HEATER_TEMPERATURE, TURN_OFF_HEATERS) are checked here and handed
//! out by [`Printer::take_thermal`] to whoever runs the heaters.

use crate::heaters::{MAX_HEATERS, SensorRef, ThermalCommand, ThermalError, Wait, WaitError};
use crate::outputs::{AccessoryCommand, AccessoryError, AccessoryNames};
use core::fmt::{self, Write};
use core::mem::MaybeUninit;
use core::ptr::addr_of_mut;
use onechip_planner::extruder_stepper::{self, ExtruderStepper, MAX_EXTRUDER_STEPPERS};
use onechip_planner::gcode::{self, Command, Line};
use onechip_planner::gcode_move::{CommandError, GcodeMove};
use onechip_planner::machine::Machine;
use onechip_planner::math::clamp;
use onechip_planner::move_sink::MoveSink;
use onechip_planner::sensor_section::MAX_SENSORS;
use onechip_planner::toolhead::Toolhead;

/// Why a line failed.
#[derive(Debug, Clone, PartialEq)]
pub enum LineError<'l> {
    /// A G-code or motion error.
    Command(CommandError<'l>),
    /// A heater command was refused.
    Thermal(ThermalError),
    /// A fan or pin command was refused.
    Accessory(AccessoryError<'l>),
    /// A TEMPERATURE_WAIT was refused.
    Wait(WaitError<'l>),
}

impl<'l> From<CommandError<'l>> for LineError<'l> {
    fn from(e: CommandError<'l>) -> Self {
        Self::Command(e)
    }
}

impl<'l> From<gcode::GcodeError<'l>> for LineError<'l> {
    fn from(e: gcode::GcodeError<'l>) -> Self {
        Self::Command(CommandError::Gcode(e))
    }
}

impl fmt::Display for LineError<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Command(e) => e.fmt(f),
            Self::Thermal(e) => e.fmt(f),
            Self::Accessory(e) => e.fmt(f),
            Self::Wait(e) => e.fmt(f),
        }
    }
}

/// A heater as G-code names it.
#[derive(Debug, Clone, Copy, PartialEq)]
struct HeaterName<'a> {
    name: &'a str,
    min_temp: f64,
    max_temp: f64,
}

/// Idle input time after which queued moves are released, s (Klipper's
/// priming delay).
pub const PRIMING_TIME: f64 = 0.100;

/// The motion side of a printer.
#[derive(Debug, Clone)]
pub struct Printer<'a, const N: usize> {
    pub(crate) toolhead: Toolhead<N>,
    pub(crate) gcode: GcodeMove,
    /// The probe, G28's variant and their state ([`crate::probe`]).
    pub(crate) probing: crate::probe::Probing<'a>,
    heaters: heapless::Vec<HeaterName<'a>, MAX_HEATERS>,
    /// The `[temperature_sensor NAME]`s' names.
    sensors: heapless::Vec<&'a str, MAX_SENSORS>,
    has_fan: bool,
    /// Heater and fan commands not yet taken.
    thermal: heapless::Deque<ThermalCommand, MAX_HEATERS>,
    /// The named fans and output pins G-code may set.
    accessories: AccessoryNames<'a>,
    /// The stepper drivers are enabled (moves since start or M84/M18).
    motors: bool,
    /// The steppers following the extruder, as G-code has set them.
    extruder_steppers: heapless::Vec<ExtruderStepper<'a>, MAX_EXTRUDER_STEPPERS>,
}

impl<'a, const N: usize> Printer<'a, N> {
    /// A printer for `machine`, at rest at position 0.
    pub fn new(machine: &Machine<'a>) -> Self {
        let mut slot = MaybeUninit::uninit();
        Self::init_in(&mut slot, machine);
        // SAFETY: `init_in` initialised it.
        unsafe { slot.assume_init() }
    }

    /// [`Self::new`] built in place in `slot` (its lookahead is too large
    /// to pass through a small stack); returns it.
    pub fn init_in<'s>(slot: &'s mut MaybeUninit<Self>, machine: &Machine<'a>) -> &'s mut Self {
        let heaters = machine
            .heaters
            .iter()
            .map(|h| HeaterName {
                name: h.name,
                min_temp: h.min_temp,
                max_temp: h.max_temp,
            })
            .collect();
        let p = slot.as_mut_ptr();
        // SAFETY: `p` is valid for writes; every field is written exactly
        // once (the toolhead in place) before the slot is taken as
        // initialised.
        unsafe {
            let toolhead = &mut *addr_of_mut!((*p).toolhead).cast::<MaybeUninit<Toolhead<N>>>();
            machine
                .toolhead_in(toolhead)
                .set_can_extrude(machine.can_extrude_cold());
            addr_of_mut!((*p).gcode).write(GcodeMove::default());
            addr_of_mut!((*p).probing).write(crate::probe::Probing::new(machine));
            addr_of_mut!((*p).heaters).write(heaters);
            addr_of_mut!((*p).sensors).write(machine.sensors.iter().map(|s| s.name).collect());
            addr_of_mut!((*p).has_fan).write(machine.fan.is_some());
            addr_of_mut!((*p).thermal).write(heapless::Deque::new());
            addr_of_mut!((*p).accessories).write(AccessoryNames::new(&machine.accessories));
            addr_of_mut!((*p).motors).write(false);
            addr_of_mut!((*p).extruder_steppers).write(machine.extruder_steppers.clone());
            slot.assume_init_mut()
        }
    }

    /// Starts print time `origin` s after the MCU's clock did (a printer
    /// powered on long before the print).
    pub fn set_time_origin(&mut self, origin: f64) {
        self.toolhead.set_time_origin(origin);
    }

    /// Steps have been generated up to print time `t` s (see
    /// [`Toolhead::note_steps_generated`]).
    pub fn note_steps_generated(&mut self, t: f64) {
        self.toolhead.note_steps_generated(t);
    }

    /// Whether moves with E motion may run: the extruder's heater is at
    /// or above min_extrude_temp ([`crate::heaters::Heaters::can_extrude`]).
    /// While false, such moves are refused with Klipper's "Extrude below
    /// minimum temp". The session sets it before each line.
    pub fn set_can_extrude(&mut self, can_extrude: bool) {
        self.toolhead.set_can_extrude(can_extrude);
    }

    /// True while nothing is queued or moving.
    pub fn is_idle(&self) -> bool {
        self.toolhead.is_idle()
    }

    /// True once moves flow: their print times are fixed.
    pub fn is_flowing(&self) -> bool {
        self.toolhead.is_flowing()
    }

    /// If idle, the next move starts no earlier than print time `t` s.
    pub fn hold_until(&mut self, t: f64) {
        self.toolhead.hold_until(t);
    }

    /// Runs one line of G-code; replies other than `ok` go to `out`.
    pub fn execute<'l>(
        &mut self,
        line: &Line<'l>,
        sink: &mut impl MoveSink,
        out: &mut impl Write,
    ) -> Result<(), LineError<'l>>
    where
        'a: 'l,
    {
        if self.thermal(line, sink)? || self.probe_command(line, sink, out)? {
            return Ok(());
        }
        let print_time = self.toolhead.print_time();
        if let Some(command) = self
            .accessories
            .parse(line, print_time)
            .map_err(LineError::Accessory)?
        {
            self.push_thermal(ThermalCommand::Accessory(command));
            return Ok(());
        }
        if let Command::Extended(e) = &line.command
            && extruder_stepper::command(
                &mut self.extruder_steppers,
                e,
                &mut self.toolhead,
                sink,
                out,
            )?
        {
            return Ok(());
        }
        self.gcode.execute(line, &mut self.toolhead, sink, out)?;
        self.note_motors(line);
        Ok(())
    }

    /// Klipper enables the stepper drivers with a move and disables them
    /// with M84/M18: controller fans follow, and so do the enable pins on
    /// secondary MCUs.
    fn note_motors(&mut self, line: &Line<'_>) {
        let Command::Traditional(t) = line.command else {
            return;
        };
        let on = match (t.letter, t.number) {
            (b'G', 0..=3 | 28) => true,
            (b'M', 18 | 84) => false,
            _ => return,
        };
        // A motor off always goes out: drivers may have been enabled by
        // moves that were no G-code moves (probing, homing overrides).
        if on != self.motors || !on {
            self.motors = on;
            self.push_thermal(ThermalCommand::Accessory(AccessoryCommand::Motors(on)));
        }
    }

    /// The next heater or fan command of the lines run so far.
    pub fn take_thermal(&mut self) -> Option<ThermalCommand> {
        self.thermal.pop_front()
    }

    /// Handles `line` if it is a heater or fan command; false otherwise
    /// (also for fan commands without a `[fan]`: "Unknown command", as
    /// Klipper).
    // Not inlined (nor is `probe_command`): inlined into `execute`, their
    // locals and error exits widened its frame past the reach of short
    // stack addressing (600 bytes more flash).
    #[inline(never)]
    fn thermal<'l>(
        &mut self,
        line: &Line<'l>,
        sink: &mut impl MoveSink,
    ) -> Result<bool, LineError<'l>> {
        let target = |printer: &Self, heater: &str, celsius: f64, wait: bool| {
            let index = printer.heater(heater)?;
            let h = printer.heaters[index];
            if celsius != 0.0 && !(h.min_temp..=h.max_temp).contains(&celsius) {
                return Err(LineError::Thermal(ThermalError::OutOfRange {
                    celsius,
                    min: h.min_temp,
                    max: h.max_temp,
                }));
            }
            Ok(ThermalCommand::Target {
                heater: index,
                celsius,
                wait: wait && celsius > 0.0,
            })
        };
        let command = match line.command {
            Command::Traditional(t) if t.letter == b'M' && t.sub.is_none() => {
                let s = t.float("S")?;
                match t.number {
                    104 | 109 => {
                        if t.float("T")?.is_some_and(|n| n != 0.0) {
                            return Err(LineError::Thermal(ThermalError::NoHeater));
                        }
                        target(self, "extruder", s.unwrap_or(0.0), t.number == 109)?
                    }
                    140 | 190 => target(self, "heater_bed", s.unwrap_or(0.0), t.number == 190)?,
                    105 => ThermalCommand::Report,
                    106 | 107 if self.has_fan => ThermalCommand::Fan {
                        speed: if t.number == 107 {
                            0.0
                        } else {
                            clamp(s.unwrap_or(255.0) / 255.0, 0.0, 1.0)
                        },
                        print_time: self.toolhead.print_time(),
                    },
                    _ => return Ok(false),
                }
            }
            Command::Extended(e) if e.name.eq_ignore_ascii_case("SET_HEATER_TEMPERATURE") => {
                let heater = e.get("HEATER")?.unwrap_or("");
                target(self, heater, e.float("TARGET")?.unwrap_or(0.0), false)?
            }
            Command::Extended(e) if e.name.eq_ignore_ascii_case("TEMPERATURE_WAIT") => {
                let name = e.get("SENSOR")?.unwrap_or("");
                let sensor = self
                    .sensor_ref(name)
                    .ok_or(LineError::Wait(WaitError::UnknownSensor(name)))?;
                let min = e.float("MINIMUM")?.unwrap_or(f64::NEG_INFINITY);
                let max = e.float("MAXIMUM")?.unwrap_or(f64::INFINITY);
                if min == f64::NEG_INFINITY && max == f64::INFINITY {
                    return Err(LineError::Wait(WaitError::NoRange));
                }
                if max <= min {
                    return Err(LineError::Wait(WaitError::MaximumNotAbove(min)));
                }
                ThermalCommand::Wait(Wait::Within { sensor, min, max })
            }
            Command::Extended(e) if e.name.eq_ignore_ascii_case("TURN_OFF_HEATERS") => {
                for heater in 0..self.heaters.len() {
                    self.push_thermal(ThermalCommand::Target {
                        heater,
                        celsius: 0.0,
                        wait: false,
                    });
                }
                return Ok(true);
            }
            _ => return Ok(false),
        };
        if let ThermalCommand::Target { wait: true, .. } | ThermalCommand::Wait(_) = command {
            // Waiting starts once every queued move has been planned.
            self.toolhead.wait_moves(sink);
        }
        self.push_thermal(command);
        Ok(true)
    }

    /// The heater or temperature sensor TEMPERATURE_WAIT's SENSOR names
    /// (`extruder`, `temperature_sensor chamber`).
    fn sensor_ref(&self, name: &str) -> Option<SensorRef> {
        if let Some(sensor) = name.strip_prefix("temperature_sensor ") {
            let sensor = sensor.trim();
            return self
                .sensors
                .iter()
                .position(|&s| s == sensor)
                .map(SensorRef::Sensor);
        }
        self.heaters
            .iter()
            .position(|h| h.name == name)
            .map(SensorRef::Heater)
    }

    /// The index of the heater named `name`.
    fn heater<'l>(&self, name: &str) -> Result<usize, LineError<'l>> {
        self.heaters
            .iter()
            .position(|h| h.name == name)
            .ok_or(LineError::Thermal(ThermalError::NoHeater))
    }

    /// Queues a heater or fan command, dropping the oldest untaken one if
    /// full (the caller did not take them).
    fn push_thermal(&mut self, command: ThermalCommand) {
        if self.thermal.is_full() {
            self.thermal.pop_front();
        }
        let _ = self.thermal.push_back(command);
    }

    /// If [`Self::priming_timeout`] would plan moves now: how many of them
    /// are toolhead moves.
    pub fn priming_moves(&self) -> Option<usize> {
        self.toolhead.priming_moves()
    }

    /// To call when no input has arrived for [`PRIMING_TIME`] s: plans and
    /// releases moves still waiting for the lookahead to fill, as Klipper's
    /// priming timer does, so a streamed move does not wait for the next.
    pub fn priming_timeout(&mut self, sink: &mut impl MoveSink) {
        self.toolhead.priming_timeout(sink);
    }

    /// While moves flow: plans and releases every queued move once those
    /// released end within a second of print time `now` (s), as klippy's
    /// flush timer does when the input stalls.
    pub fn flush_if_low(&mut self, now: f64, sink: &mut impl MoveSink) {
        self.toolhead.flush_if_low(now, sink);
    }

    /// Ends the input as klippy does: a 0.5 s dwell, then every move.
    pub fn finish(&mut self, sink: &mut impl MoveSink) {
        self.gcode.finish(&mut self.toolhead, sink);
    }

    /// Print time queued so far, s.
    pub fn print_time(&self) -> f64 {
        self.toolhead.print_time()
    }

    /// The G-code position (X, Y, Z, E), mm.
    pub fn position(&self) -> [f64; 4] {
        self.gcode.gcode_position()
    }
}
