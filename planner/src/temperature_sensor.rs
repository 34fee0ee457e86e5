//! A heater's temperature sensor, as its `sensor_type` names it: one of
//! Klipper's built-in thermistors or tables, or a custom `[thermistor
//! NAME]` or `[adc_temperature NAME]` section (which wins over a built-in
//! type of the same name, as the section is read first in Klipper). The
//! sensor converts an ADC reading (fraction of full scale) to °C for the
//! heater control, and °C back to a reading for the MCU's range check and
//! the simulator's thermal plant.
//!
//! Klipper's SPI converters (MAX6675, MAX31855, MAX31856, MAX31865) are
//! [`crate::spi_temperature`]'s: their "reading" is the chip's raw
//! register value instead of a fraction of an ADC's full scale. I2C and
//! 1-wire sensors and (on a heater) the MCU's internal sensor are refused
//! with a config error naming `sensor_type`.

use crate::adc_temperature::{self, Column, LinearSensor, Samples};
use crate::reader::{Errors, Read, Reader};
use crate::spi_temperature::{self, Chip, SpiBus, SpiSensor};
use crate::thermistor::{self, Curve, Thermistor};
use onechip_config::Config;

/// A sensor read through an ADC input, or an SPI converter chip.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TemperatureSensor {
    /// A thermistor behind a pullup resistor.
    Thermistor(Thermistor),
    /// A table of volts or Ω, interpolated.
    Linear(LinearSensor),
    /// An SPI converter: its readings are the chip's raw register values
    /// (as `f64`), not fractions of an ADC's full scale.
    Spi(SpiSensor),
}

impl TemperatureSensor {
    /// Temperature at ADC reading `adc` (fraction of full scale; an SPI
    /// chip's raw value), °C.
    pub fn temperature(&self, adc: f64) -> f64 {
        match self {
            Self::Thermistor(t) => t.temperature(adc),
            Self::Linear(l) => l.temperature(adc),
            Self::Spi(s) => s.temperature(adc as u32),
        }
    }

    /// ADC reading (fraction of full scale; an SPI chip's raw value) at
    /// temperature `celsius`, °C.
    pub fn adc(&self, celsius: f64) -> f64 {
        match self {
            Self::Thermistor(t) => t.adc(celsius),
            Self::Linear(l) => l.adc(celsius),
            Self::Spi(s) => f64::from(s.raw(celsius)),
        }
    }

    /// The SPI chip, if the sensor is one.
    pub fn spi(&self) -> Option<&SpiSensor> {
        match self {
            Self::Spi(s) => Some(s),
            _ => None,
        }
    }
}

/// What a `sensor_type` names: a thermistor curve, or a table.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Definition {
    Thermistor(Curve),
    Table(Samples, Column),
}

/// The kinds of sections that define sensor types.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Thermistor,
    AdcTemperature,
}

/// The kind and the sensor name of a `[thermistor NAME]` or
/// `[adc_temperature NAME]` section.
fn definition_name(section: &str) -> Option<(Kind, &str)> {
    let (kind, name) = section.split_once(' ')?;
    let kind = match kind {
        "thermistor" => Kind::Thermistor,
        "adc_temperature" => Kind::AdcTemperature,
        _ => return None,
    };
    let name = name.trim();
    (!name.is_empty()).then_some((kind, name))
}

/// True if `section` defines sensor types: `[thermistor NAME]`,
/// `[adc_temperature NAME]`, or Klipper's bare `[adc_temperature]` (which
/// loads the built-in tables, always there in onechip).
pub fn is_definition_section(section: &str) -> bool {
    section == "adc_temperature" || definition_name(section).is_some()
}

/// Reads the definition section `name`.
fn read_definition<'c>(
    config: &'c Config<'_>,
    errors: &Errors<'c>,
    name: &'c str,
    kind: Kind,
) -> Read<Option<Definition>> {
    let Some(section) = config.section(name) else {
        return Ok(None);
    };
    let section = Reader::new(section, errors);
    Ok(Some(match kind {
        Kind::Thermistor => Definition::Thermistor(thermistor::read_section(&section)?),
        Kind::AdcTemperature => {
            let (samples, column) = adc_temperature::read_section(&section)?;
            Definition::Table(samples, column)
        }
    }))
}

/// Checks every `[thermistor NAME]` and `[adc_temperature NAME]` section,
/// used by a heater or not (Klipper reads them all).
pub(crate) fn read_definitions<'c>(config: &'c Config<'_>, errors: &Errors<'c>) -> Read<()> {
    for section in config.section_names() {
        if let Some((kind, _)) = definition_name(section) {
            read_definition(config, errors, section, kind)?;
        }
    }
    Ok(())
}

