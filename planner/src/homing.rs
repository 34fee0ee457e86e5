//! Homing (G28) as Klipper performs it in its batch mode, where each
//! endstop "triggers" exactly when its homing move ends.
//!
//! Per axis: the axis is declared to be far beyond its endstop (1.5 times
//! the travel), a homing move runs to the endstop at `homing_speed`, the
//! axis retracts by `homing_retract_dist`, and a second homing move runs at
//! `second_homing_speed`. A delta homes its three towers together: the
//! toolhead is declared far below its home position (every carriage at
//! its endstop), each tower's endstop stops that tower alone, and the
//! homing move ends when all three have triggered; then the same retract
//! and second homing move, with stepper_a's options. Homing moves are "drip" moves: planned alone,
//! starting after the endstop start delay and the step generator's scan
//! window. With real endstops the trigger ends the move early: the sink
//! reports where and when the steppers stopped
//! ([`MoveSink::homing_move_end`]), and print time goes on from the stop.

use crate::move_sink::{HomingEnd, HomingMove, MoveSink};
use crate::planned_move::E;
use crate::toolhead::{DeltaHoming, HomingInfo, MoveError, Toolhead};

/// Delay between arming endstops and starting a homing move, s.
pub const HOMING_START_DELAY: f64 = 0.001;

/// What runs around homing moves on a probe (a BLTouch's deploy and
/// stow), as Klipper's homing events: around all of an axis' homing moves
/// (`home_rails_begin`/`_end`) and around each (`homing_move_begin`/`_end`).
pub trait HomingHooks<const N: usize> {
    /// Before the homing moves of an axis homing on the probe.
    fn rails_begin(&mut self) {}
    /// After them.
    fn rails_end(
        &mut self,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
    ) -> Result<(), MoveError> {
        let _ = (toolhead, sink);
        Ok(())
    }
    /// Before a homing move whose endstop is the probe's.
    fn move_begin(
        &mut self,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
    ) -> Result<(), MoveError> {
        let _ = (toolhead, sink);
        Ok(())
    }
    /// After it.
    fn move_end(
        &mut self,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
    ) -> Result<(), MoveError> {
        let _ = (toolhead, sink);
        Ok(())
    }
}

/// No probe to deploy.
pub struct NoHooks;

impl<const N: usize> HomingHooks<N> for NoHooks {}

/// Klipper's errors for a homing move that ran its whole length without
/// its endstop triggering, by the rail's short name: X, Y, Z, then a
/// delta's towers A, B, C.
pub const NO_TRIGGER_RAIL: [&str; 6] = [
    "No trigger on x after full movement",
    "No trigger on y after full movement",
    "No trigger on z after full movement",
    "No trigger on a after full movement",
    "No trigger on b after full movement",
    "No trigger on c after full movement",
];

/// The same for a rail's extra steppers' own endstops, by axis and the
/// number in the section's name (`[stepper_z1]`: z1).
pub const NO_TRIGGER_EXTRA: [[&str; 3]; 3] = [
    [
        "No trigger on x1 after full movement",
        "No trigger on x2 after full movement",
        "No trigger on x3 after full movement",
    ],
    [
        "No trigger on y1 after full movement",
        "No trigger on y2 after full movement",
        "No trigger on y3 after full movement",
    ],
    [
        "No trigger on z1 after full movement",
        "No trigger on z2 after full movement",
        "No trigger on z3 after full movement",
    ],
];

/// Klipper's error for a homing move ended by a communication timeout
/// (another MCU's trsync reports stopped), by the endstop's name as in
/// [`NO_TRIGGER_RAIL`].
pub const COMMS_TIMEOUT: [&str; 6] = [
    "Error during homing x: Communication timeout during homing",
    "Error during homing y: Communication timeout during homing",
    "Error during homing z: Communication timeout during homing",
    "Error during homing a: Communication timeout during homing",
    "Error during homing b: Communication timeout during homing",
    "Error during homing c: Communication timeout during homing",
];

