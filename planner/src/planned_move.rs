//! One requested move and the trapezoid the lookahead gives it.
//!
//! Units: positions and distances in mm, velocities in mm/s, accelerations
//! in mm/s², times in s; `_v2` values are squared velocities. Axes are
//! X, Y, Z and the extruder E (index 3). The junction rules are Klipper's:
//! the start speed of a move is limited by the previous move's cruise and
//! reachable speed, by "approximated centripetal velocity" from
//! square_corner_velocity (junction deviation), by the approximated circle
//! touching the moves no further than mid-move, and by the extruder's
//! instantaneous_corner_velocity.

use crate::math::sqrt;

/// Index of the extruder axis in positions.
pub const E: usize = 3;

/// Velocity and acceleration limits of the toolhead, with the values derived
/// from them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Limits {
    /// Maximum velocity, mm/s.
    pub max_velocity: f64,
    /// Maximum acceleration, mm/s².
    pub max_accel: f64,
    /// Fraction of each move that must be at cruise speed (0..1).
    pub min_cruise_ratio: f64,
    /// Speed allowed through a 90° corner, mm/s.
    pub square_corner_velocity: f64,
    /// Junction deviation derived from square_corner_velocity, mm.
    pub junction_deviation: f64,
    /// Acceleration used for "smoothed" lookahead, mm/s².
    pub max_accel_to_decel: f64,
}

impl Limits {
    /// Limits with derived values computed.
    pub fn new(
        max_velocity: f64,
        max_accel: f64,
        min_cruise_ratio: f64,
        square_corner_velocity: f64,
    ) -> Self {
        let mut limits = Self {
            max_velocity,
            max_accel,
            min_cruise_ratio,
            square_corner_velocity,
            junction_deviation: 0.0,
            max_accel_to_decel: 0.0,
        };
        limits.update_derived();
        limits
    }

    /// Recomputes junction deviation and accel-to-decel after a change.
    pub fn update_derived(&mut self) {
        let scv2 = self.square_corner_velocity * self.square_corner_velocity;
        self.junction_deviation = scv2 * (core::f64::consts::SQRT_2 - 1.0) / self.max_accel;
        self.max_accel_to_decel = self.max_accel * (1.0 - self.min_cruise_ratio);
    }
}

/// A move request and, once the lookahead has run, its trapezoid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Move {
    /// Start position (X, Y, Z, E), mm.
    pub start_pos: [f64; 4],
    /// End position, mm.
    pub end_pos: [f64; 4],
    /// Per-axis distance, mm.
    pub axes_d: [f64; 4],
    /// Per-axis distance over move length.
    pub axes_r: [f64; 4],
    /// Length of the move (XYZ, or E for extrude-only moves), mm.
    pub move_d: f64,
    /// False for extrude-only moves.
    pub is_kinematic: bool,
    /// Acceleration, mm/s².
    pub accel: f64,
    junction_deviation: f64,
    /// Shortest time the move can take, s.
    pub min_move_t: f64,
    max_start_v2: f64,
    /// Highest cruise speed squared.
    pub max_cruise_v2: f64,
    delta_v2: f64,
    max_smoothed_v2: f64,
    smooth_delta_v2: f64,
    next_junction_v2: f64,
    /// Planned start velocity, mm/s.
    pub start_v: f64,
    /// Planned cruise velocity, mm/s.
    pub cruise_v: f64,
    /// Planned end velocity, mm/s.
    pub end_v: f64,
    /// Planned acceleration phase, s.
    pub accel_t: f64,
    /// Planned cruise phase, s.
    pub cruise_t: f64,
    /// Planned deceleration phase, s.
    pub decel_t: f64,
}

/// A distance below which a move has no XYZ motion, mm.
const MIN_KINEMATIC_D: f64 = 0.000_000_001;
/// Acceleration given to extrude-only moves before extruder limits apply.
const EXTRUDE_ONLY_ACCEL: f64 = 99_999_999.9;
/// Initial "no limit" for the next junction, (mm/s)².
const NO_JUNCTION_LIMIT_V2: f64 = 999_999_999.9;

