//! Clock arithmetic that survives the 32-bit hardware timer wrapping.
//!
//! The wire and the hardware timer carry `u32` ticks, which wrap (every 8.26 s
//! at 520 MHz). Two clocks are compared by the sign of their wrapping
//! difference, which is correct while they are less than 2^31 ticks apart.
//! Internally, times are `u64` ticks that never wrap; [`Extender`] rebuilds
//! them from successive `u32` readings.

/// True if `a` is strictly before `b`, for clocks less than 2^31 ticks apart.
#[inline]
pub fn is_before(a: u32, b: u32) -> bool {
    (a.wrapping_sub(b) as i32) < 0
}

/// The earlier of two optional clocks (by wrapping order).
pub fn earliest(a: Option<u32>, b: Option<u32>) -> Option<u32> {
    match (a, b) {
        (Some(a), Some(b)) => Some(if is_before(b, a) { b } else { a }),
        (a, b) => a.or(b),
    }
}

/// `at`, if it is due at clock `now` (not after it).
pub fn due(at: Option<u32>, now: u32) -> Option<u32> {
    at.filter(|&at| !is_before(now, at))
}

/// The 64-bit clock of the 32-bit clock `at`, which lies less than 2^31
/// ticks from the 64-bit clock `now` (before or after it; 0 at the least).
pub fn widen(at: u32, now: u64) -> u64 {
    let ahead = i64::from(at.wrapping_sub(now as u32) as i32);
    now.saturating_add_signed(ahead)
}

/// Rebuilds a monotonic 64-bit clock from 32-bit readings.
///
/// Invariant: consecutive readings passed to [`Extender::extend`] are less
/// than 2^32 ticks apart (the caller reads the timer at least once a wrap).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Extender {
    last: u64,
}

impl Extender {
    /// Starts from a known 64-bit clock.
    pub const fn new(start: u64) -> Self {
        Self { last: start }
    }

    /// Returns the 64-bit clock whose low 32 bits are `now` and which is the
    /// first such clock not before the previous result.
    pub fn extend(&mut self, now: u32) -> u64 {
        let advance = now.wrapping_sub(self.last as u32);
        self.last += u64::from(advance);
        self.last
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_32_bit_clock_widens_to_the_64_bit_one_near_now_across_a_wrap() {
        let now = (3u64 << 32) + 10;
        assert_eq!(widen(5, now), now - 5);
        assert_eq!(widen(u32::MAX - 4, now), now - 15);
        assert_eq!(widen(1_000, now), now + 990);
        assert_eq!(widen(u32::MAX, 3), 0);
    }

    #[test]
    fn ordering_holds_across_the_wrap() {
        assert!(is_before(0xffff_fff0, 0x0000_0010));
        assert!(!is_before(0x0000_0010, 0xffff_fff0));
        assert!(is_before(1, 2));
        assert!(!is_before(2, 2));
        assert!(is_before(0, 0x7fff_ffff));
        assert!(!is_before(0x7fff_ffff, 0));
    }

    #[test]
    fn extender_follows_many_wraps_exactly() {
        let start = (1u64 << 32) - 1_000;
        let mut ext = Extender::new(start);
        let mut truth = start;
        // Irregular steps, some close to a full wrap, over ~40 wraps.
        let mut x: u64 = 0x9e37_79b9_7f4a_7c15;
        for _ in 0..10_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            // Mostly short steps; now and then the longest legal one, 2^32 - 1.
            truth += if x.is_multiple_of(97) {
                (1 << 32) - 1
            } else {
                x % (1 << 24)
            };
            assert_eq!(ext.extend(truth as u32), truth);
        }
        assert!(truth > 40 << 32);
    }
}
