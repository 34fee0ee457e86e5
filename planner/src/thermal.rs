//! Heaters and the part-cooling fan as printer.cfg describes them: the
//! heater options of `[extruder]`, `[heater_bed]` and `[fan]` (whose
//! options every fan section shares), each
//! heater's `[verify_heater NAME]` checks and the `[idle_timeout]` that
//! turns the heaters off, with Klipper's option names, defaults and
//! limits. A heater's sensor is [`crate::temperature_sensor`]'s.

use crate::reader::{Read, Reader};
use crate::temperature_sensor::{self, TemperatureSensor};
use crate::thermistor::ZERO_CELSIUS;
use onechip_config::{Bounds, Config};

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

/// A heater and its sensor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Heater<'a> {
    /// `extruder` or `heater_bed`.
    pub name: &'a str,
    /// heater_pin, as written (`!` inverts).
    pub heater_pin: &'a str,
    /// sensor_pin (an ADC pin, or an SPI chip's chip select).
    pub sensor_pin: &'a str,
    /// The temperature sensor.
    pub sensor: TemperatureSensor,
    /// An SPI sensor's bus (None: an ADC sensor).
    pub spi: Option<crate::spi_temperature::SpiBus<'a>>,
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
// Out of line: see `Machine::from_config_in`.
#[inline(never)]
pub(crate) fn read_verify_heater(section: &Reader<'_, '_, '_>, heater: &str) -> Read<VerifyHeater> {
    let defaults = VerifyHeater::defaults(heater);
    Ok(VerifyHeater {
        hysteresis: section.float("hysteresis", defaults.hysteresis, Bounds::NON_NEGATIVE)?,
        max_error: section.float("max_error", defaults.max_error, Bounds::NON_NEGATIVE)?,
        heating_gain: section.float("heating_gain", defaults.heating_gain, Bounds::POSITIVE)?,
        check_gain_time: section.float(
            "check_gain_time",
            defaults.check_gain_time,
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
// Out of line: see `Machine::from_config_in`.
#[inline(never)]
pub(crate) fn read_idle_timeout<'a>(section: &Reader<'_, '_, 'a>) -> Read<IdleTimeoutConfig<'a>> {
    let timeout = section.float("timeout", 600.0, Bounds::POSITIVE)?;
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
    /// Lowest power of a running fan, 0..1 (`min_power`: any speed above
    /// 0 maps onto min_power..max_power).
    pub min_power: f64,
    /// PWM cycle, s.
    pub cycle_time: f64,
    /// The pin is a hardware PWM channel (`hardware_pwm`).
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

/// `min_temp` and `max_temp` (°C), with these defaults (None: required):
/// not below absolute zero, max_temp above min_temp.
pub(crate) fn read_temperature_limits(
    section: &Reader<'_, '_, '_>,
    min_default: Option<f64>,
    max_default: Option<f64>,
) -> Read<(f64, f64)> {
    let min_temp = section.get_float(
        "min_temp",
        min_default,
        Bounds {
            minval: Some(-ZERO_CELSIUS),
            ..Bounds::NONE
        },
    )?;
    let max_temp = section.get_float(
        "max_temp",
        max_default,
        Bounds {
            above: Some(min_temp),
            ..Bounds::NONE
        },
    )?;
    Ok((min_temp, max_temp))
}

/// Reads a heater from `section` (`[extruder]` or `[heater_bed]`) of
/// `config` (which holds the sensor types it may name).
pub(crate) fn read_heater<'c, 'a>(
    config: &'c Config<'a>,
    section: &Reader<'_, 'c, 'a>,
) -> Read<Heater<'a>> {
    let (sensor, spi) = temperature_sensor::read(config, section)?;
    let (min_temp, max_temp) = read_temperature_limits(section, None, None)?;
    let control = match section.get_choice("control", &["pid", "watermark"], None)? {
        "pid" => Control::Pid {
            kp: section.required_float("pid_kp", Bounds::NONE)?,
            ki: section.required_float("pid_ki", Bounds::NONE)?,
            kd: section.required_float("pid_kd", Bounds::NONE)?,
        },
        _ => Control::Watermark {
            max_delta: section.float("max_delta", 2.0, Bounds::POSITIVE)?,
        },
    };
    let min_extrude_temp = section.float(
        "min_extrude_temp",
        170.0,
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
        sensor,
        spi,
        control,
        min_temp,
        max_temp,
        max_power: section.float("max_power", 1.0, Bounds::UNIT_ABOVE_ZERO)?,
        smooth_time: section.float("smooth_time", 1.0, Bounds::POSITIVE)?,
        pwm_cycle_time: section.float(
            "pwm_cycle_time",
            0.100,
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

/// Reads `[fan]`.
pub(crate) fn read_fan<'a>(section: &Reader<'_, '_, 'a>) -> Read<Fan<'a>> {
    read_fan_options(section, 0.0)
}

/// Reads the options every Klipper fan section has (`[fan]`,
/// `[heater_fan]`, `[controller_fan]`, `[fan_generic]`,
/// `[temperature_fan]`) from `section`; `default_shutdown_speed` (0..1)
/// is the section kind's default for `shutdown_speed`. A tachometer
/// (`tachometer_pin`, `tachometer_ppr`, `tachometer_poll_interval`) is
/// accepted but its speed is not measured yet.
pub(crate) fn read_fan_options<'a>(
    section: &Reader<'_, '_, 'a>,
    default_shutdown_speed: f64,
) -> Read<Fan<'a>> {
    let min_power = section.float("min_power", 0.0, Bounds::UNIT_BELOW_ONE)?;
    section.accept(&[
        "tachometer_pin",
        "tachometer_ppr",
        "tachometer_poll_interval",
    ]);
    Ok(Fan {
        pin: section.get("pin")?,
        max_power: section.float("max_power", 1.0, Bounds::UNIT_ABOVE_ZERO)?,
        min_power,
        cycle_time: section.float("cycle_time", 0.010, Bounds::POSITIVE)?,
        hard_pwm: section.get_bool("hardware_pwm", false)?,
        shutdown_speed: section.float("shutdown_speed", default_shutdown_speed, Bounds::UNIT)?,
        kick_start_time: section.float("kick_start_time", 0.1, Bounds::NON_NEGATIVE)?,
        off_below: section.float("off_below", 0.0, Bounds::UNIT)?,
    })
}

impl Fan<'_> {
    /// The power (0..1) a requested speed (0..1) gives, as Klipper's
    /// `Fan.set_speed`: 0 below off_below, else mapped onto
    /// min_power..max_power.
    pub fn power(&self, speed: f64) -> f64 {
        let speed = if speed < self.off_below { 0.0 } else { speed };
        let power = if speed > 0.0 {
            crate::math::clamp(
                (self.max_power - self.min_power) * speed + self.min_power,
                self.min_power,
                self.max_power,
            )
        } else {
            speed
        };
        crate::math::clamp(power, 0.0, 1.0)
    }
}
