//! Fans and pins besides the heaters, run with them: the named fans
//! (`[heater_fan]`, `[controller_fan]`, `[fan_generic]`), `[output_pin]`s
//! and `[static_digital_output]` pins, as outputs of the heaters' io
//! after the heaters and the part fan. Klipper's fan speed rules
//! ([`FanControl`], also the part fan's) and its once-a-second checks of
//! heater and controller fans run here, in the heaters' timer; output
//! pins with `maximum_mcu_duration` have their value repeated in time.
//! Every output has its shutdown value as its default, so a shutdown
//! sets it (heater fans: full speed).
//!
//! G-code (`SET_FAN_SPEED`, `SET_PIN`) is parsed by [`AccessoryNames`]
//! into [`AccessoryCommand`]s that travel as the heaters' commands do.

use crate::heaters::{full_scale, scaled, ticks};
use onechip_config::decimal::Fixed;
use onechip_planner::accessories::{Accessories, MAX_OUTPUTS};
use onechip_planner::fan_sections::{CoolingLaw, FanRole, MAX_COOLING, MAX_FANS, TemperatureFan};
use onechip_planner::gcode::{Command, Extended, GcodeError, Line};
use onechip_planner::math::clamp;
use onechip_planner::output_pin::{MAX_OUTPUT_PINS, OutputPin};
use onechip_planner::thermal::Fan;
use onechip_sched::clock::is_before;
use onechip_sched::outputs::{OutputConfig, OutputKind};
use onechip_sched::shutdown::Shutdown;

/// Least time between two updates of a fan or pin, and from a check to
/// the update it causes, s (Klipper's FAN_MIN_TIME and PIN_MIN_TIME).
pub const PIN_MIN_TIME: f64 = 0.100;
/// Time between two checks of the heater and controller fans, s.
pub const CHECK_TIME: f64 = 1.0;
/// How long before maximum_mcu_duration runs out a pin's value is sent
/// again, s (Klipper's RESEND_HOST_TIME).
pub const RESEND_HOST_TIME: f64 = 0.300 + PIN_MIN_TIME;

/// An output's start and shutdown levels, 0..1 of its full scale, as
/// printer.cfg gives them (before an MCU scales them: a secondary's
/// hardware PWM channel takes them times its own PWM_MAX).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Levels {
    /// From start-up.
    pub start: f64,
    /// At shutdown.
    pub shutdown: f64,
}

/// A fan's levels: off at start, its shutdown_speed (at most max_power)
/// at shutdown.
pub fn fan_levels(fan: &Fan<'_>) -> Levels {
    Levels {
        start: 0.0,
        shutdown: fan.shutdown_speed.min(fan.max_power),
    }
}

/// The MCU output of a fan: software PWM of its cycle_time, or a
/// hardware PWM channel, at its [`fan_levels`]; no max_duration.
pub fn fan_config(fan: &Fan<'_>, freq: f64) -> OutputConfig {
    let cycle_ticks = ticks(fan.cycle_time, freq);
    let kind = if fan.hard_pwm {
        OutputKind::HardPwm { cycle_ticks }
    } else {
        OutputKind::Digital { cycle_ticks }
    };
    OutputConfig {
        kind,
        value: 0,
        default: scaled(fan_levels(fan).shutdown, full_scale(kind)),
        max_duration: 0,
    }
}

/// An `[output_pin]`'s levels: its `value` and its `shutdown_value`.
fn pin_levels(pin: &OutputPin<'_>) -> Levels {
    Levels {
        start: pin.value,
        shutdown: pin.shutdown_value,
    }
}

/// The MCU output of an `[output_pin]`: steady (on/off) or PWM, at its
/// [`pin_levels`].
fn pin_config(pin: &OutputPin<'_>, freq: f64) -> OutputConfig {
    let cycle_ticks = ticks(pin.cycle_time, freq);
    let kind = match (pin.pwm, pin.hardware_pwm) {
        (false, _) => OutputKind::Digital { cycle_ticks: 0 },
        (true, true) => OutputKind::HardPwm { cycle_ticks },
        (true, false) => OutputKind::Digital { cycle_ticks },
    };
    let levels = pin_levels(pin);
    OutputConfig {
        kind,
        value: pin_value(levels.start, kind),
        default: pin_value(levels.shutdown, kind),
        max_duration: ticks(pin.max_duration, freq),
    }
}

/// A pin's value (0..1) on output `kind`: on/off for a steady pin.
fn pin_value(fraction: f64, kind: OutputKind) -> u32 {
    match kind {
        OutputKind::Digital { cycle_ticks: 0 } => u32::from(fraction != 0.0),
        kind => scaled(fraction, full_scale(kind)),
    }
}