/// The definition of sensor type `name`: the last section defining it,
/// else the built-in type.
fn find<'c>(config: &'c Config<'_>, errors: &Errors<'c>, name: &str) -> Read<Option<Definition>> {
    let custom = config
        .section_names()
        .filter_map(|s| {
            definition_name(s)
                .filter(|(_, n)| *n == name)
                .map(|(k, _)| (s, k))
        })
        .last();
    if let Some((section, kind)) = custom {
        return read_definition(config, errors, section, kind);
    }
    Ok(thermistor::built_in(name)
        .map(Definition::Thermistor)
        .or_else(|| adc_temperature::built_in(name).map(|(s, c)| Definition::Table(s, c))))
}

/// The index of `name` in `names` (kept out of line: a lookup in a
/// constant list would otherwise be unrolled into one comparison each).
#[inline(never)]
pub(crate) fn position(names: &[&str], name: &str) -> Option<usize> {
    names.iter().position(|n| *n == name)
}

/// Why onechip refuses sensor type `name`.
fn unsupported(name: &str) -> &'static str {
    if name == "temperature_mcu" {
        "is the MCU's own sensor, which onechip does not read yet"
    } else {
        "is not a sensor type onechip knows (no I2C or 1-wire sensors yet)"
    }
}

/// Reads the sensor of the heater section `section` (`sensor_type`, and
/// the options its kind reads: a thermistor's `pullup_resistor` and
/// `inline_resistor`, a volts table's `adc_voltage` and `voltage_offset`,
/// an Ω table's `pullup_resistor`, an SPI chip's own and bus options),
/// with Klipper's defaults; an SPI chip's bus too.
pub(crate) fn read<'c, 'a>(
    config: &'c Config<'a>,
    section: &Reader<'_, 'c, 'a>,
) -> Read<(TemperatureSensor, Option<SpiBus<'a>>)> {
    let name = section.get("sensor_type")?;
    // A `[thermistor NAME]` of the same name wins, as over the built-in
    // thermistors.
    let definition = find(config, section.errors(), name)?;
    if let (None, Some(chip)) = (definition, Chip::from_name(name)) {
        let (sensor, bus) = spi_temperature::read(section, chip)?;
        return Ok((TemperatureSensor::Spi(sensor), Some(bus)));
    }
    let definition =
        definition.ok_or_else(|| section.error_for("sensor_type", unsupported(name)))?;
    Ok((read_adc_sensor(section, definition)?, None))
}

