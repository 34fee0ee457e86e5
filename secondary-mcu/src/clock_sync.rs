//! Clock synchronisation with a secondary MCU, as klippy's clocksync does
//! it: the MCU's clock is sampled with `get_clock` about once a second, a
//! decaying linear regression of clock against host time (with outlier
//! filtering) estimates it, and print time is mapped onto it by a line
//! that is re-fitted ahead of the queued moves so that the mapping never
//! jumps.
//!
//! Host time is the main MCU's clock in seconds: print time itself (the
//! main MCU's clock is print time's source, on the board and in the
//! simulator alike), so the main MCU needs no synchronisation of its own.

/// Seconds between two `get_clock` queries (klippy's odd period, so the
/// queries do not beat with other periodic events).
pub const QUERY_PERIOD: f64 = 0.9839;
/// Queries without an answer after which the link counts as lost
/// (klippy's `is_active`: more than four pending).
pub const MAX_PENDING_QUERIES: u32 = 4;
/// Weight of each new sample in the regression.
const DECAY: f64 = 1.0 / 30.0;
/// How fast the best round trip seen so far ages, s per s.
const RTT_AGE: f64 = 0.000_010 / (60.0 * 60.0);

/// The regression's estimate of an MCU's clock, and its print time line.
#[derive(Debug, Clone, Copy)]
pub struct ClockSync {
    /// The MCU's nominal clock (`CLOCK_FREQ`), Hz.
    mcu_freq: f64,
    /// Latest clock seen, widened to 64 bits, ticks.
    last_clock: u64,
    min_half_rtt: f64,
    min_rtt_time: f64,
    time_avg: f64,
    time_variance: f64,
    clock_avg: f64,
    clock_covariance: f64,
    prediction_variance: f64,
    last_prediction_time: f64,
    /// The estimate: at host time `.0` (s) the clock was `.1` (ticks),
    /// running at `.2` Hz.
    estimate: (f64, f64, f64),
    /// `get_clock` queries sent and not answered.
    pending_queries: u32,
    /// Print time to clock: `clock = (print_time - .0) × .1`.
    print_line: (f64, f64),
    /// Print time up to which the current line was fitted, s.
    last_sync_time: f64,
}

impl ClockSync {
    /// Starts from a `get_uptime` answer (`uptime high clock`), `clock`
    /// 64-bit, asked at host time `sent` (s), on an MCU of `mcu_freq` Hz.
    pub fn new(mcu_freq: f64, clock: u64, sent: f64) -> Self {
        let mut sync = Self {
            mcu_freq,
            last_clock: clock,
            min_half_rtt: f64::MAX,
            min_rtt_time: 0.0,
            time_avg: sent,
            time_variance: 0.0,
            clock_avg: clock as f64,
            clock_covariance: 0.0,
            prediction_variance: (0.001 * mcu_freq) * (0.001 * mcu_freq),
            last_prediction_time: -9999.0,
            estimate: (sent, clock as f64, mcu_freq),
            pending_queries: 0,
            print_line: (0.0, mcu_freq),
            last_sync_time: 0.0,
        };
        let local = sync.clock_at(sent) as f64 / mcu_freq;
        sync.print_line = (sent - local, mcu_freq);
        sync
    }

    /// The MCU's nominal clock, Hz.
    pub fn mcu_freq(&self) -> f64 {
        self.mcu_freq
    }

    /// A `get_clock` query went out.
    pub fn query_sent(&mut self) {
        self.pending_queries += 1;
    }

    /// True while the MCU answers its clock queries.
    pub fn is_active(&self) -> bool {
        self.pending_queries <= MAX_PENDING_QUERIES
    }

    /// Widens a 32-bit clock from the MCU to 64 bits, near the latest.
    pub fn widen(&self, clock32: u32) -> u64 {
        let delta = clock32.wrapping_sub(self.last_clock as u32) as i32;
        self.last_clock.wrapping_add_signed(i64::from(delta))
    }

