//! Heaters, their thermistors and the part-cooling fan as printer.cfg
//! describes them: the heater options of `[extruder]`, `[heater_bed]` and
//! `[fan]`, each heater's `[verify_heater NAME]` checks and the
//! `[idle_timeout]` that turns the heaters off, with Klipper's option
//! names, defaults and limits.
//!
//! A thermistor is read through a voltage divider (a pullup resistor to
//! the ADC reference); its resistance follows the Steinhart-Hart equation
//! `1/T = c1 + c2 ln R + c3 (ln R)^3` (T in kelvin), whose coefficients
//! come from three (temperature, resistance) points of its data sheet, or
//! from a beta value (`c3 = 0`).

use onechip_config::{Bounds, ConfigError, Section};

/// 0 °C in kelvin.
const ZERO_CELSIUS: f64 = 273.15;

/// The heater control (`control:`), with its options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Control {
    /// `pid`: the PID gains as printer.cfg gives them (Klipper scales
    /// them by 1/255 to act on power 0..1).
    Pid {
        /// pid_Kp.
        kp: f64,
        /// pid_Ki.
        ki: f64,
        /// pid_Kd.
        kd: f64,
    },
    /// `watermark`: full power below target − max_delta, off above
    /// target + max_delta, °C.
    Watermark {
        /// max_delta, °C.
        max_delta: f64,
    },
}

/// A thermistor behind a pullup resistor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Thermistor {
    c1: f64,
    c2: f64,
    c3: f64,
    /// pullup_resistor, ohm.
    pullup: f64,
    /// inline_resistor, ohm.
    inline: f64,
}

/// How a built-in sensor type is defined: three (°C, ohm) points, or one
/// point and a beta.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Definition {
    Points([(f64, f64); 3]),
    Beta((f64, f64), f64),
}

/// The thermistors Klipper knows by `sensor_type` name, with their data
/// sheet points.
const SENSORS: [(&str, Definition); 9] = [
    (
        "EPCOS 100K B57560G104F",
        Definition::Points([(25.0, 100_000.0), (150.0, 1641.9), (250.0, 226.15)]),
    ),
    (
        "ATC Semitec 104GT-2",
        Definition::Points([(20.0, 126_800.0), (150.0, 1360.0), (300.0, 80.65)]),
    ),
    (
        "ATC Semitec 104NT-4-R025H42G",
        Definition::Points([(25.0, 100_000.0), (160.0, 1074.0), (300.0, 82.78)]),
    ),
    (
        "Generic 3950",
        Definition::Points([(25.0, 100_000.0), (150.0, 1770.0), (250.0, 230.0)]),
    ),
    (
        "SliceEngineering 450",
        Definition::Points([(25.0, 500_000.0), (200.0, 3734.0), (400.0, 240.0)]),
    ),
    (
        "TDK NTCG104LH104JT1",
        Definition::Points([(25.0, 100_000.0), (50.0, 31_230.0), (125.0, 2066.0)]),
    ),
    (
        "Honeywell 100K 135-104LAG-J01",
        Definition::Beta((25.0, 100_000.0), 3974.0),
    ),
    (
        "NTC 100K beta 3950",
        Definition::Beta((25.0, 100_000.0), 3950.0),
    ),
    (
        "NTC 100K MGB18-104F39050L32",
        Definition::Beta((25.0, 100_000.0), 4100.0),
    ),
];

impl Thermistor {
    /// The built-in sensor type `name` behind `pullup` and `inline` ohm.
    pub fn named(name: &str, pullup: f64, inline: f64) -> Option<Self> {
        let (_, definition) = SENSORS.iter().find(|(n, _)| *n == name)?;
        Some(match *definition {
            Definition::Points(points) => Self::from_points(points, pullup, inline),
            Definition::Beta(point, beta) => Self::from_beta(point, beta, pullup, inline),
        })
    }

