//! `[temperature_sensor NAME]`: a temperature that is read, range-checked
//! and reported, and drives nothing (Klipper's `temperature_sensor`).
//!
//! The sensor is any `sensor_type` a heater may have (read through an
//! ADC pin), or `temperature_mcu`: the main MCU's own temperature sensor,
//! read through its internal ADC channel (Klipper's pin
//! `ADC_TEMPERATURE`) and converted with the chip's factory calibration,
//! or with `sensor_temperature1`/`sensor_adc1` (and optionally `…2`)
//! where printer.cfg gives them. Readings outside `min_temp..max_temp`
//! shut the printer down, as a heater's do; `gcode_id` makes the sensor
//! part of the M105 report.

use crate::reader::{Errors, Read, Reader};
use crate::temperature_sensor::{self, TemperatureSensor};
use crate::thermal;
use crate::thermistor::ZERO_CELSIUS;
use onechip_config::{Bounds, Config};

/// Most `[temperature_sensor]` sections.
pub const MAX_SENSORS: usize = 4;

/// The internal ADC channel's pin name (Klipper's).
pub const MCU_TEMPERATURE_PIN: &str = "ADC_TEMPERATURE";

/// Klipper's default max_temp of a temperature_sensor, °C.
const NO_MAX_TEMP: f64 = 99_999_999.9;

/// One `[temperature_sensor NAME]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorSection<'a> {
    /// NAME, as written.
    pub name: &'a str,
    /// The whole section name, as written (`temperature_sensor NAME`,
    /// `temperature_fan NAME`): where its options are.
    pub section: &'a str,
    /// Where the reading comes from.
    pub input: SensorInput<'a>,
    /// Lowest temperature it may read, °C (below: shutdown).
    pub min_temp: f64,
    /// Highest temperature it may read, °C (above: shutdown).
    pub max_temp: f64,
    /// Its M105 label, if it has one (`gcode_id`).
    pub gcode_id: Option<&'a str>,
}

/// How a sensor is read.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SensorInput<'a> {
    /// A sensor type on ADC pin `pin`.
    Adc {
        /// sensor_pin, as written.
        pin: &'a str,
        /// Its conversion.
        sensor: TemperatureSensor,
    },
    /// An SPI converter chip (Klipper's `spi_temperature`).
    Spi {
        /// The chip and its conversion.
        sensor: crate::spi_temperature::SpiSensor,
        /// Its bus (`sensor_pin` is the chip select).
        bus: crate::spi_temperature::SpiBus<'a>,
    },
    /// `temperature_mcu`: the main MCU's internal sensor.
    Mcu(McuCalibration),
}

impl<'a> SensorInput<'a> {
    /// The ADC pin read (an SPI chip's chip select).
    pub fn pin(&self) -> &'a str {
        match self {
            Self::Adc { pin, .. } => pin,
            Self::Spi { bus, .. } => bus.cs_pin,
            Self::Mcu(_) => MCU_TEMPERATURE_PIN,
        }
    }
}

/// TS_CAL1 and TS_CAL2 of a typical STM32H7 (the datasheet's 0.62 V at
/// 30 °C and 2 mV/°C, over 3.3 V in 16 bits): the simulated chip's, and
/// the board's where its calibration words are blank.
pub const TYPICAL_STM32H7_CAL: (u16, u16) = (12_312, 15_490);

/// A temperature, °C, and the reading there (fraction of the ADC's full
/// scale).
pub type CalibrationPoint = (f64, f64);

/// printer.cfg's calibration of the MCU's sensor, over the chip's
/// factory one (Klipper's `sensor_temperature1`, `sensor_adc1`,
/// `sensor_temperature2`, `sensor_adc2`): with one point the factory
/// slope is kept and moved through it; with two, both are replaced.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct McuCalibration {
    /// The first point, if given.
    pub point1: Option<CalibrationPoint>,
    /// The second point, if given (only with the first).
    pub point2: Option<CalibrationPoint>,
}

/// The linear conversion of the MCU's sensor: °C = `base` + `slope` ×
/// reading (a fraction of full scale), as Klipper's temperature_mcu.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinearConversion {
    /// °C at reading 0.
    pub base: f64,
    /// °C per full scale.
    pub slope: f64,
}

impl LinearConversion {
    /// Through two points.
    pub fn through(a: CalibrationPoint, b: CalibrationPoint) -> Self {
        let slope = (b.0 - a.0) / (b.1 - a.1);
        Self {
            base: a.0 - a.1 * slope,
            slope,
        }
    }