impl Move {
    /// A move from `start` to `end` at `speed` mm/s under `limits`; None if
    /// it goes nowhere.
    pub fn new(limits: &Limits, start: [f64; 4], end: [f64; 4], speed: f64) -> Option<Self> {
        let mut end_pos = end;
        let mut axes_d = [0.0; 4];
        for i in 0..4 {
            axes_d[i] = end[i] - start[i];
        }
        let mut move_d =
            sqrt(axes_d[0] * axes_d[0] + axes_d[1] * axes_d[1] + axes_d[2] * axes_d[2]);
        let mut accel = limits.max_accel;
        let mut velocity = speed.min(limits.max_velocity);
        let is_kinematic = move_d >= MIN_KINEMATIC_D;
        if !is_kinematic {
            end_pos[..3].copy_from_slice(&start[..3]);
            axes_d[..3].fill(0.0);
            move_d = axes_d[E].abs();
            accel = EXTRUDE_ONLY_ACCEL;
            velocity = speed;
        }
        if move_d == 0.0 {
            return None;
        }
        let inv_move_d = 1.0 / move_d;
        let axes_r = axes_d.map(|d| d * inv_move_d);
        Some(Self {
            start_pos: start,
            end_pos,
            axes_d,
            axes_r,
            move_d,
            is_kinematic,
            accel,
            junction_deviation: limits.junction_deviation,
            min_move_t: move_d / velocity,
            max_start_v2: 0.0,
            max_cruise_v2: velocity * velocity,
            delta_v2: 2.0 * move_d * accel,
            max_smoothed_v2: 0.0,
            smooth_delta_v2: 2.0 * move_d * limits.max_accel_to_decel,
            next_junction_v2: NO_JUNCTION_LIMIT_V2,
            start_v: 0.0,
            cruise_v: 0.0,
            end_v: 0.0,
            accel_t: 0.0,
            cruise_t: 0.0,
            decel_t: 0.0,
        })
    }

    /// Total planned duration, s.
    pub fn move_t(&self) -> f64 {
        self.accel_t + self.cruise_t + self.decel_t
    }

    /// Lowers the move's speed and acceleration limits.
    pub fn limit_speed(&mut self, speed: f64, accel: f64) {
        let speed2 = speed * speed;
        if speed2 < self.max_cruise_v2 {
            self.max_cruise_v2 = speed2;
            self.min_move_t = self.move_d / speed;
        }
        self.accel = self.accel.min(accel);
        self.delta_v2 = 2.0 * self.move_d * self.accel;
        self.smooth_delta_v2 = self.smooth_delta_v2.min(self.delta_v2);
    }

    /// Limits the speed at the junction after this move.
    pub fn limit_next_junction_speed(&mut self, speed: f64) {
        self.next_junction_v2 = self.next_junction_v2.min(speed * speed);
    }

    /// Computes the highest start speed given the previous move;
    /// `extruder_v2` is the extruder's limit for this junction.
    pub fn calc_junction(&mut self, prev: &Move, extruder_v2: f64) {
        if !self.is_kinematic || !prev.is_kinematic {
            return;
        }
        let mut max_start_v2 = self
            .max_cruise_v2
            .min(prev.max_cruise_v2)
            .min(prev.next_junction_v2)
            .min(prev.max_start_v2 + prev.delta_v2)
            .min(extruder_v2);
        let (r, p) = (&self.axes_r, &prev.axes_r);
        let junction_cos_theta = -(r[0] * p[0] + r[1] * p[1] + r[2] * p[2]);
        let sin_theta_d2 = sqrt((0.5 * (1.0 - junction_cos_theta)).max(0.0));
        let cos_theta_d2 = sqrt((0.5 * (1.0 + junction_cos_theta)).max(0.0));
        let one_minus_sin_theta_d2 = 1.0 - sin_theta_d2;
        if one_minus_sin_theta_d2 > 0.0 && cos_theta_d2 > 0.0 {
            let r_jd = sin_theta_d2 / one_minus_sin_theta_d2;
            let move_jd_v2 = r_jd * self.junction_deviation * self.accel;
            let pmove_jd_v2 = r_jd * prev.junction_deviation * prev.accel;
            // The approximated circle touches the moves no further than mid-move.
            let quarter_tan_theta_d2 = 0.25 * sin_theta_d2 / cos_theta_d2;
            let move_centripetal_v2 = self.delta_v2 * quarter_tan_theta_d2;
            let pmove_centripetal_v2 = prev.delta_v2 * quarter_tan_theta_d2;
            max_start_v2 = max_start_v2
                .min(move_jd_v2)
                .min(pmove_jd_v2)
                .min(move_centripetal_v2)
                .min(pmove_centripetal_v2);
        }
        self.max_start_v2 = max_start_v2;
        self.max_smoothed_v2 = max_start_v2.min(prev.max_smoothed_v2 + prev.smooth_delta_v2);
    }

