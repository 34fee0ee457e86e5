//! Step times of one stepper: where its position crosses the half-step
//! boundaries, searched the way Klipper's itersolve searches them.
//!
//! A step happens when the stepper's position moves half a step away from
//! its last step's position (steps sit at `position_set ± (k + ½)·step`).
//! The search widens a time window until the position has moved half a step,
//! then narrows onto the crossing by false position to 1 ns. A direction
//! change is only taken once the position is past the midpoint, so jitter
//! at a reversal does not produce extra steps.

use crate::segment::Segment;
use onechip_planner::kinematics::StepperKinematics;
use onechip_planner::math::sqrt;

/// Time resolution of the crossing search, s.
const TIME_EPSILON: f64 = 0.000_000_001;
/// First widening of the search window, s, and its cap near reversals.
const FIRST_SEEK: f64 = 0.000_100;
/// Step generation runs in windows of this much print time, s, aligned to
/// multiples of it; the search restarts at each window's start. Klipper's
/// search also restarts where its step-generation flushes cut the queue;
/// with short fixed windows a direction excursion of a few milliseconds
/// (a pressure-advance retraction) is found wherever klippy's flushes
/// happened to fall, instead of being jumped over by a widened search.
pub const GENERATION_WINDOW: f64 = 0.005;

/// How far a stepper's steps can lie around the segments that move it, s.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Margins {
    /// Steps may come this long before such a segment starts.
    pub before: f64,
    /// Steps may come this long after such a segment ends.
    pub after: f64,
}

impl Margins {
    /// The same margin on both sides, s.
    pub fn both(margin: f64) -> Self {
        Self {
            before: margin,
            after: margin,
        }
    }
}

/// A stepper's position (mm) as a function of the time into a segment (s).
pub trait PositionFn {
    /// The position at `t`.
    fn at(&self, t: f64) -> f64;

    /// The time in `low..=high` where the position is `target`, if it can
    /// be solved for directly; None leaves it to the search.
    fn crossing(&self, _low: f64, _high: f64, _target: f64) -> Option<f64> {
        None
    }

    /// Some(true) if the position only ever rises over a segment of
    /// `move_t` s (Some(false): only falls), with [`Self::crossing`]
    /// exact: its steps are then solved one after another without a
    /// search. None if it may turn or stand still.
    fn monotonic(&self, _move_t: f64) -> Option<bool> {
        None
    }
}

impl<F: Fn(f64) -> f64> PositionFn for F {
    fn at(&self, t: f64) -> f64 {
        self(t)
    }
}

/// `base + ratio · distance(t)` along a segment starting at `start_v`
/// with half-acceleration `half_accel`: the position of a stepper whose
/// kinematics is linear in the toolhead position.
#[derive(Debug, Clone, Copy)]
pub struct AlongSegment {
    /// Position at the segment's start, mm.
    pub base: f64,
    /// Stepper travel per toolhead distance.
    pub ratio: f64,
    /// The segment's start velocity, mm/s.
    pub start_v: f64,
    /// The segment's half acceleration, mm/s².
    pub half_accel: f64,
}

impl PositionFn for AlongSegment {
    fn at(&self, t: f64) -> f64 {
        self.base + self.ratio * ((self.start_v + self.half_accel * t) * t)
    }

    fn crossing(&self, low: f64, high: f64, target: f64) -> Option<f64> {
        let r = self.ratio;
        Quadratic([self.base, r * self.start_v, r * self.half_accel]).crossing(low, high, target)
    }

    /// The velocity `start_v + 2·half_accel·t` keeps its sign over the
    /// segment when it has the same sign at both ends (trapq segments
    /// never turn inside: a move only slows to a stop at its end).
    fn monotonic(&self, move_t: f64) -> Option<bool> {
        let (v0, v1) = (self.start_v, self.start_v + 2.0 * self.half_accel * move_t);
        let moving = self.ratio * (v0 + v1);
        (v0 * v1 >= 0.0 && moving != 0.0).then_some(moving > 0.0)
    }
}

