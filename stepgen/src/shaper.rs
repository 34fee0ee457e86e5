//! Input shaping as Klipper applies it: a stepper whose kinematics uses a
//! shaped axis (X or Y) follows that axis' position convolved with the
//! shaper's impulses, `x̃(t) = Σ aᵢ · x(t + tᵢ)`, across segment
//! boundaries. Z and the extruder are never shaped.

use crate::segment::Segment;
use crate::solver::{Margins, PositionFn, Quadratic};
use onechip_planner::kinematics::StepperKinematics;
use onechip_planner::shaper_config::{InputShaperConfig, MAX_PULSES, ShaperPulses};

/// The shaping one stepper sees: the shapers of the axes its kinematics
/// uses.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct StepperShaper {
    /// Per axis X, Y (Z is never shaped).
    axes: [Option<ShaperPulses>; 2],
}

impl StepperShaper {
    /// The shapers of `config` that act on a stepper with kinematics `kin`.
    pub fn new(config: &InputShaperConfig, kin: StepperKinematics) -> Self {
        let uses = |axis: usize| match kin {
            StepperKinematics::Axis(a) => a == axis,
            StepperKinematics::Sum(a, b) | StepperKinematics::Difference(a, b) => {
                a == axis || b == axis
            }
            StepperKinematics::DeltaTower { .. } => true,
        };
        let pulses = |axis: usize, shaper: Option<_>| {
            shaper
                .filter(|_| uses(axis))
                .map(|s: onechip_planner::shaper_config::AxisShaper| s.pulses())
        };
        Self {
            axes: [pulses(0, config.x), pulses(1, config.y)],
        }
    }

    /// True if any axis of this stepper is shaped.
    pub fn is_active(&self) -> bool {
        self.axes.iter().any(Option::is_some)
    }

    /// How far steps may lie around the segments that move this stepper.
    pub fn margins(&self) -> Margins {
        self.axes
            .iter()
            .flatten()
            .fold(Margins::default(), |m, p| Margins {
                before: m.before.max(p.lead()),
                after: m.after.max(p.lag()),
            })
    }

    /// The shaped position of a stepper with kinematics `kin` along
    /// `segs[i]`, with each impulse's segment found once for the segment
    /// instead of at every evaluation. `segs` must have no time gaps (see
    /// [`crate::segment::fill_gaps`]).
    pub fn on_segment<'s>(
        &self,
        segs: &'s [Segment],
        i: usize,
        kin: StepperKinematics,
    ) -> ShapedSegment<'s> {
        // Built in place: the segment is large (its taps and pieces).
        let mut shaped = ShapedSegment {
            segs,
            i,
            kin,
            taps: [[Tap::default(); MAX_PULSES]; 2],
            lens: [0, 1].map(|a| self.axes[a].map_or(0, |p| p.len)),
            pieces: [Piece::default(); MAX_PIECES],
            pieces_len: 0,
        };
        for (axis, pulses) in self.axes.iter().enumerate() {
            if let Some(p) = pulses {
                for (k, tap) in shaped.taps[axis].iter_mut().enumerate().take(p.len) {
                    // Walk to the segment holding the impulse at t = 0.
                    let (mut j, mut offset) = (i, p.t[k]);
                    while offset < 0.0 && j > 0 {
                        j -= 1;
                        offset += segs[j].move_t;
                    }
                    while offset > segs[j].move_t && j + 1 < segs.len() {
                        offset -= segs[j].move_t;
                        j += 1;
                    }
                    *tap = Tap {
                        amplitude: p.a[k],
                        offset,
                        seg: j,
                    };
                }
            }
        }
        if let Some(w) = kin.linear_weights() {
            shaped.pieces_len = shaped.build_pieces(w).unwrap_or(0);
        }
        shaped
    }
}

/// Most pieces a shaped segment is split into (see [`ShapedSegment`]).
const MAX_PIECES: usize = 16;

/// One impulse of a shaper, placed relative to a segment.
#[derive(Debug, Clone, Copy, Default)]
struct Tap {
    amplitude: f64,
    /// Time into `seg` of the impulse at the segment's start, s.
    offset: f64,
    seg: usize,
}

