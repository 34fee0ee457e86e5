//! The stepper engine: executes queued `(interval, count, add)` moves the
//! way Klipper's MCU does, from a timer.
//!
//! A move's first step comes `interval` ticks after the previous step (or
//! after the stepper's reset clock); each following step `interval + add`
//! after the one before, the interval growing by `add` each time. The
//! direction set by `set_next_step_dir` applies from the next queued move.
//! Clocks are the hardware's 32-bit ticks; a step is never more than 2^31
//! ticks ahead, so comparisons are rollover-safe.

use crate::clock::is_before;
use crate::shutdown::Shutdown;

/// One queued move (a `queue_step` command with its direction).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Move {
    interval: u32,
    count: u16,
    add: i16,
    dir: bool,
}

/// What the engine does to the pins.
pub trait StepPins {
    /// Sets the direction pin (true: positive), before the step that needs it.
    fn set_dir(&mut self, positive: bool);
    /// Pulses the step pin, at the step's clock.
    fn step(&mut self);
}

/// One stepper's engine with a queue of `M` moves.
#[derive(Debug, Clone)]
pub struct Stepper<const M: usize> {
    queue: heapless::Deque<Move, M>,
    /// Direction for moves queued from now on.
    next_dir: bool,
    /// Clock of the last step (or of the reset), ticks.
    last_step: u32,
    /// The move being executed: steps left, its interval, add and
    /// direction.
    count: u32,
    interval: u32,
    add: i32,
    active_dir: bool,
    /// The pin's current direction.
    dir: Option<bool>,
    /// Position in steps (+1 per positive step).
    position: i64,
    /// Moves started so far (wrapping).
    loads: u32,
}

impl<const M: usize> Default for Stepper<M> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const M: usize> Stepper<M> {
    /// An idle stepper whose step clock is 0.
    pub const fn new() -> Self {
        Self {
            queue: heapless::Deque::new(),
            next_dir: false,
            last_step: 0,
            count: 0,
            interval: 0,
            add: 0,
            active_dir: false,
            dir: None,
            position: 0,
            loads: 0,
        }
    }

    /// `set_next_step_dir`: the direction of the moves queued next.
    pub fn set_next_dir(&mut self, positive: bool) {
        self.next_dir = positive;
    }

    /// `reset_step_clock`: the next move's first interval counts from
    /// `clock`. Only while idle.
    pub fn reset_clock(&mut self, clock: u32) {
        if self.count == 0 && self.queue.is_empty() {
            self.last_step = clock;
        }
    }

    /// `queue_step`: appends a move. `now` is the current clock: a move
    /// that starts an idle stepper with its first step already past means
    /// step generation fell behind.
    pub fn queue(&mut self, interval: u32, count: u16, add: i16, now: u32) -> Result<(), Shutdown> {
        if count == 0 {
            return Ok(());
        }
        let m = Move {
            interval,
            count,
            add,
            dir: self.next_dir,
        };
        if self.count == 0 && self.queue.is_empty() {
            let first = self.last_step.wrapping_add(interval);
            if is_before(first, now) {
                return Err(Shutdown::StepperTooFarInPast);
            }
        }
        self.queue
            .push_back(m)
            .map_err(|_| Shutdown::MoveQueueOverflow)
    }

    /// Free room in the move queue.
    pub fn free(&self) -> usize {
        M - self.queue.len()
    }

    /// The clock of the next step, if any is queued.
    pub fn next_step(&mut self) -> Option<u32> {
        if self.count == 0 {
            self.load()?;
        }
        Some(self.last_step.wrapping_add(self.interval))
    }

    /// The timer's work at the clock [`Self::next_step`] returned: one step.
    /// Returns the clock of the following step, if any.
    #[inline]
    pub fn step(&mut self, pins: &mut impl StepPins) -> Option<u32> {
        if self.count == 0 {
            self.load()?;
        }
        if self.dir != Some(self.active_dir) {
            self.dir = Some(self.active_dir);
            pins.set_dir(self.active_dir);
        }
        pins.step();
        self.last_step = self.last_step.wrapping_add(self.interval);
        self.position += if self.active_dir { 1 } else { -1 };
        self.count -= 1;
        if self.count > 0 {
            self.interval = self.interval.wrapping_add(self.add as u32);
            return Some(self.last_step.wrapping_add(self.interval));
        }
        self.next_step()
    }

    /// Moves started so far (wrapping): a change means the queue gained
    /// room.
    pub fn loads(&self) -> u32 {
        self.loads
    }

    /// Position in steps since start (+1 per positive step).
    pub fn position(&self) -> i64 {
        self.position
    }

    /// True when no step is queued or in progress.
    pub fn is_idle(&self) -> bool {
        self.count == 0 && self.queue.is_empty()
    }

    /// Drops every queued move (shutdown).
    pub fn stop(&mut self) {
        self.queue.clear();
        self.count = 0;
    }

    /// Makes the next queued move the active one.
    fn load(&mut self) -> Option<()> {
        let m = self.queue.pop_front()?;
        self.loads = self.loads.wrapping_add(1);
        self.count = u32::from(m.count);
        self.interval = m.interval;
        self.add = i32::from(m.add);
        self.active_dir = m.dir;
        Some(())
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec::Vec;

    /// Records (clock, direction) of each step.
    struct Record {
        dir: bool,
        clock: u32,
        steps: Vec<(u32, bool)>,
    }

    impl StepPins for Record {
        fn set_dir(&mut self, positive: bool) {
            self.dir = positive;
        }
        fn step(&mut self) {
            self.steps.push((self.clock, self.dir));
        }
    }

    fn run(s: &mut Stepper<8>) -> Vec<(u32, bool)> {
        let mut pins = Record {
            dir: false,
            clock: 0,
            steps: Vec::new(),
        };
        let mut next = s.next_step();
        while let Some(clock) = next {
            pins.clock = clock;
            next = s.step(&mut pins);
        }
        pins.steps
    }

    #[test]
    fn moves_expand_with_growing_intervals_and_directions() {
        let mut s = Stepper::<8>::new();
        s.set_next_dir(true);
        s.queue(100, 3, 10, 0).expect("room");
        s.set_next_dir(false);
        s.queue(50, 2, -5, 0).expect("room");
        assert_eq!(
            run(&mut s),
            [
                (100, true),
                (210, true),
                (330, true),
                (380, false),
                (425, false)
            ]
        );
        assert_eq!(s.position(), 1);
        assert!(s.is_idle());
    }

    #[test]
    fn clocks_wrap_without_a_hitch() {
        let mut s = Stepper::<8>::new();
        s.reset_clock(u32::MAX - 150);
        s.set_next_dir(true);
        s.queue(100, 3, 0, u32::MAX - 200).expect("room");
        let steps: Vec<u32> = run(&mut s).iter().map(|x| x.0).collect();
        assert_eq!(steps, [u32::MAX - 50, 49, 149]);
    }

    #[test]
    fn overflow_and_a_late_first_step_are_shutdowns() {
        let mut s = Stepper::<2>::new();
        assert_eq!(
            s.queue(1000, 1, 0, 2000),
            Err(Shutdown::StepperTooFarInPast)
        );
        s.queue(1000, 1, 0, 500).expect("room");
        s.queue(1000, 1, 0, 500).expect("room");
        assert_eq!(s.queue(1000, 1, 0, 500), Err(Shutdown::MoveQueueOverflow));
    }
}