/// A delta tower's carriage position along a segment:
/// `z + r_z·d + √(arm² − (x + r_x·d)² − (y + r_y·d)²)` with `d` the distance
/// travelled (as in [`AlongSegment`]) and `(x, y, z)` the segment's start
/// relative to the tower.
#[derive(Debug, Clone, Copy)]
pub struct AlongDeltaSegment {
    /// Arm length squared, mm².
    pub arm2: f64,
    /// The segment's start relative to the tower (X, Y) and its Z, mm.
    pub start: [f64; 3],
    /// The segment's unit direction.
    pub axes_r: [f64; 3],
    /// The segment's start velocity, mm/s.
    pub start_v: f64,
    /// The segment's half acceleration, mm/s².
    pub half_accel: f64,
}

impl AlongDeltaSegment {
    /// The carriage position after `d` mm along the segment.
    fn at_distance(&self, d: f64) -> f64 {
        let [x, y, z] = self.start;
        let [rx, ry, rz] = self.axes_r;
        let (dx, dy) = (x + rx * d, y + ry * d);
        sqrt(self.arm2 - dx * dx - dy * dy) + z + rz * d
    }
}

impl PositionFn for AlongDeltaSegment {
    fn at(&self, t: f64) -> f64 {
        self.at_distance((self.start_v + self.half_accel * t) * t)
    }

    /// Squaring `√(arm² − …) = target − z − r_z·d` gives a quadratic in
    /// `d`; its roots where the right side is not negative (the carriage
    /// above the effector) are the crossings, each reached at a time
    /// solved from the segment's own quadratic. The earliest in the
    /// window is taken.
    fn crossing(&self, low: f64, high: f64, target: f64) -> Option<f64> {
        let [x, y, z] = self.start;
        let [rx, ry, rz] = self.axes_r;
        let height = target - z;
        let distance = Quadratic([
            x * x + y * y + height * height - self.arm2,
            2.0 * (x * rx + y * ry - height * rz),
            rx * rx + ry * ry + rz * rz,
        ]);
        let travel = Quadratic([0.0, self.start_v, self.half_accel]);
        let mut first: Option<f64> = None;
        for d in distance.roots().into_iter().flatten() {
            if height - rz * d < 0.0 {
                continue;
            }
            if let Some(t) = travel.crossing(low, high, d) {
                first = Some(first.map_or(t, |f| f.min(t)));
            }
        }
        first
    }
}

/// `c[0] + c[1]·t + c[2]·t²`: a position (mm) at time `t` (s) along
/// constant-acceleration motion.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Quadratic(pub [f64; 3]);

impl Quadratic {
    /// The value at `t`.
    pub fn at(&self, t: f64) -> f64 {
        let [c, b, a] = self.0;
        c + (b + a * t) * t
    }

    /// The time in `low..=high` where the value is `target`, if there is
    /// one: exact where the search would stop within a nanosecond of it.
    pub fn crossing(&self, low: f64, high: f64, target: f64) -> Option<f64> {
        let [c, b, a] = self.0;
        let in_window = |t: f64| (low..=high).contains(&t).then_some(t);
        let [r0, r1] = Self([c - target, b, a]).roots();
        r0.and_then(in_window).or_else(|| r1.and_then(in_window))
    }

    /// Where the value is 0: up to two real roots (None where there is
    /// none), computed without cancellation.
    pub fn roots(&self) -> [Option<f64>; 2] {
        let [c, b, a] = self.0;
        if a == 0.0 {
            return [(b != 0.0).then(|| -c / b), None];
        }
        let disc = b * b - 4.0 * a * c;
        if disc < 0.0 {
            return [None, None];
        }
        // The two roots as q / a and c / q.
        let q = -0.5 * (b + sqrt(disc).copysign(b));
        [Some(q / a), (q != 0.0).then(|| c / q)]
    }
}

