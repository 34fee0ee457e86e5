//! The lookahead queue: moves wait here until enough follow them to plan
//! their junction speeds, as Klipper's toolhead does.
//!
//! Moves are planned backwards from the newest, assuming the toolhead stops
//! after it. A lazy flush releases only the moves whose plan can no longer
//! change; a full flush releases all. The queue holds at most `N` moves
//! (no heap); when it is full, a lazy flush makes room, and only if none is
//! possible does a full flush (a stop after the oldest moves) happen.

use crate::planned_move::Move;

/// Time of moves to queue before a lazy flush is tried, s.
pub const LOOKAHEAD_FLUSH_TIME: f64 = 0.250;

/// The lookahead queue, holding at most `N` moves.
#[derive(Debug, Clone)]
pub struct LookAhead<const N: usize> {
    queue: heapless::Vec<Move, N>,
    junction_flush: f64,
}

impl<const N: usize> Default for LookAhead<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> LookAhead<N> {
    /// An empty queue.
    pub const fn new() -> Self {
        Self {
            queue: heapless::Vec::new(),
            junction_flush: LOOKAHEAD_FLUSH_TIME,
        }
    }

    /// Forgets every queued move.
    pub fn reset(&mut self) {
        self.queue.clear();
        self.junction_flush = LOOKAHEAD_FLUSH_TIME;
    }

    /// Sets how much move time to gather before the next lazy flush, s.
    pub fn set_flush_time(&mut self, flush_time: f64) {
        self.junction_flush = flush_time;
    }

    /// The newest queued move.
    pub fn last_mut(&mut self) -> Option<&mut Move> {
        self.queue.last_mut()
    }

    /// The queued moves, oldest first.
    pub fn moves(&self) -> &[Move] {
        &self.queue
    }

    /// True if no move is queued.
    pub fn is_empty(&self) -> bool {
        self.queue.is_empty()
    }

    /// True if the queue cannot take another move.
    pub fn is_full(&self) -> bool {
        self.queue.is_full()
    }

    /// Queues `m` (its junction with the previous move computed with the
    /// extruder limit `extruder_v2`); true if a lazy flush is due.
    /// The caller flushes first when [`LookAhead::is_full`].
    pub fn add(&mut self, mut m: Move, extruder_v2: impl FnOnce(&Move, &Move) -> f64) -> bool {
        if let Some(prev) = self.queue.last() {
            let limit = extruder_v2(prev, &m);
            m.calc_junction(prev, limit);
            self.junction_flush -= m.min_move_t;
        }
        let first = self.queue.is_empty();
        // Callers flush when the queue is full, so this cannot fail.
        let _ = self.queue.push(m);
        !first && self.junction_flush <= 0.0
    }

    /// Plans the queue; returns how many of the oldest moves are final, to
    /// be taken with [`LookAhead::take`]. A full flush (`lazy == false`)
    /// plans a stop after the newest move and finalises everything.
    pub fn flush(&mut self, lazy: bool) -> usize {
        self.junction_flush = LOOKAHEAD_FLUSH_TIME;
        self.plan(lazy)
    }

    /// Hands the `count` oldest moves to `emit`, in order, and drops them.
    pub fn take(&mut self, count: usize, emit: impl FnMut(&Move)) {
        let count = count.min(self.queue.len());
        self.queue[..count].iter().for_each(emit);
        self.queue.rotate_left(count);
        self.queue.truncate(self.queue.len() - count);
    }

