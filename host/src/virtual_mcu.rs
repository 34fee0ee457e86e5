//! The MCU role in virtual time: each stepper's commands go into the same
//! stepper engine the board runs ([`onechip_sched::stepper::Stepper`]),
//! which is run forward as far as step generation has committed, and every
//! step it makes is recorded with its 64-bit clock.

use onechip_planner::homing::HomingMove;
use onechip_planner::kinematics::{StepperKinematics, calc_position};
use onechip_planner::machine::MAX_STEPPERS;
use onechip_sched::endstop::{Check, Endstop};
use onechip_sched::shutdown::Shutdown;
use onechip_sched::stepper::{StepPins, Stepper};
use onechip_stepgen::compress::StepCommand;
use onechip_stepgen::motion::StepSink;
use std::collections::VecDeque;

/// Endstop sampling while homing, as Klipper configures it: once a trigger
/// is seen, this many samples this far apart must agree.
const ENDSTOP_SAMPLE_COUNT: u8 = 4;
const ENDSTOP_SAMPLE_TIME: f64 = 0.000_015;

/// The machine as physics sees it, for endstops: where the motion steppers
/// really are.
#[derive(Debug, Clone, PartialEq)]
pub struct Physics {
    /// How the three motion steppers follow the toolhead.
    pub kinematics: [StepperKinematics; 3],
    /// mm per step of each motion stepper.
    pub step_dist: [f64; 3],
    /// The motion steppers' positions at power-on, mm.
    pub start: [f64; 3],
    /// MCU clock, Hz.
    pub freq: f64,
}

impl Physics {
    /// The toolhead's real position after `steps` steps of each motion
    /// stepper, mm.
    fn toolhead(&self, steps: [i64; 3]) -> [f64; 3] {
        let s = core::array::from_fn(|k| self.start[k] + steps[k] as f64 * self.step_dist[k]);
        calc_position(&self.kinematics, s)
    }
}

/// Moves each virtual stepper can hold (Klipper's STM32 builds hold 1024
/// across all steppers; this is per stepper).
pub const MOVE_QUEUE: usize = 256;

/// The steps one stepper made.
#[derive(Debug, Clone, Default)]
pub struct StepLog {
    /// Every step: 64-bit MCU clock and direction (true: positive).
    pub steps: Vec<(u64, bool)>,
    /// Position in steps (+1 per positive step).
    pub position: i64,
    /// Shortest time between two steps, ticks.
    pub min_interval: Option<u64>,
}

/// Records the pins' activity at a known clock.
struct Pins<'a> {
    log: &'a mut StepLog,
    clock: u64,
    dir: bool,
}

impl StepPins for Pins<'_> {
    fn set_dir(&mut self, positive: bool) {
        self.dir = positive;
    }

    fn step(&mut self) {
        if let Some(&(last, _)) = self.log.steps.last() {
            let gap = self.clock - last;
            self.log.min_interval = Some(self.log.min_interval.map_or(gap, |m| m.min(gap)));
        }
        self.log.steps.push((self.clock, self.dir));
        self.log.position += if self.dir { 1 } else { -1 };
    }
}

/// One stepper: the engine, and the 64-bit clocks of its queued moves.
struct Channel {
    engine: Stepper<MOVE_QUEUE>,
    /// First-step clock and step count of each queued move.
    moves: VecDeque<(u64, u32)>,
    /// Steps left in the move being executed.
    left: u32,
    /// 64-bit clock of the next step, if any.
    next: Option<u64>,
    log: StepLog,
}

/// The virtual MCU.
pub struct VirtualMcu {
    channels: Vec<Channel>,
    /// Virtual time: every step before it has happened, ticks.
    now: u64,
    shutdown: Option<Shutdown>,
    /// With physics, homing moves stop at their endstops; without, they run
    /// to their end (klippy's batch mode).
    physics: Option<Physics>,
    /// Where each endstop triggered: axis, toolhead position, clock.
    triggers: Vec<(usize, [f64; 3], u64)>,
    /// The homing move being watched: its start clock, and its endstop
    /// with the 64-bit clock of its next reading.
    watch: Option<(u64, Endstop, u64)>,
}

impl VirtualMcu {
    /// An MCU with `steppers` idle steppers, at clock `start`.
    pub fn new(steppers: usize, start: u64) -> Self {
        Self {
            channels: (0..steppers)
                .map(|_| Channel {
                    engine: Stepper::new(),
                    moves: VecDeque::new(),
                    left: 0,
                    next: None,
                    log: StepLog::default(),
                })
                .collect(),
            now: start,
            shutdown: None,
            physics: None,
            triggers: Vec::new(),
            watch: None,
        }
    }

    /// The same MCU with endstops where `physics` puts them.
    pub fn with_physics(mut self, physics: Physics) -> Self {
        self.physics = Some(physics);
        self
    }

    /// Every endstop trigger so far: axis, the toolhead's real position
    /// when the steppers stopped (mm), and the clock.
    pub fn triggers(&self) -> &[(usize, [f64; 3], u64)] {
        &self.triggers
    }

    /// The toolhead's real position now, if physics is modelled, mm.
    pub fn real_position(&self) -> Option<[f64; 3]> {
        let physics = self.physics.as_ref()?;
        Some(physics.toolhead(self.motion_steps()))
    }

    fn motion_steps(&self) -> [i64; 3] {
        core::array::from_fn(|k| self.channels.get(k).map_or(0, |c| c.log.position))
    }

    /// Runs every stepper up to (not including) clock `until`, and moves
    /// virtual time there.
    pub fn run_until(&mut self, until: u64) {
        for i in 0..self.channels.len() {
            self.run_stepper(i, until);
        }
        self.now = self.now.max(until);
    }

