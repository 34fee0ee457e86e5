//! A timer list: which of a fixed set of timers fires next, on the 32-bit
//! clock (rollover-safe while waits are under 2^31 ticks).

use crate::clock::is_before;
use crate::shutdown::Shutdown;

/// Up to `T` timers, each armed at most once.
#[derive(Debug, Clone)]
pub struct Timers<const T: usize> {
    /// Wake time of each armed timer.
    wake: [Option<u32>; T],
}

impl<const T: usize> Default for Timers<T> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const T: usize> Timers<T> {
    /// No timer armed.
    pub const fn new() -> Self {
        Self { wake: [None; T] }
    }

    /// Arms timer `id` for clock `at`; `now` is the current clock. A time
    /// already passed is a fault: the work it stands for would be late.
    pub fn arm(&mut self, id: usize, at: u32, now: u32) -> Result<(), Shutdown> {
        if is_before(at, now) {
            return Err(Shutdown::TimerTooClose);
        }
        if let Some(slot) = self.wake.get_mut(id) {
            *slot = Some(at);
        }
        Ok(())
    }

    /// Disarms timer `id`.
    pub fn disarm(&mut self, id: usize) {
        if let Some(slot) = self.wake.get_mut(id) {
            *slot = None;
        }
    }

    /// The armed timer due first, with its wake time, relative to `now`
    /// (so that the order holds across the wrap).
    pub fn next(&self, now: u32) -> Option<(usize, u32)> {
        self.wake
            .iter()
            .enumerate()
            .filter_map(|(id, w)| w.map(|at| (id, at)))
            .min_by_key(|&(_, at)| at.wrapping_sub(now) as i32)
    }

    /// Disarms and returns the timer due at or before `now`, earliest first.
    pub fn pop_due(&mut self, now: u32) -> Option<usize> {
        let (id, at) = self.next(now)?;
        if is_before(now, at) {
            return None;
        }
        self.wake[id] = None;
        Some(id)
    }

    /// Disarms every timer (shutdown).
    pub fn clear(&mut self) {
        self.wake = [None; T];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timers_fire_in_order_across_the_wrap() {
        let mut t = Timers::<3>::new();
        let now = u32::MAX - 100;
        t.arm(0, 50, now).expect("future");
        t.arm(1, u32::MAX - 10, now).expect("future");
        t.arm(2, 10, now).expect("future");
        assert_eq!(t.next(now), Some((1, u32::MAX - 10)));
        assert_eq!(t.pop_due(now), None);
        assert_eq!(t.pop_due(60), Some(1));
        assert_eq!(t.pop_due(60), Some(2));
        assert_eq!(t.pop_due(60), Some(0));
        assert_eq!(t.pop_due(60), None);
    }

    #[test]
    fn a_time_in_the_past_is_a_fault() {
        let mut t = Timers::<1>::new();
        assert_eq!(t.arm(0, 999, 1000), Err(Shutdown::TimerTooClose));
        assert_eq!(t.next(1000), None);
    }
}