    /// The backward pass; returns how many moves (from the oldest) are final.
    fn plan(&mut self, lazy: bool) -> usize {
        let mut update_flush_count = lazy;
        let queue = &mut self.queue;
        let mut flush_count = queue.len();
        // Moves whose cruise speed waits on the next peak: (index, start, end).
        let mut delayed: heapless::Vec<(usize, f64, f64), N> = heapless::Vec::new();
        let (mut next_end_v2, mut next_smoothed_v2, mut peak_cruise_v2) = (0.0, 0.0, 0.0);
        for i in (0..flush_count).rev() {
            let (max_start_v2, delta_v2, max_smoothed_v2, smooth_delta_v2, max_cruise_v2) =
                queue[i].lookahead_terms();
            let reachable_start_v2 = next_end_v2 + delta_v2;
            let start_v2 = f64::min(max_start_v2, reachable_start_v2);
            let reachable_smoothed_v2 = next_smoothed_v2 + smooth_delta_v2;
            let smoothed_v2 = f64::min(max_smoothed_v2, reachable_smoothed_v2);
            if smoothed_v2 < reachable_smoothed_v2 {
                // This move may accelerate.
                if smoothed_v2 + smooth_delta_v2 > next_smoothed_v2 || !delayed.is_empty() {
                    // It can decelerate, or it is a full accel after a full decel.
                    if update_flush_count && peak_cruise_v2 != 0.0 {
                        flush_count = i;
                        update_flush_count = false;
                    }
                    peak_cruise_v2 =
                        f64::min(max_cruise_v2, (smoothed_v2 + reachable_smoothed_v2) * 0.5);
                    if !update_flush_count && i < flush_count {
                        let mut mc_v2 = peak_cruise_v2;
                        for &(index, ms_v2, me_v2) in delayed.iter().rev() {
                            mc_v2 = f64::min(mc_v2, ms_v2);
                            queue[index].set_junction(
                                f64::min(ms_v2, mc_v2),
                                mc_v2,
                                f64::min(me_v2, mc_v2),
                            );
                        }
                    }
                    delayed.clear();
                }
                if !update_flush_count && i < flush_count {
                    let cruise_v2 = f64::min(
                        f64::min((start_v2 + reachable_start_v2) * 0.5, max_cruise_v2),
                        peak_cruise_v2,
                    );
                    queue[i].set_junction(
                        f64::min(start_v2, cruise_v2),
                        cruise_v2,
                        f64::min(next_end_v2, cruise_v2),
                    );
                }
            } else {
                // Plan it once the next peak cruise speed is known. At most
                // one entry per queued move, so this cannot overflow.
                let _ = delayed.push((i, start_v2, next_end_v2));
            }
            next_end_v2 = start_v2;
            next_smoothed_v2 = smoothed_v2;
        }
        if update_flush_count { 0 } else { flush_count }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::planned_move::Limits;
    use std::vec::Vec;

    fn run(points: &[[f64; 2]], speed: f64) -> Vec<Move> {
        let limits = Limits::new(300.0, 3000.0, 0.5, 5.0);
        let mut q = LookAhead::<64>::new();
        let mut out = Vec::new();
        for w in points.windows(2) {
            let m = Move::new(
                &limits,
                [w[0][0], w[0][1], 0.0, 0.0],
                [w[1][0], w[1][1], 0.0, 0.0],
                speed,
            )
            .expect("moves");
            if q.add(m, |_, _| f64::MAX) {
                let n = q.flush(true);
                q.take(n, |m| out.push(*m));
            }
        }
        let n = q.flush(false);
        q.take(n, |m| out.push(*m));
        out
    }

    #[test]
    fn moves_start_and_end_at_rest_and_join_continuously() {
        let moves = run(
            &[
                [0.0, 0.0],
                [20.0, 0.0],
                [20.0, 20.0],
                [0.0, 20.0],
                [0.0, 0.0],
            ],
            100.0,
        );
        assert_eq!(moves.len(), 4);
        assert_eq!(moves[0].start_v, 0.0);
        assert_eq!(moves[3].end_v, 0.0);
        for pair in moves.windows(2) {
            assert!((pair[0].end_v - pair[1].start_v).abs() < 1e-9);
            assert!(
                (pair[1].start_v - 5.0).abs() < 1e-6,
                "square corners at 5 mm/s"
            );
        }
    }

    #[test]
    fn lazy_flushes_release_moves_in_order_and_keep_the_rest() {
        let points: Vec<[f64; 2]> = (0..200)
            .map(|i| [f64::from(i) * 2.0, if i % 2 == 0 { 0.0 } else { 5.0 }])
            .collect();
        let moves = run(&points, 200.0);
        assert_eq!(moves.len(), 199);
        for pair in moves.windows(2) {
            assert_eq!(pair[0].end_pos, pair[1].start_pos);
            assert!((pair[0].end_v - pair[1].start_v).abs() < 1e-9);
        }
    }
}
