//! Klipper's named fans: `[heater_fan NAME]` (on while its heaters are
//! hot or have a target), `[controller_fan NAME]` (on while steppers are
//! enabled or heaters have a target, then `idle_speed` for `idle_timeout`
//! s) and `[fan_generic NAME]` (set by `SET_FAN_SPEED FAN=NAME
//! SPEED=…`). Each has every `[fan]` option ([`crate::thermal::Fan`]).

use crate::output_pin::named;
use crate::reader::{Read, Reader};
use crate::sensor_section::{self, MAX_SENSORS, SensorSection};
use crate::thermal::{self, Fan};
use onechip_config::{Bounds, Config};

/// Most named fans (all kinds together).
pub const MAX_FANS: usize = 8;

/// What turns a named fan on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FanRole {
    /// `[heater_fan]`: `fan_speed` while any of `heaters` has a target or
    /// is above `heater_temp`; checked once a second.
    Heater {
        /// Bit i: the machine's heater i.
        heaters: u8,
        /// heater_temp, °C.
        heater_temp: f64,
        /// fan_speed, 0..1.
        fan_speed: f64,
    },
    /// `[controller_fan]`: `fan_speed` while a stepper is enabled or any
    /// of `heaters` has a target; then `idle_speed` for `idle_timeout`
    /// s; checked once a second.
    Controller {
        /// Bit i: the machine's heater i.
        heaters: u8,
        /// Bit i: the machine's stepper i (`stepper`; default all).
        steppers: u16,
        /// fan_speed, 0..1.
        fan_speed: f64,
        /// idle_speed, 0..1.
        idle_speed: f64,
        /// idle_timeout, s.
        idle_timeout: u32,
    },
    /// `[fan_generic]`: set by G-code only.
    Generic,
    /// `[temperature_fan]`: its own sensor's temperature held at a
    /// target by cooling; its control is entry `.0` of the temperature
    /// fans ([`crate::accessories::Accessories::cooling`]).
    Temperature(u8),
}

/// Most `[temperature_fan]`s.
pub const MAX_COOLING: usize = 2;

/// A `[temperature_fan]`'s control, with Klipper's options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TemperatureFan {
    /// Its fan: index among the named fans.
    pub fan: usize,
    /// Its sensor: index into the machine's temperature sensors.
    pub sensor: usize,
    /// target_temp, °C.
    pub target: f64,
    /// min_temp and max_temp, °C (the range a target may have).
    pub min_temp: f64,
    /// max_temp, °C.
    pub max_temp: f64,
    /// min_speed, 0..1.
    pub min_speed: f64,
    /// max_speed, 0..1.
    pub max_speed: f64,
    /// `control`.
    pub law: CoolingLaw,
}

/// How a temperature fan's speed follows its temperature.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CoolingLaw {
    /// `watermark`: max_speed from target + max_delta up, off from
    /// target − max_delta down.
    Watermark {
        /// max_delta, °C.
        max_delta: f64,
    },
    /// `pid`: the gains as Klipper uses them (printer.cfg's over 255).
    Pid {
        /// pid_Kp / 255.
        kp: f64,
        /// pid_Ki / 255.
        ki: f64,
        /// pid_Kd / 255.
        kd: f64,
        /// pid_deriv_time, s.
        deriv_time: f64,
    },
}

/// A named fan.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NamedFan<'a> {
    /// NAME (`SET_FAN_SPEED FAN=NAME`).
    pub name: &'a str,
    /// The section as written (`heater_fan hotend_fan`).
    pub section: &'a str,
    /// The fan options.
    pub fan: Fan<'a>,
    /// What drives it.
    pub role: FanRole,
}

/// The section kinds this module reads, by prefix.
pub const PREFIXES: [&str; 4] = [
    "heater_fan",
    "controller_fan",
    "fan_generic",
    "temperature_fan",
];

/// True if `section` is a named fan this module reads.
pub fn is_section(section: &str) -> bool {
    PREFIXES.iter().any(|p| named(section, p).is_some())
}

/// The bits of the names in the comma-separated `list` among `names`.
/// A name not among them is an error naming `option`, unless `config`
/// has a section of that name (a heater or stepper onechip does not drive
/// yet, itself reported unsupported): it has no bit.
fn bits<'c>(
    config: &Config<'_>,
    section: &Reader<'_, 'c, '_>,
    option: &'c str,
    list: &str,
    names: &[&str],
) -> Read<u32> {
    let mut mask = 0;
    for item in crate::output_pin::list_items(list) {
        match names.iter().position(|n| *n == item) {
            Some(index) => mask |= 1 << index,
            None if config.has_section(item) => {}
            None => return Err(section.error_for(option, "names one that is not configured")),
        }
    }
    Ok(mask)
}

/// What a temperature fan adds besides its fan: its sensor and control.
pub struct CoolingTables<'t, 'a> {
    /// The machine's temperature sensors.
    pub sensors: &'t mut heapless::Vec<SensorSection<'a>, MAX_SENSORS>,
    /// The temperature fans' controls.
    pub cooling: &'t mut heapless::Vec<TemperatureFan, MAX_COOLING>,
    /// The index the fan read will have among the named fans.
    pub fan: usize,
}