    /// Takes a `clock clock=…` answer to a query sent at host time `sent`
    /// and received at `received` (s); `sent` is None when the query may
    /// have been retransmitted (its round trip means nothing).
    pub fn on_clock(&mut self, clock32: u32, sent: Option<f64>, received: f64) {
        self.pending_queries = 0;
        let delta = u64::from(clock32.wrapping_sub(self.last_clock as u32));
        let clock = self.last_clock + delta;
        self.last_clock = clock;
        let Some(sent) = sent else {
            return;
        };
        let clock = clock as f64;
        // The best round trip so far, slowly aged.
        let half_rtt = 0.5 * (received - sent);
        let aged_rtt = (sent - self.min_rtt_time) * RTT_AGE;
        if half_rtt < self.min_half_rtt + aged_rtt {
            self.min_half_rtt = half_rtt;
            self.min_rtt_time = sent;
        }
        // Extreme outliers are dropped (or, if they persist, accepted
        // with a wide variance).
        let expected = (sent - self.time_avg) * self.estimate.2 + self.clock_avg;
        let diff2 = (clock - expected) * (clock - expected);
        let floor = 0.000_500 * self.mcu_freq;
        if diff2 > 25.0 * self.prediction_variance && diff2 > floor * floor {
            if clock > expected && sent < self.last_prediction_time + 10.0 {
                return;
            }
            self.prediction_variance = (0.001 * self.mcu_freq) * (0.001 * self.mcu_freq);
        } else {
            self.last_prediction_time = sent;
            self.prediction_variance = (1.0 - DECAY) * (self.prediction_variance + diff2 * DECAY);
        }
        // Decaying linear regression of clock on send time.
        let diff_time = sent - self.time_avg;
        self.time_avg += DECAY * diff_time;
        self.time_variance = (1.0 - DECAY) * (self.time_variance + diff_time * diff_time * DECAY);
        let diff_clock = clock - self.clock_avg;
        self.clock_avg += DECAY * diff_clock;
        self.clock_covariance =
            (1.0 - DECAY) * (self.clock_covariance + diff_time * diff_clock * DECAY);
        if self.time_variance > 0.0 {
            let freq = self.clock_covariance / self.time_variance;
            self.estimate = (self.time_avg + self.min_half_rtt, self.clock_avg, freq);
        }
    }

    /// The estimated MCU clock at host time `time` (s), ticks. Not inlined:
    /// it has many callers, and its soft-float arithmetic is not short.
    #[inline(never)]
    pub fn clock_at(&self, time: f64) -> u64 {
        let (t0, c0, freq) = self.estimate;
        (c0 + (time - t0) * freq).max(0.0) as u64
    }

    /// The host time (s) at which the MCU's clock is estimated to read
    /// `clock` (ticks, 64-bit).
    pub fn time_at(&self, clock: u64) -> f64 {
        let (t0, c0, freq) = self.estimate;
        t0 + (clock as f64 - c0) / freq
    }

    /// The estimated clock frequency, Hz.
    pub fn estimated_freq(&self) -> f64 {
        self.estimate.2
    }

    /// The MCU clock of print time `print_time` (s), ticks.
    pub fn print_time_to_clock(&self, print_time: f64) -> u64 {
        let (offset, freq) = self.print_line;
        ((print_time - offset) * freq).max(0.0) as u64
    }

    /// The print time of MCU clock `clock` (ticks), s.
    pub fn clock_to_print_time(&self, clock: u64) -> f64 {
        let (offset, freq) = self.print_line;
        clock as f64 / freq + offset
    }

    /// The print time line as `(offset s, frequency Hz)`: step clocks are
    /// `(t - offset) × frequency`.
    pub fn print_line(&self) -> (f64, f64) {
        self.print_line
    }