/// Every accessory output, in the order the io numbers them: named fans,
/// output pins, static pins (on); the pin as written, its configuration
/// and its levels.
pub fn output_configs<'m, 'a>(
    accessories: &'m Accessories<'a>,
    freq: f64,
) -> impl Iterator<Item = (&'a str, OutputConfig, Levels)> + 'm {
    let fans = (accessories.fans.iter())
        .map(move |f| (f.fan.pin, fan_config(&f.fan, freq), fan_levels(&f.fan)));
    let pins =
        (accessories.output_pins.iter()).map(move |p| (p.pin, pin_config(p, freq), pin_levels(p)));
    let on = OutputConfig {
        kind: OutputKind::Digital { cycle_ticks: 0 },
        value: 1,
        default: 1,
        max_duration: 0,
    };
    let full_on = Levels {
        start: 1.0,
        shutdown: 1.0,
    };
    let statics = (accessories.static_pins.iter()).map(move |p| (p.pin, on, full_on));
    fans.chain(pins).chain(statics)
}

/// Up to two timed output values (a kick, then the speed).
pub type Updates = heapless::Vec<(u32, u32), 2>;

/// Klipper's fan speed rules for one fan: off below off_below, speeds
/// mapped onto min_power..max_power, updates at least [`PIN_MIN_TIME`]
/// apart, and full power for kick_start_time when starting from still or
/// rising by more than half.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FanControl {
    /// The fan's speed options (its pin left out).
    fan: Fan<'static>,
    /// kick_start_time, ticks.
    kick_ticks: u32,
    /// [`PIN_MIN_TIME`], ticks.
    min_ticks: u32,
    /// The output's full scale.
    full: u32,
    /// The power last set, 0..1.
    power: f64,
    /// When it was set (clock).
    last_at: Option<u32>,
}

impl FanControl {
    /// The control of `fan`, whose output has full scale `full`, on a
    /// clock of `freq` Hz.
    pub fn new(fan: &Fan<'_>, full: u32, freq: f64) -> Self {
        Self {
            fan: Fan { pin: "", ..*fan },
            kick_ticks: ticks(fan.kick_start_time, freq),
            min_ticks: ticks(PIN_MIN_TIME, freq),
            full,
            power: 0.0,
            last_at: None,
        }
    }

    /// The power last set, 0..1.
    pub fn power(&self) -> f64 {
        self.power
    }

    /// The output's full scale.
    pub fn full(&self) -> u32 {
        self.full
    }

    /// The clock before which a new update must wait ([`PIN_MIN_TIME`]
    /// after the last), while it matters: the owner runs
    /// [`Self::expire`] then, so that no clock kept here is ever old
    /// enough for the 32-bit clock's wrap to make it look ahead.
    pub fn busy_until(&self) -> Option<u32> {
        self.last_at.map(|at| at.wrapping_add(self.min_ticks))
    }

    /// Forgets the last update's time once `now` is past
    /// [`Self::busy_until`].
    pub fn expire(&mut self, now: u32) {
        if self
            .busy_until()
            .is_some_and(|until| !is_before(now, until))
        {
            self.last_at = None;
        }
    }

    /// The fan to `speed` (0..1) at `clock` (not before `now`): the
    /// output values to queue, in time order.
    pub fn set(&mut self, speed: f64, clock: u32, now: u32) -> Updates {
        let power = self.fan.power(speed);
        let max_power = self.fan.max_power;
        let mut updates = Updates::new();
        if power == self.power {
            return updates;
        }
        self.expire(now);
        let mut at = later(clock, now);
        if let Some(until) = self.busy_until() {
            at = later(at, until);
        }
        let starting = self.power == 0.0 || power - self.power > 0.5;
        if power > 0.0 && power < max_power && self.kick_ticks > 0 && starting {
            let _ = updates.push((at, scaled(max_power, self.full)));
            at = at.wrapping_add(self.kick_ticks);
        }
        let _ = updates.push((at, scaled(power, self.full)));
        self.power = power;
        self.last_at = Some(at);
        updates
    }
}

/// The later of two clocks.
fn later(a: u32, b: u32) -> u32 {
    if is_before(a, b) { b } else { a }
}

