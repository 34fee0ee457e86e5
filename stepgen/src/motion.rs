//! The whole step-generation pipeline of a printer: planned moves into
//! bounded motion queues, each stepper's steps found in windows as far as
//! the queued motion is final, compressed into step commands, handed to a
//! [`StepSink`] (the local stepper engine or a secondary MCU's link).
//!
//! Back-pressure: when a motion queue is full, steps are generated up to
//! the start of the move being appended (everything before it is final)
//! and the queue is pruned; the sink decides how to wait for room
//! downstream.

use crate::compress::{Compressor, StepCommand};
use crate::extruder::{self, PressureAdvance};
use crate::segment::Segment;
use crate::shaper::StepperShaper;
use crate::solver::{AlongDeltaSegment, AlongSegment, GENERATION_WINDOW, Margins, StepSolver};
use crate::trapq::Trapq;
use onechip_planner::kinematics::StepperKinematics;
use onechip_planner::kinematics::calc_position;
use onechip_planner::machine::{MAX_STEPPERS, Machine};
use onechip_planner::move_sink::{ExtruderStepperMotion, MoveSink, TrapqMove};
use onechip_planner::move_sink::{HomingEnd, HomingMove};

/// How far behind generation steps are sent, s: a command may cover up to
/// this much of the steps generated after the time it is sent for, as
/// Klipper's commands cover what its batch flushes generated beyond their
/// flush time (about 0.25 s). A constant-rate stretch then takes one
/// command per this much time or more, not one per generation slice. Every
/// step is sent at least this long after it is generated
/// ([`Motion::sent_until`]).
const COMPRESS_LAG: f64 = 0.250;

/// Print time all steppers are generated through before any goes further,
/// s.
const GENERATION_SLICE: f64 = 0.050;

/// Print time of a homing move's steps sent at a time, s (Klipper's
/// DRIP_SEGMENT_TIME).
const DRIP_TIME: f64 = 0.050;

/// Receives each stepper's commands, in order per stepper.
pub trait StepSink {
    /// The next command of stepper `index` (as in [`Machine::steppers`]);
    /// `clock` is the 64-bit MCU clock of its first step (see
    /// [`Compressor::append`]).
    fn command(&mut self, index: usize, cmd: StepCommand, clock: u64);

    /// A homing move is running, its commands sent up to `until_clock`:
    /// run its steps before that clock with the endstop of `homing.axis`
    /// (or with `homing.towers` each tower's own) armed from `start_clock`
    /// (called again with later clocks as more steps are sent). On a
    /// trigger, the steppers it stops stop and the rest of their queued
    /// steps is dropped (and those sent later, until their step clock is
    /// reset); returns when and how the move ended once every endstop has
    /// triggered, or once the move ran to its end with some endstop
    /// untriggered. None: not over yet (or no endstops here).
    fn home(
        &mut self,
        homing: &HomingMove,
        start_clock: u64,
        until_clock: u64,
    ) -> Option<HomingStop> {
        let _ = (homing, start_clock, until_clock);
        None
    }
}

/// A sink behind a reference (`&mut dyn StepSink` included) is one.
impl<S: StepSink + ?Sized> StepSink for &mut S {
    fn command(&mut self, index: usize, cmd: StepCommand, clock: u64) {
        (**self).command(index, cmd, clock);
    }

    fn home(
        &mut self,
        homing: &HomingMove,
        start_clock: u64,
        until_clock: u64,
    ) -> Option<HomingStop> {
        (**self).home(homing, start_clock, until_clock)
    }
}

/// How a homing move's steppers stopped at their endstops.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HomingStop {
    /// 64-bit MCU clock the homing move ended at: the (last) trigger's,
    /// or the move's end if an endstop never triggered, ticks.
    pub clock: u64,
    /// Each stepper's steps between its trigger and its stop.
    pub overshoot: [i64; MAX_STEPPERS],
    /// Some stepper was stopped by a trigger (it moves again only from a
    /// step clock reset).
    pub stopped: bool,
    /// A watched endstop that never triggered (see
    /// [`HomingEnd::untriggered`]), if any.
    pub untriggered: Option<usize>,
    /// Ended by a trsync communication timeout (see
    /// [`HomingEnd::comms_timeout`]).
    pub comms_timeout: bool,
}

