//! Heaters and the part-cooling fan, from printer.cfg to the MCU role's
//! outputs: each heater is a software-PWM output with Klipper's 3 s
//! max_duration and a thermistor ADC input sampled 8 times every 0.3 s and
//! range-checked against min_temp/max_temp (or an SPI chip read once every
//! 0.3 s with Klipper's range and fault checks, [`InputQuery::Spi`]); each
//! temperature report runs
//! the heater's control (PID or watermark) at once, which queues the next
//! PWM value 0.308 s after the report, as Klipper's host does. An ADC
//! input on another MCU (`NAME:PIN`, a secondary board) is sampled there,
//! not here: its reports come in through [`Heaters::remote_reading`].
//!
//! Klipper's host-side heater safety runs here too, on the same reports:
//! each heater's `[verify_heater]` checks (once a second of heater time;
//! a heater that does not heat as expected shuts everything down with
//! Klipper's message), and whether the extruder is hot enough to extrude
//! (min_extrude_temp, read by the session before each line through
//! [`Heaters::can_extrude`]).
//!
//! [`Heaters`] owns the MCU role's [`Io`] so that report, control and
//! update happen in one place and in time: the board runs it from a timer
//! interrupt, the host build in virtual time. G-code reaches it as
//! [`ThermalCommand`]s that the printer hands out.

use core::fmt::Write;
use onechip_planner::machine::Machine;
use onechip_planner::math::clamp;
use onechip_planner::sensor_section::{Conversion, MAX_SENSORS};
// The internal sensor's conversion, for the shells that read the chip's
// calibration.
pub use onechip_planner::sensor_section::{
    LinearConversion, MCU_TEMPERATURE_PIN, TYPICAL_STM32H7_CAL,
};
use onechip_planner::spi_temperature::Chip;
// An SPI sensor's chip and bus, for the shells that wire or simulate it.
use crate::secondary::thermal::Reading;
pub use onechip_planner::spi_temperature::{SpiBus, SpiBusPins, SpiSensor};
use onechip_planner::temperature_sensor::TemperatureSensor;
use onechip_planner::thermal::{Control, PWM_DELAY, VerifyHeater};
use onechip_sched::adc::AdcQuery;
use onechip_sched::clock::is_before;
use onechip_sched::io::{Io, Peripherals};
use onechip_sched::outputs::{OutputConfig, OutputKind, QueueError};
use onechip_sched::shutdown::{self, Shutdown};
use onechip_sched::thermocouple::{SpiChip, SpiQuery, SpiReport};

use crate::outputs::{
    AccessoryCommand, AccessoryOutputs, FanControl, Levels, fan_config, fan_levels,
};
use onechip_config::decimal::Fixed;

/// Time between a thermistor's readings, s.
pub const SAMPLE_TIME: f64 = 0.001;
/// Readings per report.
pub const SAMPLE_COUNT: u8 = 8;
/// Time between reports, s.
pub const REPORT_TIME: f64 = 0.300;
/// Reports out of range in a row that shut everything down.
pub const RANGE_CHECK_COUNT: u8 = 4;
/// Bad reads of an SPI sensor in a row that are tolerated (Klipper's
/// MAX_INVALID_COUNT: the next one shuts everything down).
pub const SPI_MAX_INVALID: u8 = 3;
/// Longest a heater output may hold a value without an update, s.
pub const MAX_HEAT_TIME: f64 = 3.0;
/// Full scale of a hardware PWM duty in the MCU role's io. Fine enough
/// (2^24) that a duty set as a fraction with up to three decimals, or as
/// M106's n/255, rescales to a secondary's own PWM_MAX (255 to 65535) as
/// klippy rounds it from the fraction itself.
pub const PWM_MAX: u32 = 1 << 24;
/// Delay from start-up to the first readings, s.
pub const FIRST_REPORT: f64 = 0.2;
/// Time between two verify_heater checks of a heater, s (Klipper's).
pub const VERIFY_TIME: f64 = 1.0;
/// The temperature the PID starts from, °C.
const AMBIENT: f64 = 25.0;
/// A PID heater is settled within this of its target, °C.
const PID_SETTLE_DELTA: f64 = 1.0;
/// ... and changing slower than this, °C per report.
const PID_SETTLE_SLOPE: f64 = 0.1;

/// Heaters: the extruder's and the bed's.
pub const MAX_HEATERS: usize = 2;
/// ADC inputs: the heaters' thermistors, then the
/// `[temperature_sensor]`s.
pub const INPUTS: usize = MAX_HEATERS + MAX_SENSORS;
/// Longest `gcode_id` of a temperature sensor kept for M105.
const MAX_LABEL: usize = 8;
/// Outputs: the heaters, the fan, then the named fans and pins
/// ([`crate::outputs`]).
pub const OUTPUTS: usize = MAX_HEATERS + 1 + onechip_planner::accessories::MAX_OUTPUTS;

/// Each heater's label (`T`, `B`), smoothed temperature and target (°C)
/// and power (0..1), then each temperature sensor with a `gcode_id` and
/// its last temperature; displayed as the M105 report, Marlin's
/// `T:200.0 /200.0 B:60.0 /60.0 C:35.2 /0.0 @:127 B@:0` (power on
/// Marlin's 0..127).
#[derive(Debug, Clone, PartialEq)]
pub struct Temperatures {
    heaters: heapless::Vec<(&'static str, f64, f64, f64), MAX_HEATERS>,
    sensors: heapless::Vec<(heapless::String<MAX_LABEL>, f64, f64), MAX_SENSORS>,
}

impl core::fmt::Display for Temperatures {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        let heaters = self
            .heaters
            .iter()
            .map(|(l, t, target, _)| (*l, *t, *target));
        let sensors = self
            .sensors
            .iter()
            .map(|(l, t, target)| (l.as_str(), *t, *target));
        for (i, (label, temperature, target)) in heaters.chain(sensors).enumerate() {
            let sep = if i == 0 { "" } else { " " };
            write!(
                f,
                "{sep}{label}:{} /{}",
                Fixed(temperature, 1),
                Fixed(target, 1)
            )?;
        }
        for (label, _, _, power) in &self.heaters {
            // The hot end's power is `@:`, the others' `B@:`.
            let label = if *label == "T" { "" } else { label };
            write!(
                f,
                " {label}@:{}",
                Fixed(clamp(power * 127.0, 0.0, 127.0), 0)
            )?;
        }
        Ok(())
    }
}

/// What a G-code line asks of the heaters and fan.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ThermalCommand {
    /// Heater `heater` to `celsius` (0: off).
    Target {
        /// Index into [`Machine::heaters`].
        heater: usize,
        /// Target, °C.
        celsius: f64,
        /// Wait until it is reached (M109, M190).
        wait: bool,
    },
    /// Report temperatures (M105).
    Report,
    /// The fan to `speed` (0..1) at print time `print_time`.
    Fan {
        /// Speed, 0..1 (before max_power and off_below).
        speed: f64,
        /// When, s of print time.
        print_time: f64,
    },
    /// A named fan, an output pin, or the motors' state.
    Accessory(AccessoryCommand),
    /// Wait until a temperature is within a range (TEMPERATURE_WAIT).
    Wait(Wait),
}