/// What G-code asks of the fans and pins.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum AccessoryCommand {
    /// `SET_FAN_SPEED`: named fan `fan` to `speed` (0..1).
    Fan {
        /// Index among the named fans.
        fan: usize,
        /// Speed, 0..1.
        speed: f64,
        /// When, s of print time.
        print_time: f64,
    },
    /// `SET_PIN`: output pin `pin` to `value` (0..1 of full scale).
    Pin {
        /// Index among the output pins.
        pin: usize,
        /// Value, 0..1.
        value: f64,
        /// When, s of print time.
        print_time: f64,
    },
    /// The stepper drivers were enabled (a move) or disabled (M84, M18):
    /// controller fans follow.
    Motors(bool),
    /// `SET_TEMPERATURE_FAN_TARGET`: temperature fan `fan` (index among
    /// the temperature fans) holds `target` (°C, 0: off) within its
    /// speeds.
    Cooling {
        /// Index among the temperature fans.
        fan: usize,
        /// Target, °C.
        target: f64,
        /// min_speed, 0..1.
        min_speed: f64,
        /// max_speed, 0..1.
        max_speed: f64,
    },
}

/// Why an accessory command was refused (Klipper's messages).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum AccessoryError<'l> {
    /// A parameter is missing or not a number.
    Gcode(GcodeError<'l>),
    /// `FAN=`, `PIN=` names nothing configured.
    NotValid {
        /// The parameter.
        key: &'static str,
        /// Its value.
        value: &'l str,
    },
    /// `VALUE` outside 0..scale.
    OutOfRange {
        /// scale.
        max: f64,
    },
    /// `VALUE` other than 0 or 1 on a pin that is not PWM.
    InvalidPinValue,
    /// `CYCLE_TIME` other than the configured cycle_time.
    CycleTime,
    /// A temperature fan's TARGET outside min_temp..max_temp, °C.
    TargetOutOfRange {
        /// Requested.
        celsius: f64,
        /// min_temp.
        min: f64,
        /// max_temp.
        max: f64,
    },
    /// MIN_SPEED above MAX_SPEED.
    MinAboveMax {
        /// MIN_SPEED.
        min: f64,
        /// MAX_SPEED.
        max: f64,
    },
    /// A speed outside 0..1 (`which`: min or max).
    SpeedOutOfRange {
        /// `min` or `max`.
        which: &'static str,
        /// Requested.
        speed: f64,
    },
}

impl<'l> From<GcodeError<'l>> for AccessoryError<'l> {
    fn from(e: GcodeError<'l>) -> Self {
        Self::Gcode(e)
    }
}

impl core::fmt::Display for AccessoryError<'_> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Gcode(e) => e.fmt(f),
            Self::NotValid { key, value } => {
                write!(f, "The value '{value}' is not valid for {key}")
            }
            Self::OutOfRange { max } => write!(f, "VALUE must have maximum of {}", Fixed(*max, 6)),
            Self::InvalidPinValue => f.write_str("Invalid pin value"),
            Self::CycleTime => {
                f.write_str("CYCLE_TIME other than the pin's cycle_time is not supported yet")
            }
            Self::TargetOutOfRange { celsius, min, max } => write!(
                f,
                "Requested temperature ({}) out of range ({}:{})",
                Fixed(*celsius, 1),
                Fixed(*min, 1),
                Fixed(*max, 1)
            ),
            Self::MinAboveMax { min, max } => write!(
                f,
                "Requested min speed ({}) is greater than max speed ({})",
                Fixed(*min, 1),
                Fixed(*max, 1)
            ),
            Self::SpeedOutOfRange { which, speed } => write!(
                f,
                "Requested {which} speed ({}) out of range (0.0 : 1.0)",
                Fixed(*speed, 1)
            ),
        }
    }
}

/// A named fan or output pin as G-code names it.
#[derive(Debug, Clone, Copy, PartialEq)]
struct PinName<'a> {
    name: &'a str,
    pwm: bool,
    scale: f64,
    cycle_time: f64,
}

/// A temperature fan as SET_TEMPERATURE_FAN_TARGET sees it: its
/// configured target and range, and the speeds last set.
#[derive(Debug, Clone, Copy, PartialEq)]
struct CoolingName<'a> {
    name: &'a str,
    role: TemperatureFan,
}

/// The names G-code uses for the fans and pins.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct AccessoryNames<'a> {
    fans: heapless::Vec<&'a str, MAX_FANS>,
    cooling: heapless::Vec<CoolingName<'a>, MAX_COOLING>,
    pins: heapless::Vec<PinName<'a>, MAX_OUTPUT_PINS>,
}

impl<'a> AccessoryNames<'a> {
    /// The names in `accessories`.
    pub fn new(accessories: &Accessories<'a>) -> Self {
        Self {
            fans: accessories.fans.iter().map(|f| f.name).collect(),
            cooling: (accessories.cooling.iter())
                .map(|&role| CoolingName {
                    name: accessories.fans.get(role.fan).map_or("", |f| f.name),
                    role,
                })
                .collect(),
            pins: accessories
                .output_pins
                .iter()
                .map(|p| PinName {
                    name: p.name,
                    pwm: p.pwm,
                    scale: p.scale,
                    cycle_time: p.cycle_time,
                })
                .collect(),
        }
    }

