//! Klipper's named fans: `[heater_fan NAME]` (on while its heaters are
//! hot or have a target), `[controller_fan NAME]` (on while steppers are
//! enabled or heaters have a target, then `idle_speed` for `idle_timeout`
//! s) and `[fan_generic NAME]` (set by `SET_FAN_SPEED FAN=NAME
//! SPEED=…`). Each has every `[fan]` option ([`crate::thermal::Fan`]).

use crate::output_pin::named;
use crate::thermal::{self, Fan};
use onechip_config::{Bounds, Config, ConfigError, Section};

/// Most named fans (all kinds together).
pub const MAX_FANS: usize = 8;

/// `[0, 1]`.
const UNIT: Bounds = Bounds {
    minval: Some(0.0),
    maxval: Some(1.0),
    above: None,
    below: None,
};

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
pub const PREFIXES: [&str; 3] = ["heater_fan", "controller_fan", "fan_generic"];

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
    section: &Section<'c, '_>,
    option: &'c str,
    list: &str,
    names: &[&str],
) -> Result<u32, ConfigError<'c>> {
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

/// Reads the named fan `section`; `heaters` and `steppers` are the
/// machine's heater and stepper names, in order.
#[inline(never)]
pub fn read<'c, 'a>(
    config: &Config<'a>,
    section: &Section<'c, 'a>,
    heaters: &[&str],
    steppers: &[&str],
) -> Result<NamedFan<'a>, ConfigError<'c>> {
    let written = section.name_in_file();
    let (kind, name) = PREFIXES
        .iter()
        .find_map(|p| named(written, p).map(|n| (*p, n)))
        .unwrap_or(("fan_generic", written));
    let heater_list = |section: &Section<'c, 'a>| {
        let list = section.get_opt("heater").unwrap_or("extruder");
        bits(config, section, "heater", list, heaters).map(|m| m as u8)
    };
    let (role, shutdown) = match kind {
        "heater_fan" => (
            FanRole::Heater {
                heaters: heater_list(section)?,
                heater_temp: section.get_float("heater_temp", Some(50.0), Bounds::NONE)?,
                fan_speed: section.get_float("fan_speed", Some(1.0), UNIT)?,
            },
            1.0,
        ),
        "controller_fan" => {
            let fan_speed = section.get_float("fan_speed", Some(1.0), UNIT)?;
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
                    idle_speed: section.get_float("idle_speed", Some(fan_speed), UNIT)?,
                    idle_timeout: u32::try_from(idle_timeout).unwrap_or(u32::MAX),
                },
                0.0,
            )
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

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;

    const HEATERS: [&str; 2] = ["extruder", "heater_bed"];
    const STEPPERS: [&str; 4] = ["stepper_x", "stepper_y", "stepper_z", "extruder"];

    fn fan(text: &str, section: &str) -> Result<NamedFan<'static>, std::string::String> {
        let text: &'static str = std::boxed::Box::leak(text.into());
        let config: &'static Config<'static> = std::boxed::Box::leak(std::boxed::Box::new(
            Config::parse("printer.cfg", text).expect("parses"),
        ));
        let section = config.section(section).expect("section");
        read(config, &section, &HEATERS, &STEPPERS).map_err(|e| std::format!("{e}"))
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
