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
struct QueuedMove {
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
    /// True while the endstop of this stepper's rail reads pressed (read
    /// only while homing; a stepper without one never triggers).
    fn endstop_triggered(&mut self) -> bool {
        false
    }
}

/// One stepper's engine with a queue of `M` moves.
///
/// Only [`Self::step`] runs for every step: it pulses the pin and works
/// out the next step's clock. Everything else a move needs (direction
/// pin, position) is done once, by [`Self::load`]. The caller keeps the
/// clock of the coming step (its timer's wake time).
///
/// The fields the step path uses come first.
#[derive(Debug, Clone)]
#[repr(C)]
pub struct Stepper<const M: usize> {
    /// Steps left in the active move, the coming one included (0: idle).
    count: u32,
    /// Ticks from the coming step to the one after it.
    interval: u32,
    /// Change of the interval after each step, ticks (two's complement).
    add: u32,
    /// Clock of the last step of the previous move (or of the reset),
    /// ticks: the next move's first interval counts from here.
    last: u32,
    queue: heapless::Deque<QueuedMove, M>,
    /// Direction for moves queued from now on.
    next_dir: bool,
    /// The direction pin's state (None before the first move).
    dir: Option<bool>,
    /// Position when the active move ends, steps (+1 per positive step).
    end_position: i64,
    /// Stopped by an endstop: moves are dropped until the step clock is
    /// reset (those sent before the stop was known are void).
    needs_reset: bool,
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
            count: 0,
            interval: 0,
            add: 0,
            last: 0,
            queue: heapless::Deque::new(),
            next_dir: false,
            dir: None,
            end_position: 0,
            needs_reset: false,
        }
    }

    /// `set_next_step_dir`: the direction of the moves queued next.
    pub fn set_next_dir(&mut self, positive: bool) {
        self.next_dir = positive;
    }

    /// `reset_step_clock`: the next move's first interval counts from
    /// `clock`. Only while idle.
    pub fn reset_clock(&mut self, clock: u32) {
        if self.is_idle() {
            self.last = clock;
            self.needs_reset = false;
        }
    }

    /// `queue_step`: appends a move. `now` is the current clock: a move
    /// that starts an idle stepper with its first step already past means
    /// step generation fell behind.
    pub fn queue(&mut self, interval: u32, count: u16, add: i16, now: u32) -> Result<(), Shutdown> {
        if count == 0 || self.needs_reset {
            return Ok(());
        }
        if self.is_idle() && is_before(self.last.wrapping_add(interval), now) {
            return Err(Shutdown::StepperTooFarInPast);
        }
        self.queue
            .push_back(QueuedMove {
                interval,
                count,
                add,
                dir: self.next_dir,
            })
            .map_err(|_| Shutdown::MoveQueueOverflow)
    }

    /// Free room in the move queue.
    pub fn free(&self) -> usize {
        M - self.queue.len()
    }

    /// Starts an idle stepper on its first queued move: the clock of its
    /// first step, or None if nothing is queued (or a move is active).
    pub fn start(&mut self, pins: &mut impl StepPins) -> Option<u32> {
        if self.count > 0 {
            return None;
        }
        self.load(pins, self.last)
    }

    /// The timer's work at `at`, the clock of the coming step: one step.
    /// Returns the clock of the following step of the same move; None
    /// when the move is done (then [`Self::load`] the next).
    #[inline(always)]
    pub fn step(&mut self, pins: &mut impl StepPins, at: u32) -> Option<u32> {
        pins.step();
        self.count -= 1;
        if self.count == 0 {
            return None;
        }
        let next = at.wrapping_add(self.interval);
        self.interval = self.interval.wrapping_add(self.add);
        Some(next)
    }

    /// After the move's last step at clock `last`: makes the next queued
    /// move the active one, sets the direction pin if it changes, and
    /// returns the move's first step clock (None: idle).
    #[inline(never)]
    #[cfg_attr(feature = "itcm", unsafe(link_section = ".itcm_text"))]
    pub fn load(&mut self, pins: &mut impl StepPins, last: u32) -> Option<u32> {
        self.last = last;
        let m = self.queue.pop_front()?;
        if self.dir != Some(m.dir) {
            self.dir = Some(m.dir);
            pins.set_dir(m.dir);
        }
        let add = i32::from(m.add) as u32;
        self.count = u32::from(m.count);
        self.interval = m.interval.wrapping_add(add);
        self.add = add;
        let count = i64::from(m.count);
        self.end_position += if m.dir { count } else { -count };
        Some(last.wrapping_add(m.interval))
    }

    /// True while a move has steps left.
    pub fn in_move(&self) -> bool {
        self.count > 0
    }

    /// Position in steps since start (+1 per positive step).
    pub fn position(&self) -> i64 {
        let left = i64::from(self.count);
        match self.dir {
            Some(true) => self.end_position - left,
            _ => self.end_position + left,
        }
    }

    /// True when no step is queued or in progress.
    pub fn is_idle(&self) -> bool {
        self.count == 0 && self.queue.is_empty()
    }

    /// Drops every queued move (shutdown); the position stays where the
    /// last step left it.
    pub fn stop(&mut self) {
        self.end_position = self.position();
        self.queue.clear();
        self.count = 0;
    }

    /// Stops as an endstop stops it: as [`Self::stop`], and the moves that
    /// come before the next [`Self::reset_clock`] are dropped.
    pub fn stop_until_reset(&mut self) {
        self.stop();
        self.needs_reset = true;
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
        let mut next = s.start(&mut pins);
        while let Some(clock) = next {
            pins.clock = clock;
            next = s
                .step(&mut pins, clock)
                .or_else(|| s.load(&mut pins, clock));
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

    #[test]
    fn after_an_endstop_stop_moves_wait_for_a_clock_reset() {
        let mut s = Stepper::<8>::new();
        s.set_next_dir(true);
        s.queue(100, 5, 0, 0).expect("room");
        s.stop_until_reset();
        // Sent before the stop was known: void.
        s.queue(100, 5, 0, 0).expect("accepted");
        assert!(s.is_idle());
        s.reset_clock(10_000);
        s.queue(100, 2, 0, 10_000).expect("room");
        assert_eq!(run(&mut s), [(10_100, true), (10_200, true)]);
    }
}