    /// Why the MCU shut down, if it did.
    pub fn shutdown(&self) -> Option<Shutdown> {
        self.shutdown
    }

    /// The steps each stepper made.
    pub fn logs(&self) -> impl Iterator<Item = &StepLog> {
        self.channels.iter().map(|c| &c.log)
    }

    /// Runs stepper `i` before clock `until`.
    fn run_stepper(&mut self, i: usize, until: u64) {
        let ch = &mut self.channels[i];
        while let Some(clock) = ch.next.filter(|&c| c < until) {
            step(ch, clock);
        }
    }

    /// Runs stepper `i` until its move queue has room.
    fn make_room(&mut self, i: usize) {
        let ch = &mut self.channels[i];
        while ch.engine.free() == 0 {
            let Some(clock) = ch.next else { break };
            step(ch, clock);
        }
    }

    fn queue(&mut self, i: usize, interval: u32, count: u16, add: i16, first: u64) {
        self.make_room(i);
        // Like klippy, send a step far in the future only when the MCU's
        // 32-bit clock can tell when it is due.
        let now = self.now.max(first.saturating_sub(1 << 30)) as u32;
        let ch = &mut self.channels[i];
        if let Err(reason) = ch.engine.queue(interval, count, add, now) {
            self.stop(reason);
            return;
        }
        ch.moves.push_back((first, u32::from(count)));
        if ch.next.is_none() {
            ch.next = ch.engine.next_step().map(|low| next_clock(ch, first, low));
        }
    }

    fn stop(&mut self, reason: Shutdown) {
        if self.shutdown.is_none() {
            self.shutdown = Some(reason);
        }
        for ch in &mut self.channels {
            ch.engine.stop();
            ch.moves.clear();
            ch.next = None;
        }
    }
}

/// Makes the step due at `clock` and finds the next.
fn step(ch: &mut Channel, clock: u64) {
    let dir = ch.log.steps.last().is_some_and(|s| s.1);
    let mut pins = Pins {
        log: &mut ch.log,
        clock,
        dir,
    };
    let following = ch.engine.step(&mut pins);
    ch.left = ch.left.saturating_sub(1);
    ch.next = following.map(|low| next_clock(ch, clock, low));
}

/// The 64-bit clock of a step whose low 32 bits are `low`: a new move's
/// first step is where step generation put it; within a move, steps follow
/// the previous one (`prev`) by less than 2^32 ticks.
fn next_clock(ch: &mut Channel, prev: u64, low: u32) -> u64 {
    if ch.left == 0
        && let Some((first, count)) = ch.moves.pop_front()
    {
        ch.left = count;
        return first;
    }
    prev + u64::from(low.wrapping_sub(prev as u32))
}

impl StepSink for VirtualMcu {
    fn command(&mut self, index: usize, cmd: StepCommand, clock: u64) {
        if self.shutdown.is_some() {
            return;
        }
        match cmd {
            StepCommand::Dir(positive) => self.channels[index].engine.set_next_dir(positive),
            StepCommand::ResetClock(at) => self.channels[index].engine.reset_clock(at as u32),
            StepCommand::Steps {
                interval,
                count,
                add,
            } => self.queue(index, interval, count, add, clock),
        }
    }

    fn home(
        &mut self,
        homing: &HomingMove,
        start_clock: u64,
        until_clock: u64,
    ) -> Option<[i64; MAX_STEPPERS]> {
        let physics = self.physics.clone()?;
        let freq = physics.freq;
        // Klipper samples about once per step of the homing move, then
        // confirms a trigger with a few quick samples.
        let finest = physics
            .step_dist
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min);
        let rest = ((finest / homing.speed) * freq).max(1.0) as u32;
        let confirm = (ENDSTOP_SAMPLE_TIME * freq).max(1.0) as u32;
        let reached = |pos: [f64; 3]| {
            let coord = pos[homing.axis];
            if homing.positive_dir {
                coord >= homing.position_endstop
            } else {
                coord <= homing.position_endstop
            }
        };
        let (mut endstop, mut read_at) = match self.watch {
            Some((start, endstop, at)) if start == start_clock => (endstop, at),
            _ => {
                let at = start_clock.max(self.now);
                let endstop = Endstop::home(at as u32, confirm, ENDSTOP_SAMPLE_COUNT, rest);
                (endstop, at)
            }
        };
        let triggered_at = loop {
            let next_step = self
                .channels
                .iter()
                .enumerate()
                .filter_map(|(i, c)| c.next.map(|t| (t, i)))
                .min();
            match next_step {
                Some((t, i)) if t < read_at => step(&mut self.channels[i], t),
                _ if read_at >= until_clock => {
                    self.watch = Some((start_clock, endstop, read_at));
                    return None;
                }
                _ => match endstop.read(reached(physics.toolhead(self.motion_steps()))) {
                    Check::Triggered(_) => break read_at,
                    Check::At(next) => read_at += u64::from(next.wrapping_sub(read_at as u32)),
                },
            }
        };
        // Triggered: the steppers stop at once, so none overshoots the
        // trigger; their remaining steps are dropped.
        self.watch = None;
        for ch in &mut self.channels {
            ch.engine.stop();
            ch.moves.clear();
            ch.left = 0;
            ch.next = None;
        }
        self.now = self.now.max(triggered_at);
        let real = physics.toolhead(self.motion_steps());
        self.triggers.push((homing.axis, real, triggered_at));
        Some([0; MAX_STEPPERS])
    }
}