    /// The command `line` gives, if it is SET_FAN_SPEED, SET_PIN or
    /// SET_TEMPERATURE_FAN_TARGET; `print_time` is when the queued moves
    /// end.
    pub fn parse<'l>(
        &mut self,
        line: &Line<'l>,
        print_time: f64,
    ) -> Result<Option<AccessoryCommand>, AccessoryError<'l>> {
        let Command::Extended(e) = line.command else {
            return Ok(None);
        };
        if e.name.eq_ignore_ascii_case("SET_TEMPERATURE_FAN_TARGET") {
            return self.cooling_target(&e).map(Some);
        }
        if e.name.eq_ignore_ascii_case("SET_FAN_SPEED") {
            let fan = Self::find(&e, "FAN", self.fans.iter().copied())?;
            let speed = e.float("SPEED")?.unwrap_or(0.0);
            return Ok(Some(AccessoryCommand::Fan {
                fan,
                speed,
                print_time,
            }));
        }
        if !e.name.eq_ignore_ascii_case("SET_PIN") {
            return Ok(None);
        }
        let index = Self::find(&e, "PIN", self.pins.iter().map(|p| p.name))?;
        let pin = self.pins[index];
        let value = e.float("VALUE")?.ok_or(GcodeError::Missing("VALUE"))?;
        if !(0.0..=pin.scale).contains(&value) {
            return Err(AccessoryError::OutOfRange { max: pin.scale });
        }
        if e.float("CYCLE_TIME")?.is_some_and(|c| c != pin.cycle_time) {
            return Err(AccessoryError::CycleTime);
        }
        let value = value / pin.scale;
        if !pin.pwm && value != 0.0 && value != 1.0 {
            return Err(AccessoryError::InvalidPinValue);
        }
        Ok(Some(AccessoryCommand::Pin {
            pin: index,
            value,
            print_time,
        }))
    }

    /// SET_TEMPERATURE_FAN_TARGET TEMPERATURE_FAN= [TARGET=] [MIN_SPEED=]
    /// [MAX_SPEED=], checked as Klipper does: TARGET defaults to the
    /// configured target, the speeds to those last set.
    fn cooling_target<'l>(
        &mut self,
        e: &Extended<'l>,
    ) -> Result<AccessoryCommand, AccessoryError<'l>> {
        let index = Self::find(e, "TEMPERATURE_FAN", self.cooling.iter().map(|c| c.name))?;
        let configured = self.cooling[index].role;
        let target = e.float("TARGET")?.unwrap_or(configured.target);
        if target != 0.0 && !(configured.min_temp..=configured.max_temp).contains(&target) {
            return Err(AccessoryError::TargetOutOfRange {
                celsius: target,
                min: configured.min_temp,
                max: configured.max_temp,
            });
        }
        let c = &mut self.cooling[index];
        let min = e.float("MIN_SPEED")?.unwrap_or(c.role.min_speed);
        let max = e.float("MAX_SPEED")?.unwrap_or(c.role.max_speed);
        if min > max {
            return Err(AccessoryError::MinAboveMax { min, max });
        }
        for (which, speed) in [("min", min), ("max", max)] {
            if speed != 0.0 && !(0.0..=1.0).contains(&speed) {
                return Err(AccessoryError::SpeedOutOfRange { which, speed });
            }
        }
        (c.role.min_speed, c.role.max_speed) = (min, max);
        Ok(AccessoryCommand::Cooling {
            fan: index,
            target,
            min_speed: min,
            max_speed: max,
        })
    }

    /// The index of the name parameter `key` gives among `names`.
    fn find<'l>(
        e: &Extended<'l>,
        key: &'static str,
        mut names: impl Iterator<Item = &'a str>,
    ) -> Result<usize, AccessoryError<'l>> {
        let value = e.get(key)?.ok_or(GcodeError::Missing(key))?;
        names
            .position(|n| n == value)
            .ok_or(AccessoryError::NotValid { key, value })
    }
}

/// Klipper's temperature fans' update spacing: a speed is sent again at
/// least this often (0.75 of its MAX_FAN_TIME of 5 s), s.
const COOLING_REFRESH: f64 = 0.75 * 5.0;
/// The temperature a temperature fan's PID starts from, °C (Klipper's).
const COOLING_AMBIENT: f64 = 25.0;