/// Reads the named fan `section`; `heaters` and `steppers` are the
/// machine's heater and stepper names, in order; a temperature fan's
/// sensor and control join `tables`.
#[inline(never)]
pub(crate) fn read<'c, 'a>(
    config: &'c Config<'a>,
    section: &Reader<'_, 'c, 'a>,
    heaters: &[&str],
    steppers: &[&str],
    tables: CoolingTables<'_, 'a>,
) -> Read<NamedFan<'a>> {
    let written = section.name_in_file();
    let (kind, name) = PREFIXES
        .iter()
        .find_map(|p| named(written, p).map(|n| (*p, n)))
        .unwrap_or(("fan_generic", written));
    let heater_list = |section: &Reader<'_, 'c, 'a>| {
        let list = section.get_opt("heater").unwrap_or("extruder");
        bits(config, section, "heater", list, heaters).map(|m| m as u8)
    };
    let (role, shutdown) = match kind {
        "heater_fan" => (
            FanRole::Heater {
                heaters: heater_list(section)?,
                heater_temp: section.float("heater_temp", 50.0, Bounds::NONE)?,
                fan_speed: section.float("fan_speed", 1.0, Bounds::UNIT)?,
            },
            1.0,
        ),
        "controller_fan" => {
            let fan_speed = section.float("fan_speed", 1.0, Bounds::UNIT)?;
            let steppers = match section.get_opt("stepper") {
                Some(list) => bits(config, section, "stepper", list, steppers)? as u16,
                None => u16::MAX,
            };
            let idle_timeout = section.get_int("idle_timeout", Some(30), Some(0))?;
            (
                FanRole::Controller {
                    heaters: heater_list(section)?,
                    steppers,
                    fan_speed,
                    idle_speed: section.float("idle_speed", fan_speed, Bounds::UNIT)?,
                    idle_timeout: u32::try_from(idle_timeout).unwrap_or(u32::MAX),
                },
                0.0,
            )
        }
        "temperature_fan" => {
            let mut control = read_temperature_fan(config, section, tables.sensors)?;
            control.fan = tables.fan;
            let index = tables.cooling.len() as u8;
            tables
                .cooling
                .push(control)
                .map_err(|_| section.error_for("pin", "is one temperature fan too many"))?;
            (FanRole::Temperature(index), 1.0)
        }
        _ => (FanRole::Generic, 0.0),
    };
    Ok(NamedFan {
        name,
        section: written,
        fan: thermal::read_fan_options(section, shutdown)?,
        role,
    })
}

/// A `[temperature_fan]`'s sensor (min_temp and max_temp required) and
/// control, with Klipper's defaults.
fn read_temperature_fan<'c, 'a>(
    config: &'c Config<'a>,
    section: &Reader<'_, 'c, 'a>,
    sensors: &mut heapless::Vec<SensorSection<'a>, MAX_SENSORS>,
) -> Read<TemperatureFan> {
    let sensor = sensor_section::read(config, section, (None, None))?;
    let (min_temp, max_temp) = (sensor.min_temp, sensor.max_temp);
    let index = sensors.len();
    sensors
        .push(sensor)
        .map_err(|_| section.error_for("sensor_type", "too many temperature sensors"))?;
    let max_speed = section.float("max_speed", 1.0, Bounds::UNIT_ABOVE_ZERO)?;
    let min_speed = section.float("min_speed", 0.3, Bounds::UNIT)?;
    let target = section.float(
        "target_temp",
        if max_temp > 40.0 { 40.0 } else { max_temp },
        Bounds {
            minval: Some(min_temp),
            maxval: Some(max_temp),
            ..Bounds::NONE
        },
    )?;
    let law = match section.get_choice("control", &["watermark", "pid"], None)? {
        "pid" => CoolingLaw::Pid {
            kp: section.required_float("pid_kp", Bounds::NONE)? / PID_PARAM_BASE,
            ki: section.required_float("pid_ki", Bounds::NONE)? / PID_PARAM_BASE,
            kd: section.required_float("pid_kd", Bounds::NONE)? / PID_PARAM_BASE,
            deriv_time: section.float("pid_deriv_time", 2.0, Bounds::POSITIVE)?,
        },
        _ => CoolingLaw::Watermark {
            max_delta: section.float("max_delta", 2.0, Bounds::POSITIVE)?,
        },
    };
    Ok(TemperatureFan {
        fan: 0,
        sensor: index,
        target,
        min_temp,
        max_temp,
        min_speed,
        max_speed,
        law,
    })
}