/// Part of a segment over which every impulse stays within one segment:
/// there a linear stepper's shaped position is one quadratic.
#[derive(Debug, Clone, Copy, Default)]
struct Piece {
    /// Time into the segment where the piece ends (the next starts), s.
    end: f64,
    position: Quadratic,
}

/// A shaped stepper position along one segment (see
/// [`StepperShaper::on_segment`]).
///
/// For kinematics linear in the toolhead position, the segment is split
/// where an impulse passes from one segment to the next, and the position
/// over each piece is one quadratic: evaluating it costs a few operations,
/// and a step's time is solved for rather than searched. Where more pieces
/// would be needed than fit, the impulses are summed at each evaluation.
#[derive(Debug, Clone, Copy)]
pub struct ShapedSegment<'s> {
    segs: &'s [Segment],
    i: usize,
    kin: StepperKinematics,
    taps: [[Tap; MAX_PULSES]; 2],
    lens: [usize; 2],
    /// `pieces[..pieces_len]`, in time order, covering the segment (none:
    /// sum the impulses).
    pieces: [Piece; MAX_PIECES],
    pieces_len: usize,
}

impl ShapedSegment<'_> {
    /// The impulses acting on coordinate `axis` (none if it is not shaped).
    fn axis_taps(&self, axis: usize) -> &[Tap] {
        match (self.taps.get(axis), self.lens.get(axis)) {
            (Some(taps), Some(&len)) => &taps[..len],
            _ => &[],
        }
    }

    /// Splits the segment where impulses change segments and fits each
    /// piece's quadratic, for position weights `w`; the number of pieces,
    /// None if they do not fit.
    fn build_pieces(&mut self, w: [f64; 3]) -> Option<usize> {
        let segs = self.segs;
        let move_t = segs[self.i].move_t;
        let mut cuts = heapless::Vec::<f64, { MAX_PIECES + 1 }>::new();
        cuts.push(0.0).ok()?;
        for axis in (0..3).filter(|&a| w[a] != 0.0) {
            for tap in self.axis_taps(axis) {
                // Where the impulse leaves each segment it passes.
                let (mut j, mut cut) = (tap.seg, segs[tap.seg].move_t - tap.offset);
                while cut < move_t && j + 1 < segs.len() {
                    if cut > 0.0 {
                        cuts.push(cut).ok()?;
                    }
                    j += 1;
                    cut += segs[j].move_t;
                }
            }
        }
        cuts.push(move_t).ok()?;
        cuts.sort_unstable_by(f64::total_cmp);
        let mut len = 0;
        for piece in cuts.windows(2) {
            let (start, end) = (piece[0], piece[1]);
            if end > start {
                let position = self.fit(w, 0.5 * (start + end));
                *self.pieces.get_mut(len)? = Piece { end, position };
                len += 1;
            }
        }
        Some(len)
    }

    /// The quadratic that the position follows around time `mid` (s into
    /// the segment), with every impulse in the segment it is in then.
    fn fit(&self, w: [f64; 3], mid: f64) -> Quadratic {
        // Adds `scale` times coordinate `axis` of `segs[j]` at `t + offset`.
        let add = |q: &mut [f64; 3], j: usize, offset: f64, axis: usize, scale: f64| {
            let seg = &self.segs[j];
            let r = scale * seg.axes_r[axis];
            let (v, h) = (r * seg.start_v, r * seg.half_accel);
            q[0] += scale * seg.start_pos[axis] + (v + h * offset) * offset;
            q[1] += v + 2.0 * h * offset;
            q[2] += h;
        };
        let mut q = [0.0; 3];
        for axis in (0..3).filter(|&a| w[a] != 0.0) {
            let taps = self.axis_taps(axis);
            if taps.is_empty() {
                add(&mut q, self.i, 0.0, axis, w[axis]);
            }
            for tap in taps {
                // The impulse's time into segment j is `t + offset - mid`.
                let (j, offset) = locate(self.segs, tap.seg, mid + tap.offset);
                add(&mut q, j, offset - mid, axis, w[axis] * tap.amplitude);
            }
        }
        Quadratic(q)
    }

    /// The position at `t` (s into the segment), impulse by impulse.
    fn summed(&self, t: f64) -> f64 {
        let mut pos = self.segs[self.i].position(t);
        for (axis, taps) in self.taps.iter().enumerate() {
            if self.lens[axis] > 0 {
                pos[axis] = taps[..self.lens[axis]]
                    .iter()
                    .map(|tap| tap.amplitude * axis_at(self.segs, tap.seg, t + tap.offset, axis))
                    .sum();
            }
        }
        self.kin.position(pos)
    }

    /// The piece holding time `t` (s into the segment), if there are pieces.
    fn piece(&self, t: f64) -> Option<&Piece> {
        let pieces = &self.pieces[..self.pieces_len];
        pieces.iter().find(|p| t < p.end).or(pieces.last())
    }
}

