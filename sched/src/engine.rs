//! The stepper interrupt's work for several steppers: commands waiting in
//! per-stepper outboxes are released to the steppers' move queues once
//! their first step is close enough for the 32-bit clock to place it (as
//! klippy holds back far steps), and every step due is made.
//!
//! The board calls [`Engine::run`] from its timer interrupt with the
//! timer's count and re-arms the timer for the clock it returns; thread
//! code fills the outboxes with [`Engine::push`].

use crate::clock::{Extender, is_before};
use crate::shutdown::Shutdown;
use crate::stepper::{StepPins, Stepper};

/// How far ahead a command is released to its stepper, ticks (a quarter
/// of the 32-bit clock's range, so comparisons stay unambiguous).
pub const RELEASE_AHEAD: u64 = 1 << 30;

/// The first 64-bit clock at which a command whose first step is at
/// `clock` may be released.
fn release_time(clock: u64) -> u64 {
    (clock + 1).saturating_sub(RELEASE_AHEAD)
}

/// A step command for one stepper, as on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Command {
    /// `set_next_step_dir`.
    Dir(bool),
    /// `queue_step`.
    Steps {
        /// Ticks to the first step.
        interval: u32,
        /// Number of steps.
        count: u16,
        /// Change of the interval after each step.
        add: i16,
    },
    /// `reset_step_clock`.
    ResetClock(u32),
}

/// The outbox is full: call again once the engine has made room.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Full;

/// `S` steppers with move queues of `M` and outboxes of `O` commands.
#[derive(Debug)]
pub struct Engine<P, const S: usize, const M: usize, const O: usize> {
    steppers: [Stepper<M>; S],
    pins: [P; S],
    /// Commands not yet released, with their first step's 64-bit clock.
    outboxes: [heapless::Deque<(Command, u64), O>; S],
    /// Clock of each stepper's next step.
    next: [Option<u32>; S],
    clock: Extender,
    shutdown: Option<Shutdown>,
    /// True when an outbox may hold a command ready for release.
    check_outboxes: bool,
    /// When a held command may next be released, 64-bit ticks.
    release_at: Option<u64>,
}

impl<P: StepPins, const S: usize, const M: usize, const O: usize> Engine<P, S, M, O> {
    /// Idle steppers driving `pins`, the clock starting at 0.
    pub fn new(pins: [P; S]) -> Self {
        Self {
            steppers: core::array::from_fn(|_| Stepper::new()),
            pins,
            outboxes: core::array::from_fn(|_| heapless::Deque::new()),
            next: [None; S],
            clock: Extender::new(0),
            shutdown: None,
            check_outboxes: false,
            release_at: None,
        }
    }

    /// Queues `cmd` for stepper `index`; `first_clock` is its first step's
    /// 64-bit clock (for a direction or reset: the clock it applies from).
    pub fn push(&mut self, index: usize, cmd: Command, first_clock: u64) -> Result<(), Full> {
        let outbox = self.outboxes.get_mut(index).ok_or(Full)?;
        if self.shutdown.is_some() {
            // Everything stopped: accept and drop.
            return Ok(());
        }
        outbox.push_back((cmd, first_clock)).map_err(|_| Full)?;
        self.check_outboxes = true;
        Ok(())
    }

    /// The 64-bit clock at timer count `now` (call at least once per
    /// wrap of the 32-bit timer).
    pub fn clock(&mut self, now: u32) -> u64 {
        self.clock.extend(now)
    }

    /// Why the engine shut down, if it did.
    pub fn shutdown_reason(&self) -> Option<Shutdown> {
        self.shutdown
    }

    /// Position of stepper `index` in steps.
    pub fn position(&self, index: usize) -> Option<i64> {
        self.steppers.get(index).map(Stepper::position)
    }

    /// The interrupt's work at timer count `now`: releases the commands
    /// now close enough, makes every step due, and returns the clock to
    /// wake at next (None: nothing queued). Outboxes are looked at only
    /// after a push, when a stepper's queue gains room, or on a wake that
    /// makes no step (the heartbeat, or a far command's release time), so
    /// that a step costs little more than the step itself.
    pub fn run(&mut self, now: u32) -> Option<u32> {
        let now64 = self.clock.extend(now);
        if self.check_outboxes || self.release_at.is_some_and(|at| now64 >= at) {
            self.check_outboxes = false;
            for i in 0..S {
                self.release(i, now, now64);
            }
            // The next time a held command may go, for steppers with room
            // (a full queue signals room itself, by finishing a move).
            self.release_at = (0..S)
                .filter(|&i| self.steppers[i].free() > 0)
                .filter_map(|i| self.outboxes[i].front())
                .map(|&(_, clock)| release_time(clock))
                .min();
        }
        let mut stepped = false;
        for i in 0..S {
            if let Some(at) = self.next[i]
                && !is_before(now, at)
            {
                stepped = true;
                self.next[i] = self.step_due(i, now);
            }
        }
        let (mut earliest, mut soonest) = (None, i32::MAX);
        for &at in self.next.iter().flatten() {
            let ahead = at.wrapping_sub(now) as i32;
            if ahead < soonest {
                (earliest, soonest) = (Some(at), ahead);
            }
        }
        if !stepped {
            // Not a step's wake (a heartbeat): look at the outboxes.
            self.check_outboxes = true;
        }
        // Also wake when a held command may be released.
        if let Some(at) = self.release_at {
            let wait = at.saturating_sub(now64).min(u64::from(u32::MAX >> 2)) as u32;
            if (wait as i32) < soonest {
                earliest = Some(now.wrapping_add(wait));
            }
        }
        earliest
    }