    /// Steinhart-Hart through three (°C, ohm) points; if they need a
    /// negative cubic term, the beta of the outer two instead.
    fn from_points(points: [(f64, f64); 3], pullup: f64, inline: f64) -> Self {
        let [(t1, r1), (t2, r2), (t3, r3)] = points;
        let inv = |t: f64| 1.0 / (t + ZERO_CELSIUS);
        let (l1, l2, l3) = (libm::log(r1), libm::log(r2), libm::log(r3));
        let (i12, i13) = (inv(t1) - inv(t2), inv(t1) - inv(t3));
        let (l12, l13) = (l1 - l2, l1 - l3);
        let (c12, c13) = (l1 * l1 * l1 - l2 * l2 * l2, l1 * l1 * l1 - l3 * l3 * l3);
        let c3 = (i12 - i13 * l12 / l13) / (c12 - c13 * l12 / l13);
        if c3 <= 0.0 {
            return Self::from_beta((t1, r1), l13 / i13, pullup, inline);
        }
        let c2 = (i12 - c3 * c12) / l12;
        Self {
            c1: inv(t1) - c2 * l1 - c3 * l1 * l1 * l1,
            c2,
            c3,
            pullup,
            inline,
        }
    }

    /// Beta equation through one (°C, ohm) point.
    fn from_beta((t1, r1): (f64, f64), beta: f64, pullup: f64, inline: f64) -> Self {
        let c2 = 1.0 / beta;
        Self {
            c1: 1.0 / (t1 + ZERO_CELSIUS) - c2 * libm::log(r1),
            c2,
            c3: 0.0,
            pullup,
            inline,
        }
    }

    /// Temperature at ADC reading `adc` (fraction of full scale), °C.
    pub fn temperature(&self, adc: f64) -> f64 {
        let adc = adc.clamp(0.00001, 0.99999);
        let r = self.pullup * adc / (1.0 - adc);
        let ln_r = libm::log(r - self.inline);
        1.0 / (self.c1 + self.c2 * ln_r + self.c3 * ln_r * ln_r * ln_r) - ZERO_CELSIUS
    }

    /// ADC reading (fraction of full scale) at temperature `t`, °C.
    pub fn adc(&self, t: f64) -> f64 {
        if t <= -ZERO_CELSIUS {
            return 1.0;
        }
        let inv_t = 1.0 / (t + ZERO_CELSIUS);
        let ln_r = if self.c3 != 0.0 {
            // The cubic c3 x^3 + c2 x + (c1 - 1/T) = 0, by Cardano.
            let y = (self.c1 - inv_t) / (2.0 * self.c3);
            let x = libm::sqrt(libm::pow(self.c2 / (3.0 * self.c3), 3.0) + y * y);
            libm::cbrt(x - y) - libm::cbrt(x + y)
        } else {
            (inv_t - self.c1) / self.c2
        };
        let r = libm::exp(ln_r) + self.inline;
        r / (self.pullup + r)
    }
}

/// A heater and its sensor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Heater<'a> {
    /// `extruder` or `heater_bed`.
    pub name: &'a str,
    /// heater_pin, as written (`!` inverts).
    pub heater_pin: &'a str,
    /// sensor_pin (an ADC pin).
    pub sensor_pin: &'a str,
    /// The sensor.
    pub thermistor: Thermistor,
    /// The control.
    pub control: Control,
    /// Lowest temperature the sensor may read, °C (below: shutdown).
    pub min_temp: f64,
    /// Highest temperature the sensor may read, °C (above: shutdown).
    pub max_temp: f64,
    /// Highest power, 0..1.
    pub max_power: f64,
    /// Time over which temperature readings are smoothed, s.
    pub smooth_time: f64,
    /// The heater's software PWM cycle, s.
    pub pwm_cycle_time: f64,
    /// Extrusion is refused while the smoothed temperature is below this,
    /// °C (`min_extrude_temp`; 0 or less: never refused).
    pub min_extrude_temp: f64,
    /// The checks that the heater heats as it should (`[verify_heater]`).
    pub verify: VerifyHeater,
}

/// Klipper's `[verify_heater NAME]`: checked once a second of heater time
/// against the smoothed temperature and the target. Every heater has it,
/// with these defaults unless its section overrides them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VerifyHeater {
    /// Largest accumulated error (°C below target − hysteresis, summed
    /// once a second) before the heater faults, °C·s (`max_error`).
    pub max_error: f64,
    /// Time in which a heater approaching its target must gain
    /// `heating_gain`, s (`check_gain_time`: 20 s, 60 s for the bed).
    pub check_gain_time: f64,
    /// Distance from the target within which the heater counts as at
    /// temperature, °C (`hysteresis`).
    pub hysteresis: f64,
    /// Gain expected within each `check_gain_time` while approaching the
    /// target, °C (`heating_gain`).
    pub heating_gain: f64,
}