/// What is homed together: one axis, or a delta's three towers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Rails {
    /// One axis (0 = X) on its endstop (or the probe).
    Axis(usize),
    /// The three towers, each on its own endstop.
    Towers,
}

impl<const N: usize> Toolhead<N> {
    /// Homes each of `axes` (0 = X, 1 = Y, 2 = Z) in turn; a delta homes
    /// its three towers together whichever axes are named, as Klipper.
    pub fn home(&mut self, axes: &[usize], sink: &mut impl MoveSink) -> Result<(), MoveError> {
        self.home_with(axes, sink, &mut NoHooks)
    }

    /// [`Self::home`], with `hooks` run around the moves on the probe.
    pub fn home_with(
        &mut self,
        axes: &[usize],
        sink: &mut impl MoveSink,
        hooks: &mut impl HomingHooks<N>,
    ) -> Result<(), MoveError> {
        if let Some(delta) = self.kinematics.delta_homing() {
            return self.home_delta(&delta, sink);
        }
        for &axis in axes {
            let Some(info) = self.kinematics.homing_info(axis) else {
                return Err(MoveError {
                    reason: "Homing is not supported for this kinematics yet",
                    end: self.position(),
                    detail: crate::toolhead::Detail::Position,
                });
            };
            if info.probe {
                hooks.rails_begin();
            }
            let homed = self.home_axis(axis, &info, sink, hooks);
            let stowed = match info.probe {
                true => hooks.rails_end(self, sink),
                false => Ok(()),
            };
            homed?;
            stowed?;
        }
        Ok(())
    }

    /// Klipper's delta `home`: the toolhead is taken to be far below the
    /// home position, then the towers home together (every carriage up
    /// to its own endstop, never the probe) with stepper_a's speeds and
    /// retract.
    fn home_delta(
        &mut self,
        delta: &DeltaHoming,
        sink: &mut impl MoveSink,
    ) -> Result<(), MoveError> {
        let mut force = self.position();
        force[..3].copy_from_slice(&delta.home);
        force[2] = delta.force_z;
        let mut home = self.position();
        home[..3].copy_from_slice(&delta.home);
        self.set_position(force, sink);
        self.kinematics.set_homed();
        self.home_rails(Rails::Towers, &delta.info, force, home, sink, &mut NoHooks)
    }

    fn home_axis(
        &mut self,
        axis: usize,
        hi: &HomingInfo,
        sink: &mut impl MoveSink,
        hooks: &mut impl HomingHooks<N>,
    ) -> Result<(), MoveError> {
        let (min, max) = hi.range;
        let mut force = self.position();
        force[axis] = if hi.positive_dir {
            hi.position_endstop - 1.5 * (hi.position_endstop - min)
        } else {
            hi.position_endstop + 1.5 * (max - hi.position_endstop)
        };
        let mut home = self.position();
        home[axis] = hi.position_endstop;
        self.set_position(force, sink);
        self.kinematics.set_axis_homed(axis);
        self.home_rails(Rails::Axis(axis), hi, force, home, sink, hooks)
    }

    /// Klipper's `home_rails` once the position is forced to `force`: a
    /// homing move to `home` at the homing speed, then (with a retract
    /// distance) a retract along the same line and a second homing move
    /// at the second homing speed. A homing move whose endstop never
    /// triggers fails with Klipper's message, and every axis must be
    /// homed again.
    fn home_rails(
        &mut self,
        rails: Rails,
        hi: &HomingInfo,
        force: [f64; 4],
        home: [f64; 4],
        sink: &mut impl MoveSink,
        hooks: &mut impl HomingHooks<N>,
    ) -> Result<(), MoveError> {
        let end = self.homing_move(rails, hi, home, hi.speed, sink, hooks)?;
        self.check_triggered(rails, &end)?;
        if hi.retract_dist > 0.0 {
            let mut axes_d = [0.0; 4];
            for i in 0..3 {
                axes_d[i] = home[i] - force[i];
            }
            let move_d = crate::math::sqrt(
                axes_d[0] * axes_d[0] + axes_d[1] * axes_d[1] + axes_d[2] * axes_d[2],
            );
            let retract_r = (hi.retract_dist / move_d).min(1.0);
            let mut retract = home;
            let mut start = home;
            for i in 0..3 {
                retract[i] = home[i] - axes_d[i] * retract_r;
                start[i] = retract[i] - axes_d[i] * retract_r;
            }
            self.move_to(retract, hi.retract_speed, sink)?;
            self.set_position(start, sink);
            let end = self.homing_move(rails, hi, home, hi.second_speed, sink, hooks)?;
            self.check_triggered(rails, &end)?;
        }
        self.flush_step_generation(sink);
        Ok(())
    }

