//! Klipper's `[output_pin NAME]` (a pin G-code sets with `SET_PIN
//! PIN=NAME VALUE=…`, steady or PWM) and `[static_digital_output NAME]`
//! (pins driven high, or low if written `!`, from start-up on), with
//! Klipper's option names, defaults and bounds.

use crate::reader::{Errors, Read, Reader};
use onechip_config::{Bounds, Config};

/// Most `[output_pin]` sections.
pub const MAX_OUTPUT_PINS: usize = 8;
/// Most pins all `[static_digital_output]` sections list together.
pub const MAX_STATIC_PINS: usize = 16;
/// Longest PWM cycle and maximum_mcu_duration, s (Klipper's
/// MAX_SCHEDULE_TIME).
pub const MAX_SCHEDULE_TIME: f64 = 5.0;
/// Shortest maximum_mcu_duration, s.
pub const MIN_MCU_DURATION: f64 = 0.500;

/// An `[output_pin NAME]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutputPin<'a> {
    /// NAME, as SET_PIN's `PIN=` names it.
    pub name: &'a str,
    /// The section as written (`output_pin beeper`).
    pub section: &'a str,
    /// pin, as written (`!` inverts).
    pub pin: &'a str,
    /// `pwm`: values between 0 and `scale`; otherwise on or off.
    pub pwm: bool,
    /// `hardware_pwm`: a hardware PWM channel.
    pub hardware_pwm: bool,
    /// `cycle_time`: the PWM cycle, s (0 for an on/off pin).
    pub cycle_time: f64,
    /// `scale`: the VALUE that means fully on (PWM pins; 1 otherwise).
    pub scale: f64,
    /// `value` at start-up, 0..1 of full scale.
    pub value: f64,
    /// `shutdown_value`, 0..1 of full scale.
    pub shutdown_value: f64,
    /// `maximum_mcu_duration`, s (0: none): the MCU shuts down if no
    /// update arrives for this long while the pin is not at its
    /// shutdown value; the host repeats the value to keep it alive.
    pub max_duration: f64,
}

/// One pin of a `[static_digital_output]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StaticPin<'a> {
    /// The section as written.
    pub section: &'a str,
    /// The pin, as written (`!` drives it low).
    pub pin: &'a str,
}

/// The NAME of a `[PREFIX NAME]` section, if `section` is one.
pub fn named<'s>(section: &'s str, prefix: &str) -> Option<&'s str> {
    let rest = section.strip_prefix(prefix)?;
    let name = rest.trim();
    (rest.starts_with(char::is_whitespace) && !name.is_empty()).then_some(name)
}

/// The items of a comma-separated list option (`pins`, `aliases`,
/// `heater`), over several lines if need be: comments (`#` or `;` to the
/// line's end) and empty items left out.
pub fn list_items(text: &str) -> ListItems<'_> {
    ListItems { rest: text }
}

/// The iterator [`list_items`] returns.
#[derive(Debug, Clone)]
pub struct ListItems<'a> {
    rest: &'a str,
}

impl<'a> Iterator for ListItems<'a> {
    type Item = &'a str;

    fn next(&mut self) -> Option<&'a str> {
        while !self.rest.is_empty() {
            let rest = self.rest;
            // Every delimiter is one byte: slicing next to it is safe.
            let end = rest.find([',', '\n', '#', ';']).unwrap_or(rest.len());
            let item = rest[..end].trim();
            self.rest = match rest.as_bytes().get(end) {
                Some(b'#' | b';') => rest[end..].find('\n').map_or("", |n| &rest[end + n + 1..]),
                Some(_) => &rest[end + 1..],
                None => "",
            };
            if !item.is_empty() {
                return Some(item);
            }
        }
        None
    }
}

/// Each section name of `config` once, in file order (a section written
/// twice is one section).
pub fn unique_sections<'c, 'a>(config: &'c Config<'a>) -> impl Iterator<Item = &'a str> + 'c {
    config
        .section_names()
        .enumerate()
        .filter(move |&(i, name)| !config.section_names().take(i).any(|n| n == name))
        .map(|(_, name)| name)
}