/// A temperature G-code can name: a heater's (its smoothed temperature,
/// as Klipper's heaters report) or a `[temperature_sensor]`'s.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SensorRef {
    /// Index into [`Machine::heaters`].
    Heater(usize),
    /// Index into [`Machine::sensors`].
    Sensor(usize),
}

/// What a thermal wait waits for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Wait {
    /// M109/M190: heater `.0` has reached its target and settled.
    Settled(usize),
    /// TEMPERATURE_WAIT: the temperature of `sensor` is within
    /// `min..=max` (°C).
    Within {
        /// Whose temperature.
        sensor: SensorRef,
        /// MINIMUM, °C (−∞ if not given).
        min: f64,
        /// MAXIMUM, °C (+∞ if not given).
        max: f64,
    },
}

/// Why a TEMPERATURE_WAIT was refused (Klipper's messages).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum WaitError<'l> {
    /// SENSOR names no heater or temperature sensor.
    UnknownSensor(&'l str),
    /// Neither MINIMUM nor MAXIMUM.
    NoRange,
    /// MAXIMUM is not above MINIMUM (`.0`, °C).
    MaximumNotAbove(f64),
}

impl core::fmt::Display for WaitError<'_> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::UnknownSensor(name) => write!(f, "Unknown sensor '{name}'"),
            Self::NoRange => {
                f.write_str("Error on 'TEMPERATURE_WAIT': missing MINIMUM or MAXIMUM.")
            }
            Self::MaximumNotAbove(min) => write!(
                f,
                "Error on 'TEMPERATURE_WAIT': MAXIMUM must be above {}",
                Fixed(*min, 3)
            ),
        }
    }
}

/// -1, 0 or 1.
fn sign(x: f64) -> i8 {
    i8::from(x > 0.0) - i8::from(x < 0.0)
}

/// A heater's control loop state.
#[derive(Debug, Clone, Copy, PartialEq)]
enum ControlState {
    Pid {
        kp: f64,
        ki: f64,
        kd: f64,
        prev_temp: f64,
        prev_err: f64,
        prev_der: f64,
        integral: f64,
    },
    Watermark {
        max_delta: f64,
        heating: bool,
    },
}

impl ControlState {
    fn new(control: Control) -> Self {
        // Klipper's gains act on 0..255; the output here is 0..1.
        match control {
            Control::Pid { kp, ki, kd } => Self::Pid {
                kp: kp / 255.0,
                ki: ki / 255.0,
                kd: kd / 255.0,
                prev_temp: AMBIENT,
                prev_err: 0.0,
                prev_der: 0.0,
                integral: 0.0,
            },
            Control::Watermark { max_delta } => Self::Watermark {
                max_delta,
                heating: false,
            },
        }
    }

    /// The power (0..max_power) after a reading of `temp` (°C), with the
    /// target `target` (°C) and readings `dt` s apart, smoothed over
    /// `smooth_time` s.
    fn update(&mut self, temp: f64, target: f64, max_power: f64, dt: f64, smooth: f64) -> f64 {
        match self {
            Self::Watermark { max_delta, heating } => {
                if *heating && temp >= target + *max_delta {
                    *heating = false;
                } else if !*heating && temp <= target - *max_delta {
                    *heating = true;
                }
                if *heating { max_power } else { 0.0 }
            }
            Self::Pid {
                kp,
                ki,
                kd,
                prev_temp,
                prev_err,
                prev_der,
                integral,
            } => {
                let err = target - temp;
                // Trapezoidal integral; derivative on the measurement,
                // smoothed as a moving average over `smooth` readings.
                let step = (*prev_err + err) * 0.5 * dt;
                let candidate = *integral + step;
                let der = ((smooth - 1.0) * *prev_der - (temp - *prev_temp) / dt) / smooth;
                let out = *kp * err + *ki * candidate + *kd * der;
                let power = clamp(out, 0.0, max_power);
                *prev_temp = temp;
                *prev_der = der;
                if target > 0.0 {
                    *prev_err = err;
                    // Integrate unless saturated the same way as the step.
                    if out == power || sign(out) != sign(step) {
                        *integral = candidate;
                    }
                } else {
                    *prev_err = 0.0;
                    *integral = 0.0;
                }
                power
            }
        }
    }

    /// True while the heater is still reaching its target (M109 waits).
    fn busy(&self, smoothed: f64, target: f64) -> bool {
        match *self {
            Self::Watermark { max_delta, .. } => smoothed < target - max_delta,
            Self::Pid { prev_der, .. } => {
                (target - smoothed).abs() > PID_SETTLE_DELTA || prev_der.abs() > PID_SETTLE_SLOPE
            }
        }
    }
}

/// Klipper's verify_heater state machine for one heater, advanced by
/// [`Verify::check`] once a second of heater time. Time is counted in
/// checks (s), not clock ticks: a 32-bit clock at 260 MHz wraps in 16 s,
/// shorter than check_gain_time.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Verify {
    config: VerifyHeater,
    /// Heating towards a new target, and gaining as expected so far.
    approaching: bool,
    /// The first gain towards that target is not yet made.
    starting: bool,
    /// The target at the previous check, °C.
    last_target: f64,
    /// The temperature to reach by `goal_time`, °C.
    goal_temp: f64,
    /// When `goal_temp` must be reached, s (in checks).
    goal_time: f64,
    /// Accumulated shortfall below target − hysteresis, °C·s.
    error: f64,
    /// Checks so far, s.
    time: f64,
    /// Clock of the next check (None: at the next report).
    next_check: Option<u32>,
}

impl Verify {
    fn new(config: VerifyHeater) -> Self {
        Self {
            config,
            approaching: false,
            starting: false,
            last_target: 0.0,
            goal_temp: 0.0,
            goal_time: 0.0,
            error: 0.0,
            time: 0.0,
            next_check: None,
        }
    }

    /// One check of the smoothed temperature `temp` against `target`
    /// (°C), one second after the previous; false: the heater failed.
    ///
    /// Near the target (within hysteresis below it, or no target) all is
    /// well, and the error clears unless the heater is above target +
    /// hysteresis. Below it the shortfall accumulates every second. A new
    /// target starts an approach: the heater must gain heating_gain
    /// within every check_gain_time (each gain clears the error). Once it
    /// stops gaining, the accumulated error must stay below max_error.
    fn check(&mut self, temp: f64, target: f64) -> bool {
        let c = self.config;
        self.time += VERIFY_TIME;
        let now = self.time;
        let last_target = core::mem::replace(&mut self.last_target, target);
        if target <= 0.0 || temp >= target - c.hysteresis {
            self.approaching = false;
            self.starting = false;
            if temp <= target + c.hysteresis {
                self.error = 0.0;
            }
            return true;
        }
        self.error += target - c.hysteresis - temp;
        if !self.approaching {
            if target != last_target {
                self.approaching = true;
                self.starting = true;
                self.set_goal(temp, now);
            } else if self.error >= c.max_error {
                return false;
            }
        } else if temp >= self.goal_temp {
            self.starting = false;
            self.error = 0.0;
            self.set_goal(temp, now);
        } else if now >= self.goal_time {
            self.approaching = false;
        } else if self.starting {
            self.goal_temp = self.goal_temp.min(temp + c.heating_gain);
        }
        true
    }

