//! The MCU role in virtual time: each stepper's commands go into the same
//! stepper engine the board runs ([`onechip_sched::stepper::Stepper`]),
//! which is run forward as far as step generation has committed, and every
//! step it makes is recorded with its 64-bit clock.

use onechip_sched::shutdown::Shutdown;
use onechip_sched::stepper::{StepPins, Stepper};
use onechip_stepgen::compress::StepCommand;
use onechip_stepgen::motion::StepSink;
use std::collections::VecDeque;

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
        }
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
            StepCommand::Steps {
                interval,
                count,
                add,
            } => self.queue(index, interval, count, add, clock),
        }
    }
}