/// One generated step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Step {
    /// When, s (print time).
    pub time: f64,
    /// True for the positive direction.
    pub dir: bool,
}

/// A point of the stepper's motion: time into the segment (s) and position (mm).
#[derive(Debug, Clone, Copy, PartialEq)]
struct TimePos {
    t: f64,
    pos: f64,
}

/// Step generation state of one stepper.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepSolver {
    kin: StepperKinematics,
    half_step: f64,
    /// The stepper's position at its last step (the centre between two
    /// step boundaries), mm.
    commanded_pos: f64,
    /// Direction of the last step (None before any).
    dir: Option<bool>,
    /// Steps are generated up to this print time, s.
    generated_until: f64,
    /// End of the last segment that moved this stepper, s.
    last_active_end: f64,
}

impl StepSolver {
    /// A solver for a stepper moving `step_dist` mm per step, with the
    /// toolhead at `pos`.
    pub fn new(kin: StepperKinematics, step_dist: f64, pos: [f64; 3]) -> Self {
        Self {
            kin,
            half_step: 0.5 * step_dist,
            commanded_pos: kin.position(pos),
            dir: None,
            generated_until: f64::NEG_INFINITY,
            last_active_end: f64::NEG_INFINITY,
        }
    }

    /// Sets the toolhead position without stepping (homing,
    /// SET_KINEMATIC_POSITION).
    pub fn set_position(&mut self, pos: [f64; 3]) {
        self.commanded_pos = self.kin.position(pos);
    }

    /// Steps `step_dist` mm from now on, from where the stepper stands
    /// (SET_EXTRUDER_ROTATION_DISTANCE).
    pub fn set_step_dist(&mut self, step_dist: f64) {
        self.half_step = 0.5 * step_dist;
    }

    /// The stepper's position is counted the other way from now on (its
    /// direction reversed): the same steps follow, mirrored.
    pub fn mirror(&mut self) {
        self.commanded_pos = -self.commanded_pos;
        self.dir = self.dir.map(|forward| !forward);
    }

    /// Steps resume from print time `at` s (the motion was cut short
    /// there; nothing after it was generated or will be).
    pub fn restart(&mut self, at: f64) {
        self.generated_until = at;
        self.last_active_end = self.last_active_end.min(at);
    }

    /// The stepper's position at its last step, mm.
    pub fn commanded_pos(&self) -> f64 {
        self.commanded_pos
    }

    /// Print time up to which steps have been generated, s.
    pub fn generated_until(&self) -> f64 {
        self.generated_until
    }

    /// True if `seg` can move this stepper.
    pub fn is_active(&self, seg: &Segment) -> bool {
        let r = seg.axes_r;
        match self.kin {
            StepperKinematics::Axis(a) => r[a] != 0.0,
            StepperKinematics::Sum(a, b) | StepperKinematics::Difference(a, b) => {
                r[a] != 0.0 || r[b] != 0.0
            }
            StepperKinematics::DeltaTower { .. } => r.iter().any(|&v| v != 0.0),
        }
    }

    /// Generates the steps of `seg` between print times `start` and `end`
    /// (clipped to the segment).
    pub fn generate(&mut self, seg: &Segment, start: f64, end: f64, emit: impl FnMut(Step)) {
        let kin = self.kin;
        self.generate_with(seg, start, end, &|t| kin.position(seg.position(t)), emit);
    }

