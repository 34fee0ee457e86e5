//! The extruder's step position, with Klipper's smoothed pressure advance.
//!
//! Without pressure advance the extruder follows its nominal position. With
//! it, moves that may use it (extrusion with XY motion) add
//! `pressure_advance × velocity`, and the result is averaged with a
//! triangular weight over `±smooth_time/2`:
//!
//! `smooth(t) = ∫ pa_position(x) · (hst - |t - x|) dx / hst²`, over
//! `[t - hst, t + hst]`, `hst = smooth_time / 2`.
//!
//! The extruder's queue has gaps (travel moves do not extrude); like
//! Klipper's trapq they are filled with stationary segments
//! ([`crate::segment::fill_gaps`]), so that the average sees the filament
//! at rest there.

use crate::segment::Segment;

/// Pressure advance settings of an extruder.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PressureAdvance {
    /// pressure_advance, s.
    pub advance: f64,
    /// Half of pressure_advance_smooth_time, s.
    pub half_smooth_time: f64,
}

impl PressureAdvance {
    /// Settings from `pressure_advance` (s) and
    /// `pressure_advance_smooth_time` (s). Without advance nothing is
    /// smoothed, as in Klipper.
    pub fn new(advance: f64, smooth_time: f64) -> Self {
        let half_smooth_time = if advance == 0.0 {
            0.0
        } else {
            0.5 * smooth_time
        };
        Self {
            advance,
            half_smooth_time,
        }
    }
}

/// ∫ position(x) dx over `[start, end]` for `position(x) = base + x·(v + x·ha)`.
fn integrate(base: f64, v: f64, ha: f64, start: f64, end: f64) -> f64 {
    let (half_v, sixth_a) = (0.5 * v, ha / 3.0);
    let f = |t: f64| t * (base + t * (half_v + t * sixth_a));
    f(end) - f(start)
}

/// ∫ x·position(x) dx over `[start, end]`.
fn integrate_time(base: f64, v: f64, ha: f64, start: f64, end: f64) -> f64 {
    let (half_b, third_v, eighth_a) = (0.5 * base, v / 3.0, 0.25 * ha);
    let f = |t: f64| t * t * (half_b + t * (third_v + t * eighth_a));
    f(end) - f(start)
}

/// Weighted integral of one segment's pressure-advanced position over
/// `[start, end]` (segment time, clipped to the segment), offset by `base`.
fn segment_integral(
    seg: &Segment,
    pa: &PressureAdvance,
    base: f64,
    start: f64,
    end: f64,
    time_offset: f64,
) -> f64 {
    let (start, end) = (start.max(0.0), end.min(seg.move_t));
    // The second axis of an extruder segment flags "may use pressure advance".
    let advance = if seg.axes_r[1] != 0.0 {
        pa.advance
    } else {
        0.0
    };
    let base = base + advance * seg.start_v;
    let v = seg.start_v + advance * 2.0 * seg.half_accel;
    let ha = seg.half_accel;
    integrate_time(base, v, ha, start, end) - time_offset * integrate(base, v, ha, start, end)
}

/// The smoothed extruder position at `t` s into `segs[i]`, mm.
pub fn position(segs: &[Segment], i: usize, t: f64, pa: &PressureAdvance) -> f64 {
    let seg = &segs[i];
    let hst = pa.half_smooth_time;
    if hst == 0.0 {
        return seg.start_pos[0] + seg.distance(t);
    }
    let (mut start, mut end) = (t - hst, t + hst);
    let origin = seg.start_pos[0];
    let mut area = segment_integral(seg, pa, 0.0, start, t, start)
        - segment_integral(seg, pa, 0.0, t, end, end);
    let mut j = i;
    while start < 0.0 && j > 0 {
        j -= 1;
        start += segs[j].move_t;
        area += segment_integral(
            &segs[j],
            pa,
            segs[j].start_pos[0] - origin,
            start,
            segs[j].move_t,
            start,
        );
    }
    let mut k = i;
    while end > segs[k].move_t && k + 1 < segs.len() {
        end -= segs[k].move_t;
        k += 1;
        area -= segment_integral(&segs[k], pa, segs[k].start_pos[0] - origin, 0.0, end, end);
    }
    origin + area / (hst * hst)
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::segment::fill_gaps;
    use std::vec::Vec;

    fn filled(segs: &[Segment]) -> Vec<Segment> {
        let mut out = Vec::new();
        fill_gaps(segs, 0.1, |s| out.push(s));
        out
    }

    #[test]
    fn without_smoothing_the_nominal_position_is_returned() {
        let seg = Segment {
            print_time: 0.0,
            move_t: 1.0,
            start_v: 2.0,
            half_accel: 0.0,
            start_pos: [5.0, 1.0, 0.0],
            axes_r: [1.0, 1.0, 0.0],
        };
        let pa = PressureAdvance {
            advance: 0.05,
            half_smooth_time: 0.0,
        };
        assert_eq!(position(&[seg], 0, 0.5, &pa), 6.0);
    }

    #[test]
    fn smoothing_a_constant_speed_adds_advance_times_speed() {
        // 2 mm/s for 1 s after 1 s at rest; far from the edges the smoothed,
        // advanced position is nominal + 0.05 s x 2 mm/s.
        let seg = Segment {
            print_time: 1.0,
            move_t: 1.0,
            start_v: 2.0,
            half_accel: 0.0,
            start_pos: [5.0, 0.0, 0.0],
            axes_r: [1.0, 1.0, 0.0],
        };
        let segs = filled(&[seg]);
        let pa = PressureAdvance {
            advance: 0.05,
            half_smooth_time: 0.02,
        };
        let p = position(&segs, 1, 0.5, &pa);
        assert!((p - (5.0 + 1.0 + 0.1)).abs() < 1e-12, "{p}");
        // At rest long before the move, nothing moves.
        let before = position(&segs, 0, 0.1, &pa);
        assert!((before - 5.0).abs() < 1e-12, "{before}");
        // Long after it, the filament is where the move left it.
        let after = position(&segs, 2, 0.5, &pa);
        assert!((after - 7.0).abs() < 1e-12, "{after}");
    }

    #[test]
    fn moves_without_the_flag_get_no_advance() {
        let seg = Segment {
            print_time: 1.0,
            move_t: 1.0,
            start_v: 2.0,
            half_accel: 0.0,
            start_pos: [5.0, 0.0, 0.0],
            axes_r: [1.0, 0.0, 0.0],
        };
        let segs = filled(&[seg]);
        let pa = PressureAdvance {
            advance: 0.05,
            half_smooth_time: 0.02,
        };
        assert!((position(&segs, 1, 0.5, &pa) - 6.0).abs() < 1e-12);
    }
}