/// A temperature fan's control at run time: Klipper's `ControlBangBang`
/// or `ControlPID`, and `set_tf_speed`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Cooling {
    /// Target and speeds as last set.
    role: TemperatureFan,
    /// Watermark: below target − max_delta until above target + max_delta.
    heating: bool,
    /// PID: the previous reading (°C), its clock, the temperature's
    /// derivative (°C/s) and the error's integral (°C·s).
    prev_temp: f64,
    prev_clock: Option<u32>,
    prev_deriv: f64,
    prev_integ: f64,
    /// The speed last sent, and the clock before which a change under 5 %
    /// is not sent.
    last_speed: f64,
    next_speed: u32,
}

impl Cooling {
    fn new(role: TemperatureFan) -> Self {
        Self {
            role,
            heating: false,
            prev_temp: COOLING_AMBIENT,
            prev_clock: None,
            prev_deriv: 0.0,
            prev_integ: 0.0,
            last_speed: 0.0,
            next_speed: 0,
        }
    }

    /// A reading of `temp` °C at `clock` (on a `freq` Hz clock): the
    /// speed the control asks for.
    fn speed(&mut self, temp: f64, clock: u32, freq: f64) -> f64 {
        let r = self.role;
        match r.law {
            CoolingLaw::Watermark { max_delta } => {
                if self.heating && temp >= r.target + max_delta {
                    self.heating = false;
                } else if !self.heating && temp <= r.target - max_delta {
                    self.heating = true;
                }
                if self.heating { 0.0 } else { r.max_speed }
            }
            CoolingLaw::Pid {
                kp,
                ki,
                kd,
                deriv_time,
            } => {
                // Klipper measures from time 0 before its first reading.
                let since = self.prev_clock.map_or(clock, |p| clock.wrapping_sub(p));
                let dt = f64::from(since) / freq;
                let diff = temp - self.prev_temp;
                let deriv = if dt >= deriv_time {
                    diff / dt
                } else {
                    (self.prev_deriv * (deriv_time - dt) + diff) / deriv_time
                };
                let err = r.target - temp;
                let integ_max = if ki != 0.0 { r.max_speed / ki } else { 0.0 };
                let integ = clamp(self.prev_integ + err * dt, 0.0, integ_max);
                let co = kp * err + ki * integ - kd * deriv;
                let bounded = clamp(co, 0.0, r.max_speed);
                (self.prev_temp, self.prev_clock, self.prev_deriv) = (temp, Some(clock), deriv);
                if co == bounded {
                    self.prev_integ = integ;
                }
                r.min_speed.max(r.max_speed - bounded)
            }
        }
    }

    /// Klipper's `set_tf_speed` for a reading at `clock`: the speed to
    /// send and when (`delay` ticks later), unless the change is too
    /// small to send yet.
    fn update(&mut self, speed: f64, clock: u32, delay: u32, refresh: u32) -> Option<(u32, f64)> {
        let mut speed = if speed <= 0.0 {
            0.0
        } else {
            speed.max(self.role.min_speed)
        };
        if self.role.target <= 0.0 {
            speed = 0.0;
        }
        let early = is_before(clock, self.next_speed) || self.last_speed == 0.0;
        if early && (speed - self.last_speed).abs() < 0.05 {
            return None;
        }
        let at = clock.wrapping_add(delay);
        self.next_speed = at.wrapping_add(refresh);
        self.last_speed = speed;
        Some((at, speed))
    }
}

/// One accessory output's run-time state.
#[derive(Debug, Clone, Copy, PartialEq)]
enum State {
    /// A named fan.
    Fan {
        control: FanControl,
        role: FanRole,
        /// Checks left at idle_speed (controller fans).
        idle_left: u32,
    },
    /// An output pin.
    Pin {
        /// The value last set, 0..1, and its clock.
        value: f64,
        last_at: Option<u32>,
        shutdown_value: f64,
        kind: OutputKind,
        /// Ticks between repeats of a value (0: none).
        resend_ticks: u32,
    },
    /// A static pin: nothing to do.
    Static,
}

impl State {
    /// True for a pin whose value is repeated (maximum_mcu_duration, away
    /// from its shutdown value).
    fn resending(&self) -> bool {
        matches!(*self, State::Pin { resend_ticks, value, shutdown_value, .. }
            if resend_ticks > 0 && value != shutdown_value)
    }

    /// The clock by which this output needs a poll, if any: a repeat, or
    /// the end of its update spacing.
    fn deadline(&self, min_ticks: u32) -> Option<u32> {
        match *self {
            State::Fan { control, .. } => control.busy_until(),
            State::Pin {
                last_at: Some(last),
                resend_ticks,
                ..
            } => Some(last.wrapping_add(if self.resending() {
                resend_ticks
            } else {
                min_ticks
            })),
            _ => None,
        }
    }