    /// Fixes the trapezoid from the junction speeds (squared).
    pub fn set_junction(&mut self, start_v2: f64, cruise_v2: f64, end_v2: f64) {
        let half_inv_accel = 0.5 / self.accel;
        let accel_d = (cruise_v2 - start_v2) * half_inv_accel;
        let decel_d = (cruise_v2 - end_v2) * half_inv_accel;
        let cruise_d = self.move_d - accel_d - decel_d;
        self.start_v = sqrt(start_v2);
        self.cruise_v = sqrt(cruise_v2);
        self.end_v = sqrt(end_v2);
        self.accel_t = accel_d / ((self.start_v + self.cruise_v) * 0.5);
        self.cruise_t = cruise_d / self.cruise_v;
        self.decel_t = decel_d / ((self.end_v + self.cruise_v) * 0.5);
    }
}

/// The squared-velocity bookkeeping the lookahead reads from a move.
impl Move {
    pub(crate) fn lookahead_terms(&self) -> (f64, f64, f64, f64, f64) {
        (
            self.max_start_v2,
            self.delta_v2,
            self.max_smoothed_v2,
            self.smooth_delta_v2,
            self.max_cruise_v2,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> Limits {
        Limits::new(300.0, 3000.0, 0.5, 5.0)
    }

    #[test]
    fn a_square_corner_runs_at_square_corner_velocity() {
        let l = limits();
        let a = Move::new(&l, [0.0; 4], [20.0, 0.0, 0.0, 0.0], 100.0).expect("moves");
        let mut b =
            Move::new(&l, [20.0, 0.0, 0.0, 0.0], [20.0, 20.0, 0.0, 0.0], 100.0).expect("moves");
        b.calc_junction(&a, f64::MAX);
        let v = sqrt(b.max_start_v2);
        assert!((v - 5.0).abs() < 1e-9, "{v}");
    }

    #[test]
    fn straight_continuations_keep_full_speed() {
        let l = limits();
        let a = Move::new(&l, [0.0; 4], [20.0, 0.0, 0.0, 0.0], 100.0).expect("moves");
        let mut b =
            Move::new(&l, [20.0, 0.0, 0.0, 0.0], [40.0, 0.0, 0.0, 0.0], 100.0).expect("moves");
        b.calc_junction(&a, f64::MAX);
        assert_eq!(
            b.max_start_v2,
            (100.0f64).powi(2).min(a.max_start_v2 + a.delta_v2)
        );
    }

    #[test]
    fn trapezoid_covers_the_distance() {
        let l = limits();
        let mut m = Move::new(&l, [0.0; 4], [20.0, 0.0, 0.0, 0.0], 100.0).expect("moves");
        m.set_junction(0.0, 100.0 * 100.0, 25.0);
        let d = m.accel_t * (m.start_v + m.cruise_v) / 2.0
            + m.cruise_t * m.cruise_v
            + m.decel_t * (m.cruise_v + m.end_v) / 2.0;
        assert!((d - 20.0).abs() < 1e-12, "{d}");
        assert!((m.accel_t - 100.0 / 3000.0).abs() < 1e-15);
    }

    #[test]
    fn extrude_only_moves_use_e_distance() {
        let l = limits();
        let m = Move::new(&l, [1.0, 2.0, 3.0, 0.0], [1.0, 2.0, 3.0, -2.0], 35.0).expect("moves");
        assert!(!m.is_kinematic);
        assert_eq!(m.move_d, 2.0);
        assert_eq!(m.axes_r[E], -1.0);
        assert!(Move::new(&l, [0.0; 4], [0.0; 4], 10.0).is_none());
    }
}