    /// An STM32H7's, from its factory calibration words TS_CAL1 (30 °C)
    /// and TS_CAL2 (110 °C), 16-bit readings at 3.3 V (as Klipper reads
    /// them on the H7).
    pub fn stm32h7((ts_cal1, ts_cal2): (u16, u16)) -> Self {
        let reading = |raw: u16| f64::from(raw) / 65535.0;
        Self::through((30.0, reading(ts_cal1)), (110.0, reading(ts_cal2)))
    }

    /// This conversion with printer.cfg's calibration applied.
    pub fn calibrated(self, cal: &McuCalibration) -> Self {
        match (cal.point1, cal.point2) {
            (Some(p1), Some(p2)) => Self::through(p1, p2),
            (Some(p1), None) => Self {
                base: p1.0 - p1.1 * self.slope,
                ..self
            },
            _ => self,
        }
    }

    /// °C at `reading` (fraction of full scale).
    pub fn temperature(&self, reading: f64) -> f64 {
        self.base + reading * self.slope
    }

    /// The reading (fraction of full scale) at `celsius`.
    pub fn reading(&self, celsius: f64) -> f64 {
        (celsius - self.base) / self.slope
    }
}

/// A sensor's reading (fraction of the ADC's full scale) to °C and back.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Conversion {
    /// A sensor type's curve or table.
    Sensor(TemperatureSensor),
    /// The MCU's internal sensor's line.
    Linear(LinearConversion),
}

impl Conversion {
    /// °C at `reading`.
    pub fn temperature(&self, reading: f64) -> f64 {
        match self {
            Self::Sensor(s) => s.temperature(reading),
            Self::Linear(l) => l.temperature(reading),
        }
    }

    /// The reading at `celsius`.
    pub fn reading(&self, celsius: f64) -> f64 {
        match self {
            Self::Sensor(s) => s.adc(celsius),
            Self::Linear(l) => l.reading(celsius),
        }
    }

    /// The readings between `min_temp` and `max_temp` (°C), lowest first,
    /// within `0..=1`: a limit beyond what the sensor can read (Klipper's
    /// defaults of absolute zero and 10⁸ °C) does not limit.
    pub fn reading_range(&self, min_temp: f64, max_temp: f64) -> (f64, f64) {
        let (a, b) = (self.reading(min_temp), self.reading(max_temp));
        let (low, high) = (a.min(b), a.max(b));
        let within = |v: f64, otherwise: f64| {
            if v.is_finite() {
                crate::math::clamp(v, 0.0, 1.0)
            } else {
                otherwise
            }
        };
        (within(low, 0.0), within(high, 1.0))
    }
}

impl SensorSection<'_> {
    /// The sensor's conversion, on an MCU whose internal sensor the
    /// factory calibrated as `factory`.
    pub fn conversion(&self, factory: LinearConversion) -> Conversion {
        match self.input {
            SensorInput::Adc { sensor, .. } => Conversion::Sensor(sensor),
            SensorInput::Spi { sensor, .. } => Conversion::Sensor(TemperatureSensor::Spi(sensor)),
            SensorInput::Mcu(cal) => Conversion::Linear(factory.calibrated(&cal)),
        }
    }
}

/// True for the sections this module reads.
pub fn is_section(name: &str) -> bool {
    name.starts_with("temperature_sensor ")
}

/// Reads every `[temperature_sensor NAME]`.
// Out of line: see `Machine::from_config_in`.
#[inline(never)]
pub(crate) fn read_all<'c, 'a>(
    config: &'c Config<'a>,
    errors: &Errors<'c>,
) -> Read<heapless::Vec<SensorSection<'a>, MAX_SENSORS>> {
    let mut sensors = heapless::Vec::new();
    for name in config.section_names().filter(|n| is_section(n)) {
        let Some(section) = config.section(name) else {
            continue;
        };
        let section = Reader::new(section, errors);
        let sensor = read(config, &section, (Some(-ZERO_CELSIUS), Some(NO_MAX_TEMP)))?;
        sensors
            .push(sensor)
            .map_err(|_| section.error_for("sensor_type", "too many temperature sensors"))?;
    }
    Ok(sensors)
}

