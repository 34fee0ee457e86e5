//! PWM outputs: a hardware channel (the timer makes the waveform; the MCU
//! role only holds the duty) and software PWM (the MCU role toggles a pin
//! from a timer), both returning to their default value if not refreshed
//! within max_duration, as Klipper's `pwm_out` and soft-PWM `digital_out`.

use crate::clock::is_before;
use crate::shutdown::Shutdown;

/// Safety timeout shared by both kinds: a value away from the default must
/// be refreshed within `max_duration` ticks (0: no limit).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Timeout {
    default: u16,
    max_duration: u32,
    since: u32,
}

impl Timeout {
    fn check(&self, value: u16, now: u32) -> Result<(), Shutdown> {
        let expires = self.since.wrapping_add(self.max_duration);
        if self.max_duration > 0 && value != self.default && !is_before(now, expires) {
            return Err(Shutdown::PwmExpired);
        }
        Ok(())
    }
}

/// A hardware PWM channel: duty in `0..=max` (the MCU's PWM_MAX).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HardPwm {
    value: u16,
    timeout: Timeout,
}

impl HardPwm {
    /// `config_pwm_out`: starts at `value`.
    pub const fn new(value: u16, default: u16, max_duration: u32, now: u32) -> Self {
        Self {
            value,
            timeout: Timeout {
                default,
                max_duration,
                since: now,
            },
        }
    }

    /// The duty the timer should output.
    pub fn value(&self) -> u16 {
        self.value
    }

    /// Sets the duty at clock `now` (restarting the timeout).
    pub fn set(&mut self, value: u16, now: u32) {
        self.value = value;
        self.timeout.since = now;
    }

    /// Checks the timeout at clock `now`.
    pub fn check(&self, now: u32) -> Result<(), Shutdown> {
        self.timeout.check(self.value, now)
    }

    /// Back to the default duty (shutdown).
    pub fn reset(&mut self) {
        self.value = self.timeout.default;
    }
}

/// A software PWM pin with a cycle of `cycle_ticks`, on for
/// `on_ticks` of it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SoftPwm {
    cycle_ticks: u32,
    on_ticks: u32,
    /// The pin's level, and the clock of its next change.
    level: bool,
    next: u32,
    timeout: Timeout,
}

impl SoftPwm {
    /// A pin cycling every `cycle_ticks`, off, from clock `now`;
    /// `default_on_ticks` is where shutdown returns it.
    pub const fn new(cycle_ticks: u32, default_on_ticks: u16, max_duration: u32, now: u32) -> Self {
        Self {
            cycle_ticks,
            on_ticks: default_on_ticks as u32,
            level: false,
            next: now,
            timeout: Timeout {
                default: default_on_ticks,
                max_duration,
                since: now,
            },
        }
    }

    /// Sets the on time per cycle (ticks, at most the cycle) at `now`.
    pub fn set(&mut self, on_ticks: u32, now: u32) {
        self.on_ticks = on_ticks.min(self.cycle_ticks);
        self.timeout.since = now;
    }

    /// Clock of the pin's next change.
    pub fn next(&self) -> u32 {
        self.next
    }

    /// The timer's work at [`Self::next`]: returns the pin's new level.
    pub fn toggle(&mut self) -> bool {
        let off = self.cycle_ticks - self.on_ticks;
        // Stay at a constant level at 0 % and 100 %.
        let (level, hold) = match (self.level, self.on_ticks, off) {
            (_, 0, _) => (false, self.cycle_ticks),
            (_, _, 0) => (true, self.cycle_ticks),
            (false, on, _) => (true, on),
            (true, _, off) => (false, off),
        };
        self.level = level;
        self.next = self.next.wrapping_add(hold);
        level
    }

    /// Checks the timeout at clock `now`.
    pub fn check(&self, now: u32) -> Result<(), Shutdown> {
        self.timeout
            .check(self.on_ticks.min(u32::from(u16::MAX)) as u16, now)
    }

    /// Back to the default on time (shutdown).
    pub fn reset(&mut self) {
        self.on_ticks = u32::from(self.timeout.default);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn soft_pwm_spends_its_on_time_high_each_cycle() {
        let mut fan = SoftPwm::new(1000, 0, 0, 0);
        fan.set(250, 0);
        let (mut high, mut last, mut level) = (0u32, 0u32, false);
        while fan.next() < 10_000 {
            let at = fan.next();
            if level {
                high += at - last;
            }
            last = at;
            level = fan.toggle();
        }
        assert_eq!(high, 2500);
        // 0 % and 100 % hold a constant level.
        fan.set(0, 0);
        assert!(!fan.toggle() && !fan.toggle());
        fan.set(5000, 0);
        assert!(fan.toggle() && fan.toggle());
    }

    #[test]
    fn pwm_left_away_from_default_past_max_duration_is_a_fault() {
        let mut heater = HardPwm::new(0, 0, 1000, 0);
        heater.set(20_000, 10);
        assert_eq!(heater.check(1009), Ok(()));
        assert_eq!(heater.check(1010), Err(Shutdown::PwmExpired));
        heater.reset();
        assert_eq!(heater.check(5000), Ok(()));
        let mut fan = SoftPwm::new(1000, 0, 1000, 0);
        fan.set(600, 0);
        assert_eq!(fan.check(1000), Err(Shutdown::PwmExpired));
    }
}
