//! Input shaping as Klipper applies it: a stepper whose kinematics uses a
//! shaped axis (X or Y) follows that axis' position convolved with the
//! shaper's impulses, `x̃(t) = Σ aᵢ · x(t + tᵢ)`, across segment
//! boundaries. Z and the extruder are never shaped.

use crate::segment::Segment;
use crate::solver::{Margins, PositionFn};
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
        let mut taps = [[Tap::default(); MAX_PULSES]; 2];
        for (axis, pulses) in self.axes.iter().enumerate() {
            if let Some(p) = pulses {
                for (k, tap) in taps[axis].iter_mut().enumerate().take(p.len) {
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
        ShapedSegment {
            segs,
            i,
            kin,
            taps,
            lens: [0, 1].map(|a| self.axes[a].map_or(0, |p| p.len)),
        }
    }
}

/// One impulse of a shaper, placed relative to a segment.
#[derive(Debug, Clone, Copy, Default)]
struct Tap {
    amplitude: f64,
    /// Time into `seg` of the impulse at the segment's start, s.
    offset: f64,
    seg: usize,
}

/// A shaped stepper position along one segment (see
/// [`StepperShaper::on_segment`]).
#[derive(Debug, Clone, Copy)]
pub struct ShapedSegment<'s> {
    segs: &'s [Segment],
    i: usize,
    kin: StepperKinematics,
    taps: [[Tap; MAX_PULSES]; 2],
    lens: [usize; 2],
}

impl PositionFn for ShapedSegment<'_> {
    fn at(&self, t: f64) -> f64 {
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
}

/// Coordinate `axis` at `t` s into `segs[j]` (`t` may leave it: the
/// neighbouring segments are used, as far as the queue reaches), mm.
fn axis_at(segs: &[Segment], mut j: usize, mut t: f64, axis: usize) -> f64 {
    while t < 0.0 && j > 0 {
        j -= 1;
        t += segs[j].move_t;
    }
    while t > segs[j].move_t && j + 1 < segs.len() {
        t -= segs[j].move_t;
        j += 1;
    }
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
}