    /// The next gain to make: heating_gain above `temp` within
    /// check_gain_time of `now`.
    fn set_goal(&mut self, temp: f64, now: f64) {
        self.goal_temp = temp + self.config.heating_gain;
        self.goal_time = now + self.config.check_gain_time;
    }
}

/// One heater: configuration and state.
#[derive(Debug, Clone, Copy, PartialEq)]
struct HeaterState {
    /// Which heater it is.
    which: shutdown::Heater,
    /// `T` or `B`, as M105 reports it.
    label: &'static str,
    min_temp: f64,
    max_temp: f64,
    max_power: f64,
    /// The PID's derivative is averaged over this many reports.
    smooth: f64,
    /// smooth_time, s.
    smooth_time: f64,
    sensor: onechip_planner::temperature_sensor::TemperatureSensor,
    cycle_ticks: u32,
    control: ControlState,
    target: f64,
    smoothed: f64,
    /// Clock of the last report.
    last_report: Option<u32>,
    /// Last power queued (0..1), and the clock by which to repeat it.
    last_power: f64,
    refresh_by: u32,
    /// min_extrude_temp, °C.
    min_extrude_temp: f64,
    /// The smoothed temperature is at least min_extrude_temp (Klipper's
    /// `can_extrude`, updated at each report).
    can_extrude: bool,
    /// verify_heater.
    verify: Verify,
}

/// The MCU configuration of the heaters and fan, as Klipper sends it:
/// outputs (in [`Heaters`] order: heaters, the fan, then the named fans
/// and pins) and ADC queries.
#[derive(Debug, Clone, PartialEq)]
pub struct McuSetup<'a> {
    /// Each output's pin (as printer.cfg writes it) and configuration.
    pub outputs: heapless::Vec<(&'a str, OutputConfig), OUTPUTS>,
    /// Each output's levels, by the index of `outputs`.
    pub levels: heapless::Vec<Levels, OUTPUTS>,
    /// Each heater's sensor pin and query, then each temperature
    /// sensor's (an SPI chip's pin is its chip select).
    pub inputs: heapless::Vec<(&'a str, InputQuery), INPUTS>,
}

/// How an input is read: an ADC channel's query, or an SPI chip's.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InputQuery {
    /// Klipper's `query_analog_in`.
    Adc(AdcQuery),
    /// Klipper's `query_thermocouple`, with the chip's start-up bytes.
    Spi(SpiQuery),
}

impl InputQuery {
    /// The ADC query, if it is one.
    pub fn adc(&self) -> Option<&AdcQuery> {
        match self {
            Self::Adc(q) => Some(q),
            Self::Spi(_) => None,
        }
    }

    /// The SPI query, if it is one.
    pub fn spi(&self) -> Option<&SpiQuery> {
        match self {
            Self::Spi(q) => Some(q),
            Self::Adc(_) => None,
        }
    }
}

/// The MCU's query of SPI chip `sensor`: a read every [`REPORT_TIME`]
/// from clock `start`, its raw values of `min_temp` and `max_temp` the
/// range (Klipper's `setup_minmax`).
fn spi_query(sensor: &SpiSensor, min_temp: f64, max_temp: f64, freq: f64, start: u32) -> SpiQuery {
    let (min, max) = sensor.raw_range(min_temp, max_temp);
    let mut init = [0; 4];
    let bytes = sensor.init_bytes();
    let len = bytes.len().min(init.len());
    init[..len].copy_from_slice(&bytes[..len]);
    SpiQuery {
        chip: match sensor.chip {
            Chip::Max6675 => SpiChip::Max6675,
            Chip::Max31855 => SpiChip::Max31855,
            Chip::Max31856 => SpiChip::Max31856,
            Chip::Max31865 => SpiChip::Max31865,
        },
        clock: start,
        rest_ticks: ticks(REPORT_TIME, freq),
        min,
        max,
        max_invalid: SPI_MAX_INVALID,
        init,
        init_len: len as u8,
    }
}

/// The query of a sensor read as `conversion` says, limited to
/// `min_temp..max_temp`.
fn input_query(
    conversion: &Conversion,
    (min_temp, max_temp): (f64, f64),
    freq: f64,
    adc_max: u16,
    start: u32,
) -> InputQuery {
    match conversion {
        Conversion::Sensor(TemperatureSensor::Spi(chip)) => {
            InputQuery::Spi(spi_query(chip, min_temp, max_temp, freq, start))
        }
        _ => {
            let range = conversion.reading_range(min_temp, max_temp);
            InputQuery::Adc(adc_query(range, freq, adc_max, start))
        }
    }
}

/// A fraction (0..1) of an output's full scale, rounded, as Klipper's
/// `set_pwm` computes on ticks or duty.
pub(crate) fn scaled(fraction: f64, full: u32) -> u32 {
    (fraction * f64::from(full) + 0.5) as u32
}

/// Seconds to ticks, as Klipper's `seconds_to_clock` (truncated).
pub(crate) fn ticks(seconds: f64, freq: f64) -> u32 {
    (seconds * freq) as u32
}

impl<'a> McuSetup<'a> {
    /// The configuration for `machine` on an MCU whose clock runs at
    /// `freq` Hz, whose ADC reads 0..=`adc_max` and whose internal
    /// temperature sensor the factory calibrated as `mcu_sensor`; the
    /// first readings at clock `start`.
    pub fn new(
        machine: &Machine<'a>,
        freq: f64,
        adc_max: u16,
        mcu_sensor: LinearConversion,
        start: u32,
    ) -> Self {
        let mut setup = Self {
            outputs: heapless::Vec::new(),
            levels: heapless::Vec::new(),
            inputs: heapless::Vec::new(),
        };
        let off = Levels {
            start: 0.0,
            shutdown: 0.0,
        };
        for heater in &machine.heaters {
            let output = OutputConfig {
                kind: OutputKind::Digital {
                    cycle_ticks: ticks(heater.pwm_cycle_time, freq),
                },
                value: 0,
                default: 0,
                max_duration: ticks(MAX_HEAT_TIME, freq),
            };
            let _ = setup.outputs.push((heater.heater_pin, output));
            let _ = setup.levels.push(off);
            let limits = (heater.min_temp, heater.max_temp);
            let conversion = Conversion::Sensor(heater.sensor);
            let query = input_query(&conversion, limits, freq, adc_max, start);
            let _ = setup.inputs.push((heater.sensor_pin, query));
        }
        for sensor in &machine.sensors {
            let limits = (sensor.min_temp, sensor.max_temp);
            let conversion = sensor.conversion(mcu_sensor);
            let query = input_query(&conversion, limits, freq, adc_max, start);
            let _ = setup.inputs.push((sensor.input.pin(), query));
        }
        let part_fan =
            (machine.fan.iter()).map(|fan| (fan.pin, fan_config(fan, freq), fan_levels(fan)));
        let accessories = crate::outputs::output_configs(&machine.accessories, freq);
        for (pin, config, levels) in part_fan.chain(accessories) {
            if setup.outputs.push((pin, config)).is_err() {
                break;
            }
            let _ = setup.levels.push(levels);
        }
        setup
    }
}