/// What a stepper's position follows.
#[derive(Debug, Clone, Copy)]
enum Follows {
    /// The toolhead through its kinematics (shaped by the channel's
    /// shaper, if active).
    Toolhead(StepperKinematics),
    /// The extruder's queue, with pressure advance.
    Extruder(PressureAdvance),
    /// Nothing: an extruder stepper synced to no extruder stands still.
    Nothing,
}

impl Follows {
    /// The segments this follows, of the toolhead's and the extruder's
    /// queues (none for [`Self::Nothing`]).
    fn queue<'q, const N: usize>(
        &self,
        toolhead: &'q Trapq<N>,
        extruder: &'q Trapq<N>,
    ) -> &'q [Segment] {
        match self {
            Self::Toolhead(..) => toolhead.segments(),
            Self::Extruder(_) => extruder.segments(),
            Self::Nothing => &[],
        }
    }

    /// How an extruder stepper follows the extruder's queue with `motion`.
    fn extruder(motion: &ExtruderStepperMotion) -> Self {
        if motion.synced {
            Self::Extruder(PressureAdvance::new(
                motion.pressure_advance,
                motion.smooth_time,
            ))
        } else {
            Self::Nothing
        }
    }

    /// How far before and after a time its steps may lie from the motion
    /// then (pressure advance's smoothing; an input shaper's are the
    /// channel's own).
    fn margins(&self) -> Margins {
        match self {
            Self::Extruder(pa) => Margins::both(pa.half_smooth_time),
            _ => Margins::default(),
        }
    }
}

/// One stepper's generation and compression state.
#[derive(Debug, Clone)]
struct Channel<const Q: usize> {
    solver: StepSolver,
    follows: Follows,
    shaper: StepperShaper,
    margins: Margins,
    compressor: Compressor<Q>,
    /// mm per step.
    step_dist: f64,
    /// The stepper's position per mm of its queue's coordinate 0: 1, or
    /// -1 for an extruder stepper turning the other way (a negative
    /// rotation distance).
    direction: f64,
    /// Print time at the compressor's clock 0, s (0 on the main MCU; a
    /// secondary MCU's clock runs from elsewhere).
    time_offset: f64,
}

/// The position `w · p` (`w`: a linear stepper's weights of the
/// coordinates) along `seg`: two coefficients per segment, two operations
/// per time.
fn along_segment(seg: &Segment, w: [f64; 3]) -> AlongSegment {
    let dot = |v: [f64; 3]| w[0] * v[0] + w[1] * v[1] + w[2] * v[2];
    AlongSegment {
        base: dot(seg.start_pos),
        ratio: dot(seg.axes_r),
        start_v: seg.start_v,
        half_accel: seg.half_accel,
    }
}