/// Reads the sensor of `section` (a `[temperature_sensor]`, or a
/// `[temperature_fan]`'s), min_temp and max_temp with these defaults
/// (None: required).
pub(crate) fn read<'c, 'a>(
    config: &'c Config<'a>,
    section: &Reader<'_, 'c, 'a>,
    (min_default, max_default): (Option<f64>, Option<f64>),
) -> Read<SensorSection<'a>> {
    let input = if section
        .get("sensor_type")?
        .eq_ignore_ascii_case("temperature_mcu")
    {
        if section.get_opt("sensor_mcu").is_some_and(|m| m != "mcu") {
            return Err(section.error_for(
                "sensor_mcu",
                "only the main MCU's temperature can be read (not a secondary's)",
            ));
        }
        section.float("reference_voltage", 3.3, Bounds::POSITIVE)?;
        SensorInput::Mcu(read_calibration(section)?)
    } else {
        match temperature_sensor::read(config, section)? {
            (TemperatureSensor::Spi(sensor), Some(bus)) => SensorInput::Spi { sensor, bus },
            (sensor, _) => SensorInput::Adc {
                pin: section.get("sensor_pin")?,
                sensor,
            },
        }
    };
    let (min_temp, max_temp) = thermal::read_temperature_limits(section, min_default, max_default)?;
    let name = section.name_in_file();
    Ok(SensorSection {
        name: name.split_once(' ').map_or(name, |(_, n)| n.trim()),
        section: name,
        input,
        min_temp,
        max_temp,
        gcode_id: section.get_opt("gcode_id"),
    })
}

/// `sensor_temperature1`/`sensor_adc1` and `…2`.
fn read_calibration(section: &Reader<'_, '_, '_>) -> Read<McuCalibration> {
    let mut cal = McuCalibration::default();
    if let Some(t1) = section.get_float_opt("sensor_temperature1", Bounds::NONE)? {
        cal.point1 = Some((t1, section.required_float("sensor_adc1", Bounds::UNIT)?));
        if let Some(t2) = section.get_float_opt("sensor_temperature2", Bounds::NONE)? {
            cal.point2 = Some((t2, section.required_float("sensor_adc2", Bounds::UNIT)?));
        }
    }
    Ok(cal)
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::format;

    /// `extra`'s sensors, or its config error as text, handed to `check`.
    fn with_sensors(
        extra: &str,
        check: impl FnOnce(Result<&[SensorSection<'_>], std::string::String>),
    ) {
        let text = format!("[printer]\n{extra}");
        let config = Config::parse("printer.cfg", &text).expect("parses");
        match Errors::run(|errors| read_all(&config, errors)) {
            Ok(sensors) => check(Ok(&sensors)),
            Err(e) => check(Err(format!("{e}"))),
        }
    }

    #[test]
    fn a_thermistor_and_the_mcu_sensor_are_read_with_klippers_defaults() {
        with_sensors(
            "[temperature_sensor chamber]\nsensor_type: EPCOS 100K B57560G104F\n\
             sensor_pin: PF5\ngcode_id: C\n\
             [temperature_sensor mcu_temp]\nsensor_type: temperature_mcu\nmax_temp: 100\n",
            |s| {
                let s = s.expect("valid");
                assert_eq!(s.len(), 2);
                assert_eq!((s[0].name, s[0].gcode_id), ("chamber", Some("C")));
                assert_eq!(s[0].input.pin(), "PF5");
                assert_eq!((s[0].min_temp, s[0].max_temp), (-ZERO_CELSIUS, NO_MAX_TEMP));
                assert_eq!(s[1].input, SensorInput::Mcu(McuCalibration::default()));
                assert_eq!(s[1].input.pin(), MCU_TEMPERATURE_PIN);
                assert_eq!(s[1].max_temp, 100.0);
            },
        );
    }

    #[test]
    fn printer_cfg_calibration_moves_or_replaces_the_factory_line() {
        let factory = LinearConversion::through((30.0, 0.2), (110.0, 0.3));
        assert!((factory.temperature(0.25) - 70.0).abs() < 1e-9);
        assert!((factory.reading(70.0) - 0.25).abs() < 1e-12);
        let one = McuCalibration {
            point1: Some((25.0, 0.2)),
            point2: None,
        };
        let moved = factory.calibrated(&one);
        assert!((moved.slope - factory.slope).abs() < 1e-9);
        assert!((moved.temperature(0.2) - 25.0).abs() < 1e-9);
        let two = McuCalibration {
            point1: Some((20.0, 0.1)),
            point2: Some((120.0, 0.6)),
        };
        let replaced = factory.calibrated(&two);
        assert!((replaced.temperature(0.35) - 70.0).abs() < 1e-9);
    }

    #[test]
    fn a_secondary_mcus_sensor_or_a_missing_adc_point_is_a_config_error() {
        with_sensors(
            "[temperature_sensor t]\nsensor_type: temperature_mcu\nsensor_mcu: toolboard\n",
            |s| {
                let e = s.expect_err("secondary");
                assert!(e.contains("sensor_mcu"), "{e}");
            },
        );
        with_sensors(
            "[temperature_sensor t]\nsensor_type: temperature_mcu\nsensor_temperature1: 25\n",
            |s| {
                let e = s.expect_err("no adc1");
                assert!(e.contains("sensor_adc1"), "{e}");
            },
        );
    }
}