impl PositionFn for ShapedSegment<'_> {
    /// The first crossing in `low..=high`, piece by piece.
    fn crossing(&self, low: f64, high: f64, target: f64) -> Option<f64> {
        let mut start = 0.0;
        for piece in &self.pieces[..self.pieces_len] {
            if start > high {
                break;
            }
            if piece.end > low {
                let window = (low.max(start), high.min(piece.end));
                if let Some(t) = piece.position.crossing(window.0, window.1, target) {
                    return Some(t);
                }
            }
            start = piece.end;
        }
        None
    }

    /// Monotonic if every piece's slope keeps one sign at both its ends
    /// (a quadratic's slope is linear in between).
    fn monotonic(&self, _move_t: f64) -> Option<bool> {
        let (mut start, mut rising, mut falling) = (0.0, false, false);
        for piece in &self.pieces[..self.pieces_len] {
            let [_, b, a] = piece.position.0;
            for t in [start, piece.end] {
                let slope = b + 2.0 * a * t;
                rising |= slope > 0.0;
                falling |= slope < 0.0;
            }
            start = piece.end;
        }
        (rising != falling).then_some(rising)
    }

    fn at(&self, t: f64) -> f64 {
        match self.piece(t) {
            Some(piece) => piece.position.at(t),
            None => self.summed(t),
        }
    }
}

/// The segment that holds time `t` s into `segs[j]` (`t` may leave it:
/// the neighbouring segments are used, as far as the queue reaches), and
/// the time into that segment.
fn locate(segs: &[Segment], mut j: usize, mut t: f64) -> (usize, f64) {
    while t < 0.0 && j > 0 {
        j -= 1;
        t += segs[j].move_t;
    }
    while t > segs[j].move_t && j + 1 < segs.len() {
        t -= segs[j].move_t;
        j += 1;
    }
    (j, t)
}