impl<const Q: usize> Channel<Q> {
    /// Generates up to `until` (s) from `segs` and sends the steps that lie
    /// [`COMPRESS_LAG`] behind what is generated.
    fn generate(&mut self, index: usize, segs: &[Segment], until: f64, sink: &mut impl StepSink) {
        let Self {
            solver,
            follows,
            shaper,
            margins,
            compressor,
            time_offset,
            direction,
            ..
        } = self;
        let (offset, direction) = (*time_offset, *direction);
        let mut out = |cmd, clock| sink.command(index, cmd, clock);
        let mut emit = |s: crate::solver::Step| compressor.append(s.time - offset, s.dir, &mut out);
        match follows {
            Follows::Toolhead(kin) => match kin.linear_weights() {
                Some(w) if !shaper.is_active() => {
                    // Affine in the distance along each segment: two
                    // coefficients per segment, two operations per time.
                    let position = |i: usize| along_segment(&segs[i], w);
                    solver.generate_until(segs, *margins, until, position, &mut emit);
                }
                None if !shaper.is_active()
                    && let StepperKinematics::DeltaTower { arm2, tower } = *kin =>
                {
                    let position = |i: usize| {
                        let seg: &Segment = &segs[i];
                        let [x, y, z] = seg.start_pos;
                        AlongDeltaSegment {
                            arm2,
                            start: [x - tower[0], y - tower[1], z],
                            axes_r: seg.axes_r,
                            start_v: seg.start_v,
                            half_accel: seg.half_accel,
                        }
                    };
                    solver.generate_until(segs, *margins, until, position, &mut emit);
                }
                _ => {
                    let (kin, shaper) = (*kin, *shaper);
                    let position = |i: usize| shaper.on_segment(segs, i, kin);
                    solver.generate_until(segs, *margins, until, position, &mut emit);
                }
            },
            Follows::Extruder(pa) if pa.half_smooth_time != 0.0 => {
                let pa = *pa;
                let position =
                    |i: usize| move |t: f64| direction * extruder::position(segs, i, t, &pa);
                solver.generate_until(segs, *margins, until, position, &mut emit);
            }
            // Without pressure advance the filament follows its own
            // queue's segments: coordinate 0 (signed velocities), in the
            // stepper's direction. Following nothing, there are no
            // segments: time passes without steps.
            Follows::Extruder(_) | Follows::Nothing => {
                let position = |i: usize| along_segment(&segs[i], [direction, 0.0, 0.0]);
                solver.generate_until(segs, *margins, until, position, &mut emit);
            }
        }
        let done = solver.generated_until();
        if done.is_finite() {
            compressor.flush_until(done - COMPRESS_LAG - offset, done - offset, &mut out);
        }
    }

    /// How far back of its generated time this stepper still reads, s.
    fn look_back(&self) -> f64 {
        self.margins.before.max(self.margins.after)
    }
}

/// Step generation for a machine: motion queues of `N` segments, step
/// compressors holding `Q` steps.
#[derive(Debug, Clone)]
pub struct Motion<const N: usize, const Q: usize> {
    toolhead: Trapq<N>,
    extruder: Trapq<N>,
    channels: heapless::Vec<Channel<Q>, MAX_STEPPERS>,
    /// Motion before this print time is final (later moves start after), s.
    known_until: f64,
    error: Option<MotionError>,
    /// The compressors' max_error, s.
    max_error_time: f64,
    /// MCU clock, Hz.
    freq: f64,
}

/// A fault of the step-generation pipeline.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MotionError {
    /// A move did not fit its queue even after generating every step
    /// before it: the segments within the filters' look-back window
    /// outnumber the queue (a build with too small a queue).
    QueueTooSmall,
}

impl core::fmt::Display for MotionError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::QueueTooSmall => {
                f.write_str("Motion queue too small for the step generation window")
            }
        }
    }
}

impl<const N: usize, const Q: usize> Motion<N, Q> {
    /// Step generation for `machine`'s steppers, with an MCU clock of `freq`
    /// Hz and steps within `max_error` ticks; the toolhead starts at `pos`.
    pub fn new(machine: &Machine<'_>, freq: f64, max_error: u32, pos: [f64; 3]) -> Self {
        let mut slot = core::mem::MaybeUninit::uninit();
        Self::init_in(&mut slot, machine, freq, max_error, pos);
        // SAFETY: `init_in` initialised it.
        unsafe { slot.assume_init() }
    }