    /// Forgets clocks that no longer matter at `now` (so that none is old
    /// enough for the 32-bit clock's wrap to make it look ahead).
    fn expire(&mut self, now: u32, min_ticks: u32) {
        let resending = self.resending();
        match self {
            State::Fan { control, .. } => control.expire(now),
            State::Pin { last_at, .. }
                if !resending
                    && last_at.is_some_and(|at| !is_before(now, at.wrapping_add(min_ticks))) =>
            {
                *last_at = None;
            }
            _ => {}
        }
    }
}

/// What the fan checks read of each heater: (target, smoothed
/// temperature), °C.
pub type HeaterReadings<'h> = &'h [(f64, f64)];

/// The fans and pins at run time.
#[derive(Debug, Clone, PartialEq)]
pub struct AccessoryOutputs {
    /// In io order, from io output `first`.
    states: heapless::Vec<State, MAX_OUTPUTS>,
    /// The temperature fans' controls.
    cooling: heapless::Vec<Cooling, MAX_COOLING>,
    first: usize,
    /// Clock of the next fan check.
    next_check: u32,
    check_ticks: u32,
    min_ticks: u32,
    /// Any stepper driver enabled.
    motors: bool,
    freq: f64,
}

impl AccessoryOutputs {
    /// The outputs of `accessories`, io outputs from `first` on, as
    /// [`output_configs`] configured them; the first check at `start`.
    pub fn new(accessories: &Accessories<'_>, first: usize, freq: f64, start: u32) -> Self {
        let configs = output_configs(accessories, freq);
        let fans = accessories.fans.iter().map(|f| (Some(f), None));
        let pins = accessories.output_pins.iter().map(|p| (None, Some(p)));
        let statics = accessories.static_pins.iter().map(|_| (None, None));
        let states = fans
            .chain(pins)
            .chain(statics)
            .zip(configs)
            .map(|(which, (_, config, _))| match which {
                (Some(f), _) => State::Fan {
                    control: FanControl::new(&f.fan, full_scale(config.kind), freq),
                    role: f.role,
                    idle_left: match f.role {
                        FanRole::Controller { .. } => 0,
                        _ => u32::MAX,
                    },
                },
                (None, Some(p)) => State::Pin {
                    value: p.value,
                    last_at: None,
                    shutdown_value: p.shutdown_value,
                    kind: config.kind,
                    resend_ticks: if p.max_duration > 0.0 {
                        ticks((p.max_duration - RESEND_HOST_TIME).max(0.0), freq)
                    } else {
                        0
                    },
                },
                (None, None) => State::Static,
            })
            .collect();
        Self {
            states,
            cooling: accessories
                .cooling
                .iter()
                .map(|&t| Cooling::new(t))
                .collect(),
            first,
            next_check: start,
            check_ticks: ticks(CHECK_TIME, freq),
            min_ticks: ticks(PIN_MIN_TIME, freq),
            motors: false,
            freq,
        }
    }

    /// Index in the io of named fan `fan`'s output.
    pub fn fan_output(&self, fan: usize) -> usize {
        self.first + fan
    }

    /// When [`Self::poll`] must run next (clock), if ever: the next
    /// check of heater and controller fans, a pin's repeat, or the end of
    /// an output's [`PIN_MIN_TIME`] spacing (to forget its clock).
    pub fn next_wake(&self) -> Option<u32> {
        let checks = self.states.iter().any(|s| {
            matches!(
                s,
                State::Fan {
                    role: FanRole::Heater { .. } | FanRole::Controller { .. },
                    ..
                }
            )
        });
        let deadlines = self
            .states
            .iter()
            .filter_map(|s| s.deadline(self.min_ticks));
        deadlines.fold(checks.then_some(self.next_check), |a, b| match a {
            Some(a) if is_before(a, b) => Some(a),
            _ => Some(b),
        })
    }

    /// The work due at clock `now`: the heater and controller fans'
    /// checks once a second (`heaters`: each heater's target and
    /// temperature), and repeats of pins with maximum_mcu_duration.
    /// `queue(io output, clock, value)` queues an output update.
    pub fn poll(
        &mut self,
        now: u32,
        heaters: HeaterReadings<'_>,
        queue: &mut impl FnMut(usize, u32, u32) -> Result<(), Shutdown>,
    ) -> Result<(), Shutdown> {
        let at = now.wrapping_add(self.min_ticks);
        let check = !is_before(now, self.next_check);
        if check {
            self.next_check = self.next_check.wrapping_add(self.check_ticks);
            if is_before(self.next_check, now) {
                self.next_check = now.wrapping_add(self.check_ticks);
            }
        }
        for index in 0..self.states.len() {
            let output = self.first + index;
            self.states[index].expire(now, self.min_ticks);
            match &mut self.states[index] {
                State::Fan {
                    control,
                    role,
                    idle_left,
                    ..
                } if check => {
                    let speed = Self::fan_speed(*role, idle_left, self.motors, heaters);
                    if let Some(speed) = speed {
                        for (clock, value) in control.set(speed, at, now) {
                            queue(output, clock, value)?;
                        }
                    }
                }
                State::Pin {
                    value,
                    last_at: Some(last),
                    shutdown_value,
                    kind,
                    resend_ticks,
                } if *resend_ticks > 0
                    && *value != *shutdown_value
                    && !is_before(now, last.wrapping_add(*resend_ticks)) =>
                {
                    *last = at;
                    queue(output, at, pin_value(*value, *kind))?;
                }
                _ => {}
            }
        }
        Ok(())
    }

