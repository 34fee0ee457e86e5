//! ADC inputs sampled from the MCU role's timer, as Klipper's `analog_in`:
//! every `rest_ticks`, `sample_count` readings `sample_ticks` apart are
//! summed into one report, and a sum outside `[min, max]` for
//! `range_check_count` reports in a row shuts everything down (a
//! thermistor that is shorted, open or reading past the heater's limits).

use crate::shutdown::Shutdown;

/// Klipper's `query_analog_in`: when and how to sample, and the range.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AdcQuery {
    /// Clock of the first reading, ticks.
    pub clock: u32,
    /// Ticks between the readings of one report.
    pub sample_ticks: u32,
    /// Readings summed per report (at least 1).
    pub sample_count: u8,
    /// Ticks from one report's first reading to the next report's.
    pub rest_ticks: u32,
    /// Lowest good sum, raw counts.
    pub min: u16,
    /// Highest good sum, raw counts.
    pub max: u16,
    /// Reports out of range in a row that are a fault (0: no check).
    pub range_check_count: u8,
}

/// One report: the sum of a report's readings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AdcReport {
    /// Clock of the report's first reading, ticks.
    pub clock: u32,
    /// Sum of its readings, raw counts (saturated at `u16::MAX`).
    pub value: u16,
}

/// An ADC input and its sampling state.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct AnalogIn {
    query: Option<AdcQuery>,
    /// Clock of the current report's first reading.
    start: u32,
    /// Clock of the next reading.
    next: u32,
    sum: u32,
    taken: u8,
    invalid: u8,
    report: Option<AdcReport>,
}

impl AnalogIn {
    /// Starts sampling as `query` says (replacing any earlier query).
    pub fn query(&mut self, query: AdcQuery) {
        *self = Self {
            query: Some(AdcQuery {
                sample_count: query.sample_count.max(1),
                ..query
            }),
            start: query.clock,
            next: query.clock,
            ..Self::default()
        };
    }

    /// Stops sampling (shutdown).
    pub fn stop(&mut self) {
        self.query = None;
    }

    /// Clock of the next reading, while sampling.
    pub fn next_event(&self) -> Option<u32> {
        self.query.map(|_| self.next)
    }

    /// The newest report not yet taken.
    pub fn take_report(&mut self) -> Option<AdcReport> {
        self.report.take()
    }

    /// Takes the reading due at [`Self::next_event`]; Err when the range
    /// check fails.
    pub fn sample(&mut self, reading: u16) -> Result<(), Shutdown> {
        let Some(q) = self.query else {
            return Ok(());
        };
        self.sum += u32::from(reading);
        self.taken += 1;
        if self.taken < q.sample_count {
            self.next = self.next.wrapping_add(q.sample_ticks);
            return Ok(());
        }
        let value = self.sum.min(u32::from(u16::MAX)) as u16;
        self.report = Some(AdcReport {
            clock: self.start,
            value,
        });
        self.start = self.start.wrapping_add(q.rest_ticks);
        self.next = self.start;
        self.sum = 0;
        self.taken = 0;
        if q.range_check_count == 0 || (q.min..=q.max).contains(&value) {
            self.invalid = 0;
            return Ok(());
        }
        self.invalid = self.invalid.saturating_add(1);
        if self.invalid >= q.range_check_count {
            return Err(Shutdown::AdcOutOfRange);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn thermistor() -> AnalogIn {
        let mut adc = AnalogIn::default();
        adc.query(AdcQuery {
            clock: u32::MAX - 10,
            sample_ticks: 5,
            sample_count: 4,
            rest_ticks: 1000,
            min: 400,
            max: 16000,
            range_check_count: 3,
        });
        adc
    }

    /// Takes one report's readings, all `reading`, at their clocks.
    fn report(adc: &mut AnalogIn, reading: u16) -> Result<(), Shutdown> {
        for _ in 0..4 {
            adc.sample(reading)?;
        }
        Ok(())
    }

    #[test]
    fn readings_are_summed_into_reports_at_their_clocks() {
        let mut adc = thermistor();
        let mut clocks = [0; 4];
        for clock in &mut clocks {
            *clock = adc.next_event().expect("sampling");
            adc.sample(1000).expect("in range");
        }
        assert_eq!(clocks, [u32::MAX - 10, u32::MAX - 5, u32::MAX, 4]);
        assert_eq!(
            adc.take_report(),
            Some(AdcReport {
                clock: u32::MAX - 10,
                value: 4000
            })
        );
        assert_eq!(adc.take_report(), None);
        assert_eq!(adc.next_event(), Some(989));
        adc.stop();
        assert_eq!(adc.next_event(), None);
    }

    #[test]
    fn consecutive_reports_out_of_range_are_a_fault() {
        let mut adc = thermistor();
        // Two bad reports, a good one, then three bad: the third faults.
        assert_eq!(report(&mut adc, 50), Ok(()));
        assert_eq!(report(&mut adc, 4095), Ok(()));
        assert_eq!(report(&mut adc, 2000), Ok(()));
        assert_eq!(report(&mut adc, 4095), Ok(()));
        assert_eq!(report(&mut adc, 4095), Ok(()));
        assert_eq!(report(&mut adc, 4095), Err(Shutdown::AdcOutOfRange));
        assert_eq!(adc.take_report().map(|r| r.value), Some(16380));
    }
}