    /// Generates the steps of a time-ordered segment queue, the way
    /// Klipper's itersolve walks its trapq, from where the last call
    /// stopped up to print time `until` (s). Splitting generation at
    /// multiples of [`GENERATION_WINDOW`] gives the same steps as one
    /// call; elsewhere the split restarts the search, as Klipper's flushes
    /// do. Segments that do not move this
    /// stepper are skipped, except within `margins` of segments that do
    /// (where a filtered position, such as pressure advance's or an input
    /// shaper's, already or still moves). `position(i)` gives the
    /// stepper's position (mm) as a function of the time into `segs[i]`
    /// (s), so that per-segment work is done once.
    ///
    /// `segs` must reach past `until` by the margins (later segments may
    /// not change steps already generated), and with non-zero margins it
    /// must have no time gaps (see [`crate::segment::fill_gaps`] and
    /// [`crate::trapq::Trapq`]). Segments may be dropped from its front
    /// once they end before [`Self::generated_until`] less the margins.
    pub fn generate_until<P: PositionFn>(
        &mut self,
        segs: &[Segment],
        margins: Margins,
        until: f64,
        position: impl Fn(usize) -> P,
        mut emit: impl FnMut(Step),
    ) {
        let since = self.generated_until;
        if until <= since {
            return;
        }
        self.generated_until = until;
        let mut range = |solver: &mut Self, i: usize, start: f64, end: f64| {
            let seg = &segs[i];
            let from = start.max(since).max(seg.print_time);
            let to = end.min(until).min(seg.end_time());
            let mut from = from;
            if from < to {
                let at = position(i);
                while from < to {
                    let window_end = next_window_start(from).min(to);
                    solver.generate_with(seg, from, window_end, &at, &mut emit);
                    from = window_end;
                }
            }
        };
        // Steps are still due until this print time, s.
        let mut active_until = self.last_active_end + margins.after;
        // Inactive segments passed since the last generated one.
        let mut skipped = 0usize;
        let first = segs.partition_point(|seg| seg.end_time() <= since);
        for (i, seg) in segs.iter().enumerate().skip(first) {
            if self.is_active(seg) {
                if skipped > 0 && margins.before > 0.0 {
                    // Lead in: the skipped segments within the margin.
                    let from = (seg.print_time - margins.before).max(active_until);
                    let mut lead = i - 1;
                    while skipped > 1 && segs[lead].print_time > from {
                        skipped -= 1;
                        lead -= 1;
                    }
                    for j in lead..i {
                        range(self, j, from, f64::INFINITY);
                    }
                }
                range(self, i, f64::NEG_INFINITY, f64::INFINITY);
                if seg.end_time() >= until {
                    return;
                }
                skipped = 0;
                self.last_active_end = seg.end_time();
                active_until = seg.end_time() + margins.after;
            } else {
                if seg.print_time < active_until {
                    // Lead out after the last active segment.
                    range(self, i, f64::NEG_INFINITY, active_until);
                    skipped = 1;
                } else {
                    skipped += 1;
                }
                if until + margins.before <= seg.end_time() {
                    return;
                }
            }
        }
    }

    /// Generates steps from `position` (mm at `t` s into `seg`) between
    /// print times `start` and `end`, clipped to the segment.
    fn generate_with(
        &mut self,
        seg: &Segment,
        start: f64,
        end: f64,
        position: &impl PositionFn,
        mut emit: impl FnMut(Step),
    ) {
        let start = (start - seg.print_time).max(0.0);
        let end = (end - seg.print_time).min(seg.move_t);
        let Some(forward) = position.monotonic(seg.move_t) else {
            self.search(seg, start, end, position, &mut emit, false);
            return;
        };
        let mut from = start;
        if self.dir != Some(forward) {
            // The first step, or the first after a reversal, is searched
            // for with the midpoint rule.
            match self.search(seg, start, end, position, &mut emit, true) {
                Some(t) if self.dir == Some(forward) => from = t,
                Some(t) => {
                    self.search(seg, t, end, position, &mut emit, false);
                    return;
                }
                None => return,
            }
        }
        // Moving one way only: each next step is where the position
        // crosses the next half-step boundary (the search would find the
        // same crossing), until none is left before `end`.
        let step = if forward {
            self.half_step
        } else {
            -self.half_step
        };
        let mut pos = self.commanded_pos;
        while let Some(t) = position.crossing(from, end, pos + step) {
            emit(Step {
                time: seg.print_time + t,
                dir: forward,
            });
            pos = pos + step + step;
            from = t;
        }
        self.commanded_pos = pos;
        // No crossing is left; should the position at `end` say otherwise
        // (a root rounded past a piece's or the segment's end), the search
        // takes the rest.
        if (position.at(end) - pos).abs() >= self.half_step {
            self.search(seg, from, end, position, &mut emit, false);
        }
    }