/// Each input's SPI bus (None: an ADC input), in [`McuSetup::inputs`]'
/// order: the heaters', then the temperature sensors'.
pub fn input_buses<'m, 'a>(
    machine: &'m Machine<'a>,
) -> impl Iterator<Item = Option<SpiBus<'a>>> + 'm {
    let heaters = machine.heaters.iter().map(|h| h.spi);
    let sensors = machine.sensors.iter().map(|s| match s.input {
        onechip_planner::sensor_section::SensorInput::Spi { bus, .. } => Some(bus),
        _ => None,
    });
    heaters.chain(sensors)
}

/// Each input's SPI chip (None: an ADC input), in
/// [`McuSetup::inputs`]' order.
pub fn input_chips<'m>(machine: &'m Machine<'_>) -> impl Iterator<Item = Option<SpiSensor>> + 'm {
    let heaters = machine.heaters.iter().map(|h| h.sensor.spi().copied());
    let sensors = machine.sensors.iter().map(|s| match s.input {
        onechip_planner::sensor_section::SensorInput::Spi { sensor, .. } => Some(sensor),
        _ => None,
    });
    heaters.chain(sensors)
}

/// An output's full-scale value: its cycle ticks (software PWM) or
/// [`PWM_MAX`] (hardware PWM).
pub fn full_scale(kind: OutputKind) -> u32 {
    match kind {
        OutputKind::Digital { cycle_ticks } => cycle_ticks,
        OutputKind::HardPwm { .. } => PWM_MAX,
    }
}

/// A report's full scale: the sum of its readings at 0..=`adc_max`.
fn adc_full(adc_max: u16) -> f64 {
    f64::from(SAMPLE_COUNT) * f64::from(adc_max)
}

/// Queues an output update on `io`; a full queue drops it (the next
/// report or check repeats it), a late one has shut everything down.
fn queue_on(
    io: &mut Io<OUTPUTS, INPUTS>,
    index: usize,
    clock: u32,
    value: u32,
    now: u32,
    hw: &mut impl Peripherals,
) -> Result<(), Shutdown> {
    match io.queue(index, clock, value, now, hw) {
        Err(QueueError::Late) => Err(Shutdown::TimerTooClose),
        _ => Ok(()),
    }
}

/// A sensor's query: 8 readings 1 ms apart every 0.3 s, the sum within
/// `(low, high)`, the readings (fractions of full scale) of min_temp and
/// max_temp, lowest first.
fn adc_query((low, high): (f64, f64), freq: f64, adc_max: u16, start: u32) -> AdcQuery {
    let full = adc_full(adc_max);
    let counts = |v: f64| clamp(v, 0.0, f64::from(u16::MAX)) as u16;
    AdcQuery {
        clock: start,
        sample_ticks: ticks(SAMPLE_TIME, freq),
        sample_count: SAMPLE_COUNT,
        rest_ticks: ticks(REPORT_TIME, freq),
        min: counts(low * full),
        max: counts(libm::ceil(high * full)),
        range_check_count: RANGE_CHECK_COUNT,
    }
}

/// Why a heater command was refused.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ThermalError {
    /// No such heater.
    NoHeater,
    /// The target is outside min_temp..max_temp.
    OutOfRange {
        /// Requested, °C.
        celsius: f64,
        /// min_temp, °C.
        min: f64,
        /// max_temp, °C.
        max: f64,
    },
}

impl core::fmt::Display for ThermalError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::NoHeater => f.write_str("No such heater configured"),
            Self::OutOfRange { celsius, min, max } => write!(
                f,
                "Requested temperature ({}) out of range ({}:{})",
                Fixed(*celsius, 1),
                Fixed(*min, 1),
                Fixed(*max, 1)
            ),
        }
    }
}

/// A `[temperature_sensor]` at run time.
#[derive(Debug, Clone)]
struct SensorState {
    conversion: Conversion,
    /// Its M105 label (`gcode_id`), if any.
    label: Option<heapless::String<MAX_LABEL>>,
    /// The last temperature read, °C.
    reading: Option<f64>,
}

/// The heaters, the fan, the temperature sensors and the MCU role's io
/// that drives and reads them.
#[derive(Debug, Clone)]
pub struct Heaters {
    io: Io<OUTPUTS, INPUTS>,
    heaters: heapless::Vec<HeaterState, MAX_HEATERS>,
    sensors: heapless::Vec<SensorState, MAX_SENSORS>,
    fan: Option<FanControl>,
    /// The named fans and pins, io outputs after the fan.
    accessories: AccessoryOutputs,
    /// Ticks from a report to the update it causes.
    pwm_delay: u32,
    /// Ticks after which a heater's unchanged power is sent again.
    refresh_ticks: u32,
    /// Ticks a report's readings take: klippy times a report by their
    /// end.
    sampling_ticks: u32,
    /// Ticks between verify_heater checks.
    verify_ticks: u32,
    freq: f64,
    adc_full: f64,
}

impl Heaters {
    /// The heaters, fan and temperature sensors of `machine` on an MCU at
    /// `freq` Hz with ADC range 0..=`adc_max` and its internal sensor
    /// calibrated as `mcu_sensor`, configured on `hw` with the first
    /// readings at clock `start`. Outputs: heaters, then the fan; ADC
    /// inputs: heaters, then the temperature sensors.
    pub fn new(
        machine: &Machine<'_>,
        freq: f64,
        adc_max: u16,
        mcu_sensor: LinearConversion,
        start: u32,
        hw: &mut impl Peripherals,
    ) -> Self {
        let setup = McuSetup::new(machine, freq, adc_max, mcu_sensor, start);
        let mut io = Io::new();
        for (_, config) in &setup.outputs {
            let _ = io.add_output(*config, hw);
        }
        for (pin, query) in &setup.inputs {
            // One on another MCU is read there: its reports come through
            // `remote_reading`.
            let here = crate::mcu_config::on_main(pin);
            match query {
                InputQuery::Adc(q) => {
                    if let Ok(index) = io.add_input()
                        && here
                    {
                        let _ = io.query(index, *q);
                    }
                }
                InputQuery::Spi(q) => {
                    if let Ok(index) = io.add_spi_input()
                        && here
                    {
                        let _ = io.query_spi(index, *q, hw);
                    }
                }
            }
        }
        // Each output's scale comes from its MCU configuration: heaters
        // first, then the fan.
        let dt = PWM_DELAY;
        let heaters = machine
            .heaters
            .iter()
            .zip(&setup.outputs)
            .map(|(h, (_, output))| HeaterState {
                which: if h.name == "heater_bed" {
                    shutdown::Heater::Bed
                } else {
                    shutdown::Heater::Extruder
                },
                label: if h.name == "heater_bed" { "B" } else { "T" },
                min_temp: h.min_temp,
                max_temp: h.max_temp,
                max_power: h.max_power,
                smooth: 1.0 + h.smooth_time / dt,
                smooth_time: h.smooth_time,
                sensor: h.sensor,
                cycle_ticks: full_scale(output.kind),
                control: ControlState::new(h.control),
                target: 0.0,
                smoothed: 0.0,
                last_report: None,
                last_power: 0.0,
                refresh_by: start,
                min_extrude_temp: h.min_extrude_temp,
                can_extrude: h.min_extrude_temp <= 0.0,
                verify: Verify::new(h.verify),
            })
            .collect();
        let fan_config = setup.outputs.get(machine.heaters.len());
        let fan = machine
            .fan
            .zip(fan_config)
            .map(|(f, (_, output))| FanControl::new(&f, full_scale(output.kind), freq));
        let sensors = machine
            .sensors
            .iter()
            .map(|s| SensorState {
                conversion: s.conversion(mcu_sensor),
                label: s
                    .gcode_id
                    .and_then(|id| heapless::String::try_from(id).ok()),
                reading: None,
            })
            .collect();
        let first = machine.heaters.len() + usize::from(fan.is_some());
        let accessories = AccessoryOutputs::new(&machine.accessories, first, freq, start);
        Self {
            io,
            heaters,
            sensors,
            fan,
            accessories,
            pwm_delay: ticks(PWM_DELAY, freq),
            // klippy's: three report periods (and a ms) short of
            // max_duration, so that the next report's update comes in
            // time even over a secondary MCU's link.
            refresh_ticks: ticks(MAX_HEAT_TIME - (3.0 * REPORT_TIME + 0.001), freq),
            sampling_ticks: ticks(f64::from(SAMPLE_COUNT) * SAMPLE_TIME, freq),
            verify_ticks: ticks(VERIFY_TIME, freq),
            freq,
            adc_full: adc_full(adc_max),
        }
    }

