//! What the planner hands out: planned moves for the motion queues, and
//! homing moves for the step side to run against an endstop
//! ([`MoveSink`]). The planner's one interface to step generation.

/// One entry of a trapezoid motion queue, as `trapq_append` receives it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrapqMove {
    /// Start of the move, s.
    pub print_time: f64,
    /// Acceleration phase, s.
    pub accel_t: f64,
    /// Cruise phase, s.
    pub cruise_t: f64,
    /// Deceleration phase, s.
    pub decel_t: f64,
    /// Start position, mm (extruder: `[e, 0, 0]`).
    pub start_pos: [f64; 3],
    /// Direction (extruder: `[1, pressure advance allowed, 0]`).
    pub axes_r: [f64; 3],
    /// Start velocity, mm/s.
    pub start_v: f64,
    /// Cruise velocity, mm/s.
    pub cruise_v: f64,
    /// Acceleration, mm/s².
    pub accel: f64,
}

/// How one of the extruder's steppers follows the extruder's motion
/// queue.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExtruderStepperMotion {
    /// It follows the queue (false: it stands still).
    pub synced: bool,
    /// Pressure advance, s.
    pub pressure_advance: f64,
    /// Pressure advance's smoothing time, s.
    pub smooth_time: f64,
    /// Filament per step, mm.
    pub step_dist: f64,
    /// It steps the other way than configured (a negative rotation
    /// distance).
    pub inverted: bool,
}

/// Receives planned moves.
pub trait MoveSink {
    /// A toolhead (XYZ) move.
    fn toolhead(&mut self, m: &TrapqMove);
    /// An extruder move.
    fn extruder(&mut self, m: &TrapqMove);
    /// The toolhead position was set without moving (homing,
    /// SET_KINEMATIC_POSITION), after every move so far: steppers take
    /// `pos` (mm) as where they are. Sinks that only look at moves may
    /// ignore it.
    fn set_position(&mut self, pos: [f64; 3]) {
        let _ = pos;
    }
    /// After every move so far has been handed over: extruder stepper
    /// `stepper` (the machine's index) follows `motion` from now on
    /// (SET_PRESSURE_ADVANCE, SET_EXTRUDER_ROTATION_DISTANCE,
    /// SYNC_EXTRUDER_MOTION); with `position`, it takes that extruder
    /// position (mm) as where it stands, without stepping. Sinks that
    /// make no steps ignore it.
    fn extruder_stepper(
        &mut self,
        stepper: usize,
        motion: &ExtruderStepperMotion,
        position: Option<f64>,
    ) {
        let _ = (stepper, motion, position);
    }
    /// The probe's control pin (a BLTouch's servo signal) takes
    /// `pulse_width` s pulses (0: signal off) from print time `print_time`
    /// s on. Sinks without a probe ignore it.
    fn probe_pin(&mut self, print_time: f64, pulse_width: f64) {
        let _ = (print_time, pulse_width);
    }
    /// Whether the probe's input reads `triggered` (pressed, or open if
    /// false) at some time from print time `from` to `until` (s), as
    /// Klipper's BLTouch checks its sensor with a short homing on it, and
    /// the MCU's print time when the check ended (s): the step side waits
    /// for it. Sinks without a probe input say it does, at `from`.
    fn probe_reads(&mut self, from: f64, until: f64, triggered: bool) -> (bool, f64) {
        let _ = (until, triggered);
        (true, from)
    }
    /// A homing move has been handed over entirely: the sink runs it with
    /// the endstop armed and returns where and when the steppers stopped.
    /// Sinks without endstops let the move complete: at the target, at
    /// its end.
    fn homing_move_end(&mut self, homing: &HomingMove) -> HomingEnd {
        HomingEnd {
            position: homing.target,
            stopped_at: None,
            untriggered: None,
            comms_timeout: false,
        }
    }
}

/// A homing move, as the step side needs it to watch the endstop.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HomingMove {
    /// The axis homed (0 = X, 1 = Y, 2 = Z).
    pub axis: usize,
    /// Where the move goes: the endstop position on the homed axis, mm.
    pub target: [f64; 3],
    /// position_endstop, mm.
    pub position_endstop: f64,
    /// True if the endstop is approached in the positive direction.
    pub positive_dir: bool,
    /// The move's speed, mm/s.
    pub speed: f64,
    /// The endstop is the probe's input (probing, or homing on
    /// `probe:z_virtual_endstop`), not the rail's own.
    pub probe: bool,
    /// Each of the three motion steppers homes on its own endstop, whose
    /// trigger stops that stepper alone (a delta's towers, homed
    /// together); the move ends once all have triggered. False: the
    /// endstop of `axis` (or the probe) stops every motion stepper.
    pub towers: bool,
    /// Print time the endstop is armed at (just before the move), s.
    pub start_time: f64,
    /// Print time at the end of the move, s.
    pub end_time: f64,
}

/// Where and when a homing move ended, as the step side reports it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HomingEnd {
    /// The toolhead position where the steppers stopped, as Klipper
    /// computes it (the target, plus any overshoot past the trigger), mm.
    pub position: [f64; 3],
    /// Print time the steppers stopped at (with several endstops: the
    /// last trigger), s: None if the move ran to its end (no endstop
    /// triggered, or none is modelled).
    pub stopped_at: Option<f64>,
    /// An endstop that was watched and never triggered although the whole
    /// move ran: the motion stepper it stops (for a tower) or the engine
    /// slot it is read on. None if every endstop triggered, or if no
    /// endstop is modelled (klippy's batch mode, where the move's end
    /// counts as the trigger).
    pub untriggered: Option<usize>,
    /// The move was ended by a trsync communication timeout: another MCU's
    /// reports stopped reaching the host in time, so every MCU stopped its
    /// steppers by itself (Klipper's `Communication timeout during
    /// homing`).
    pub comms_timeout: bool,
}