    /// Searches for the steps from `position` between `start` and `end`
    /// (s into `seg`), stopping after the first one if `first_only`; the
    /// time of the last step found, s into `seg`.
    fn search(
        &mut self,
        seg: &Segment,
        start: f64,
        end: f64,
        position: &impl PositionFn,
        mut emit: impl FnMut(Step),
        first_only: bool,
    ) -> Option<f64> {
        let half = self.half_step;
        let mut found = None;
        let mut last = TimePos {
            t: start,
            pos: self.commanded_pos,
        };
        let (mut low, mut high) = (last, last);
        let mut seek = FIRST_SEEK;
        let mut dir = self.dir;
        // True from a reversal until the first step after it.
        let mut reversing = false;
        loop {
            let dist = high.pos - last.pos;
            let mut widen = dist.abs() < half;
            if !widen {
                let next_dir = dist > 0.0;
                if dir != Some(next_dir) {
                    if dist.abs() < half + TIME_EPSILON {
                        // Only reverse once past the midpoint.
                        widen = true;
                    } else {
                        // A reversal: search around it closely, so that a
                        // short excursion is not jumped over.
                        reversing = true;
                        seek = seek.min(FIRST_SEEK);
                        if low.t > last.t {
                            dir = Some(next_dir);
                        } else if high.t < last.t + TIME_EPSILON {
                            // Search must restart after the last step's time.
                            widen = true;
                        } else {
                            high.t = (last.t + high.t) * 0.5;
                            high.pos = position.at(high.t);
                            continue;
                        }
                    }
                }
            }
            if widen {
                if !widen_window(position, &mut low, &mut high, last, &mut seek, end) {
                    break;
                }
                continue;
            }
            let forward = dir == Some(true);
            let target = last.pos + if forward { half } else { -half };
            let next = find_crossing(position, low, high, target);
            emit(Step {
                time: seg.print_time + next.t,
                dir: forward,
            });
            seek = (next.t - last.t).max(TIME_EPSILON);
            if reversing {
                seek = seek.min(FIRST_SEEK);
                reversing = false;
            }
            last = TimePos {
                t: next.t,
                pos: target + if forward { half } else { -half },
            };
            found = Some(next.t);
            if first_only {
                break;
            }
            low = next;
            // A spent window is widened from the new step.
            if last.t >= high.t
                && !widen_window(position, &mut low, &mut high, last, &mut seek, end)
            {
                break;
            }
        }
        self.commanded_pos = last.pos;
        self.dir = dir;
        found
    }
}

/// Moves the search window past `high`: the old high end becomes the low
/// end, the new high end lies `seek` after the last step (doubling `seek`),
/// capped at `end`. False when the window already reached `end`.
fn widen_window(
    position: &impl PositionFn,
    low: &mut TimePos,
    high: &mut TimePos,
    last: TimePos,
    seek: &mut f64,
    end: f64,
) -> bool {
    if high.t >= end {
        return false;
    }
    *low = *high;
    loop {
        high.t = last.t + *seek;
        *seek += *seek;
        if high.t > low.t {
            break;
        }
    }
    high.t = high.t.min(end);
    high.pos = position.at(high.t);
    true
}