    /// When [`Self::run`] must run next (MCU clock), if ever.
    pub fn next_wake(&self) -> Option<u32> {
        let io = self.io.next_wake();
        if self.io.shutdown_reason().is_some() {
            return io;
        }
        let fan = self.fan.and_then(|f| f.busy_until());
        [self.accessories.next_wake(), fan]
            .into_iter()
            .fold(io, |a, b| match (a, b) {
                (Some(a), Some(b)) => Some(if is_before(b, a) { b } else { a }),
                (a, b) => a.or(b),
            })
    }

    /// The timer's work at clock `now`: outputs, readings, and each new
    /// temperature report's control update. A fault (ADC out of range, an
    /// output past max_duration) has shut every output down and is
    /// returned; the caller stops the steppers too.
    pub fn run(&mut self, now: u32, hw: &mut impl Peripherals) -> Result<(), Shutdown> {
        self.io.run(now, hw)?;
        for index in 0..self.heaters.len() + self.sensors.len() {
            let Some(conversion) = self.conversion(index) else {
                continue;
            };
            if let Some((clock, temp)) = self.reading(index, &conversion) {
                self.on_temperature(index, clock, temp, now, hw)?;
            }
        }
        if self.io.shutdown_reason().is_some() {
            return Ok(());
        }
        if let Some(fan) = &mut self.fan {
            fan.expire(now);
        }
        let readings: heapless::Vec<(f64, f64), MAX_HEATERS> = self
            .heaters
            .iter()
            .map(|h| (h.target, h.smoothed))
            .collect();
        let io = &mut self.io;
        self.accessories
            .poll(now, &readings, &mut |index, clock, value| {
                queue_on(io, index, clock, value, now, hw)
            })
    }

    /// A report of io input `reading.input` taken by another MCU (a
    /// secondary's `analog_in_state`, as the secondaries hand it over):
    /// the sum of its samples as `reading.value` (0..1 of its full scale),
    /// the first of them at host time `reading.at` (s), which is this
    /// MCU's clock of `freq` Hz in seconds; `now` is this MCU's clock. It
    /// is handled as this MCU's own reports are (the heater's control and
    /// verify_heater, a temperature fan's update); a fault is returned.
    /// Ignored after a shutdown (the other MCU may report until it hears
    /// of it).
    pub fn remote_reading(
        &mut self,
        reading: &Reading,
        freq: f64,
        now: u32,
        hw: &mut impl Peripherals,
    ) -> Result<(), Shutdown> {
        if self.io.shutdown_reason().is_some() {
            return Ok(());
        }
        let Some(conversion) = self.conversion(reading.input) else {
            return Ok(());
        };
        let clock = (reading.at * freq).max(0.0) as u64 as u32;
        let temp = conversion.temperature(reading.value);
        self.on_temperature(reading.input, clock, temp, now, hw)
    }

    /// Input `index`'s conversion (the heaters', then the temperature
    /// sensors').
    fn conversion(&self, index: usize) -> Option<Conversion> {
        match self.heaters.get(index) {
            Some(h) => Some(Conversion::Sensor(h.sensor)),
            None => Some(self.sensors.get(index - self.heaters.len())?.conversion),
        }
    }

    /// Input `index`'s temperature `temp` (°C) read at clock `clock`: a
    /// heater's control, or a temperature sensor's reading (and its
    /// temperature fan's update).
    fn on_temperature(
        &mut self,
        index: usize,
        clock: u32,
        temp: f64,
        now: u32,
        hw: &mut impl Peripherals,
    ) -> Result<(), Shutdown> {
        let Some(i) = index.checked_sub(self.heaters.len()) else {
            return self.control(index, clock, temp, now, hw);
        };
        let delay = ticks(REPORT_TIME, self.freq);
        let io = &mut self.io;
        self.accessories.sensor_report(
            i,
            temp,
            clock,
            now,
            delay,
            &mut |index, clock, value| queue_on(io, index, clock, value, now, hw),
        )?;
        if let Some(sensor) = self.sensors.get_mut(i) {
            sensor.reading = Some(temp);
        }
        Ok(())
    }

    /// Input `index`'s new report, if any, as its clock and temperature
    /// (°C) through `conversion`. An SPI chip's report with its fault
    /// register set carries no temperature (Klipper's host logs the fault
    /// and drops it; the MCU counts it towards a shutdown).
    fn reading(&mut self, index: usize, conversion: &Conversion) -> Option<(u32, f64)> {
        if let Some(report) = self.io.take_report(index) {
            let reading = f64::from(report.value) / self.adc_full;
            return Some((report.clock, conversion.temperature(reading)));
        }
        let SpiReport {
            clock,
            value,
            fault,
        } = self.io.take_spi_report(index)?;
        (fault == 0).then(|| (clock, conversion.temperature(f64::from(value))))
    }

    /// A heater's report (temperature `temp`, °C, read at `clock`): the
    /// control, and the update it causes (Klipper's
    /// `temperature_callback` and `set_pwm`); then, if a second has
    /// passed since the last, its verify_heater check, whose failure
    /// shuts everything down.
    fn control(
        &mut self,
        index: usize,
        clock: u32,
        temp: f64,
        now: u32,
        hw: &mut impl Peripherals,
    ) -> Result<(), Shutdown> {
        let Some(h) = self.heaters.get_mut(index) else {
            return Ok(());
        };
        let dt = PWM_DELAY;
        let mut power = h.control.update(temp, h.target, h.max_power, dt, h.smooth);
        // Exponential smoothing over smooth_time (the first reading is
        // taken as it is).
        let weight = h.last_report.map_or(1.0, |last| {
            let elapsed = f64::from(clock.wrapping_sub(last)) / self.freq;
            (elapsed / h.smooth_time).min(1.0)
        });
        h.last_report = Some(clock);
        h.smoothed += (temp - h.smoothed) * weight;
        h.can_extrude = h.smoothed >= h.min_extrude_temp;
        if !Self::verify(h, clock, self.verify_ticks) {
            let reason = Shutdown::NotHeating(h.which);
            self.io.shutdown(reason, hw);
            return Err(reason);
        }
        if h.target <= 0.0 {
            power = 0.0;
        }
        let read = clock.wrapping_add(self.sampling_ticks);
        let fresh = is_before(read, h.refresh_by) && h.last_power != 0.0;
        if (fresh || h.last_power == 0.0) && (power - h.last_power).abs() < 0.05 {
            return Ok(());
        }
        let at = clock.wrapping_add(self.pwm_delay);
        h.refresh_by = at.wrapping_add(self.refresh_ticks);
        h.last_power = power;
        let on_ticks = scaled(power, h.cycle_ticks);
        self.queue(index, at, on_ticks, now, hw)
    }