    /// Re-fits the print time line at host time `now` (s), with moves
    /// queued up to `print_time` (s): the line keeps its clock at the later
    /// of the two (no jump for what is queued) and meets the estimate a
    /// few seconds on, as klippy's `calibrate_clock`.
    pub fn calibrate(&mut self, print_time: f64, now: f64) -> (f64, f64) {
        let sync1 = print_time.max(now);
        let sync2 = (sync1 + 4.0)
            .max(self.last_sync_time)
            .max(print_time + 2.5 * (print_time - now));
        let clock1 = (sync1 - self.print_line.0) * self.print_line.1;
        let (t0, c0, freq) = self.estimate;
        let clock2 = c0 + (sync2 - t0) * freq;
        let new_freq = (clock2 - clock1) / (sync2 - sync1);
        if new_freq.is_finite() && new_freq > 0.0 {
            self.print_line = (sync1 - clock1 / new_freq, new_freq);
            self.last_sync_time = sync2;
        }
        self.print_line
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An MCU whose clock runs `ppm` fast from `start` ticks at host time 0,
    /// sampled every period with a round trip of `rtt` s (half each way),
    /// plus one late answer every tenth sample.
    fn synced(freq: f64, ppm: f64, start: u64, samples: usize) -> ClockSync {
        let true_freq = freq * (1.0 + ppm * 1e-6);
        let clock = |t: f64| start + (t * true_freq) as u64;
        let mut sync = ClockSync::new(freq, clock(0.0005), 0.0);
        for i in 1..=samples {
            let sent = i as f64 * QUERY_PERIOD;
            let delay = if i % 10 == 0 { 0.020 } else { 0.0005 };
            sync.query_sent();
            sync.on_clock(clock(sent + delay) as u32, Some(sent), sent + 2.0 * delay);
        }
        sync
    }

    #[test]
    fn the_regression_finds_a_drifting_clock_within_a_few_ticks_per_ms() {
        // A 16 MHz AVR 50 ppm fast, its 32-bit clock wrapping during the
        // run (2^32 ticks = 268 s).
        let freq = 16e6;
        let sync = synced(freq, 50.0, 4_200_000_000, 400);
        assert!((sync.estimated_freq() / (freq * 1.000_05) - 1.0).abs() < 2e-6);
        let t = 400.0 * QUERY_PERIOD;
        let truth = 4_200_000_000.0 + t * freq * 1.000_05;
        // Within 10 µs of the truth (the half round trip is 0.5 ms and
        // is measured, so it does not bias the estimate).
        let err = (sync.clock_at(t) as f64 - truth) / freq;
        assert!(err.abs() < 10e-6, "{err}");
        assert!(sync.is_active());
    }

    #[test]
    fn the_print_line_is_continuous_at_the_queued_time() {
        let mut sync = synced(50e6, -30.0, 1 << 20, 50);
        let now = 50.0 * QUERY_PERIOD;
        sync.calibrate(now + 1.0, now);
        let queued = now + 2.0;
        let before = sync.print_time_to_clock(queued);
        sync.calibrate(queued, now + 1.0);
        let after = sync.print_time_to_clock(queued);
        assert!(before.abs_diff(after) <= 1, "{before} {after}");
        // And a clock maps back to its print time.
        let t = sync.clock_to_print_time(after);
        assert!((t - queued).abs() < 1e-7);
    }

    #[test]
    fn five_unanswered_queries_mean_the_link_is_lost() {
        let mut sync = synced(16e6, 0.0, 0, 5);
        for _ in 0..MAX_PENDING_QUERIES {
            sync.query_sent();
        }
        assert!(sync.is_active());
        sync.query_sent();
        assert!(!sync.is_active());
    }

    #[test]
    fn a_32_bit_clock_widens_across_the_wrap() {
        let sync = ClockSync::new(16e6, (1 << 32) - 10, 0.0);
        assert_eq!(sync.widen(5), (1 << 32) + 5);
        assert_eq!(sync.widen(u32::MAX - 20), (1 << 32) - 21);
    }
}
