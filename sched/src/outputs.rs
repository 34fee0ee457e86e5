//! Digital outputs with Klipper's safety timeout, and ADC inputs with range
//! checks: the parts of the MCU role that keep a heater from running away
//! when the host stops talking or a sensor fails.

use crate::clock::is_before;
use crate::shutdown::Shutdown;

/// A digital output (heater, fan, LED) that must return to its default
/// value unless refreshed within `max_duration` ticks (0: no limit).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DigitalOut {
    value: bool,
    default: bool,
    max_duration: u32,
    /// When the pin last left its default value, ticks.
    since: u32,
}

impl DigitalOut {
    /// `config_digital_out`: starts at `value`.
    pub const fn new(value: bool, default: bool, max_duration: u32, now: u32) -> Self {
        Self {
            value,
            default,
            max_duration,
            since: now,
        }
    }

    /// The pin's value.
    pub fn value(&self) -> bool {
        self.value
    }

    /// Sets the pin at clock `now` (a refresh restarts the timeout).
    pub fn set(&mut self, value: bool, now: u32) {
        self.value = value;
        self.since = now;
    }

    /// Checks the timeout at clock `now`: a pin away from its default for
    /// longer than max_duration is a fault.
    pub fn check(&self, now: u32) -> Result<(), Shutdown> {
        let expires = self.since.wrapping_add(self.max_duration);
        if self.max_duration > 0 && self.value != self.default && !is_before(now, expires) {
            return Err(Shutdown::DigitalOutExpired);
        }
        Ok(())
    }

    /// Returns the pin to its default (shutdown).
    pub fn reset(&mut self) {
        self.value = self.default;
    }
}

/// An ADC input checked against `[min, max]` (raw counts): `range_count`
/// readings in a row outside it are a fault (0: no check).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AnalogIn {
    min: u16,
    max: u16,
    range_count: u8,
    invalid: u8,
}

impl AnalogIn {
    /// `query_analog_in`'s range settings.
    pub const fn new(min: u16, max: u16, range_count: u8) -> Self {
        Self {
            min,
            max,
            range_count,
            invalid: 0,
        }
    }

    /// Takes a reading.
    pub fn sample(&mut self, value: u16) -> Result<(), Shutdown> {
        if self.range_count == 0 || (self.min..=self.max).contains(&value) {
            self.invalid = 0;
            return Ok(());
        }
        self.invalid = self.invalid.saturating_add(1);
        if self.invalid >= self.range_count {
            return Err(Shutdown::AdcOutOfRange);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_output_left_on_past_max_duration_is_a_fault() {
        let mut heater = DigitalOut::new(false, false, 1000, 0);
        heater.set(true, 100);
        assert_eq!(heater.check(1099), Ok(()));
        heater.set(true, 1050);
        assert_eq!(heater.check(2049), Ok(()));
        assert_eq!(heater.check(2050), Err(Shutdown::DigitalOutExpired));
        heater.set(false, 2000);
        assert_eq!(heater.check(9999), Ok(()));
    }

    #[test]
    fn adc_faults_after_consecutive_out_of_range_readings() {
        let mut thermistor = AnalogIn::new(100, 4000, 3);
        assert_eq!(thermistor.sample(50), Ok(()));
        assert_eq!(thermistor.sample(4095), Ok(()));
        assert_eq!(thermistor.sample(2000), Ok(()));
        assert_eq!(thermistor.sample(4095), Ok(()));
        assert_eq!(thermistor.sample(4095), Ok(()));
        assert_eq!(thermistor.sample(4095), Err(Shutdown::AdcOutOfRange));
    }
}
