//! Virtual time paced by the wall clock, for a simulator that a real host
//! talks to: the MCU clock runs `speed` times as fast as the wall clock,
//! so a timer event at clock `c` runs no earlier than
//! `(c - origin) / (freq × speed)` s after the start.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// How far ahead of the wall clock an event may run without a sleep: a
/// sleep costs tens of µs, far more than the steps between two of them.
const SLACK: Duration = Duration::from_millis(1);
/// Longest single sleep, so that a raised [`Pace::release`] flag is seen
/// within it.
const MAX_SLEEP: Duration = Duration::from_millis(20);

/// The wall clock that virtual time follows.
#[derive(Debug, Clone)]
pub struct Pace {
    start: Instant,
    /// MCU clock at `start`, ticks.
    origin: u64,
    /// MCU ticks per wall-clock second (the clock frequency × speed).
    ticks_per_second: f64,
    /// Once raised, virtual time runs free (as fast as it computes): the
    /// host hung up or the user interrupted, and what is queued just has
    /// to run to its end.
    release: Arc<AtomicBool>,
}

impl Pace {
    /// Virtual time from now on: clock `origin` (ticks) is now, and the
    /// clock of `freq` Hz runs `speed` times as fast as the wall clock;
    /// free once `release` is raised.
    pub fn new(origin: u64, freq: f64, speed: f64, release: Arc<AtomicBool>) -> Self {
        Self {
            start: Instant::now(),
            origin,
            ticks_per_second: freq * speed,
            release,
        }
    }

    /// True once virtual time runs free.
    pub fn released(&self) -> bool {
        self.release.load(Ordering::Relaxed)
    }

    /// The MCU clock that the wall clock has reached, ticks.
    pub fn clock_now(&self) -> u64 {
        let elapsed = self.start.elapsed().as_secs_f64();
        self.origin + (elapsed * self.ticks_per_second) as u64
    }

    /// Sleeps until the wall clock reaches MCU clock `clock` (to within
    /// [`SLACK`]), or virtual time is released.
    pub fn sleep_until(&self, clock: u64) {
        let seconds = clock.saturating_sub(self.origin) as f64 / self.ticks_per_second;
        let Some(due) = Duration::try_from_secs_f64(seconds)
            .ok()
            .and_then(|d| self.start.checked_add(d))
        else {
            // Beyond any wall time: only a release ends the wait.
            while !self.released() {
                std::thread::sleep(MAX_SLEEP);
            }
            return;
        };
        while !self.released() {
            let ahead = due.saturating_duration_since(Instant::now());
            if ahead <= SLACK {
                return;
            }
            std::thread::sleep(ahead.min(MAX_SLEEP));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pace of 1 MHz at speed 1 (1 tick per µs), and its release flag.
    fn pace() -> (Pace, Arc<AtomicBool>) {
        let release = Arc::new(AtomicBool::new(false));
        (Pace::new(5_000, 1e6, 1.0, Arc::clone(&release)), release)
    }

    #[test]
    fn the_clock_follows_the_wall_clock_times_the_speed() {
        let release = Arc::new(AtomicBool::new(false));
        let fast = Pace::new(0, 1e6, 10.0, release);
        std::thread::sleep(Duration::from_millis(30));
        let clock = fast.clock_now();
        // 30 ms at ten times 1 MHz: at least 300 000 ticks, and not
        // seconds more.
        assert!((300_000..3_000_000).contains(&clock), "{clock}");
    }

    #[test]
    fn sleeping_until_a_clock_waits_for_its_wall_time() {
        let (pace, _release) = pace();
        let start = Instant::now();
        pace.sleep_until(5_000 + 40_000);
        let slept = start.elapsed();
        assert!(slept >= Duration::from_millis(38), "{slept:?}");
        assert!(pace.clock_now() >= 5_000 + 39_000);
        // A clock already passed does not sleep.
        let start = Instant::now();
        pace.sleep_until(0);
        assert!(start.elapsed() < Duration::from_millis(5));
    }

    #[test]
    fn a_release_ends_a_sleep_at_once() {
        let (pace, release) = pace();
        let waker = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(30));
            release.store(true, Ordering::Relaxed);
        });
        let start = Instant::now();
        // An hour of virtual time, and one beyond any wall time.
        pace.sleep_until(3_600_000_000);
        pace.sleep_until(u64::MAX);
        assert!(start.elapsed() < Duration::from_secs(1));
        assert!(pace.released());
        waker.join().expect("waker");
    }
}