    /// [`Self::new`] built in place in `slot`, without passing the queues
    /// through the stack (they are larger than a microcontroller's stack);
    /// returns it.
    pub fn init_in<'s>(
        slot: &'s mut core::mem::MaybeUninit<Self>,
        machine: &Machine<'_>,
        freq: f64,
        max_error: u32,
        pos: [f64; 3],
    ) -> &'s mut Self {
        use core::ptr::addr_of_mut;
        let p = slot.as_mut_ptr();
        // SAFETY: `p` is valid for writes; every field is written once (the
        // empty queues straight into the slot: their storage is
        // uninitialised, so only their lengths are stored) before the slot
        // is taken as initialised.
        let motion = unsafe {
            addr_of_mut!((*p).toolhead).write(Trapq::new());
            addr_of_mut!((*p).extruder).write(Trapq::new());
            addr_of_mut!((*p).channels).write(heapless::Vec::new());
            addr_of_mut!((*p).known_until).write(f64::NEG_INFINITY);
            addr_of_mut!((*p).error).write(None);
            addr_of_mut!((*p).max_error_time).write(f64::from(max_error) / freq);
            addr_of_mut!((*p).freq).write(freq);
            slot.assume_init_mut()
        };
        motion.add_channels(machine, max_error, pos);
        motion
    }

    /// A channel for each of `machine`'s steppers, compressing within
    /// `max_error` ticks; the toolhead starts at `pos`.
    fn add_channels(&mut self, machine: &Machine<'_>, max_error: u32, pos: [f64; 3]) {
        let freq = self.freq;
        for (i, stepper) in machine.steppers.iter().enumerate() {
            let (kin, follows, shaper, margins) = match machine.kinematics_of(i) {
                Some(kin) => {
                    let shaper = StepperShaper::new(&machine.input_shaper, kin);
                    let margins = if shaper.is_active() {
                        shaper.margins()
                    } else {
                        Margins::default()
                    };
                    (kin, Follows::Toolhead(kin), shaper, margins)
                }
                None => {
                    let follows = machine
                        .extruder_stepper(i)
                        .map_or(Follows::Nothing, |e| Follows::extruder(&e.motion()));
                    let kin = StepperKinematics::Axis(0);
                    (kin, follows, StepperShaper::default(), follows.margins())
                }
            };
            let start = match follows {
                Follows::Toolhead(..) => pos,
                _ => [0.0; 3],
            };
            // Machine holds at most MAX_STEPPERS steppers.
            let _ = self.channels.push(Channel {
                solver: StepSolver::new(kin, stepper.step_dist, start),
                follows,
                shaper,
                margins,
                compressor: Compressor::new(max_error, freq),
                step_dist: stepper.step_dist,
                direction: 1.0,
                time_offset: 0.0,
            });
        }
    }

    /// A [`MoveSink`] for the planner that queues moves here, generating
    /// steps into `sink` when a queue needs room.
    pub fn sink<'m, S: StepSink>(&'m mut self, steps: &'m mut S) -> MotionSink<'m, N, Q, S> {
        MotionSink {
            motion: self,
            steps,
        }
    }

    /// Generates every stepper's steps up to print time `until` (s), as far
    /// as the queued motion is final, in whole generation windows.
    pub fn generate(&mut self, until: f64, sink: &mut impl StepSink) {
        let limit = until.min(self.known_until);
        // All steppers advance together, a slice at a time, so that a long
        // stretch of one stepper's commands never waits for room ahead of
        // another stepper's earlier ones: from where the laggard stands
        // (before any generation: the first queued move) to the limit, or
        // with no limit to past the last move's end (where the queues'
        // open stationary tails start) by every look-back.
        let first_move = [&self.toolhead, &self.extruder]
            .iter()
            .filter_map(|q| q.segments().first())
            .map(|s| s.print_time)
            .fold(f64::INFINITY, f64::min);
        let motion_end = self.motion_end();
        let look_back = self
            .channels
            .iter()
            .map(Channel::look_back)
            .fold(0.0, f64::max);
        let sliced = limit.min(motion_end + look_back + GENERATION_SLICE);
        let mut upto = self
            .channels
            .iter()
            .map(|ch| {
                ch.solver
                    .generated_until()
                    .max(first_move - GENERATION_SLICE)
            })
            .fold(f64::INFINITY, f64::min);
        while upto.is_finite() && upto < sliced {
            upto = (upto + GENERATION_SLICE).min(sliced);
            self.generate_slice(upto, limit, sink);
        }
        self.generate_slice(limit, limit, sink);
        self.retire();
    }

    /// Generates every stepper up to `upto` (s), each as far as its
    /// look-ahead allows within `limit`.
    fn generate_slice(&mut self, upto: f64, limit: f64, sink: &mut impl StepSink) {
        for (i, ch) in self.channels.iter_mut().enumerate() {
            let segs = ch.follows.queue(&self.toolhead, &self.extruder);
            let to = window_floor(upto.min(limit - ch.margins.before));
            ch.generate(i, segs, to, sink);
        }
    }

    /// Where the queued motion ends (the queues' open stationary tails
    /// start), s.
    fn motion_end(&self) -> f64 {
        [&self.toolhead, &self.extruder]
            .iter()
            .filter_map(|q| q.segments().last())
            .map(|s| s.print_time)
            .fold(f64::NEG_INFINITY, f64::max)
    }

    /// Generates and sends every remaining step (the end of the motion).
    pub fn finish(&mut self, sink: &mut impl StepSink) {
        self.known_until = f64::INFINITY;
        self.generate(f64::INFINITY, sink);
        self.flush_compressors(sink);
    }

    /// The toolhead stopped and waits (M109, M190): generates and sends
    /// every step of the queued motion, so the MCU can run past its end.
    pub fn settle(&mut self, sink: &mut impl StepSink) {
        self.generate_through(sink);
        self.flush_compressors(sink);
    }

    /// Puts stepper `stepper` on another MCU's clock from now on: step
    /// clocks are `(t - offset) × freq` for print time `t` (s), within the
    /// same max_error in time. Steps already generated keep their clocks,
    /// so a new line must agree with the old one where generation stands.
    pub fn set_clock(&mut self, stepper: usize, offset: f64, freq: f64) {
        let max_error = (self.max_error_time * freq) as u32;
        if let Some(ch) = self.channels.get_mut(stepper) {
            ch.time_offset = offset;
            ch.compressor.set_clock(freq, max_error);
        }
    }

    /// Sends every step the compressors hold.
    fn flush_compressors(&mut self, sink: &mut impl StepSink) {
        for (i, ch) in self.channels.iter_mut().enumerate() {
            ch.compressor
                .flush(&mut |cmd, clock| sink.command(i, cmd, clock));
        }
    }

    /// Print time up to which some stepper's steps are generated, s
    /// (negative infinity before any): a move starting before this less the
    /// look-back would change steps already generated.
    pub fn generated_until(&self) -> f64 {
        self.channels
            .iter()
            .map(|ch| ch.solver.generated_until())
            .filter(|t| t.is_finite())
            .fold(f64::NEG_INFINITY, f64::max)
    }

    /// Print time before which every step is due has gone to the sink, s:
    /// each stepper has sent every step [`COMPRESS_LAG`] or more behind its
    /// generation; the steps its compressor still holds (queued, or in its
    /// open command) may be scheduled up to `max_error` before their time.
    pub fn sent_until(&self) -> f64 {
        self.channels
            .iter()
            .map(|ch| ch.solver.generated_until() - COMPRESS_LAG)
            .fold(f64::INFINITY, f64::min)
            - self.max_error_time
    }

    /// Drops the queued segments every stepper has passed.
    fn retire(&mut self) {
        let passed = |follows: fn(&Follows) -> bool| {
            self.channels
                .iter()
                .filter(|ch| follows(&ch.follows))
                .map(|ch| ch.solver.generated_until() - ch.look_back())
                .fold(f64::INFINITY, f64::min)
        };
        let toolhead = passed(|f| matches!(f, Follows::Toolhead(..)));
        let extruder = passed(|f| matches!(f, Follows::Extruder(_)));
        self.toolhead.retire(toolhead);
        self.extruder.retire(extruder);
    }

    fn append(&mut self, extruder: bool, m: &TrapqMove, sink: &mut impl StepSink) {
        self.known_until = self.known_until.max(m.print_time);
        if !self.queue(extruder).has_room() {
            self.generate(m.print_time, sink);
        }
        if self.queue(extruder).append(m).is_err() {
            self.error = Some(MotionError::QueueTooSmall);
        }
    }

    fn queue(&mut self, extruder: bool) -> &mut Trapq<N> {
        if extruder {
            &mut self.extruder
        } else {
            &mut self.toolhead
        }
    }

    /// Why motion was lost, if it was: the printer must stop.
    pub fn error(&self) -> Option<MotionError> {
        self.error
    }

    /// Generates every queued step, then extruder stepper `stepper`
    /// follows `motion`; with `position`, from that extruder position
    /// (mm) as where it stands.
    fn set_extruder_stepper(
        &mut self,
        stepper: usize,
        motion: &ExtruderStepperMotion,
        position: Option<f64>,
        sink: &mut impl StepSink,
    ) {
        self.generate_through(sink);
        // Steps of every stepper are made through here: a stepper synced
        // now follows the queue from here on.
        let through = self.generated_until();
        let Some(ch) = self.channels.get_mut(stepper) else {
            return;
        };
        if let Follows::Toolhead(..) = ch.follows {
            return;
        }
        ch.follows = Follows::extruder(motion);
        ch.margins = ch.follows.margins();
        ch.step_dist = motion.step_dist;
        ch.solver.set_step_dist(motion.step_dist);
        let direction = if motion.inverted { -1.0 } else { 1.0 };
        if direction != ch.direction {
            ch.direction = direction;
            ch.solver.mirror();
        }
        if let Some(e) = position {
            ch.solver.set_position([direction * e, 0.0, 0.0]);
            if ch.solver.generated_until() < through {
                ch.solver.restart(through);
            }
        }
    }

    /// Generates every queued step, then lets a new position take effect
    /// (homing, SET_KINEMATIC_POSITION).
    fn set_position(&mut self, pos: [f64; 3], sink: &mut impl StepSink) {
        self.generate_through(sink);
        for ch in &mut self.channels {
            if let Follows::Toolhead(..) = ch.follows {
                ch.solver.set_position(pos);
            }
        }
    }

    /// Runs a homing move whose steps are all generated: sends its
    /// compressed steps in drips, lets the sink run them against the
    /// endstops, and once they have stopped the steppers drops the rest of
    /// the move, restarts every motion stepper at the end (the last
    /// trigger: steppers stopped earlier stood still since, their steps
    /// sent meanwhile dropped by the MCU) and returns where the toolhead
    /// stopped, as Klipper computes it (the target, each stepper moved by
    /// its overshoot past its own trigger), with the end's print time.
    fn home(&mut self, homing: &HomingMove, sink: &mut impl StepSink) -> HomingEnd {
        let freq = self.freq;
        let clock = |t: f64| (t.max(0.0) * freq) as u64;
        let (start_clock, end_clock) = (clock(homing.start_time), clock(homing.end_time));
        self.known_until = self.known_until.max(homing.end_time);
        // Steps go out in short slices, as Klipper drips a homing move, so
        // that the endstop is watched while the steps still to come are
        // not yet queued.
        let mut until = homing.start_time;
        let stop = loop {
            until += DRIP_TIME;
            let last = until >= homing.end_time;
            let sent = if last {
                self.settle(sink);
                end_clock
            } else {
                self.generate(until, sink);
                clock(self.sent_until())
            };
            match sink.home(homing, start_clock, sent.min(end_clock)) {
                Some(stop) if stop.stopped => break stop,
                // The move ran to its end and no endstop triggered.
                Some(stop) => {
                    return HomingEnd {
                        position: homing.target,
                        stopped_at: None,
                        untriggered: stop.untriggered,
                        comms_timeout: stop.comms_timeout,
                    };
                }
                None if last => {
                    return HomingEnd {
                        position: homing.target,
                        stopped_at: None,
                        untriggered: None,
                        comms_timeout: false,
                    };
                }
                None => {}
            }
        };
        let stopped_at = stop.clock as f64 / freq;
        self.restart(stop.clock, sink);
        // The target, moved by each motion stepper's overshoot (none:
        // the target itself, as Klipper takes it).
        if stop.overshoot.iter().all(|&o| o == 0) {
            return HomingEnd {
                position: homing.target,
                stopped_at: Some(stopped_at),
                untriggered: stop.untriggered,
                comms_timeout: stop.comms_timeout,
            };
        }
        let mut kin = [StepperKinematics::Axis(0); 3];
        let mut spos = [0.0; 3];
        for (k, ch) in self.channels.iter().take(3).enumerate() {
            if let Follows::Toolhead(stepper_kin) = ch.follows {
                kin[k] = stepper_kin;
                spos[k] =
                    stepper_kin.position(homing.target) + stop.overshoot[k] as f64 * ch.step_dist;
            }
        }
        HomingEnd {
            position: calc_position(&kin, spos),
            stopped_at: Some(stopped_at),
            untriggered: stop.untriggered,
            comms_timeout: stop.comms_timeout,
        }
    }

    /// The motion stopped at 64-bit clock `clock` (a homing move's
    /// trigger): the queued motion is dropped, the motion steppers' unsent
    /// steps too (their step clocks restart there), the extruder's are
    /// sent (it stood still), and generation goes on from the stop.
    fn restart(&mut self, clock: u64, sink: &mut impl StepSink) {
        let at = clock as f64 / self.freq;
        self.toolhead.clear();
        self.extruder.clear();
        self.known_until = at;
        for (i, ch) in self.channels.iter_mut().enumerate() {
            let mut out = |cmd, clock| sink.command(i, cmd, clock);
            // A stepper on another MCU restarts at the stop on its clock.
            let own = if ch.time_offset == 0.0 && ch.compressor.freq() == self.freq {
                clock
            } else {
                ch.compressor.clock_at(at - ch.time_offset)
            };
            match ch.follows {
                Follows::Toolhead(..) => ch.compressor.reset(own, &mut out),
                _ => ch.compressor.flush(&mut out),
            }
            ch.solver.restart(at);
        }
    }

    /// Generates through the end of all queued motion and its margins.
    fn generate_through(&mut self, sink: &mut impl StepSink) {
        let end = self.motion_end();
        for (i, ch) in self.channels.iter_mut().enumerate() {
            let segs = ch.follows.queue(&self.toolhead, &self.extruder);
            ch.generate(i, segs, end + ch.margins.after, sink);
        }
        self.retire();
    }
}