impl VerifyHeater {
    /// Klipper's defaults for the heater named `heater`.
    pub fn defaults(heater: &str) -> Self {
        Self {
            max_error: 120.0,
            check_gain_time: if heater == "heater_bed" { 60.0 } else { 20.0 },
            hysteresis: 5.0,
            heating_gain: 2.0,
        }
    }
}

/// Reads `[verify_heater NAME]` for the heater `heater` from `section`,
/// with Klipper's defaults and bounds.
pub fn read_verify_heater<'c>(
    section: &Section<'c, '_>,
    heater: &str,
) -> Result<VerifyHeater, ConfigError<'c>> {
    let defaults = VerifyHeater::defaults(heater);
    Ok(VerifyHeater {
        hysteresis: section.get_float(
            "hysteresis",
            Some(defaults.hysteresis),
            Bounds::NON_NEGATIVE,
        )?,
        max_error: section.get_float(
            "max_error",
            Some(defaults.max_error),
            Bounds::NON_NEGATIVE,
        )?,
        heating_gain: section.get_float(
            "heating_gain",
            Some(defaults.heating_gain),
            Bounds::POSITIVE,
        )?,
        check_gain_time: section.get_float(
            "check_gain_time",
            Some(defaults.check_gain_time),
            Bounds {
                minval: Some(1.0),
                ..Bounds::NONE
            },
        )?,
    })
}

/// The heater name a `[verify_heater NAME]` section names, if `section`
/// is one.
pub fn verify_heater_target(section: &str) -> Option<&str> {
    let rest = section.strip_prefix("verify_heater")?;
    let name = rest.trim();
    (rest.starts_with(char::is_whitespace) && !name.is_empty()).then_some(name)
}

/// `[idle_timeout]`: after `timeout` s with nothing to do, the printer
/// runs `gcode` (Klipper loads it on every printer, with these defaults).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IdleTimeoutConfig<'a> {
    /// Idle time before `gcode` runs, s (`timeout`).
    pub timeout: f64,
    /// The G-code lines to run (`gcode`), one command a line.
    pub gcode: &'a str,
}

/// Klipper's default idle G-code: every heater off, then the motors.
pub const DEFAULT_IDLE_GCODE: &str = "TURN_OFF_HEATERS\nM84";

impl Default for IdleTimeoutConfig<'_> {
    fn default() -> Self {
        Self {
            timeout: 600.0,
            gcode: DEFAULT_IDLE_GCODE,
        }
    }
}

/// Reads `[idle_timeout]`. G-code templates (`{ }`, `{% %}`) cannot run
/// here, so a `gcode` using one is refused rather than run half-understood.
pub fn read_idle_timeout<'c, 'a>(
    section: &Section<'c, 'a>,
) -> Result<IdleTimeoutConfig<'a>, ConfigError<'c>> {
    let timeout = section.get_float("timeout", Some(600.0), Bounds::POSITIVE)?;
    let gcode = section.get_opt("gcode").unwrap_or(DEFAULT_IDLE_GCODE);
    if gcode.contains('{') {
        return Err(section.error_for(
            "gcode",
            "uses a template ({ }), which onechip does not support yet",
        ));
    }
    Ok(IdleTimeoutConfig { timeout, gcode })
}

/// The part-cooling fan (`[fan]`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fan<'a> {
    /// pin, as written.
    pub pin: &'a str,
    /// Highest power, 0..1 (M106 S255 gives this).
    pub max_power: f64,
    /// PWM cycle, s.
    pub cycle_time: f64,
    /// The pin is a hardware PWM channel.
    pub hard_pwm: bool,
    /// Speed at shutdown, 0..1.
    pub shutdown_speed: f64,
    /// Full power for this long when starting from still, s.
    pub kick_start_time: f64,
    /// Speeds below this (0..1) turn the fan off.
    pub off_below: f64,
}

/// Time from a temperature reading to the heater update it causes, s:
/// one report interval plus the readings' own time (Klipper's
/// REPORT_TIME + SAMPLE_TIME × SAMPLE_COUNT).
pub const PWM_DELAY: f64 = 0.300 + 0.001 * 8.0;