/// The time in `low..high` where the position reaches `target`, by false
/// position to [`TIME_EPSILON`]; the window's start if it does not.
fn find_crossing(position: &impl PositionFn, low: TimePos, high: TimePos, target: f64) -> TimePos {
    let mut best = high;
    let (mut lo, mut hi) = (
        TimePos {
            pos: low.pos - target,
            ..low
        },
        TimePos {
            pos: high.pos - target,
            ..high
        },
    );
    if hi.pos == 0.0 {
        return best;
    }
    let high_negative = hi.pos.is_sign_negative();
    if high_negative == lo.pos.is_sign_negative() {
        return TimePos {
            t: low.t,
            pos: target,
        };
    }
    if let Some(t) = position.crossing(low.t, high.t, target) {
        return TimePos {
            t,
            pos: position.at(t),
        };
    }
    loop {
        let guess = (lo.t * hi.pos - hi.t * lo.pos) / (hi.pos - lo.pos);
        if (guess - best.t).abs() <= TIME_EPSILON {
            return best;
        }
        best = TimePos {
            t: guess,
            pos: position.at(guess),
        };

        let offset = best.pos - target;
        if offset.is_sign_negative() == high_negative {
            hi = TimePos {
                t: guess,
                pos: offset,
            };
        } else {
            lo = TimePos {
                t: guess,
                pos: offset,
            };
        }
    }
}

/// The first window boundary after print time `t`, s: the next multiple of
/// [`GENERATION_WINDOW`], always later than `t`.
fn next_window_start(t: f64) -> f64 {
    // Print times are never negative, so truncation is the floor.
    let next = (trunc(t / GENERATION_WINDOW) + 1.0) * GENERATION_WINDOW;
    if next > t {
        next
    } else {
        // Rounding put `t` on the boundary itself.
        next + GENERATION_WINDOW
    }
}

