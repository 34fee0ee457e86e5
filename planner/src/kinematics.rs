//! Where each stepper is for a toolhead position, and back.
//!
//! Positions in mm. A stepper's position is the length of belt, screw or
//! carriage travel it has moved: for cartesian axes the coordinate itself,
//! for CoreXY `x + y` and `x - y`, for CoreXZ `x + z` and `x - z`, for a
//! delta tower the carriage height `z + sqrt(arm² - dx² - dy²)`.

use crate::math::sqrt;

/// How one stepper follows the toolhead.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StepperKinematics {
    /// Moves with one cartesian axis (0 = X, 1 = Y, 2 = Z).
    Axis(usize),
    /// Moves with the sum of two axes (CoreXY A: X + Y; CoreXZ: X + Z).
    Sum(usize, usize),
    /// Moves with the difference of two axes (CoreXY B: X - Y).
    Difference(usize, usize),
    /// A delta tower carriage.
    DeltaTower {
        /// Arm length squared, mm².
        arm2: f64,
        /// Tower position, mm.
        tower: [f64; 2],
    },
}

impl StepperKinematics {
    /// For kinematics linear in the toolhead position, the weights `w`
    /// with position = `w · p`; None for a delta tower.
    pub fn linear_weights(&self) -> Option<[f64; 3]> {
        let mut w = [0.0; 3];
        match *self {
            Self::Axis(a) => w[a] = 1.0,
            Self::Sum(a, b) => (w[a], w[b]) = (1.0, 1.0),
            Self::Difference(a, b) => (w[a], w[b]) = (1.0, -1.0),
            Self::DeltaTower { .. } => return None,
        }
        Some(w)
    }

    /// The stepper's position for toolhead position `p` (X, Y, Z), mm.
    pub fn position(&self, p: [f64; 3]) -> f64 {
        match *self {
            Self::Axis(a) => p[a],
            Self::Sum(a, b) => p[a] + p[b],
            Self::Difference(a, b) => p[a] - p[b],
            Self::DeltaTower { arm2, tower } => {
                let (dx, dy) = (tower[0] - p[0], tower[1] - p[1]);
                sqrt(arm2 - dx * dx - dy * dy) + p[2]
            }
        }
    }
}

/// The toolhead position (X, Y, Z) for stepper positions `s`, given how
/// each of the three motion steppers follows the toolhead.
pub fn calc_position(kin: &[StepperKinematics; 3], s: [f64; 3]) -> [f64; 3] {
    if let [
        StepperKinematics::DeltaTower {
            arm2: a0,
            tower: t0,
        },
        StepperKinematics::DeltaTower {
            arm2: a1,
            tower: t1,
        },
        StepperKinematics::DeltaTower {
            arm2: a2,
            tower: t2,
        },
    ] = *kin
    {
        return trilaterate(
            [
                [t0[0], t0[1], s[0]],
                [t1[0], t1[1], s[1]],
                [t2[0], t2[1], s[2]],
            ],
            [a0, a1, a2],
        );
    }
    let mut p = [0.0; 3];
    for (k, &pos) in kin.iter().zip(&s) {
        match *k {
            StepperKinematics::Axis(a) => p[a] = pos,
            // A + B = 2x and A - B = 2y: each half is added by its stepper.
            StepperKinematics::Sum(a, b) => {
                p[a] += 0.5 * pos;
                p[b] += 0.5 * pos;
            }
            StepperKinematics::Difference(a, b) => {
                p[a] += 0.5 * pos;
                p[b] -= 0.5 * pos;
            }
            StepperKinematics::DeltaTower { .. } => {}
        }
    }
    p
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn scale(a: [f64; 3], k: f64) -> [f64; 3] {
    [a[0] * k, a[1] * k, a[2] * k]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The lower intersection of three spheres (centres `c`, squared radii
/// `r2`): where the effector hangs from the three carriages.
fn trilaterate(c: [[f64; 3]; 3], r2: [f64; 3]) -> [f64; 3] {
    let s21 = sub(c[1], c[0]);
    let s31 = sub(c[2], c[0]);
    let d = sqrt(dot(s21, s21));
    let ex = scale(s21, 1.0 / d);
    let i = dot(ex, s31);
    let ey_raw = sub(s31, scale(ex, i));
    let ey = scale(ey_raw, 1.0 / sqrt(dot(ey_raw, ey_raw)));
    let ez = [
        ex[1] * ey[2] - ex[2] * ey[1],
        ex[2] * ey[0] - ex[0] * ey[2],
        ex[0] * ey[1] - ex[1] * ey[0],
    ];
    let j = dot(ey, s31);
    let x = (r2[0] - r2[1] + d * d) / (2.0 * d);
    let y = (r2[0] - r2[2] - x * x + (x - i) * (x - i) + j * j) / (2.0 * j);
    let z = -sqrt(r2[0] - x * x - y * y);
    let mut p = c[0];
    for k in 0..3 {
        p[k] += ex[k] * x + ey[k] * y + ez[k] * z;
    }
    p
}

/// Position of a delta tower at `angle_deg` degrees, `radius` mm from the
/// centre.
pub fn delta_tower(angle_deg: f64, radius: f64) -> [f64; 2] {
    let a = angle_deg * core::f64::consts::PI / 180.0;
    [libm::cos(a) * radius, libm::sin(a) * radius]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(kin: [StepperKinematics; 3]) {
        let mut x: u32 = 0x1234_5678;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            f64::from(x % 20_000) / 100.0 - 100.0
        };
        for _ in 0..1000 {
            let p = [next(), next(), next().abs()];
            let s = kin.map(|k| k.position(p));
            let back = calc_position(&kin, s);
            for a in 0..3 {
                assert!((back[a] - p[a]).abs() < 1e-9, "{p:?} -> {s:?} -> {back:?}");
            }
        }
    }

    #[test]
    fn cartesian_corexy_corexz_and_delta_invert_exactly() {
        use StepperKinematics::*;
        round_trip([Axis(0), Axis(1), Axis(2)]);
        round_trip([Sum(0, 1), Difference(0, 1), Axis(2)]);
        round_trip([Sum(0, 2), Axis(1), Difference(0, 2)]);
        let arm2 = 333.0 * 333.0;
        round_trip([210.0, 330.0, 90.0].map(|a| DeltaTower {
            arm2,
            tower: delta_tower(a, 174.75),
        }));
    }
}