/// Coordinate `axis` at `t` s into `segs[j]` (see [`locate`]), mm.
fn axis_at(segs: &[Segment], j: usize, t: f64, axis: usize) -> f64 {
    let (j, t) = locate(segs, j, t);
    let seg = &segs[j];
    seg.start_pos[axis] + seg.axes_r[axis] * seg.distance(t)
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::segment::fill_gaps;
    use onechip_planner::shaper_config::{AxisShaper, ShaperType};
    use std::vec::Vec;

    fn shaped_x() -> StepperShaper {
        let config = InputShaperConfig {
            x: Some(AxisShaper {
                kind: ShaperType::Mzv,
                freq: 40.0,
                damping_ratio: 0.1,
            }),
            y: None,
        };
        StepperShaper::new(&config, StepperKinematics::Axis(0))
    }

    #[test]
    fn only_the_axes_a_stepper_uses_are_shaped() {
        let config = InputShaperConfig {
            x: Some(AxisShaper {
                kind: ShaperType::Zv,
                freq: 50.0,
                damping_ratio: 0.1,
            }),
            y: None,
        };
        assert!(StepperShaper::new(&config, StepperKinematics::Axis(0)).is_active());
        assert!(!StepperShaper::new(&config, StepperKinematics::Axis(1)).is_active());
        assert!(!StepperShaper::new(&config, StepperKinematics::Axis(2)).is_active());
        assert!(StepperShaper::new(&config, StepperKinematics::Sum(0, 1)).is_active());
    }

    #[test]
    fn constant_speed_is_unchanged_and_a_stop_is_smoothed() {
        // 10 mm/s along X for 1 s, then at rest.
        let seg = Segment {
            print_time: 1.0,
            move_t: 1.0,
            start_v: 10.0,
            half_accel: 0.0,
            start_pos: [0.0; 3],
            axes_r: [1.0, 0.0, 0.0],
        };
        let mut segs = Vec::new();
        fill_gaps(&[seg], 0.1, |s| segs.push(s));
        let shaper = shaped_x();
        let x = |i: usize, t: f64| {
            shaper
                .on_segment(&segs, i, StepperKinematics::Axis(0))
                .at(t)
        };
        let mid = x(1, 0.5);
        assert!((mid - 5.0).abs() < 1e-12, "{mid}");
        // Right at the abrupt stop the shaped position lags behind...
        let at_stop = x(1, 1.0);
        assert!(at_stop < 10.0 && at_stop > 9.8, "{at_stop}");
        // ...and arrives once the shaper's window has passed.
        let m = shaper.margins();
        let after = x(2, m.after + 1e-9);
        assert!((after - 10.0).abs() < 1e-12, "{after}");
        assert!(m.before > 0.0 && m.after > 0.0);
    }

    #[test]
    fn pieces_follow_the_impulse_sum_and_solve_its_crossings() {
        // Short and long moves in X and Y, accelerating, cruising and
        // decelerating, with gaps, as a circle or a square makes them.
        let mut moves = Vec::new();
        let (mut t, mut pos) = (1.0, [0.0f64; 3]);
        let mut x = 0x1234_5678u32;
        for k in 0..40 {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            let angle = f64::from(x % 6283) / 1000.0;
            let move_t = [0.0007, 0.002, 0.013, 0.12][k % 4];
            let seg = Segment {
                print_time: t,
                move_t,
                start_v: f64::from(x % 150),
                half_accel: f64::from(x % 3000) - 1500.0,
                start_pos: pos,
                axes_r: [angle.cos(), angle.sin(), 0.0],
            };
            pos = seg.position(move_t);
            t += move_t + if k % 7 == 0 { 0.01 } else { 0.0 };
            moves.push(seg);
        }
        let mut segs = Vec::new();
        fill_gaps(&moves, 0.1, |s| segs.push(s));
        let config = InputShaperConfig {
            x: Some(AxisShaper {
                kind: ShaperType::Ei,
                freq: 45.0,
                damping_ratio: 0.1,
            }),
            y: Some(AxisShaper {
                kind: ShaperType::Mzv,
                freq: 38.0,
                damping_ratio: 0.1,
            }),
        };
        let mut pieced = 0;
        for kin in [
            StepperKinematics::Axis(0),
            StepperKinematics::Axis(1),
            StepperKinematics::Sum(0, 1),
            StepperKinematics::Difference(0, 1),
        ] {
            let shaper = StepperShaper::new(&config, kin);
            for i in 0..segs.len() {
                let shaped = shaper.on_segment(&segs, i, kin);
                pieced += usize::from(shaped.pieces_len > 0);
                let move_t = segs[i].move_t.min(0.2);
                for k in 0..=200 {
                    let t = move_t * f64::from(k) / 200.0;
                    let (fast, exact) = (shaped.at(t), shaped.summed(t));
                    assert!((fast - exact).abs() < 1e-9, "{kin:?} seg {i} t {t}");
                }
                // A crossing solved is where the position meets the target.
                let (low, high) = (0.3 * move_t, 0.31 * move_t);
                let target = 0.5 * (shaped.summed(low) + shaped.summed(high));
                if let Some(t) = shaped.crossing(low, high, target) {
                    assert!((low..=high).contains(&t));
                    assert!((shaped.summed(t) - target).abs() < 1e-9);
                }
            }
        }
        assert!(pieced > segs.len(), "most segments are pieced");
    }
}