    /// Makes stepper `i`'s steps due at `now`; returns its next step.
    fn step_due(&mut self, i: usize, now: u32) -> Option<u32> {
        let loads = self.steppers[i].loads();
        let mut next = None;
        while let Some(at) = self.steppers[i].step(&mut self.pins[i]) {
            if is_before(now, at) {
                next = Some(at);
                break;
            }
        }
        // A finished move leaves room for a command waiting in the outbox.
        if self.steppers[i].loads() != loads && !self.outboxes[i].is_empty() {
            self.check_outboxes = true;
        }
        next
    }

    /// Moves stepper `i`'s due commands from its outbox to its queue.
    fn release(&mut self, i: usize, now: u32, now64: u64) {
        while let Some(&(cmd, clock)) = self.outboxes[i].front() {
            if now64 < release_time(clock) || self.steppers[i].free() == 0 {
                return;
            }
            self.outboxes[i].pop_front();
            let stepper = &mut self.steppers[i];
            let result = match cmd {
                Command::Dir(positive) => {
                    stepper.set_next_dir(positive);
                    Ok(())
                }
                Command::ResetClock(at) => {
                    stepper.reset_clock(at);
                    Ok(())
                }
                Command::Steps {
                    interval,
                    count,
                    add,
                } => stepper.queue(interval, count, add, now),
            };
            if let Err(reason) = result {
                self.stop(reason);
                return;
            }
            if self.next[i].is_none() {
                self.next[i] = stepper.next_step();
            }
        }
    }

    /// Stops every stepper and drops every command; the first reason stays.
    pub fn stop(&mut self, reason: Shutdown) {
        self.shutdown.get_or_insert(reason);
        self.halt();
    }

    /// Stops every stepper at once and drops their commands, without a
    /// fault (an endstop ended a homing move).
    pub fn halt(&mut self) {
        for (stepper, outbox) in self.steppers.iter_mut().zip(&mut self.outboxes) {
            stepper.stop();
            outbox.clear();
        }
        self.next = [None; S];
    }

    /// The steppers' pins.
    pub fn pins(&self) -> &[P; S] {
        &self.pins
    }

    /// The steppers' pins, to change (a simulation sets its clock there).
    pub fn pins_mut(&mut self) -> &mut [P; S] {
        &mut self.pins
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec::Vec;

    /// Records steps with the clock the test sets before each run.
    #[derive(Default)]
    struct Pins {
        now: u32,
        dir: bool,
        steps: Vec<(u32, bool)>,
    }

    impl StepPins for Pins {
        fn set_dir(&mut self, positive: bool) {
            self.dir = positive;
        }
        fn step(&mut self) {
            self.steps.push((self.now, self.dir));
        }
    }

    /// Runs the engine like a timer interrupt until `end`; returns steps.
    fn run_until(e: &mut Engine<Pins, 2, 8, 8>, end: u64) {
        let mut now64 = 0u64;
        while now64 < end {
            for p in &mut e.pins {
                p.now = now64 as u32;
            }
            let wake = e.run(now64 as u32);
            now64 = match wake {
                Some(at) => now64 + u64::from(at.wrapping_sub(now64 as u32)).max(1),
                None => end,
            };
        }
    }

    #[test]
    fn steps_of_several_steppers_come_at_their_clocks() {
        let mut e = Engine::<Pins, 2, 8, 8>::new(Default::default());
        e.push(0, Command::Dir(true), 0).expect("room");
        e.push(
            0,
            Command::Steps {
                interval: 100,
                count: 3,
                add: 0,
            },
            100,
        )
        .expect("room");
        e.push(1, Command::Dir(false), 0).expect("room");
        e.push(
            1,
            Command::Steps {
                interval: 150,
                count: 2,
                add: 10,
            },
            150,
        )
        .expect("room");
        run_until(&mut e, 10_000);
        assert_eq!(e.pins[0].steps, [(100, true), (200, true), (300, true)]);
        assert_eq!(e.pins[1].steps, [(150, false), (310, false)]);
        assert_eq!((e.position(0), e.position(1)), (Some(3), Some(-2)));
    }

    #[test]
    fn a_far_step_is_released_when_the_clock_can_place_it() {
        // 3e9 ticks ahead: more than 2^31, a wrap away for the 32-bit clock.
        let far = 3_000_000_000u64;
        let mut e = Engine::<Pins, 2, 8, 8>::new(Default::default());
        e.push(0, Command::Dir(true), 0).expect("room");
        e.push(
            0,
            Command::Steps {
                interval: far as u32,
                count: 1,
                add: 0,
            },
            far,
        )
        .expect("room");
        e.push(
            0,
            Command::Steps {
                interval: 1000,
                count: 1,
                add: 0,
            },
            far + 1000,
        )
        .expect("room");
        run_until(&mut e, far + 10_000);
        let expect = [(far as u32, true), ((far + 1000) as u32, true)];
        assert_eq!(e.pins[0].steps, expect);
        assert_eq!(e.shutdown_reason(), None);
    }

    #[test]
    fn a_late_command_shuts_everything_down() {
        let mut e = Engine::<Pins, 2, 8, 8>::new(Default::default());
        e.push(
            1,
            Command::Steps {
                interval: 100,
                count: 5,
                add: 0,
            },
            100,
        )
        .expect("room");
        e.run(5000);
        assert_eq!(e.shutdown_reason(), Some(Shutdown::StepperTooFarInPast));
        assert!(e.pins[1].steps.is_empty());
        // Afterwards everything is dropped.
        e.push(
            0,
            Command::Steps {
                interval: 100,
                count: 1,
                add: 0,
            },
            5100,
        )
        .expect("accepted");
        assert_eq!(e.run(5200), None);
    }
}