/// Reads a heater from `section` (`[extruder]` or `[heater_bed]`).
pub fn read_heater<'c, 'a>(section: &Section<'c, 'a>) -> Result<Heater<'a>, ConfigError<'c>> {
    let pullup = section.get_float("pullup_resistor", Some(4700.0), Bounds::POSITIVE)?;
    let inline = section.get_float("inline_resistor", Some(0.0), Bounds::NON_NEGATIVE)?;
    let sensor_type = section.get("sensor_type")?;
    let thermistor = Thermistor::named(sensor_type, pullup, inline)
        .ok_or(section.error_for("sensor_type", "is not a thermistor onechip knows"))?;
    let min_temp = section.get_float(
        "min_temp",
        None,
        Bounds {
            minval: Some(-ZERO_CELSIUS),
            ..Bounds::NONE
        },
    )?;
    let max_temp = section.get_float(
        "max_temp",
        None,
        Bounds {
            above: Some(min_temp),
            ..Bounds::NONE
        },
    )?;
    let control = match section.get_choice("control", &["pid", "watermark"], None)? {
        "pid" => Control::Pid {
            kp: section.get_float("pid_kp", None, Bounds::NONE)?,
            ki: section.get_float("pid_ki", None, Bounds::NONE)?,
            kd: section.get_float("pid_kd", None, Bounds::NONE)?,
        },
        _ => Control::Watermark {
            max_delta: section.get_float("max_delta", Some(2.0), Bounds::POSITIVE)?,
        },
    };
    let min_extrude_temp = section.get_float(
        "min_extrude_temp",
        Some(170.0),
        Bounds {
            minval: Some(min_temp),
            maxval: Some(max_temp),
            ..Bounds::NONE
        },
    )?;
    let name = section.name_in_file();
    Ok(Heater {
        name,
        heater_pin: section.get("heater_pin")?,
        sensor_pin: section.get("sensor_pin")?,
        thermistor,
        control,
        min_temp,
        max_temp,
        max_power: section.get_float("max_power", Some(1.0), UNIT_ABOVE_ZERO)?,
        smooth_time: section.get_float("smooth_time", Some(1.0), Bounds::POSITIVE)?,
        pwm_cycle_time: section.get_float(
            "pwm_cycle_time",
            Some(0.100),
            Bounds {
                above: Some(0.0),
                maxval: Some(PWM_DELAY),
                ..Bounds::NONE
            },
        )?,
        min_extrude_temp,
        verify: VerifyHeater::defaults(name),
    })
}

/// `(0, 1]`.
const UNIT_ABOVE_ZERO: Bounds = Bounds {
    above: Some(0.0),
    maxval: Some(1.0),
    minval: None,
    below: None,
};

/// `[0, 1]`.
const UNIT: Bounds = Bounds {
    minval: Some(0.0),
    maxval: Some(1.0),
    above: None,
    below: None,
};

/// Reads `[fan]`.
pub fn read_fan<'c, 'a>(section: &Section<'c, 'a>) -> Result<Fan<'a>, ConfigError<'c>> {
    Ok(Fan {
        pin: section.get("pin")?,
        max_power: section.get_float("max_power", Some(1.0), UNIT_ABOVE_ZERO)?,
        cycle_time: section.get_float("cycle_time", Some(0.010), Bounds::POSITIVE)?,
        hard_pwm: section.get_bool("hard_pwm", false)?,
        shutdown_speed: section.get_float("shutdown_speed", Some(0.0), UNIT)?,
        kick_start_time: section.get_float("kick_start_time", Some(0.1), Bounds::NON_NEGATIVE)?,
        off_below: section.get_float("off_below", Some(0.0), UNIT)?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_thermistor_passes_through_its_data_sheet_points() {
        let t = Thermistor::named("EPCOS 100K B57560G104F", 4700.0, 0.0).expect("known");
        for (celsius, ohm) in [(25.0, 100_000.0), (150.0, 1641.9), (250.0, 226.15)] {
            let adc = ohm / (ohm + 4700.0);
            assert!((t.temperature(adc) - celsius).abs() < 1e-9);
            assert!((t.adc(celsius) - adc).abs() < 1e-12);
        }
        // Beta thermistors too, and the two conversions invert each other.
        let b = Thermistor::named("Generic 3950", 4700.0, 0.0).expect("known");
        let n = Thermistor::named("NTC 100K beta 3950", 4700.0, 0.0).expect("known");
        for celsius in [0.0, 20.0, 60.0, 110.0, 200.0, 280.0] {
            assert!((b.temperature(b.adc(celsius)) - celsius).abs() < 1e-6);
            assert!((n.temperature(n.adc(celsius)) - celsius).abs() < 1e-6);
        }
        assert_eq!(Thermistor::named("PT1000", 4700.0, 0.0), None);
    }
}