    /// Runs `h`'s verify_heater check if it is due at report clock
    /// `clock` (checks `verify_ticks` apart; one that came late restarts
    /// the count from this report); false: the heater failed.
    fn verify(h: &mut HeaterState, clock: u32, verify_ticks: u32) -> bool {
        let v = &mut h.verify;
        let next = match v.next_check {
            None => clock,
            Some(next) if is_before(clock, next) => return true,
            Some(next) if is_before(clock, next.wrapping_add(verify_ticks)) => next,
            Some(_) => clock,
        };
        v.next_check = Some(next.wrapping_add(verify_ticks));
        v.check(h.smoothed, h.target)
    }

    /// Queues an output update; a full queue drops it (the next report
    /// repeats it), a late one has shut everything down.
    fn queue(
        &mut self,
        index: usize,
        clock: u32,
        value: u32,
        now: u32,
        hw: &mut impl Peripherals,
    ) -> Result<(), Shutdown> {
        queue_on(&mut self.io, index, clock, value, now, hw)
    }

    /// Carries out `command` at clock `now`.
    pub fn command(
        &mut self,
        command: ThermalCommand,
        now: u32,
        hw: &mut impl Peripherals,
    ) -> Result<(), Shutdown> {
        match command {
            ThermalCommand::Target {
                heater, celsius, ..
            } => {
                if let Some(h) = self.heaters.get_mut(heater) {
                    h.target = celsius;
                }
                Ok(())
            }
            ThermalCommand::Fan { speed, print_time } => {
                let clock = (print_time * self.freq) as u64 as u32;
                self.set_fan(speed, clock, now, hw)
            }
            ThermalCommand::Report | ThermalCommand::Wait(_) => Ok(()),
            ThermalCommand::Accessory(command) => {
                let io = &mut self.io;
                self.accessories
                    .command(command, now, &mut |index, clock, value| {
                        queue_on(io, index, clock, value, now, hw)
                    })
            }
        }
    }

    /// The part fan to `speed` (0..1) at `clock` ([`FanControl`]).
    fn set_fan(
        &mut self,
        speed: f64,
        clock: u32,
        now: u32,
        hw: &mut impl Peripherals,
    ) -> Result<(), Shutdown> {
        let index = self.heaters.len();
        let Some(fan) = &mut self.fan else {
            return Ok(());
        };
        for (at, value) in fan.set(speed, clock, now) {
            queue_on(&mut self.io, index, at, value, now, hw)?;
        }
        Ok(())
    }

    /// True while `wait` is not over: a heater still reaching its target
    /// (M109, M190), or a temperature outside its range
    /// (TEMPERATURE_WAIT; before its first reading, too).
    pub fn waiting(&self, wait: Wait) -> bool {
        match wait {
            Wait::Settled(heater) => self
                .heaters
                .get(heater)
                .is_some_and(|h| h.target > 0.0 && h.control.busy(h.smoothed, h.target)),
            Wait::Within { sensor, min, max } => !self
                .temperature_of(sensor)
                .is_some_and(|t| (min..=max).contains(&t)),
        }
    }

    /// The temperature of `sensor` now, once it has been read, °C.
    pub fn temperature_of(&self, sensor: SensorRef) -> Option<f64> {
        match sensor {
            SensorRef::Heater(i) => self
                .heaters
                .get(i)
                .filter(|h| h.last_report.is_some())
                .map(|h| h.smoothed),
            SensorRef::Sensor(i) => self.sensor(i),
        }
    }

    /// True if the extruder may extrude: its heater's smoothed temperature
    /// is at least its min_extrude_temp at its last report (before the
    /// first: only if min_extrude_temp is 0 or less), or it has no
    /// heater. The
    /// session tells the planner before each line
    /// (`Printer::set_can_extrude`).
    pub fn can_extrude(&self) -> bool {
        self.heaters
            .iter()
            .find(|h| h.which == shutdown::Heater::Extruder)
            .is_none_or(|h| h.can_extrude)
    }

    /// Heater `heater`'s smoothed temperature and target, °C.
    pub fn temperature(&self, heater: usize) -> Option<(f64, f64)> {
        self.heaters.get(heater).map(|h| (h.smoothed, h.target))
    }

    /// The fan's power (0..1).
    pub fn fan_speed(&self) -> Option<f64> {
        self.fan.map(|f| f.power())
    }

    /// Named fan `fan`'s power (0..1), as last set.
    pub fn named_fan_power(&self, fan: usize) -> Option<f64> {
        self.accessories.fan_power(fan)
    }

    /// Output `index`'s value now (on ticks, or duty), in the io's order
    /// ([`McuSetup::outputs`]).
    pub fn output_value(&self, index: usize) -> Option<u32> {
        self.io.value(index)
    }

    /// The M105 report: `T:<temp> /<target> B:<temp> /<target>`.
    pub fn report(&self, out: &mut impl Write) -> core::fmt::Result {
        write!(out, "{}", self.temperatures())
    }

    /// Every heater's label, temperature and target, and every labelled
    /// sensor's temperature: a few bytes to copy where the heaters'
    /// interrupt is held off, and format after ([`Temperatures`]' Display
    /// is the M105 report).
    pub fn temperatures(&self) -> Temperatures {
        Temperatures {
            heaters: self
                .heaters
                .iter()
                .map(|h| (h.label, h.smoothed, h.target, h.last_power))
                .collect(),
            sensors: (self.sensors.iter().enumerate())
                .filter_map(|(i, s)| {
                    let target = self.accessories.cooling_target(i).unwrap_or(0.0);
                    Some((s.label.clone()?, s.reading?, target))
                })
                .collect(),
        }
    }

    /// Temperature sensor `index`'s temperature (in [`Machine::sensors`]
    /// order), once it has reported, °C.
    pub fn sensor(&self, index: usize) -> Option<f64> {
        self.sensors.get(index)?.reading
    }

    /// Why the heaters shut down, if they did.
    pub fn shutdown_reason(&self) -> Option<Shutdown> {
        self.io.shutdown_reason()
    }

