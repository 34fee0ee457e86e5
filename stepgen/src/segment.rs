//! Planned moves as constant-acceleration segments (Klipper's trapq
//! entries): each move becomes up to three segments (accelerate, cruise,
//! decelerate), each with its own start position and velocity.

use onechip_planner::move_sink::TrapqMove;

/// A span of constant acceleration along a straight line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Segment {
    /// Start time, s.
    pub print_time: f64,
    /// Duration, s.
    pub move_t: f64,
    /// Velocity at the start, mm/s.
    pub start_v: f64,
    /// Half the acceleration, mm/s².
    pub half_accel: f64,
    /// Position at the start, mm.
    pub start_pos: [f64; 3],
    /// Unit direction.
    pub axes_r: [f64; 3],
}

impl Segment {
    /// Distance travelled `t` s into the segment, mm.
    #[inline]
    pub fn distance(&self, t: f64) -> f64 {
        (self.start_v + self.half_accel * t) * t
    }

    /// Position `t` s into the segment, mm.
    #[inline]
    pub fn position(&self, t: f64) -> [f64; 3] {
        let d = self.distance(t);
        [
            self.start_pos[0] + self.axes_r[0] * d,
            self.start_pos[1] + self.axes_r[1] * d,
            self.start_pos[2] + self.axes_r[2] * d,
        ]
    }

    /// End time, s.
    pub fn end_time(&self) -> f64 {
        self.print_time + self.move_t
    }
}

/// Splits a planned move into its non-empty phases, in time order.
pub fn segments(m: &TrapqMove) -> impl Iterator<Item = Segment> {
    let mut print_time = m.print_time;
    let mut start_pos = m.start_pos;
    let phases = [
        (m.accel_t, m.start_v, 0.5 * m.accel),
        (m.cruise_t, m.cruise_v, 0.0),
        (m.decel_t, m.cruise_v, -0.5 * m.accel),
    ];
    phases
        .into_iter()
        .filter(|(t, _, _)| *t != 0.0)
        .map(move |(move_t, start_v, half_accel)| {
            let seg = Segment {
                print_time,
                move_t,
                start_v,
                half_accel,
                start_pos,
                axes_r: m.axes_r,
            };
            print_time += move_t;
            start_pos = seg.position(move_t);
            seg
        })
}

/// Longest stationary segment put before the first move, s.
const MAX_NULL_MOVE: f64 = 1.0;

/// `segments` with their time gaps filled by stationary segments, plus one
/// before the first and one after the last of at least `margin` s (as
/// Klipper's trapq does), so that filters looking across segments
/// (pressure advance, input shaping) always find one.
pub fn fill_gaps(segments: &[Segment], margin: f64, mut out: impl FnMut(Segment)) {
    let still = |print_time: f64, move_t: f64, pos: [f64; 3]| Segment {
        print_time,
        move_t,
        start_v: 0.0,
        half_accel: 0.0,
        start_pos: pos,
        axes_r: [0.0; 3],
    };
    let Some(first) = segments.first() else {
        return;
    };
    let lead = MAX_NULL_MOVE.max(margin);
    out(still(first.print_time - lead, lead, first.start_pos));
    let mut end = first.print_time;
    for seg in segments {
        if seg.print_time > end {
            out(still(end, seg.print_time - end, seg.start_pos));
        }
        out(*seg);
        end = seg.end_time();
    }
    if let Some(last) = segments.last() {
        out(still(
            end,
            margin.max(MAX_NULL_MOVE),
            last.position(last.move_t),
        ));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn phases_join_continuously_and_cover_the_move() {
        let m = TrapqMove {
            print_time: 1.0,
            accel_t: 0.1,
            cruise_t: 0.2,
            decel_t: 0.1,
            start_pos: [10.0, 0.0, 0.0],
            axes_r: [1.0, 0.0, 0.0],
            start_v: 0.0,
            cruise_v: 100.0,
            accel: 1000.0,
        };
        let segs: heapless::Vec<Segment, 3> = segments(&m).collect();
        assert_eq!(segs.len(), 3);
        assert_eq!(segs[1].start_pos[0], 15.0);
        assert_eq!(segs[2].print_time, 1.0 + 0.1 + 0.2);
        let end = segs[2].position(segs[2].move_t)[0];
        assert!((end - 40.0).abs() < 1e-12, "{end}");
    }
}