/// Klipper's PID gains are written 255 times what acts on 0..1.
const PID_PARAM_BASE: f64 = 255.0;

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::reader::Errors;

    const HEATERS: [&str; 2] = ["extruder", "heater_bed"];

    std::thread_local! {
        /// The temperature fan control the last [`fan`] read, if any.
        static COOLING: std::cell::RefCell<Option<TemperatureFan>> =
            const { std::cell::RefCell::new(None) };
    }
    const STEPPERS: [&str; 4] = ["stepper_x", "stepper_y", "stepper_z", "extruder"];

    fn fan(text: &str, section: &str) -> Result<NamedFan<'static>, std::string::String> {
        let text: &'static str = std::boxed::Box::leak(text.into());
        let config: &'static Config<'static> = std::boxed::Box::leak(std::boxed::Box::new(
            Config::parse("printer.cfg", text).expect("parses"),
        ));
        let section = config.section(section).expect("section");
        let (mut sensors, mut cooling) = (heapless::Vec::new(), heapless::Vec::new());
        let tables = CoolingTables {
            sensors: &mut sensors,
            cooling: &mut cooling,
            fan: 0,
        };
        let fan = Errors::run(|errors| {
            let section = Reader::new(section, errors);
            read(config, &section, &HEATERS, &STEPPERS, tables)
        })
        .map_err(|e| std::format!("{e}"))?;
        COOLING.with(|c| *c.borrow_mut() = cooling.first().copied());
        Ok(fan)
    }

    #[test]
    fn named_fans_read_with_klippers_defaults() {
        let heater = fan(
            "[heater_fan hotend_fan]\npin: PE5\n",
            "heater_fan hotend_fan",
        )
        .expect("reads");
        assert_eq!(heater.name, "hotend_fan");
        assert_eq!(
            heater.role,
            FanRole::Heater {
                heaters: 0b01,
                heater_temp: 50.0,
                fan_speed: 1.0
            }
        );
        // A heater fan runs at full speed when the printer shuts down.
        assert_eq!(heater.fan.shutdown_speed, 1.0);
        let controller = fan(
            "[controller_fan board]\npin: PD12\nheater: heater_bed, extruder\nstepper: stepper_z\n\
             idle_speed: 0.5\n",
            "controller_fan board",
        )
        .expect("reads");
        assert_eq!(
            controller.role,
            FanRole::Controller {
                heaters: 0b11,
                steppers: 0b100,
                fan_speed: 1.0,
                idle_speed: 0.5,
                idle_timeout: 30
            }
        );
        assert_eq!(controller.fan.shutdown_speed, 0.0);
        let generic = fan(
            "[fan_generic aux]\npin: PD13\nmax_power: 0.5\n",
            "fan_generic aux",
        )
        .expect("reads");
        assert_eq!(
            (generic.role, generic.fan.max_power),
            (FanRole::Generic, 0.5)
        );
    }

    #[test]
    fn a_temperature_fan_reads_its_sensor_and_control_with_klippers_defaults() {
        let f = fan(
            "[temperature_fan board]\npin: PD12\nsensor_type: temperature_mcu\nmin_temp: 0\n\
             max_temp: 90\ncontrol: pid\npid_Kp: 2\npid_Ki: 5\npid_Kd: 0.5\n",
            "temperature_fan board",
        )
        .expect("reads");
        assert_eq!(f.role, FanRole::Temperature(0));
        let t = COOLING.with(|c| c.borrow().expect("a control"));
        assert_eq!(
            (t.sensor, t.target, t.min_temp, t.max_temp),
            (0, 40.0, 0.0, 90.0)
        );
        assert_eq!((t.min_speed, t.max_speed), (0.3, 1.0));
        assert_eq!(
            t.law,
            CoolingLaw::Pid {
                kp: 2.0 / 255.0,
                ki: 5.0 / 255.0,
                kd: 0.5 / 255.0,
                deriv_time: 2.0
            }
        );
        // Full speed at shutdown, as Klipper's temperature fans.
        assert_eq!(f.fan.shutdown_speed, 1.0);
        let low = fan(
            "[temperature_fan t]\npin: PD12\nsensor_type: temperature_mcu\nmin_temp: 0\n\
             max_temp: 30\ncontrol: watermark\n",
            "temperature_fan t",
        )
        .expect("reads");
        assert_eq!(low.role, FanRole::Temperature(0));
        let t = COOLING.with(|c| c.borrow().expect("a control"));
        assert_eq!(
            (t.target, t.law),
            (30.0, CoolingLaw::Watermark { max_delta: 2.0 })
        );
        let e = fan(
            "[temperature_fan t]\npin: PD12\nsensor_type: temperature_mcu\nmax_temp: 30\n\
             control: watermark\n",
            "temperature_fan t",
        )
        .expect_err("min_temp is required");
        assert!(e.contains("min_temp"), "{e}");
    }

    #[test]
    fn an_unknown_heater_names_the_option() {
        let e = fan(
            "[heater_fan f]\npin: PE5\nheater: extruder1\n",
            "heater_fan f",
        )
        .expect_err("refused");
        assert_eq!(
            e,
            "printer.cfg:3: option 'heater' in section 'heater_fan f' names one that is not configured"
        );
    }
}
