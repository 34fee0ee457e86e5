//! The fans, pins and sensors around the motion and the heaters:
//! `[board_pins]`, `[heater_fan]`, `[controller_fan]`, `[fan_generic]`,
//! `[output_pin]`, `[static_digital_output]` and
//! `[filament_switch_sensor]`, read together for [`crate::machine`].

use crate::board_pins::{self, BoardPins};
use crate::fan_sections::{self, CoolingTables, MAX_COOLING, MAX_FANS, NamedFan, TemperatureFan};
use crate::filament_sensor::{self, FilamentSensor, MAX_FILAMENT_SENSORS};
use crate::output_pin::{self, MAX_OUTPUT_PINS, MAX_STATIC_PINS, OutputPin, StaticPin};
use crate::reader::{Errors, Read, Reader};
use crate::sensor_section::{MAX_SENSORS, SensorSection};
use onechip_config::Config;

/// Most outputs all these sections drive together (fans, output pins,
/// static pins).
pub const MAX_OUTPUTS: usize = 24;

/// Everything this module reads from printer.cfg.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Accessories<'a> {
    /// Pin aliases.
    pub board_pins: BoardPins<'a>,
    /// Named fans, in printer.cfg's order.
    pub fans: heapless::Vec<NamedFan<'a>, MAX_FANS>,
    /// The temperature fans' controls, in printer.cfg's order.
    pub cooling: heapless::Vec<TemperatureFan, MAX_COOLING>,
    /// `[output_pin]`s, in printer.cfg's order.
    pub output_pins: heapless::Vec<OutputPin<'a>, MAX_OUTPUT_PINS>,
    /// Every `[static_digital_output]` pin.
    pub static_pins: heapless::Vec<StaticPin<'a>, MAX_STATIC_PINS>,
    /// Filament switch sensors.
    pub filament_sensors: heapless::Vec<FilamentSensor<'a>, MAX_FILAMENT_SENSORS>,
}

/// True if `section` is read by [`Accessories::read`].
pub fn is_section(section: &str) -> bool {
    board_pins::is_section(section)
        || fan_sections::is_section(section)
        || output_pin::named(section, "output_pin").is_some()
        || output_pin::named(section, "static_digital_output").is_some()
        || filament_sensor::is_section(section)
}

impl<'a> Accessories<'a> {
    /// Reads them from `config`; `heaters` and `steppers` are the
    /// machine's heater and stepper names, in order; temperature fans'
    /// sensors join `sensors`. A section past a table's size is an error
    /// naming it.
    // Out of line: see `Machine::from_config_in`.
    #[inline(never)]
    pub(crate) fn read<'c>(
        config: &'c Config<'a>,
        errors: &Errors<'c>,
        heaters: &[&str],
        steppers: &[&str],
        sensors: &mut heapless::Vec<SensorSection<'a>, MAX_SENSORS>,
    ) -> Read<Self> {
        let mut this = Self {
            board_pins: BoardPins::read(config, errors)?,
            ..Self::default()
        };
        output_pin::read_static_outputs(config, errors, &mut this.static_pins)?;
        for name in output_pin::unique_sections(config) {
            let Some(section) = config.section(name) else {
                continue;
            };
            let section = Reader::new(section, errors);
            let full = "is in one section too many of its kind for onechip";
            if fan_sections::is_section(name) {
                let tables = CoolingTables {
                    sensors: &mut *sensors,
                    cooling: &mut this.cooling,
                    fan: this.fans.len(),
                };
                let fan = fan_sections::read(config, &section, heaters, steppers, tables)?;
                this.fans
                    .push(fan)
                    .map_err(|_| section.error_for("pin", full))?;
            } else if output_pin::named(name, "output_pin").is_some() {
                let pin = output_pin::read_output_pin(&section)?;
                this.output_pins
                    .push(pin)
                    .map_err(|_| section.error_for("pin", full))?;
            } else if filament_sensor::is_section(name) {
                let sensor = filament_sensor::read(&section)?;
                this.filament_sensors
                    .push(sensor)
                    .map_err(|_| section.error_for("switch_pin", full))?;
            }
        }
        if this.output_count() > MAX_OUTPUTS {
            let last = this.static_pins.last().map(|p| (p.section, "pins"));
            let last = last.or(this.output_pins.last().map(|p| (p.section, "pin")));
            let (section, option) = last
                .or(this.fans.last().map(|f| (f.section, "pin")))
                .unwrap_or(("", "pin"));
            if let Some(s) = config.section(section) {
                return Err(Reader::new(s, errors).error_for(
                    option,
                    "is one output too many: onechip drives at most 24 fans and pins besides [fan]",
                ));
            }
        }
        Ok(this)
    }

    /// Outputs these sections drive: fans, output pins, static pins.
    pub fn output_count(&self) -> usize {
        self.fans.len() + self.output_pins.len() + self.static_pins.len()
    }

    /// Every pin these sections use: `(section, option, pin as written)`.
    pub fn pins(&self) -> impl Iterator<Item = (&'a str, &'static str, &'a str)> + '_ {
        let fans = self.fans.iter().map(|f| (f.section, "pin", f.fan.pin));
        let outputs = self.output_pins.iter().map(|p| (p.section, "pin", p.pin));
        let statics = self.static_pins.iter().map(|p| (p.section, "pins", p.pin));
        let sensors = self
            .filament_sensors
            .iter()
            .map(|s| (s.section, "switch_pin", s.switch_pin));
        fans.chain(outputs).chain(statics).chain(sensors)
    }
}
