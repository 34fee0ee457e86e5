//! Klipper's filament switch sensors at run time (its `RunoutHelper`):
//! each sensor's switch is read between lines; filament going missing
//! while printing is a runout (the print pauses if pause_on_runout, then
//! runout_gcode runs), filament arriving while not printing an insert
//! (insert_gcode runs). No event in the first 2 s, nor within event_delay
//! of the last one, nor while a sensor is disabled (SET_FILAMENT_SENSOR
//! ENABLE=0). QUERY_FILAMENT_SENSOR reports the switch.

use core::fmt::Write;
use onechip_planner::filament_sensor::FilamentSensor;
pub use onechip_planner::filament_sensor::MAX_FILAMENT_SENSORS;
use onechip_planner::gcode::{Command, GcodeError, Line};

/// Time from start-up before the first event, s (Klipper's).
pub const START_DELAY: f64 = 2.0;

/// What a change of a switch asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FilamentEvent<'a> {
    /// Filament ran out while printing.
    Runout {
        /// Pause the print first (pause_on_runout).
        pause: bool,
        /// runout_gcode, if any.
        gcode: Option<&'a str>,
    },
    /// Filament was inserted while not printing: insert_gcode.
    Insert {
        /// insert_gcode.
        gcode: &'a str,
    },
}

/// One sensor's state.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Sensor<'a> {
    config: FilamentSensor<'a>,
    present: bool,
    enabled: bool,
}

/// Every filament switch sensor.
#[derive(Debug, Clone, PartialEq)]
pub struct FilamentSensors<'a> {
    sensors: heapless::Vec<Sensor<'a>, MAX_FILAMENT_SENSORS>,
    /// No event before this time, s.
    quiet_until: f64,
}

impl<'a> FilamentSensors<'a> {
    /// The sensors of `sensors`, started at time `start` (s).
    pub fn new(sensors: &[FilamentSensor<'a>], start: f64) -> Self {
        Self {
            sensors: sensors
                .iter()
                .map(|&config| Sensor {
                    config,
                    present: false,
                    enabled: true,
                })
                .collect(),
            quiet_until: start + START_DELAY,
        }
    }

    /// How many sensors there are.
    pub fn len(&self) -> usize {
        self.sensors.len()
    }

    /// True without sensors.
    pub fn is_empty(&self) -> bool {
        self.sensors.is_empty()
    }

    /// Reads every switch at time `now` (s); `present(i)`: sensor i's
    /// switch reads filament; `printing`: a print is running (Klipper's
    /// idle_timeout state Printing). The event a change causes, if any.
    pub fn poll(
        &mut self,
        now: f64,
        mut present: impl FnMut(usize) -> bool,
        printing: bool,
    ) -> Option<FilamentEvent<'a>> {
        let mut event = None;
        for (i, sensor) in self.sensors.iter_mut().enumerate() {
            let reads = present(i);
            if reads == sensor.present {
                continue;
            }
            sensor.present = reads;
            if event.is_some() || now < self.quiet_until || !sensor.enabled {
                continue;
            }
            let c = &sensor.config;
            event = match (reads, printing) {
                (true, false) => c.insert_gcode.map(|gcode| FilamentEvent::Insert { gcode }),
                (false, true) if c.pause_on_runout || c.runout_gcode.is_some() => {
                    Some(FilamentEvent::Runout {
                        pause: c.pause_on_runout,
                        gcode: c.runout_gcode,
                    })
                }
                _ => None,
            };
            if event.is_some() {
                self.quiet_until = now + c.event_delay;
            }
        }
        event
    }

    /// QUERY_FILAMENT_SENSOR and SET_FILAMENT_SENSOR: true if `line` was
    /// one (its reply written to `out`).
    pub fn command<'l>(
        &mut self,
        line: &Line<'l>,
        out: &mut impl Write,
    ) -> Result<bool, SensorError<'l>> {
        let Command::Extended(e) = line.command else {
            return Ok(false);
        };
        let query = e.name.eq_ignore_ascii_case("QUERY_FILAMENT_SENSOR");
        if !query && !e.name.eq_ignore_ascii_case("SET_FILAMENT_SENSOR") {
            return Ok(false);
        }
        let name = e.get("SENSOR")?.ok_or(GcodeError::Missing("SENSOR"))?;
        let sensor = self
            .sensors
            .iter_mut()
            .find(|s| s.config.name == name)
            .ok_or(SensorError::NotValid(name))?;
        if query {
            let not = if sensor.present { "" } else { "not " };
            let _ = writeln!(out, "// Filament Sensor {name}: filament {not}detected");
        } else {
            sensor.enabled = e.float("ENABLE")?.is_none_or(|v| v != 0.0);
        }
        Ok(true)
    }
}

/// Why a filament sensor command was refused.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SensorError<'l> {
    /// A parameter is missing or malformed.
    Gcode(GcodeError<'l>),
    /// `SENSOR=` names no sensor.
    NotValid(&'l str),
}

impl<'l> From<GcodeError<'l>> for SensorError<'l> {
    fn from(e: GcodeError<'l>) -> Self {
        Self::Gcode(e)
    }
}

impl core::fmt::Display for SensorError<'_> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Gcode(e) => e.fmt(f),
            Self::NotValid(name) => write!(f, "The value '{name}' is not valid for SENSOR"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sensor(pause: bool, insert: Option<&'static str>) -> FilamentSensor<'static> {
        FilamentSensor {
            name: "runout",
            section: "filament_switch_sensor runout",
            switch_pin: "PG12",
            pause_on_runout: pause,
            runout_gcode: None,
            insert_gcode: insert,
            event_delay: 3.0,
            pause_delay: 0.5,
        }
    }

    #[test]
    fn a_runout_while_printing_pauses_once_per_event_delay() {
        let mut s = FilamentSensors::new(&[sensor(true, None)], 0.0);
        // Filament seen at 1 s (quiet: start-up), runs out at 10 s.
        assert_eq!(s.poll(1.0, |_| true, true), None);
        let runout = Some(FilamentEvent::Runout {
            pause: true,
            gcode: None,
        });
        assert_eq!(s.poll(10.0, |_| false, true), runout);
        // Back and out again within event_delay: nothing.
        assert_eq!(s.poll(11.0, |_| true, true), None);
        assert_eq!(s.poll(12.0, |_| false, true), None);
        assert_eq!(s.poll(14.0, |_| true, true), None);
        assert_eq!(s.poll(14.5, |_| false, true), runout);
        // Not printing: no runout.
        assert_eq!(s.poll(20.0, |_| true, false), None);
        assert_eq!(s.poll(30.0, |_| false, false), None);
    }

    #[test]
    fn inserts_run_insert_gcode_when_idle_and_disabled_sensors_say_nothing() {
        let mut s = FilamentSensors::new(&[sensor(false, Some("M117 loaded"))], 0.0);
        assert_eq!(
            s.poll(5.0, |_| true, false),
            Some(FilamentEvent::Insert {
                gcode: "M117 loaded"
            })
        );
        let line = onechip_planner::gcode::parse("SET_FILAMENT_SENSOR SENSOR=runout ENABLE=0")
            .expect("parses");
        let mut out = heapless::String::<64>::new();
        assert_eq!(s.command(&line, &mut out), Ok(true));
        assert_eq!(s.poll(10.0, |_| false, true), None);
        let line =
            onechip_planner::gcode::parse("QUERY_FILAMENT_SENSOR SENSOR=runout").expect("parses");
        assert_eq!(s.command(&line, &mut out), Ok(true));
        assert_eq!(out, "// Filament Sensor runout: filament not detected\n");
    }
}
