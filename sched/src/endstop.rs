//! Endstop checking during homing, as Klipper's MCU does it: the pin is
//! read every `rest_ticks`; once it reads "triggered", it is read
//! `sample_count` times `sample_ticks` apart, and only if every reading
//! agrees does the endstop trigger, at the last reading's clock. The
//! trigger stops the steppers of the homing move (several at once, as
//! Klipper's trsync does) and its clock is reported.

use crate::clock::is_before;

/// What the endstop check wants next.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Check {
    /// Read the pin again at this clock.
    At(u32),
    /// Triggered at this clock: stop the steppers.
    Triggered(u32),
}

/// One armed endstop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Endstop {
    rest_ticks: u32,
    sample_ticks: u32,
    sample_count: u8,
    /// Readings in a row that saw the trigger.
    agreeing: u8,
    /// Clock of the next reading.
    next: u32,
}

/// Readings that must agree on a press before it counts (Klipper's
/// homing default).
pub const SAMPLE_COUNT: u8 = 4;
/// Time between those readings, s.
pub const SAMPLE_TIME: f64 = 0.000_015;

impl Endstop {
    /// Armed from clock `start` for a homing move at `speed` mm/s whose
    /// finest stepper moves `step_dist` mm per step, on a `freq` Hz clock:
    /// read about once per step, a press confirmed by [`SAMPLE_COUNT`]
    /// readings [`SAMPLE_TIME`] apart.
    pub fn for_homing(start: u32, freq: f64, speed: f64, step_dist: f64) -> Self {
        let rest = ((step_dist / speed) * freq).max(1.0) as u32;
        let confirm = (SAMPLE_TIME * freq).max(1.0) as u32;
        Self::home(start, confirm, SAMPLE_COUNT, rest)
    }

    /// `endstop_home`: armed from clock `start`.
    pub const fn home(start: u32, sample_ticks: u32, sample_count: u8, rest_ticks: u32) -> Self {
        Self {
            rest_ticks,
            sample_ticks,
            sample_count,
            agreeing: 0,
            next: start,
        }
    }

    /// Its sampling as `endstop_home` gives it: `(sample_ticks,
    /// sample_count, rest_ticks)`, ticks (for arming the same endstop on
    /// another MCU, in its clock).
    pub fn sampling(&self) -> (u32, u8, u32) {
        (self.sample_ticks, self.sample_count, self.rest_ticks)
    }

    /// Clock of the next reading.
    pub fn next(&self) -> u32 {
        self.next
    }

    /// True if a reading is due at clock `now`.
    pub fn is_due(&self, now: u32) -> bool {
        !is_before(now, self.next)
    }

    /// Takes the reading due now: `triggered` is the pin seen as the
    /// endstop pressed.
    pub fn read(&mut self, triggered: bool) -> Check {
        let at = self.next;
        if !triggered {
            self.agreeing = 0;
            self.next = at.wrapping_add(self.rest_ticks);
            return Check::At(self.next);
        }
        self.agreeing += 1;
        if self.agreeing >= self.sample_count {
            return Check::Triggered(at);
        }
        self.next = at.wrapping_add(self.sample_ticks);
        Check::At(self.next)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_trigger_needs_every_confirming_reading() {
        let mut e = Endstop::home(1000, 15, 4, 500);
        assert_eq!(e.read(false), Check::At(1500));
        assert_eq!(e.read(true), Check::At(1515));
        // A bounce restarts the confirmation.
        assert_eq!(e.read(false), Check::At(2015));
        assert_eq!(e.read(true), Check::At(2030));
        assert_eq!(e.read(true), Check::At(2045));
        assert_eq!(e.read(true), Check::At(2060));
        assert_eq!(e.read(true), Check::Triggered(2060));
        assert!(e.is_due(2060) && !e.is_due(2059));
    }
}