/// An ADC sensor's options, for its definition.
fn read_adc_sensor(
    section: &Reader<'_, '_, '_>,
    definition: Definition,
) -> Read<TemperatureSensor> {
    Ok(match definition {
        Definition::Thermistor(curve) => {
            let (pullup, inline) = thermistor::read_resistors(section)?;
            TemperatureSensor::Thermistor(Thermistor::new(curve, pullup, inline))
        }
        Definition::Table(samples, column) => {
            let input = adc_temperature::read_input(section, column)?;
            let sensor = LinearSensor::new(samples, input)
                .map_err(|e| section.error_for("sensor_type", e.reason()))?;
            TemperatureSensor::Linear(sensor)
        }
    })
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::machine::Machine;
    use std::string::{String, ToString};

    /// The sensor of an `[extruder]` whose sensor lines are `sensor`,
    /// with `extra` sections; or the config error, as text.
    fn extruder_sensor(sensor: &str, extra: &str) -> Result<TemperatureSensor, String> {
        let text = std::format!(
            concat!(
                cartesian_printer!(),
                "heater_pin: PA0\nsensor_pin: PF4\n\
            control: watermark\nmin_temp: 0\nmax_temp: 300\n{sensor}\n{extra}"
            ),
            extra = extra,
            sensor = sensor
        );
        let config = Config::parse("printer.cfg", &text).map_err(|e| e.to_string())?;
        let machine = Machine::from_config(&config).map_err(|e| e.to_string())?;
        if !machine.unsupported.is_empty() {
            return Err(std::format!("unsupported: {:?}", machine.unsupported));
        }
        Ok(machine.heaters[0].sensor)
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-6
    }

    #[test]
    fn built_in_types_read_their_own_options() {
        let s = extruder_sensor("sensor_type: AD595\nadc_voltage: 3.3", "").expect("AD595");
        // 1.015 V of 3.3 V: 100 °C.
        assert!(close(s.temperature(1.015 / 3.3), 100.0));
        let s = extruder_sensor("sensor_type: PT1000\npullup_resistor: 1000", "").expect("PT1000");
        assert!(close(s.temperature(0.5), 0.0));
        let s = extruder_sensor("sensor_type: Generic 3950\ninline_resistor: 0", "").expect("NTC");
        assert!(close(s.temperature(100_000.0 / 104_700.0), 25.0));
        // A thermistor's options are not a table's, nor the other way.
        let e = extruder_sensor("sensor_type: AD595\ninline_resistor: 10", "").expect_err("option");
        assert!(e.contains("'inline_resistor' is not valid"), "{e}");
        let e =
            extruder_sensor("sensor_type: Generic 3950\nadc_voltage: 5", "").expect_err("option");
        assert!(e.contains("'adc_voltage' is not valid"), "{e}");
        let e = extruder_sensor("sensor_type: AD595\nadc_voltage: 0", "").expect_err("bound");
        assert!(e.contains("printer.cfg:39: option 'adc_voltage'"), "{e}");
    }

    #[test]
    fn custom_thermistor_sections_define_sensor_types() {
        // generic-printrboard-g2's [thermistor G2], points in any order.
        let g2 = "[thermistor G2]\ntemperature1: 255\nresistance1: 189\ntemperature2: 20\n\
            resistance2: 140000\ntemperature3: 195\nresistance3: 593\n";
        let s = extruder_sensor("sensor_type: G2", g2).expect("G2");
        // Klipper's coefficients for G2 (solved in Python from the three
        // points): c1 8.340194631506789e-4, c2 1.9836000382053782e-4,
        // c3 1.3629240595846815e-7; at 4700 Ω (reading 0.5):
        let ln_r = libm::log(4700.0);
        let celsius = 1.0
            / (8.340194631506789e-4
                + 1.9836000382053782e-4 * ln_r
                + 1.3629240595846815e-7 * ln_r * ln_r * ln_r)
            - 273.15;
        assert!(close(s.temperature(0.5), celsius));
        assert!(close(s.temperature(593.0 / 5293.0), 195.0));
        let beta = "[thermistor my ntc]\ntemperature1: 25\nresistance1: 100000\nbeta: 3950\n";
        let s = extruder_sensor("sensor_type: my ntc", beta).expect("beta");
        let named = extruder_sensor("sensor_type: NTC 100K beta 3950", "").expect("built in");
        assert_eq!(s, named);
        // A section named as a built-in type replaces it.
        let own = "[thermistor Generic 3950]\ntemperature1: 25\nresistance1: 100000\nbeta: 3950\n";
        let s = extruder_sensor("sensor_type: Generic 3950", own).expect("own");
        assert_eq!(s, named);
        // Two alike points define no curve; a beta section has no second
        // point.
        let flat = "[thermistor flat]\ntemperature1: 25\nresistance1: 100000\n\
            temperature2: 25\nresistance2: 100000\ntemperature3: 100\nresistance3: 6000\n";
        let e = extruder_sensor("sensor_type: flat", flat).expect_err("flat");
        assert!(
            e.contains("printer.cfg:40: option 'temperature1' in section 'thermistor flat'"),
            "{e}"
        );
        let e = extruder_sensor(
            "sensor_type: my ntc",
            &std::format!("{beta}temperature2: 30\n"),
        )
        .expect_err("beta and points");
        assert!(e.contains("'temperature2' is not valid"), "{e}");
    }

    #[test]
    fn custom_adc_temperature_sections_define_tables() {
        let volts = "[adc_temperature amp]\ntemperature1: 0\nvoltage1: 0.5\n\
            temperature2: 400\nvoltage2: 4.5\n";
        let s = extruder_sensor("sensor_type: amp\nadc_voltage: 5", volts).expect("volts");
        // 2.5 V of 5 V: halfway, 200 °C; 100 °C is 1.5 V.
        assert!(close(s.temperature(0.5), 200.0));
        assert!(close(s.adc(100.0), 0.3));
        let ohms = "[adc_temperature rtd]\ntemperature1: 0\nresistance1: 100\n\
            temperature2: 100\nresistance2: 138.5\n";
        let s = extruder_sensor("sensor_type: rtd\npullup_resistor: 100", ohms).expect("ohms");
        assert!(close(s.temperature(0.5), 0.0));
        assert!(close(s.adc(100.0), 138.5 / 238.5));
        // Errors name the option at fault.
        let e = extruder_sensor(
            "sensor_type: amp",
            "[adc_temperature amp]\ntemperature1: 0\n",
        )
        .expect_err("no voltage1");
        assert!(
            e.contains("'voltage1' in section 'adc_temperature amp' must be specified"),
            "{e}"
        );
        let one = "[adc_temperature amp]\ntemperature1: 0\nvoltage1: 1\n";
        let e = extruder_sensor("sensor_type: amp", one).expect_err("one point");
        assert!(e.contains("printer.cfg:38: option 'sensor_type'"), "{e}");
        assert!(e.contains("fewer than two points"), "{e}");
        let many: String = (1..=17)
            .map(|n| std::format!("temperature{n}: {n}\nvoltage{n}: 0.{n:02}\n"))
            .collect();
        let e = extruder_sensor(
            "sensor_type: amp",
            &std::format!("[adc_temperature amp]\n{many}"),
        )
        .expect_err("17 points");
        assert!(e.contains("option 'temperature17'"), "{e}");
    }

    #[test]
    fn definitions_are_checked_even_when_no_heater_uses_them() {
        let unused = "[thermistor spare]\ntemperature1: 25\nresistance1: 100000\nbeta: -1\n";
        let e = extruder_sensor("sensor_type: Generic 3950", unused).expect_err("bad beta");
        assert!(
            e.contains("option 'beta' in section 'thermistor spare'"),
            "{e}"
        );
        // Good ones are read, not reported unsupported; nor is Klipper's
        // bare [adc_temperature].
        let spare = "[thermistor spare]\ntemperature1: 25\nresistance1: 100000\nbeta: 3950\n\
            [adc_temperature]\n";
        assert!(extruder_sensor("sensor_type: Generic 3950", spare).is_ok());
    }

    #[test]
    fn sensors_onechip_cannot_read_are_refused_naming_sensor_type() {
        for (name, why) in [
            ("temperature_mcu", "is the MCU's own sensor"),
            ("BME280", "no I2C or 1-wire"),
            ("EPCOS 100K", "is not a sensor type onechip knows"),
        ] {
            let e = extruder_sensor(&std::format!("sensor_type: {name}"), "").expect_err(name);
            assert!(
                e.starts_with("printer.cfg:38: option 'sensor_type' in section 'extruder'"),
                "{e}"
            );
            assert!(e.contains(why), "{e}");
        }
        let e = extruder_sensor("sensor_type: Generic 3950\nvo_ref: 1.5", "").expect_err("recore");
        assert!(e.contains("option 'vo_ref'"), "{e}");
    }

    #[test]
    fn spi_chips_are_read_with_their_own_options_only() {
        let s = extruder_sensor("sensor_type: MAX31855\nspi_bus: spi1", "").expect("MAX31855");
        assert_eq!(s.spi().map(|c| c.chip), Some(Chip::Max31855));
        // The reading is the raw word: 0x0320 << 18 is 200 °C.
        assert_eq!(s.temperature(f64::from(0x0320u32 << 18)), 200.0);
        assert_eq!(s.adc(200.0), f64::from(0x0320u32 << 18));
        // A thermocouple's options are not an RTD's, nor the other way.
        let e = extruder_sensor("sensor_type: MAX31855\ntc_type: J", "").expect_err("tc_type");
        assert!(e.contains("'tc_type' is not valid"), "{e}");
        let e = extruder_sensor("sensor_type: MAX31856\nrtd_nominal_r: 1000", "").expect_err("rtd");
        assert!(e.contains("'rtd_nominal_r' is not valid"), "{e}");
        let e = extruder_sensor("sensor_type: MAX31865\nrtd_nominal_r: 0", "").expect_err("bound");
        assert!(e.contains("printer.cfg:39: option 'rtd_nominal_r'"), "{e}");
    }

    #[test]
    fn the_adc_range_runs_lowest_first_for_either_kind() {
        let ntc = extruder_sensor("sensor_type: Generic 3950", "").expect("NTC");
        let range = |s| crate::sensor_section::Conversion::Sensor(s).reading_range(0.0, 300.0);
        let (low, high) = range(ntc);
        assert_eq!((low, high), (ntc.adc(300.0), ntc.adc(0.0)));
        let amp = extruder_sensor("sensor_type: AD8495", "").expect("AD8495");
        let (low, high) = range(amp);
        assert_eq!((low, high), (amp.adc(0.0), amp.adc(300.0)));
        assert!(low < high);
    }
}