    /// The speed a check gives a fan (None: set by G-code only).
    fn fan_speed(
        role: FanRole,
        idle_left: &mut u32,
        motors: bool,
        heaters: HeaterReadings<'_>,
    ) -> Option<f64> {
        let listed = |mask: u8| {
            heaters
                .iter()
                .enumerate()
                .filter(move |(i, _)| mask & (1 << i) != 0)
                .map(|(_, h)| *h)
        };
        match role {
            FanRole::Generic | FanRole::Temperature(_) => None,
            FanRole::Heater {
                heaters: mask,
                heater_temp,
                fan_speed,
            } => {
                let hot = listed(mask).any(|(target, temp)| target != 0.0 || temp > heater_temp);
                Some(if hot { fan_speed } else { 0.0 })
            }
            FanRole::Controller {
                heaters: mask,
                fan_speed,
                idle_speed,
                idle_timeout,
                ..
            } => {
                let active = motors || listed(mask).any(|(target, _)| target != 0.0);
                if active {
                    *idle_left = idle_timeout;
                    Some(fan_speed)
                } else if *idle_left > 0 {
                    *idle_left -= 1;
                    Some(idle_speed)
                } else {
                    Some(0.0)
                }
            }
        }
    }

    /// Carries out `command` at clock `now`; `queue` as for [`Self::poll`].
    pub fn command(
        &mut self,
        command: AccessoryCommand,
        now: u32,
        queue: &mut impl FnMut(usize, u32, u32) -> Result<(), Shutdown>,
    ) -> Result<(), Shutdown> {
        let clock = |print_time: f64| (print_time.max(0.0) * self.freq) as u64 as u32;
        let (index, print_time) = match command {
            AccessoryCommand::Motors(on) => {
                self.motors = on;
                return Ok(());
            }
            AccessoryCommand::Fan {
                fan, print_time, ..
            } => (fan, print_time),
            AccessoryCommand::Pin {
                pin, print_time, ..
            } => (self.fan_count() + pin, print_time),
            AccessoryCommand::Cooling {
                fan,
                target,
                min_speed,
                max_speed,
            } => {
                if let Some(c) = self.cooling.get_mut(fan) {
                    (c.role.target, c.role.min_speed, c.role.max_speed) =
                        (target, min_speed, max_speed);
                }
                return Ok(());
            }
        };
        let at = clock(print_time);
        let output = self.first + index;
        let min_ticks = self.min_ticks;
        match (self.states.get_mut(index), command) {
            (Some(State::Fan { control, .. }), AccessoryCommand::Fan { speed, .. }) => {
                for (clock, value) in control.set(speed, at, now) {
                    queue(output, clock, value)?;
                }
            }
            (
                Some(State::Pin {
                    value,
                    last_at,
                    kind,
                    ..
                }),
                AccessoryCommand::Pin { value: new, .. },
            ) => {
                if *value == new {
                    return Ok(());
                }
                let mut at = later(at, now);
                if let Some(last) = last_at.filter(|&l| is_before(now, l.wrapping_add(min_ticks))) {
                    at = later(at, last.wrapping_add(min_ticks));
                }
                *value = new;
                *last_at = Some(at);
                queue(output, at, pin_value(new, *kind))?;
            }
            _ => {}
        }
        Ok(())
    }

    /// Named fans (the first outputs).
    fn fan_count(&self) -> usize {
        self.states
            .iter()
            .take_while(|s| matches!(s, State::Fan { .. }))
            .count()
    }

    /// Temperature sensor `sensor` read `temp` °C at clock `clock`: the
    /// temperature fans it drives update their speed, `delay` ticks
    /// later (Klipper's report time); `queue` as for [`Self::poll`].
    pub fn sensor_report(
        &mut self,
        sensor: usize,
        temp: f64,
        clock: u32,
        now: u32,
        delay: u32,
        queue: &mut impl FnMut(usize, u32, u32) -> Result<(), Shutdown>,
    ) -> Result<(), Shutdown> {
        let refresh = ticks(COOLING_REFRESH, self.freq);
        for c in self.cooling.iter_mut().filter(|c| c.role.sensor == sensor) {
            let speed = c.speed(temp, clock, self.freq);
            let Some((at, speed)) = c.update(speed, clock, delay, refresh) else {
                continue;
            };
            let fan = c.role.fan;
            if let Some(State::Fan { control, .. }) = self.states.get_mut(fan) {
                for (clock, value) in control.set(speed, at, now) {
                    queue(self.first + fan, clock, value)?;
                }
            }
        }
        Ok(())
    }