    /// Fails with Klipper's message if an endstop of the homing move that
    /// ended as `end` never triggered (as Klipper's G28 then turns the
    /// motors off, every axis must be homed again).
    fn check_triggered(&mut self, rails: Rails, end: &HomingEnd) -> Result<(), MoveError> {
        if end.comms_timeout {
            // The move's first endstop names it, as in Klipper: the
            // rail's, or tower A's.
            let name = match rails {
                Rails::Axis(axis) => COMMS_TIMEOUT.get(axis),
                Rails::Towers => COMMS_TIMEOUT.get(3),
            };
            return Err(self.homing_failed(name.copied().unwrap_or(COMMS_TIMEOUT[2])));
        }
        let Some(endstop) = end.untriggered else {
            return Ok(());
        };
        let reason = match rails {
            // An extra stepper's own endstop (engine slot 3 on).
            Rails::Axis(_) if endstop >= 3 => {
                self.kinematics
                    .extra_stepper(endstop - 3)
                    .and_then(|(axis, number)| {
                        NO_TRIGGER_EXTRA
                            .get(usize::from(axis))?
                            .get(usize::from(number).checked_sub(1)?)
                            .copied()
                    })
            }
            Rails::Axis(axis) => NO_TRIGGER_RAIL.get(axis).copied(),
            Rails::Towers => NO_TRIGGER_RAIL.get(3 + endstop).copied(),
        };
        Err(self.homing_failed(reason.unwrap_or(NO_TRIGGER_RAIL[2])))
    }

    /// A homing move failed with `reason`: as Klipper's G28 then turns
    /// the motors off, every axis must be homed again.
    fn homing_failed(&mut self, reason: &'static str) -> MoveError {
        self.kinematics.clear_homed();
        MoveError {
            reason,
            end: self.position(),
            detail: crate::toolhead::Detail::Nothing,
        }
    }

    /// One homing move of `rails` to `target`, ending where the endstop
    /// triggers (the sink tells where the steppers stopped, and when).
    pub(crate) fn homing_move(
        &mut self,
        rails: Rails,
        hi: &HomingInfo,
        target: [f64; 4],
        speed: f64,
        sink: &mut impl MoveSink,
        hooks: &mut impl HomingHooks<N>,
    ) -> Result<HomingEnd, MoveError> {
        if hi.probe {
            hooks.move_begin(self, sink)?;
        }
        self.flush_step_generation(sink);
        let start_time = self.last_move_time(sink);
        self.dwell(HOMING_START_DELAY, sink);
        let mut target = target;
        target[E] = self.position()[E];
        self.drip_move(target, speed, sink)?;
        let end_time = self.last_move_time(sink);
        self.flush_step_generation(sink);
        let (axis, towers) = match rails {
            Rails::Axis(axis) => (axis, false),
            Rails::Towers => (2, true),
        };
        let end = sink.homing_move_end(&HomingMove {
            axis,
            target: [target[0], target[1], target[2]],
            position_endstop: hi.position_endstop,
            positive_dir: hi.positive_dir,
            speed,
            probe: hi.probe,
            towers,
            start_time,
            end_time,
        });
        if let Some(t) = end.stopped_at {
            // The rest of the move never ran: time goes on from the stop.
            self.rewind_to(t);
        }
        let halt = end.position;
        self.set_position([halt[0], halt[1], halt[2], target[E]], sink);
        if hi.probe {
            hooks.move_end(self, sink)?;
        }
        Ok(end)
    }
}