/// The last generation window boundary at or before `t` (s); infinite
/// times stay as they are.
fn window_floor(t: f64) -> f64 {
    if t.is_finite() {
        let floor = crate::solver::trunc(t / GENERATION_WINDOW) * GENERATION_WINDOW;
        if floor > t {
            floor - GENERATION_WINDOW
        } else {
            floor
        }
    } else {
        t
    }
}

/// The planner's view of a [`Motion`]: moves and positions go into its
/// queues, steps into `S`.
pub struct MotionSink<'m, const N: usize, const Q: usize, S> {
    motion: &'m mut Motion<N, Q>,
    steps: &'m mut S,
}

impl<const N: usize, const Q: usize, S: StepSink> MoveSink for MotionSink<'_, N, Q, S> {
    fn toolhead(&mut self, m: &TrapqMove) {
        self.motion.append(false, m, self.steps);
    }

    fn extruder(&mut self, m: &TrapqMove) {
        self.motion.append(true, m, self.steps);
    }

    fn set_position(&mut self, pos: [f64; 3]) {
        self.motion.set_position(pos, self.steps);
    }

    fn extruder_stepper(
        &mut self,
        stepper: usize,
        motion: &ExtruderStepperMotion,
        position: Option<f64>,
    ) {
        (self.motion).set_extruder_stepper(stepper, motion, position, self.steps);
    }

    fn homing_move_end(&mut self, homing: &HomingMove) -> HomingEnd {
        self.motion.home(homing, self.steps)
    }
}