    /// The target of the temperature fan that reads sensor `sensor`, if
    /// one does, °C.
    pub fn cooling_target(&self, sensor: usize) -> Option<f64> {
        self.cooling
            .iter()
            .find(|c| c.role.sensor == sensor)
            .map(|c| c.role.target)
    }

    /// Named fan `fan`'s power (0..1), as last set.
    pub fn fan_power(&self, fan: usize) -> Option<f64> {
        match self.states.get(fan)? {
            State::Fan { control, .. } => Some(control.power()),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::heaters::tests::typical_mcu;
    use crate::heaters::{Heaters, ThermalCommand};
    use onechip_config::Config;
    use onechip_planner::machine::Machine;
    use onechip_sched::io::Peripherals;
    use onechip_sched::outputs::Drive;

    /// The board's step clock, Hz: its 32-bit count wraps in 16.5 s.
    const FREQ: f64 = 260_000_000.0;
    /// A printer with a generic fan only.
    const CONFIG: &str = "[printer]\nkinematics: cartesian\nmax_velocity: 300\nmax_accel: 3000\n\
        [stepper_x]\nstep_pin: PF13\ndir_pin: PF12\nmicrosteps: 16\nrotation_distance: 40\n\
        position_endstop: 0\nposition_max: 200\n\
        [stepper_y]\nstep_pin: PG0\ndir_pin: PG1\nmicrosteps: 16\nrotation_distance: 40\n\
        position_endstop: 0\nposition_max: 200\n\
        [stepper_z]\nstep_pin: PF11\ndir_pin: PG3\nmicrosteps: 16\nrotation_distance: 8\n\
        position_endstop: 0\nposition_max: 200\n\
        [fan_generic aux]\npin: PA8\nkick_start_time: 0\n";

    /// Hardware that ignores outputs.
    struct Hw;

    impl Peripherals for Hw {
        fn drive(&mut self, _: usize, _: Drive) {}
        fn read_adc(&mut self, _: usize) -> u16 {
            2048
        }
    }

    /// Runs `heaters` at each wake up to `until` (clock, unwrapped s).
    fn run_to(heaters: &mut Heaters, now: &mut f64, until: f64) {
        while let Some(wake) = heaters.next_wake() {
            let ahead = f64::from(wake.wrapping_sub((*now * FREQ) as u64 as u32)) / FREQ;
            if *now + ahead > until {
                break;
            }
            *now += ahead;
            heaters
                .run((*now * FREQ) as u64 as u32, &mut Hw)
                .expect("runs");
        }
        *now = until;
    }

    #[test]
    fn a_fan_set_long_after_its_last_update_changes_at_once() {
        let config = Config::parse("printer.cfg", CONFIG).expect("config");
        let machine = Machine::from_config(&config).expect("machine");
        let mut heaters = Heaters::new(&machine, FREQ, 4095, typical_mcu(), 0, &mut Hw);
        let set = |heaters: &mut Heaters, speed, at: f64| {
            let command = AccessoryCommand::Fan {
                fan: 0,
                speed,
                print_time: at,
            };
            let now = (at * FREQ) as u64 as u32;
            heaters
                .command(ThermalCommand::Accessory(command), now, &mut Hw)
                .expect("queued");
        };
        let mut now = 0.0;
        set(&mut heaters, 1.0, 1.0);
        run_to(&mut heaters, &mut now, 1.001);
        assert_eq!(heaters.named_fan_power(0), Some(1.0));
        // 12 s later (more than half the clock's wrap): no spacing from
        // a clock that long gone.
        run_to(&mut heaters, &mut now, 13.0);
        set(&mut heaters, 0.0, 13.0);
        run_to(&mut heaters, &mut now, 13.001);
        assert_eq!(heaters.output_value(0), Some(0));
        // Two updates 10 ms apart: the second waits for PIN_MIN_TIME.
        set(&mut heaters, 0.5, 14.0);
        set(&mut heaters, 1.0, 14.01);
        run_to(&mut heaters, &mut now, 14.05);
        assert_eq!(heaters.output_value(0), Some(1_300_000));
        run_to(&mut heaters, &mut now, 14.101);
        assert_eq!(heaters.output_value(0), Some(2_600_000));
    }
}