    /// Shuts every output down (the steppers faulted).
    pub fn shutdown(&mut self, reason: Shutdown, hw: &mut impl Peripherals) {
        self.io.shutdown(reason, hw);
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use onechip_config::Config;
    use onechip_planner::sensor_section::TYPICAL_STM32H7_CAL;
    use onechip_sched::outputs::Drive;

    /// A typical STM32H7's internal sensor.
    pub(crate) fn typical_mcu() -> LinearConversion {
        LinearConversion::stm32h7(TYPICAL_STM32H7_CAL)
    }

    /// MCU clock, Hz: one tick per µs.
    const FREQ: f64 = 1_000_000.0;
    /// A printer with the part-cooling fan only (software PWM, 0.010 s
    /// cycle: full scale 10 000 ticks; kick_start_time 0.1 s).
    pub(crate) const FAN_ONLY: &str = "[printer]\nkinematics: cartesian\nmax_velocity: 300\nmax_accel: 3000\n\
        [stepper_x]\nstep_pin: PF13\ndir_pin: PF12\nmicrosteps: 16\nrotation_distance: 40\n\
        position_endstop: 0\nposition_max: 200\n\
        [stepper_y]\nstep_pin: PG0\ndir_pin: PG1\nmicrosteps: 16\nrotation_distance: 40\n\
        position_endstop: 0\nposition_max: 200\n\
        [stepper_z]\nstep_pin: PF11\ndir_pin: PG3\nmicrosteps: 16\nrotation_distance: 8\n\
        position_endstop: 0\nposition_max: 200\n\
        [fan]\npin: PA8\n";
    /// The shipped printer: two heaters and the fan.
    const SHIPPED: &str = include_str!("../../sdcard-configs/octopus-pro-h723/printer.cfg");

    /// Hardware that ignores outputs and reads mid-scale.
    struct Hw;

    impl Peripherals for Hw {
        fn drive(&mut self, _: usize, _: Drive) {}
        fn read_adc(&mut self, _: usize) -> u16 {
            2048
        }
    }

    /// Sets the fan to `speed` at `seconds`, then returns its output value
    /// at each of `at` (clock, µs).
    fn fan_values<const K: usize>(
        heaters: &mut Heaters,
        speed: f64,
        seconds: f64,
        at: [u32; K],
    ) -> [Option<u32>; K] {
        let fan = ThermalCommand::Fan {
            speed,
            print_time: seconds,
        };
        heaters.command(fan, 0, &mut Hw).expect("queued");
        at.map(|t| {
            heaters.run(t, &mut Hw).expect("runs");
            heaters.io.value(heaters.heaters.len())
        })
    }

    #[test]
    fn the_fan_kicks_when_it_starts_from_still() {
        let config = Config::parse("printer.cfg", FAN_ONLY).expect("config");
        let machine = Machine::from_config(&config).expect("machine");
        let mut heaters = Heaters::new(&machine, FREQ, 4095, typical_mcu(), 0, &mut Hw);
        // 0 -> 0.4: full power for kick_start_time, then 0.4.
        let kicked = fan_values(&mut heaters, 0.4, 1.0, [1_000_000, 1_100_000]);
        assert_eq!(kicked, [Some(10_000), Some(4_000)]);
        // 0.4 -> 0.6: running and rising by less than half: no kick.
        assert_eq!(
            fan_values(&mut heaters, 0.6, 2.0, [2_000_000]),
            [Some(6_000)]
        );
        // 0.1 -> 0.7: rising by more than half: a kick again.
        assert_eq!(
            fan_values(&mut heaters, 0.1, 3.0, [3_000_000]),
            [Some(1_000)]
        );
        let kicked = fan_values(&mut heaters, 0.7, 4.0, [4_000_000, 4_100_000]);
        assert_eq!(kicked, [Some(10_000), Some(7_000)]);
        // Off, then on again: from still, so a kick.
        assert_eq!(fan_values(&mut heaters, 0.0, 5.0, [5_000_000]), [Some(0)]);
        let kicked = fan_values(&mut heaters, 0.3, 6.0, [6_000_000, 6_100_000]);
        assert_eq!(kicked, [Some(10_000), Some(3_000)]);
    }

    #[test]
    fn outputs_scale_as_the_mcu_setup_configures_them() {
        let config = Config::parse("printer.cfg", SHIPPED).expect("config");
        let machine = Machine::from_config(&config).expect("machine");
        let setup = McuSetup::new(&machine, FREQ, 4095, typical_mcu(), 0);
        let heaters = Heaters::new(&machine, FREQ, 4095, typical_mcu(), 0, &mut Hw);
        let scales = setup.outputs.iter().map(|(_, c)| full_scale(c.kind));
        let used = heaters.heaters.iter().map(|h| h.cycle_ticks);
        let used = used.chain(heaters.fan.map(|f| f.full()));
        assert!(scales.clone().eq(used));
        // Klipper's defaults: heaters 0.1 s cycles, the fan 0.010 s.
        assert!(scales.eq([100_000, 100_000, 10_000]));
    }

    /// Hardware that ignores outputs; input `i` reads `.0[i]` counts.
    struct Reads([u16; 2]);

    impl Peripherals for Reads {
        fn drive(&mut self, _: usize, _: Drive) {}
        fn read_adc(&mut self, index: usize) -> u16 {
            self.0.get(index).copied().unwrap_or(0)
        }
    }

    /// Klipper's defaults for the hot end.
    fn hot_end() -> Verify {
        Verify::new(VerifyHeater::defaults("extruder"))
    }

    /// Checks `verify` once a second against `temps(second)` and `target`
    /// for up to `seconds` checks; the check (1-based) that failed.
    fn fails_at(
        verify: &mut Verify,
        seconds: u32,
        target: impl Fn(u32) -> f64,
        temps: impl Fn(u32) -> f64,
    ) -> Option<u32> {
        (1..=seconds).find(|&s| !verify.check(temps(s), target(s)))
    }

    #[test]
    fn a_heater_gaining_as_expected_never_faults() {
        // 1 °C/s up to the target, then holding it.
        let rising = |s: u32| (25.0 + f64::from(s)).min(200.0);
        assert_eq!(fails_at(&mut hot_end(), 1000, |_| 200.0, rising), None);
        // Slowing to 0.11 °C/s: still heating_gain (2 °C) within every
        // check_gain_time (20 s).
        let slow = |s: u32| 25.0 + 0.11 * f64::from(s);
        assert_eq!(fails_at(&mut hot_end(), 1000, |_| 200.0, slow), None);
        // No target: nothing to check.
        assert_eq!(fails_at(&mut hot_end(), 1000, |_| 0.0, |_| 25.0), None);
    }

    #[test]
    fn a_heater_that_stops_gaining_faults_once_its_gain_time_is_over() {
        // A dead heater: the approach starts at the first check; after 20
        // s without the 2 °C gain it is over, and the error accumulated
        // (170 °C·s a second) is far past max_error at the next check.
        assert_eq!(fails_at(&mut hot_end(), 100, |_| 200.0, |_| 25.0), Some(22));
        // 0.09 °C/s: 2 °C takes 22 s, longer than check_gain_time.
        let slow = |s: u32| 25.0 + 0.09 * f64::from(s);
        assert_eq!(fails_at(&mut hot_end(), 100, |_| 200.0, slow), Some(22));
        // The bed gets 60 s.
        let mut bed = Verify::new(VerifyHeater::defaults("heater_bed"));
        assert_eq!(fails_at(&mut bed, 100, |_| 60.0, |_| 25.0), Some(62));
    }

    #[test]
    fn within_hysteresis_is_at_temperature_and_just_below_it_accumulates() {
        // Stuck 5 °C below target (the hysteresis): at temperature.
        assert_eq!(fails_at(&mut hot_end(), 1000, |_| 200.0, |_| 195.0), None);
        // Stuck 6 °C below: 1 °C·s a second from the first check, so
        // max_error (120) is reached at the 120th.
        assert_eq!(
            fails_at(&mut hot_end(), 1000, |_| 200.0, |_| 194.0),
            Some(120)
        );
        // A heater that held its target and then sags: the error counts
        // from the sag (no new target, so no approach).
        let sags = |s: u32| if s < 100 { 200.0 } else { 190.0 };
        assert_eq!(fails_at(&mut hot_end(), 1000, |_| 200.0, sags), Some(123));
    }

    #[test]
    fn a_new_target_starts_a_new_approach() {
        // Heats to 150 °C by 25 s and stays there with a target of 200 °C:
        // its approach ends at 45 s (20 s without gain; error 45 °C·s a
        // second since). At 46 s the target goes up to 210 °C, which starts
        // a new approach instead of failing; only 20 s later without gain
        // does it fail.
        let temps = |s: u32| (25.0 + 5.0 * f64::from(s)).min(150.0);
        let target = |s: u32| if s <= 45 { 200.0 } else { 210.0 };
        let mut v = hot_end();
        assert_eq!(fails_at(&mut v, 45, target, temps), None);
        assert!(v.error > v.config.max_error && !v.approaching, "{v:?}");
        assert_eq!(
            (46..=200).find(|&s| !v.check(temps(s), target(s))),
            Some(67)
        );
        // Without the change, it fails right away.
        assert_eq!(fails_at(&mut hot_end(), 100, |_| 200.0, temps), Some(46));
    }

    #[test]
    fn a_cooling_heater_is_not_a_fault() {
        // At 200 °C, the target drops to 60 °C: above target + hysteresis
        // while it cools, no error; then the target off.
        let temps = |s: u32| (200.0 - f64::from(s)).max(60.0);
        let target = |s: u32| if s < 300 { 60.0 } else { 0.0 };
        let mut v = hot_end();
        assert_eq!(fails_at(&mut v, 1000, target, temps), None);
        assert_eq!(v.error, 0.0);
        assert!(!v.approaching);
    }

    #[test]
    fn a_heater_that_does_not_heat_shuts_everything_down_with_klippers_message() {
        let config = Config::parse("printer.cfg", SHIPPED).expect("config");
        let machine = Machine::from_config(&config).expect("machine");
        // Both thermistors read a constant 60 °C or so: the heaters do
        // nothing.
        let reading = (machine.heaters[0].sensor.adc(60.0) * 4095.0) as u16;
        let mut hw = Reads([reading, 2048]);
        let mut heaters = Heaters::new(&machine, FREQ, 4095, typical_mcu(), 0, &mut hw);
        let target = ThermalCommand::Target {
            heater: 0,
            celsius: 200.0,
            wait: false,
        };
        heaters.command(target, 0, &mut hw).expect("in range");
        let mut now;
        let fault = loop {
            let Some(wake) = heaters.next_wake() else {
                panic!("stopped without a fault")
            };
            now = wake;
            if let Err(reason) = heaters.run(now, &mut hw) {
                break reason;
            }
            assert!(now < 60_000_000, "no fault in 60 s");
        };
        assert_eq!(fault, Shutdown::NotHeating(shutdown::Heater::Extruder));
        assert_eq!(
            fault.message(),
            "Heater extruder not heating at expected rate"
        );
        assert_eq!(
            fault.hint(),
            [
                "See the 'verify_heater' section in docs/Config_Reference.md",
                "for the parameters that control this check."
            ]
        );
        // The first check at the first report (0 s), the 22nd 21 s later
        // (checks are a second apart, at the first report after each).
        let seconds = f64::from(now) / FREQ;
        assert!((21.0..21.3).contains(&seconds), "{seconds}");
        assert_eq!(heaters.shutdown_reason(), Some(fault));
        assert!(heaters.io.value(0) == Some(0) && heaters.next_wake().is_none());
        // The bed has no target: it is left alone.
        assert!(!heaters.waiting(Wait::Settled(1)));
    }

    #[test]
    fn the_extruder_may_extrude_once_its_smoothed_temperature_reaches_min_extrude_temp() {
        let config = Config::parse("printer.cfg", SHIPPED).expect("config");
        let machine = Machine::from_config(&config).expect("machine");
        let sensor = machine.heaters[0].sensor;
        let counts = |celsius: f64| (sensor.adc(celsius) * 4095.0).round() as u16;
        let mut hw = Reads([counts(25.0), 2048]);
        let mut heaters = Heaters::new(&machine, FREQ, 4095, typical_mcu(), 0, &mut hw);
        // Before any reading: min_extrude_temp (170 °C) is above 0.
        assert!(!heaters.can_extrude());
        let run_to = |heaters: &mut Heaters, hw: &mut Reads, until: u32| {
            while let Some(wake) = heaters.next_wake().filter(|&w| w <= until) {
                heaters.run(wake, hw).expect("no fault");
            }
        };
        run_to(&mut heaters, &mut hw, 2_000_000);
        assert!(!heaters.can_extrude());
        // At 175 °C, once the smoothing (1 s: 30% of the way each 0.3 s
        // report) has caught up: ten reports.
        hw.0[0] = counts(175.0);
        run_to(&mut heaters, &mut hw, 2_400_000);
        assert!(!heaters.can_extrude(), "smoothed, not the raw reading");
        run_to(&mut heaters, &mut hw, 5_500_000);
        assert!(heaters.can_extrude());
        // Cooling below 170 °C: refused again.
        hw.0[0] = counts(160.0);
        run_to(&mut heaters, &mut hw, 7_000_000);
        assert!(!heaters.can_extrude());
    }

    #[test]
    fn m105_is_formatted_from_a_copy_of_the_temperatures() {
        let config = Config::parse("printer.cfg", SHIPPED).expect("config");
        let machine = Machine::from_config(&config).expect("machine");
        let mut heaters = Heaters::new(&machine, FREQ, 4095, typical_mcu(), 0, &mut Hw);
        let target = |celsius| ThermalCommand::Target {
            heater: 0,
            celsius,
            wait: false,
        };
        heaters
            .command(target(200.0), 0, &mut Hw)
            .expect("in range");
        // The copy is all the board takes under the heaters' lock; it
        // formats as the M105 report, and stays as it was copied.
        let copy = heaters.temperatures();
        let text = |t: &dyn core::fmt::Display| {
            let mut s = heapless::String::<64>::new();
            write!(s, "{t}").expect("fits");
            s
        };
        let mut report = heapless::String::<64>::new();
        heaters.report(&mut report).expect("fits");
        assert_eq!(text(&copy), report);
        assert_eq!(report, "T:0.0 /200.0 B:0.0 /0.0 @:0 B@:0");
        // Two heaters and four sensors: a few hundred bytes at most,
        // against the whole heaters (over 1 KB).
        assert!(core::mem::size_of::<Temperatures>() <= 240);
        heaters.command(target(0.0), 0, &mut Hw).expect("off");
        assert!(text(&copy).starts_with("T:0.0 /200.0"));
    }
}
