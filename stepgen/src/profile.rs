//! Step generation at the queue sizes the firmware and the simulator run
//! with, behind functions that are not generic.
//!
//! Generic code is compiled with the opt-level of the crate that
//! instantiates it. The session that drives step generation is built for
//! size (`onechip-app` at opt-level `"z"`); these entry points take the
//! step sink as a `dyn` (one indirect call per step command, not per step),
//! so that step generation is instantiated here and keeps this crate's
//! opt-level (2) in the firmware, whoever calls it.

use crate::motion::{Motion, MotionSink, StepSink};
use onechip_planner::move_sink::{
    ExtruderStepperMotion, HomingEnd, HomingMove, MoveSink, TrapqMove,
};

/// Motion queue (trapq) length, in segments.
pub const MOTION_QUEUE: usize = 128;
/// Step buffer of each stepper's compressor: it holds half as many steps,
/// 6 bytes each (3 KiB); longer commands grow past it.
pub const COMPRESS_QUEUE: usize = 512;

/// Step generation at these sizes.
pub type ProfileMotion = Motion<MOTION_QUEUE, COMPRESS_QUEUE>;

impl ProfileMotion {
    /// [`Motion::generate`] into `sink`.
    #[inline(never)]
    pub fn generate_into(&mut self, until: f64, mut sink: &mut dyn StepSink) {
        self.generate(until, &mut sink);
    }

    /// [`Motion::settle`] into `sink`.
    #[inline(never)]
    pub fn settle_into(&mut self, mut sink: &mut dyn StepSink) {
        self.settle(&mut sink);
    }

    /// [`Motion::finish`] into `sink`.
    #[inline(never)]
    pub fn finish_into(&mut self, mut sink: &mut dyn StepSink) {
        self.finish(&mut sink);
    }

    /// The planner's view ([`Motion::sink`]), its steps into `steps`.
    pub fn moves<'m>(&'m mut self, steps: &'m mut dyn StepSink) -> ProfileMoves<'m> {
        ProfileMoves {
            motion: self,
            steps,
        }
    }
}

/// [`MotionSink`] at these sizes, into a `dyn` step sink.
pub struct ProfileMoves<'m> {
    motion: &'m mut ProfileMotion,
    steps: &'m mut dyn StepSink,
}

impl<'m> ProfileMoves<'m> {
    /// The generic view these functions instantiate.
    fn sink(&mut self) -> MotionSink<'_, MOTION_QUEUE, COMPRESS_QUEUE, &'m mut dyn StepSink> {
        self.motion.sink(&mut self.steps)
    }
}

impl MoveSink for ProfileMoves<'_> {
    #[inline(never)]
    fn toolhead(&mut self, m: &TrapqMove) {
        self.sink().toolhead(m);
    }

    #[inline(never)]
    fn extruder(&mut self, m: &TrapqMove) {
        self.sink().extruder(m);
    }

    #[inline(never)]
    fn set_position(&mut self, pos: [f64; 3]) {
        self.sink().set_position(pos);
    }

    #[inline(never)]
    fn extruder_stepper(
        &mut self,
        stepper: usize,
        motion: &ExtruderStepperMotion,
        position: Option<f64>,
    ) {
        self.sink().extruder_stepper(stepper, motion, position);
    }

    #[inline(never)]
    fn homing_move_end(&mut self, homing: &HomingMove) -> HomingEnd {
        self.sink().homing_move_end(homing)
    }
}