/// Reads an `[output_pin NAME]` section.
#[inline(never)]
pub(crate) fn read_output_pin<'a>(section: &Reader<'_, '_, 'a>) -> Read<OutputPin<'a>> {
    let written = section.name_in_file();
    let name = named(written, "output_pin").unwrap_or(written);
    let pin = section.get("pin")?;
    let pwm = section.get_bool("pwm", false)?;
    let (cycle_time, hardware_pwm, scale) = if pwm {
        let cycle_time = section.float(
            "cycle_time",
            0.100,
            Bounds {
                above: Some(0.0),
                maxval: Some(MAX_SCHEDULE_TIME),
                ..Bounds::NONE
            },
        )?;
        let hardware_pwm = section.get_bool("hardware_pwm", false)?;
        (
            cycle_time,
            hardware_pwm,
            section.float("scale", 1.0, Bounds::POSITIVE)?,
        )
    } else {
        (0.0, false, 1.0)
    };
    let fraction = |option| {
        let bounds = Bounds {
            minval: Some(0.0),
            maxval: Some(scale),
            ..Bounds::NONE
        };
        section.float(option, 0.0, bounds).map(|v| v / scale)
    };
    let max_duration = match section.get_float_opt(
        "maximum_mcu_duration",
        Bounds {
            maxval: Some(MAX_SCHEDULE_TIME),
            ..Bounds::NONE
        },
    )? {
        Some(d) if d != 0.0 && d < MIN_MCU_DURATION => {
            return Err(section.error_for("maximum_mcu_duration", "is below its minimum"));
        }
        Some(d) => d.max(0.0),
        None => 0.0,
    };
    let (value, shutdown_value) = (fraction("value")?, fraction("shutdown_value")?);
    if max_duration > 0.0 && value != shutdown_value {
        return Err(section.error_for(
            "maximum_mcu_duration",
            "needs value equal to shutdown_value (as Klipper)",
        ));
    }
    Ok(OutputPin {
        name,
        section: written,
        pin,
        pwm,
        hardware_pwm,
        cycle_time,
        scale,
        value,
        shutdown_value,
        max_duration,
    })
}

/// Reads every `[static_digital_output]` section's `pins` into `out`;
/// more than [`MAX_STATIC_PINS`] in all is an error.
#[inline(never)]
pub(crate) fn read_static_outputs<'c, 'a>(
    config: &'c Config<'a>,
    errors: &Errors<'c>,
    out: &mut heapless::Vec<StaticPin<'a>, MAX_STATIC_PINS>,
) -> Read<()> {
    for name in unique_sections(config) {
        if named(name, "static_digital_output").is_none() {
            continue;
        }
        let Some(section) = config.section(name) else {
            continue;
        };
        let section = Reader::new(section, errors);
        let pins = section.get("pins")?;
        for pin in list_items(pins) {
            out.push(StaticPin {
                section: section.name_in_file(),
                pin,
            })
            .map_err(|_| {
                section.error_for("pins", "lists more pins than onechip holds (16 in all)")
            })?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;

    /// Reads the `[output_pin]` section `name` of `config`.
    fn output_pin<'a>(
        config: &Config<'a>,
        name: &str,
    ) -> Result<OutputPin<'a>, std::string::String> {
        let section = config.section(name).expect("section");
        Errors::run(|errors| read_output_pin(&Reader::new(section, errors)))
            .map_err(|e| std::format!("{e}"))
    }

    #[test]
    fn output_pins_read_with_klippers_defaults_and_scale() {
        let text = "[output_pin beeper]\npin: PE8\n\
            [output_pin current]\npin: PA5\npwm: True\nscale: 2.0\nvalue: 1.5\nshutdown_value: 0.5\n\
            cycle_time: 0.000030\nhardware_pwm: True\n";
        let config = Config::parse("printer.cfg", text).expect("parses");
        let beeper = output_pin(&config, "output_pin beeper").expect("reads");
        assert_eq!(
            (beeper.name, beeper.pwm, beeper.value),
            ("beeper", false, 0.0)
        );
        assert_eq!((beeper.cycle_time, beeper.max_duration), (0.0, 0.0));
        let current = output_pin(&config, "output_pin current").expect("reads");
        assert_eq!((current.value, current.shutdown_value), (0.75, 0.25));
        assert!(current.hardware_pwm && current.pwm);
        let over = "[output_pin x]\npin: PA5\npwm: 1\nvalue: 1.5\n";
        let config = Config::parse("printer.cfg", over).expect("parses");
        let e = output_pin(&config, "output_pin x").expect_err("above scale");
        assert_eq!(
            e,
            "printer.cfg:4: option 'value' in section 'output_pin x' is above its maximum"
        );
    }

    #[test]
    fn static_outputs_list_every_pin() {
        let text =
            "[static_digital_output leds]\npins: PA1, !PA2,PA3\n  # more\n  PB1, PB2, ; last\n";
        let config = Config::parse("printer.cfg", text).expect("parses");
        let mut pins = heapless::Vec::new();
        Errors::run(|errors| read_static_outputs(&config, errors, &mut pins)).expect("reads");
        let written: heapless::Vec<&str, 8> = pins.iter().map(|p| p.pin).collect();
        assert_eq!(written.as_slice(), ["PA1", "!PA2", "PA3", "PB1", "PB2"]);
    }
}
