//! The timed motion queue the planner fills and step generation reads
//! (Klipper's trapq): constant-acceleration segments in time order, with
//! no gaps, ending in an open stationary tail, in a fixed-size buffer.
//!
//! A planned move becomes up to three segments; the time before it (after
//! the previous move, or a lead-in before the first) is a stationary
//! segment at the move's start position, so filters that look across
//! segments (pressure advance, input shaping) always find one. Segments
//! are dropped from the front once step generation has passed them
//! ([`Trapq::retire`]).

use crate::segment::{Segment, segments};
use onechip_planner::move_sink::TrapqMove;

/// Stationary time put before the first move, s (more than any
/// step-generation margin).
const LEAD_TIME: f64 = 1.0;

/// How long the open tail lasts, s: longer than any print.
const TAIL_TIME: f64 = 1.0e9;

/// Segments one appended move can need: a gap filler, three phases and
/// the new tail.
pub const SEGMENTS_PER_MOVE: usize = 5;

/// The queue has no room for another move.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TrapqFull;

/// A motion queue of at most `N` segments.
#[derive(Debug, Clone)]
pub struct Trapq<const N: usize> {
    segs: heapless::Vec<Segment, N>,
}

impl<const N: usize> Default for Trapq<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> Trapq<N> {
    /// An empty queue.
    pub const fn new() -> Self {
        Self {
            segs: heapless::Vec::new(),
        }
    }

    /// Empties the queue.
    pub fn clear(&mut self) {
        self.segs.clear();
    }

    /// The queued segments, the open tail last.
    pub fn segments(&self) -> &[Segment] {
        &self.segs
    }

    /// True if a move can be appended.
    pub fn has_room(&self) -> bool {
        self.segs.len() + SEGMENTS_PER_MOVE <= N
    }

    /// Appends a planned move. Moves must come in time order; one that
    /// starts before the queued motion ends is placed at its end.
    pub fn append(&mut self, m: &TrapqMove) -> Result<(), TrapqFull> {
        if !self.has_room() {
            return Err(TrapqFull);
        }
        let still = |print_time: f64, move_t: f64| Segment {
            print_time,
            move_t,
            start_v: 0.0,
            half_accel: 0.0,
            start_pos: m.start_pos,
            axes_r: [0.0; 3],
        };
        let mut start = m.print_time;
        match self.segs.pop() {
            // The tail now ends where the move starts, at its position;
            // a queue left with the tail alone (every move before it
            // passed) keeps a lead-in as a new one, so that a filter
            // looking back from the move (pressure advance turned on
            // since) finds the rest before it.
            Some(tail) => {
                start = start.max(tail.print_time);
                let from = if self.segs.is_empty() {
                    tail.print_time.min(start - LEAD_TIME)
                } else {
                    tail.print_time
                };
                if start > from {
                    self.push(still(from, start - from));
                }
            }
            None => self.push(still(start - LEAD_TIME, LEAD_TIME)),
        }
        let mut end = start;
        for mut seg in segments(&TrapqMove {
            print_time: start,
            ..*m
        }) {
            seg.print_time = end;
            end = seg.end_time();
            self.push(seg);
        }
        let end_pos = self
            .segs
            .last()
            .map_or(m.start_pos, |s| s.position(s.move_t));
        self.push(Segment {
            start_pos: end_pos,
            ..still(end, TAIL_TIME)
        });
        Ok(())
    }

    /// Drops the segments that end before print time `before` (s); the
    /// tail stays.
    pub fn retire(&mut self, before: f64) {
        let done = self
            .segs
            .iter()
            .take(self.segs.len().saturating_sub(1))
            .take_while(|s| s.end_time() < before)
            .count();
        if done > 0 {
            let len = self.segs.len();
            self.segs.copy_within(done.., 0);
            self.segs.truncate(len - done);
        }
    }

    fn push(&mut self, seg: Segment) {
        // Room was checked for a whole move in `append`.
        let _ = self.segs.push(seg);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line(print_time: f64, x: f64) -> TrapqMove {
        TrapqMove {
            print_time,
            accel_t: 0.1,
            cruise_t: 0.1,
            decel_t: 0.1,
            start_pos: [x, 0.0, 0.0],
            axes_r: [1.0, 0.0, 0.0],
            start_v: 0.0,
            cruise_v: 10.0,
            accel: 100.0,
        }
    }

    #[test]
    fn gaps_are_filled_and_an_open_tail_holds_the_end() {
        let mut q = Trapq::<32>::new();
        q.append(&line(1.0, 0.0)).expect("room");
        q.append(&line(2.0, 2.0)).expect("room");
        let s = q.segments();
        // Lead, 3 phases, gap, 3 phases, tail.
        assert_eq!(s.len(), 9);
        assert!(s.windows(2).all(|w| w[0].end_time() == w[1].print_time));
        assert_eq!(s[0].print_time, 0.0);
        assert!((s[4].print_time - 1.3).abs() < 1e-12 && s[4].end_time() == 2.0);
        let tail = s[8];
        assert!((tail.start_pos[0] - 4.0).abs() < 1e-12);
        assert!(tail.move_t > 1e6 && tail.axes_r == [0.0; 3]);
    }

    #[test]
    fn full_queue_refuses_and_retiring_makes_room() {
        let mut q = Trapq::<9>::new();
        q.append(&line(1.0, 0.0)).expect("room");
        assert_eq!(q.append(&line(2.0, 2.0)), Err(TrapqFull));
        q.retire(1.25);
        // Lead and the first two phases are gone.
        assert!((q.segments()[0].print_time - 1.2).abs() < 1e-12);
        q.append(&line(2.0, 2.0)).expect("room now");
        q.retire(f64::INFINITY);
        assert_eq!(q.segments().len(), 1, "the tail stays");
    }
}