/// `x` rounded toward zero, as `x as i64 as f64` gives it (within the
/// range of i64) but without the 64-bit integer conversions, which are
/// library calls on a 32-bit MCU.
pub(crate) fn trunc(x: f64) -> f64 {
    // From 2^52 on, every f64 is a whole number.
    const WHOLE: f64 = 4_503_599_627_370_496.0;
    let a = x.abs();
    if a >= WHOLE || a.is_nan() {
        return x;
    }
    // Adding and removing 2^52 rounds to a whole number (to nearest).
    let mut r = (a + WHOLE) - WHOLE;
    if r > a {
        r -= 1.0;
    }
    r.copysign(x)
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec::Vec;

    fn cruise(from: f64, v: f64, t: f64) -> Segment {
        Segment {
            print_time: 1.0,
            move_t: t,
            start_v: v.abs(),
            half_accel: 0.0,
            start_pos: [from, 0.0, 0.0],
            axes_r: [v.signum(), 0.0, 0.0],
        }
    }

    /// The delta crossing solved in closed form is exact (the position
    /// there is the target to 1e-9 mm) and where the false-position search
    /// lands (within what the search's own position error allows: it stops
    /// on its step size, not its error), on random segments of the
    /// golden delta's geometry; where there is no crossing, neither finds
    /// one.
    #[test]
    fn delta_crossings_in_closed_form_match_the_search() {
        struct Searched(AlongDeltaSegment);
        impl PositionFn for Searched {
            fn at(&self, t: f64) -> f64 {
                self.0.at(t)
            }
        }
        let mut x = 0x2545_f491_4f6c_dd1du64;
        let mut uniform = |low: f64, high: f64| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            low + (high - low) * (x >> 11) as f64 / (1u64 << 53) as f64
        };
        let (mut solved, mut compared) = (0, 0);
        for _ in 0..20_000 {
            let angle = uniform(0.0, core::f64::consts::TAU);
            let climb = uniform(-0.5, 0.5);
            let flat = (1.0 - climb * climb).sqrt();
            let seg = AlongDeltaSegment {
                arm2: 333.0 * 333.0,
                start: [
                    uniform(-250.0, 100.0),
                    uniform(-250.0, 100.0),
                    uniform(0.0, 200.0),
                ],
                axes_r: [flat * angle.cos(), flat * angle.sin(), climb],
                start_v: uniform(0.0, 300.0),
                half_accel: uniform(-1500.0, 1500.0),
            };
            let (low, high) = (uniform(0.0, 0.05), uniform(0.05, 0.1));
            let (at_low, at_high) = (seg.at(low), seg.at(high));
            if !(at_low.is_finite() && at_high.is_finite()) {
                continue;
            }
            let target = at_low + (at_high - at_low) * uniform(0.0, 1.0);
            let ends = |t: f64, pos: f64| TimePos { t, pos };
            let search = find_crossing(
                &Searched(seg),
                ends(low, at_low),
                ends(high, at_high),
                target,
            );
            let Some(t) = seg.crossing(low, high, target) else {
                continue;
            };
            solved += 1;
            assert!((low..=high).contains(&t));
            assert!((seg.at(t) - target).abs() < 1e-9, "{seg:?} {target}");
            // With one crossing in the window (sampled every 0.1 ms) both
            // find the same one; with several, the closed form the first.
            let above = |k: usize| seg.at(low + (high - low) * k as f64 / 500.0) > target;
            let changes = (1..=500).filter(|&k| above(k) != above(k - 1)).count();
            if changes == 1 {
                compared += 1;
                // The same crossing: no farther apart than the search's
                // own position error allows at the carriage's speed there.
                let speed = (seg.at(t + 1e-6) - seg.at(t - 1e-6)).abs() / 2e-6;
                let slack = (seg.at(search.t) - target).abs() / speed.max(1e-3);
                assert!(
                    (search.t - t).abs() < 1e-8 + 2.0 * slack,
                    "{} vs {t}",
                    search.t
                );
            }
        }
        assert!(
            solved > 15_000 && compared > 10_000,
            "{solved} solved, {compared} compared"
        );
    }

    #[test]
    fn trunc_matches_the_integer_round_trip() {
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..100_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            // Magnitudes from 1e-3 to ~1e12, both signs, and near-integers.
            let v = (x % 1_000_000_007) as f64 * 10f64.powi((x >> 40) as i32 % 7 - 3);
            for v in [v, -v, v.round(), v.round() - 1e-9, v + 0.5] {
                assert_eq!(trunc(v).to_bits(), ((v as i64) as f64).to_bits(), "{v}");
            }
        }
        assert_eq!(trunc(f64::INFINITY), f64::INFINITY);
        assert!(trunc(f64::NAN).is_nan());
        assert_eq!(trunc(-0.5).to_bits(), (-0.0f64).to_bits());
    }

    #[test]
    fn constant_speed_steps_fall_on_half_step_boundaries() {
        let mut s = StepSolver::new(StepperKinematics::Axis(0), 0.0125, [100.0, 0.0, 0.0]);
        let seg = cruise(100.0, 10.0, 0.1);
        let mut steps = Vec::new();
        s.generate(&seg, seg.print_time, seg.end_time(), |st| steps.push(st));
        // 1 mm at 0.0125 mm/step: 80 steps, the first half a step in.
        assert_eq!(steps.len(), 80);
        for (k, st) in steps.iter().enumerate() {
            let expected = 1.0 + (k as f64 + 0.5) * 0.0125 / 10.0;
            assert!(
                (st.time - expected).abs() < 2e-9,
                "step {k}: {} vs {expected}",
                st.time
            );
            assert!(st.dir);
        }
        assert!((s.commanded_pos() - 101.0).abs() < 1e-9);
    }

    #[test]
    fn reversal_changes_direction_and_returns_home() {
        let mut s = StepSolver::new(StepperKinematics::Axis(0), 0.0125, [0.0; 3]);
        let mut steps = Vec::new();
        for seg in [
            cruise(0.0, 10.0, 0.01),
            Segment {
                print_time: 1.01,
                ..cruise(0.1, -10.0, 0.01)
            },
        ] {
            s.generate(&seg, seg.print_time, seg.end_time(), |st| steps.push(st));
        }
        let forward = steps.iter().filter(|s| s.dir).count();
        assert_eq!((forward, steps.len() - forward), (8, 8));
        assert!(s.commanded_pos().abs() < 1e-9);
    }
}
