//! The stepper interrupt's work for several steppers: commands waiting in
//! per-stepper outboxes are released to the steppers' move queues once
//! their first step is close enough for the 32-bit clock to place it (as
//! klippy holds back far steps), and every step due is made.
//!
//! The board's timer interrupt calls [`Engine::on_timer`], which runs the
//! engine ([`Engine::run`]) at the timer's count and re-arms the timer for
//! the next wake; thread code fills the outboxes with [`Engine::push`].
//!
//! Like Klipper's MCU, the engine keeps a list of timers in wake order:
//! one per stepper with a step coming, and a housekeeping timer that
//! releases commands and keeps the 64-bit clock. A step costs the pulse,
//! the next interval and one comparison to keep the list in order;
//! everything else happens once per move or in housekeeping.
//!
//! With the `itcm` feature, the functions the interrupt calls out of line
//! are linked into the `.itcm_text` section (the firmware runs them from
//! the Cortex-M7's zero-wait-state instruction TCM; `cargo xtask image`
//! checks that every function the interrupt reaches is there).

use crate::clock::{Extender, is_before};
use crate::endstop::{Check, Endstop};
use crate::shutdown::Shutdown;
// The commands `push` takes, re-exported for the engine's users.
pub use crate::step_command::StepCommand;
use crate::stepper::{StepPins, Stepper};

/// How far ahead a command is released to its stepper, ticks (a quarter
/// of the 32-bit clock's range, so comparisons stay unambiguous).
pub const RELEASE_AHEAD: u64 = 1 << 30;

/// Longest wait between housekeeping runs, ticks (the 64-bit clock needs
/// a reading at least once per wrap of the 32-bit one).
const HOUSEKEEPING_EVERY: u64 = 1 << 30;

/// Timer slots: up to 14 steppers, housekeeping and the endstop check.
const TIMERS: usize = 16;

/// A timer's number: stepper `i` is timer `i`, housekeeping is timer `S`,
/// the endstop check `S + 1`.
/// Its type keeps it below [`TIMERS`], so the step path indexes the timer
/// tables without checks.
#[rustfmt::skip]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
enum Timer { T0, T1, T2, T3, T4, T5, T6, T7, T8, T9, T10, T11, T12, T13, T14, T15 }

impl Timer {
    #[rustfmt::skip]
    const ALL: [Timer; TIMERS] = {
        use Timer::*;
        [T0, T1, T2, T3, T4, T5, T6, T7, T8, T9, T10, T11, T12, T13, T14, T15]
    };

    /// Timer `index` (below [`TIMERS`]).
    fn new(index: usize) -> Self {
        Self::ALL[index % TIMERS]
    }

    fn index(self) -> usize {
        usize::from(self as u8)
    }
}

/// Longest an idle engine leaves its timer unarmed, ticks (a push raises
/// the interrupt; housekeeping needs a run at least this often).
const IDLE_WAKE: u32 = 1 << 30;

/// The hardware timer the stepper interrupt runs from: a free-running
/// 32-bit counter with a compare that raises the interrupt.
pub trait StepTimer {
    /// Ticks within which a compare could be passed before it is set:
    /// wakes closer than this are served at once.
    const MIN_AHEAD: u32;
    /// The counter now, ticks.
    fn count(&self) -> u32;
    /// Raises the next interrupt at count `at`.
    fn set_compare(&mut self, at: u32);
}

/// True if a compare set now (at count `now`) for `at` cannot be passed
/// before it is set.
#[inline(always)]
fn far_enough<T: StepTimer>(at: u32, now: u32) -> bool {
    at.wrapping_sub(now) as i32 >= T::MIN_AHEAD as i32
}

/// The first 64-bit clock at which a command whose first step is at
/// `clock` may be released.
fn release_time(clock: u64) -> u64 {
    (clock + 1).saturating_sub(RELEASE_AHEAD)
}

/// The outbox is full: call again once the engine has made room.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Full;

/// A stepper and the pins it drives.
#[derive(Debug)]
#[repr(C)]
struct Slot<P, const M: usize> {
    stepper: Stepper<M>,
    pins: P,
}

/// Most endstops watched at once (a delta's three towers, each homing on
/// its own endstop, and a spare).
pub const WATCHES: usize = 4;

/// An endstop watched while homing.
#[derive(Debug, Clone, Copy)]
struct Watch {
    /// The stepper whose pins read it.
    stepper: usize,
    endstop: Endstop,
    /// The steppers it stops (bit `i`: stepper `i`).
    stops: u32,
    /// Clock of its trigger, not yet taken; None while it is armed.
    trigger: Option<u32>,
}

/// `S` steppers (at most 14) with move queues of `M` and outboxes of `O`
/// commands.
///
/// The fields the step path reads come first, at small offsets.
#[derive(Debug)]
#[repr(C)]
pub struct Engine<P, const S: usize, const M: usize, const O: usize> {
    /// Each queued timer's wake clock (a stepper's: its coming step).
    wakes: [u32; TIMERS],
    /// Timers in wake order, `order[..queued]`: each stepper with a step
    /// coming (its index), housekeeping (`S`), which is always there, and
    /// the endstop check (`S + 1`) while homing.
    order: [Timer; TIMERS],
    queued: usize,
    slots: [Slot<P, M>; S],
    /// Commands not yet released, with their first step's 64-bit clock.
    outboxes: [heapless::Deque<(StepCommand, u64), O>; S],
    clock: Extender,
    /// The timer count when housekeeping last ran.
    housekept: u32,
    shutdown: Option<Shutdown>,
    /// The endstops watched (armed, or triggered and not yet taken).
    watches: [Option<Watch>; WATCHES],
}

impl<P: StepPins, const S: usize, const M: usize, const O: usize> Engine<P, S, M, O> {
    /// Idle steppers driving `pins`, the clock starting at 0.
    pub fn new(pins: [P; S]) -> Self {
        const { assert!(S + 2 <= TIMERS, "at most 14 steppers") };
        let mut order = [Timer::T0; TIMERS];
        order[0] = Timer::new(S);
        Self {
            slots: pins.map(|pins| Slot {
                stepper: Stepper::new(),
                pins,
            }),
            outboxes: core::array::from_fn(|_| heapless::Deque::new()),
            order,
            queued: 1,
            wakes: [0; TIMERS],
            clock: Extender::new(0),
            housekept: 0,
            shutdown: None,
            watches: [None; WATCHES],
        }
    }

    /// Homing (Klipper's `endstop_home` with a trsync): reads the endstop
    /// on stepper `stepper`'s pins as `endstop` says; when it triggers,
    /// every stepper in `stops` (bit `i`: stepper `i`) stops at once, its
    /// queued and held commands dropped (and those pushed until its step
    /// clock is reset), and the trigger's clock is kept for
    /// [`Self::take_trigger`]. Up to [`WATCHES`] endstops are watched at
    /// once, each with its own `stops` (a delta's towers); arming another
    /// when all are taken replaces the last.
    pub fn watch_endstop(&mut self, stepper: usize, endstop: Endstop, stops: u32) {
        let watch = Watch {
            stepper,
            endstop,
            stops,
            trigger: None,
        };
        let free = self.watches.iter().position(Option::is_none);
        self.watches[free.unwrap_or(WATCHES - 1)] = Some(watch);
        self.schedule_endstops();
    }

    /// Stops watching every armed endstop (the homing move ended); the
    /// triggers not yet taken stay.
    pub fn stop_watching(&mut self) {
        for w in &mut self.watches {
            if w.is_some_and(|w| w.trigger.is_none()) {
                *w = None;
            }
        }
        self.unqueue(S + 1);
    }

    /// True while an endstop is watched.
    pub fn is_watching(&self) -> bool {
        self.watches.iter().flatten().any(|w| w.trigger.is_none())
    }

    /// An endstop trigger not yet taken, if any: the stepper whose pins
    /// read that endstop (as given to [`Self::watch_endstop`]) and the
    /// trigger's clock. Each trigger is taken once.
    pub fn take_trigger(&mut self) -> Option<(usize, u32)> {
        self.watches.iter_mut().find_map(|slot| {
            let w = (*slot)?;
            let at = w.trigger?;
            *slot = None;
            Some((w.stepper, at))
        })
    }

    /// Queues `cmd` for stepper `index`; `first_clock` is its first step's
    /// 64-bit clock (for a direction or reset: the clock it applies from).
    pub fn push(&mut self, index: usize, cmd: StepCommand, first_clock: u64) -> Result<(), Full> {
        let outbox = self.outboxes.get_mut(index).ok_or(Full)?;
        if self.shutdown.is_some() {
            // Everything stopped: accept and drop.
            return Ok(());
        }
        outbox.push_back((cmd, first_clock)).map_err(|_| Full)?;
        // Housekeeping is due (it last ran no later than now).
        self.schedule(S, self.housekept);
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
        self.slots.get(index).map(|slot| slot.stepper.position())
    }

    /// The timer interrupt's work: runs the engine until its next wake is
    /// far enough ahead to arm `timer`'s compare for it.
    #[inline(always)]
    pub fn on_timer<T: StepTimer>(&mut self, timer: &mut T) {
        // The common case, straight through: one step, and the next wake
        // far enough ahead.
        if let Some(at) = self.run(timer.count())
            && far_enough::<T>(at, timer.count())
        {
            timer.set_compare(at);
            return;
        }
        self.on_timer_rest(timer);
    }

    /// [`Self::on_timer`] when a wake was close or the engine idle.
    #[cold]
    #[inline(never)]
    #[cfg_attr(feature = "itcm", unsafe(link_section = ".itcm_text"))]
    fn on_timer_rest<T: StepTimer>(&mut self, timer: &mut T) {
        loop {
            let now = timer.count();
            let at = self.run(now).unwrap_or(now.wrapping_add(IDLE_WAKE));
            if far_enough::<T>(at, timer.count()) {
                timer.set_compare(at);
                return;
            }
        }
    }

    /// The interrupt's work at timer count `now`: the timers due, in wake
    /// order. Returns the clock to wake at next (None: nothing queued or
    /// held); when a step leaves its stepper first in line, that step's
    /// next clock, which may be due already: then call again at once.
    /// Call it at least once per 2^31 ticks.
    #[inline(always)]
    pub fn run(&mut self, now: u32) -> Option<u32> {
        // The common case, one step that leaves its stepper first in
        // line, is kept apart from the rest so that it needs few registers.
        match self.run_front(now) {
            Ok(wake) => wake,
            Err((timer, clock)) => self.run_on(now, timer, clock),
        }
    }

    /// [`Self::run`] from the slow part of timer `timer`'s work on:
    /// housekeeping; or for a stepper whose step at `clock` ended its
    /// move, the next move; or for one whose next step at `clock` is not
    /// first in line, its place in the list.
    #[cold]
    #[inline(never)]
    #[cfg_attr(feature = "itcm", unsafe(link_section = ".itcm_text"))]
    fn run_on(&mut self, now: u32, mut timer: usize, mut clock: u32) -> Option<u32> {
        loop {
            match self.slots.get(timer) {
                None if timer == S => {
                    if self.housekeeping(now) {
                        return None;
                    }
                }
                None => self.check_endstops(clock),
                Some(slot) if slot.stepper.in_move() => self.schedule(timer, clock),
                Some(_) => self.move_ended(timer, clock),
            }
            (timer, clock) = match self.run_front(now) {
                Ok(wake) => return wake,
                Err(work) => work,
            };
        }
    }

    /// Runs the front timer if it is due at `now`: Ok with the wake to
    /// return, or Err with what [`Self::run_on`] needs for the rest.
    #[inline(always)]
    fn run_front(&mut self, now: u32) -> Result<Option<u32>, (usize, u32)> {
        let timer = self.order[0].index();
        let at = self.wakes[timer];
        if is_before(now, at) {
            return Ok(Some(at));
        }
        let Some(slot) = self.slots.get_mut(timer) else {
            return Err((timer, at));
        };
        let Some(next) = slot.stepper.step(&mut slot.pins, at) else {
            return Err((timer, at));
        };
        self.wakes[timer] = next;
        // The second place is always taken while a stepper is queued (by
        // another stepper or by housekeeping): if that is not due first,
        // this stepper stays at the front.
        if is_before(next, self.wakes[self.order[1].index()]) {
            // Even if it is due already: the caller comes back at once.
            return Ok(Some(next));
        }
        Err((timer, next))
    }

    /// Stepper `index`, at the front, made the last step of its move at
    /// clock `at`: it goes on with its next move or leaves the list, and
    /// as its queue now has room, housekeeping may release more.
    #[inline(never)]
    #[cfg_attr(feature = "itcm", unsafe(link_section = ".itcm_text"))]
    fn move_ended(&mut self, index: usize, at: u32) {
        let slot = &mut self.slots[index];
        match slot.stepper.load(&mut slot.pins, at) {
            Some(first) => self.schedule(index, first),
            None => self.unqueue(index),
        }
        if !self.outboxes[index].is_empty() {
            self.schedule(S, at);
        }
    }

    /// Puts timer `timer` in the list at wake `at`, in order.
    #[inline(never)]
    #[cfg_attr(feature = "itcm", unsafe(link_section = ".itcm_text"))]
    fn schedule(&mut self, timer: usize, at: u32) {
        self.unqueue(timer);
        let at_k = self.order[..self.queued]
            .iter()
            .position(|&t| is_before(at, self.wakes[t.index()]))
            .unwrap_or(self.queued);
        self.order.copy_within(at_k..self.queued, at_k + 1);
        let timer = Timer::new(timer);
        self.order[at_k] = timer;
        self.wakes[timer.index()] = at;
        self.queued += 1;
    }

    /// Takes timer `timer` out of the list, if it is there.
    fn unqueue(&mut self, timer: usize) {
        if let Some(k) = self.order[..self.queued]
            .iter()
            .position(|&t| t.index() == timer)
        {
            self.order.copy_within(k + 1..self.queued, k);
            self.queued -= 1;
        }
    }

    /// Housekeeping at timer count `now`: extends the clock, releases the
    /// commands now close enough to steppers with room, and schedules
    /// itself for the next release or the clock's next reading. Returns
    /// true when nothing is queued or held.
    #[inline(never)]
    #[cfg_attr(feature = "itcm", unsafe(link_section = ".itcm_text"))]
    fn housekeeping(&mut self, now: u32) -> bool {
        let now64 = self.clock.extend(now);
        self.housekept = now;
        for i in 0..S {
            self.release(i, now, now64);
        }
        // A full queue signals room itself, when a move ends.
        let release_at = (0..S)
            .filter(|&i| self.slots[i].stepper.free() > 0)
            .filter_map(|i| self.outboxes[i].front())
            .map(|&(_, clock)| release_time(clock))
            .min();
        let next = release_at
            .unwrap_or(u64::MAX)
            .min(now64 + HOUSEKEEPING_EVERY)
            .max(now64 + 1);
        self.schedule(S, next as u32);
        self.queued == 1 && self.outboxes.iter().all(|o| o.is_empty())
    }

    /// Reads the armed endstops whose reading is due at clock `now`: on a
    /// trigger the steppers that endstop stops stop; the check is then
    /// scheduled for the next reading of those still armed.
    #[inline(never)]
    #[cfg_attr(feature = "itcm", unsafe(link_section = ".itcm_text"))]
    fn check_endstops(&mut self, now: u32) {
        for k in 0..WATCHES {
            let Some(mut watch) = self.watches[k] else {
                continue;
            };
            if watch.trigger.is_some() || !watch.endstop.is_due(now) {
                continue;
            }
            let pressed = self
                .slots
                .get_mut(watch.stepper)
                .is_some_and(|slot| slot.pins.endstop_triggered());
            if let Check::Triggered(at) = watch.endstop.read(pressed) {
                watch.trigger = Some(at);
                self.stop_steppers(watch.stops);
            }
            self.watches[k] = Some(watch);
        }
        self.schedule_endstops();
    }

    /// Schedules the endstop check for the earliest reading of the armed
    /// endstops (none armed: no check).
    #[cfg_attr(feature = "itcm", unsafe(link_section = ".itcm_text"))]
    fn schedule_endstops(&mut self) {
        let mut next: Option<u32> = None;
        for w in &self.watches {
            if let Some(Watch {
                endstop,
                trigger: None,
                ..
            }) = w
                && next.is_none_or(|n| is_before(endstop.next(), n))
            {
                next = Some(endstop.next());
            }
        }
        match next {
            Some(at) => self.schedule(S + 1, at),
            None => self.unqueue(S + 1),
        }
    }

    /// Stops stepper `i` at once and drops its commands, and those that
    /// come until its step clock is reset.
    fn stop_stepper(&mut self, i: usize) {
        if let (Some(slot), Some(outbox)) = (self.slots.get_mut(i), self.outboxes.get_mut(i)) {
            slot.stepper.stop_until_reset();
            outbox.clear();
            self.unqueue(i);
        }
    }

    /// Moves stepper `i`'s due commands from its outbox to its queue.
    fn release(&mut self, i: usize, now: u32, now64: u64) {
        while let Some(&(cmd, clock)) = self.outboxes[i].front() {
            if now64 < release_time(clock) || self.slots[i].stepper.free() == 0 {
                return;
            }
            self.outboxes[i].pop_front();
            let Slot { stepper, pins } = &mut self.slots[i];
            let was_idle = stepper.is_idle();
            let result = match cmd {
                StepCommand::Dir(positive) => {
                    stepper.set_next_dir(positive);
                    Ok(())
                }
                StepCommand::ResetClock(at) => {
                    stepper.reset_clock(at);
                    Ok(())
                }
                StepCommand::Steps {
                    interval,
                    count,
                    add,
                } => stepper.queue(interval, count, add, now),
            };
            if let Err(reason) = result {
                self.stop(reason);
                return;
            }
            if was_idle && let Some(first) = stepper.start(pins) {
                self.schedule(i, first);
            }
        }
    }

    /// Stops every stepper and drops every command; the first reason stays.
    #[cfg_attr(feature = "itcm", unsafe(link_section = ".itcm_text"))]
    pub fn stop(&mut self, reason: Shutdown) {
        self.shutdown.get_or_insert(reason);
        self.stop_watching();
        self.halt();
    }

    /// Leaves a shutdown (FIRMWARE_RESTART): every stepper idle with no
    /// command, no endstop watched, no fault; the clock runs on, and the
    /// next commands start from a step clock reset as after start-up.
    pub fn restart(&mut self) {
        self.stop_watching();
        for i in 0..S {
            self.stop_stepper(i);
            self.slots[i].stepper = Stepper::new();
        }
        self.watches = [None; WATCHES];
        self.shutdown = None;
    }

    /// Stops every stepper at once and drops their commands, and those
    /// that come until each one's step clock is reset, without a fault (an
    /// endstop ended a homing move).
    pub fn halt(&mut self) {
        for i in 0..S {
            self.stop_stepper(i);
        }
    }

    /// A trsync triggered (a watched endstop here, or another MCU's relayed
    /// by the host): every stepper in `stops` (bit `i`: stepper `i`) stops
    /// at once, as Klipper's `trsync_do_trigger` stops the steppers tied
    /// to it; their
    /// queued and held commands are dropped, and those that come until
    /// each one's step clock is reset. No fault; a watched endstop stays
    /// armed ([`Self::stop_watching`] disarms it). In ITCM: the
    /// interrupt's endstop check calls it when thread code does too.
    #[cfg_attr(feature = "itcm", unsafe(link_section = ".itcm_text"))]
    pub fn stop_steppers(&mut self, stops: u32) {
        for i in (0..S).filter(|i| stops & (1 << i) != 0) {
            self.stop_stepper(i);
        }
    }

    /// The steppers' pins, in stepper order.
    pub fn pins(&self) -> impl Iterator<Item = &P> {
        self.slots.iter().map(|slot| &slot.pins)
    }

    /// The steppers' pins, to change (a simulation sets its clock there).
    pub fn pins_mut(&mut self) -> impl Iterator<Item = &mut P> {
        self.slots.iter_mut().map(|slot| &mut slot.pins)
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec::Vec;

    /// Records steps with the clock the test sets before each run; its
    /// endstop reads pressed from the `endstop_at`th step on.
    #[derive(Default)]
    struct Pins {
        now: u32,
        dir: bool,
        steps: Vec<(u32, bool)>,
        endstop_at: Option<usize>,
    }

    impl StepPins for Pins {
        fn set_dir(&mut self, positive: bool) {
            self.dir = positive;
        }
        fn step(&mut self) {
            self.steps.push((self.now, self.dir));
        }
        fn endstop_triggered(&mut self) -> bool {
            self.endstop_at.is_some_and(|n| self.steps.len() >= n)
        }
    }

    /// Runs the engine like a timer interrupt until `end`; returns steps.
    fn run_until<const S: usize>(e: &mut Engine<Pins, S, 8, 8>, end: u64) {
        let mut now64 = 0u64;
        while now64 < end {
            for p in e.pins_mut() {
                p.now = now64 as u32;
            }
            let wake = e.run(now64 as u32);
            now64 = match wake {
                // A wake already due: run again at once.
                Some(at) => now64 + (at.wrapping_sub(now64 as u32) as i32).max(0) as u64,
                None => end,
            };
        }
    }

    #[test]
    fn steps_of_several_steppers_come_at_their_clocks() {
        let mut e = Engine::<Pins, 2, 8, 8>::new(Default::default());
        e.push(0, StepCommand::Dir(true), 0).expect("room");
        e.push(
            0,
            StepCommand::Steps {
                interval: 100,
                count: 3,
                add: 0,
            },
            100,
        )
        .expect("room");
        e.push(1, StepCommand::Dir(false), 0).expect("room");
        e.push(
            1,
            StepCommand::Steps {
                interval: 150,
                count: 2,
                add: 10,
            },
            150,
        )
        .expect("room");
        run_until(&mut e, 10_000);
        assert_eq!(
            e.slots[0].pins.steps,
            [(100, true), (200, true), (300, true)]
        );
        assert_eq!(e.slots[1].pins.steps, [(150, false), (310, false)]);
        assert_eq!((e.position(0), e.position(1)), (Some(3), Some(-2)));
    }

    #[test]
    fn a_far_step_is_released_when_the_clock_can_place_it() {
        // 3e9 ticks ahead: more than 2^31, a wrap away for the 32-bit clock.
        let far = 3_000_000_000u64;
        let mut e = Engine::<Pins, 2, 8, 8>::new(Default::default());
        e.push(0, StepCommand::Dir(true), 0).expect("room");
        e.push(
            0,
            StepCommand::Steps {
                interval: far as u32,
                count: 1,
                add: 0,
            },
            far,
        )
        .expect("room");
        e.push(
            0,
            StepCommand::Steps {
                interval: 1000,
                count: 1,
                add: 0,
            },
            far + 1000,
        )
        .expect("room");
        run_until(&mut e, far + 10_000);
        let expect = [(far as u32, true), ((far + 1000) as u32, true)];
        assert_eq!(e.slots[0].pins.steps, expect);
        assert_eq!(e.shutdown_reason(), None);
    }

    #[test]
    fn a_late_command_shuts_everything_down() {
        let mut e = Engine::<Pins, 2, 8, 8>::new(Default::default());
        e.push(
            1,
            StepCommand::Steps {
                interval: 100,
                count: 5,
                add: 0,
            },
            100,
        )
        .expect("room");
        e.run(5000);
        assert_eq!(e.shutdown_reason(), Some(Shutdown::StepperTooFarInPast));
        assert!(e.slots[1].pins.steps.is_empty());
        // Afterwards everything is dropped.
        e.push(
            0,
            StepCommand::Steps {
                interval: 100,
                count: 1,
                add: 0,
            },
            5100,
        )
        .expect("accepted");
        let heartbeat = e.run(5200).expect("housekeeping");
        assert_eq!(e.run(heartbeat), None, "idle");
        assert!(e.pins().all(|p| p.steps.is_empty()));
    }

    #[test]
    fn random_moves_of_four_steppers_step_exactly_across_clock_wraps() {
        let mut rng = 0x2545_f491u32;
        let mut next = move |n: u32| {
            rng ^= rng << 13;
            rng ^= rng >> 17;
            rng ^= rng << 5;
            rng % n
        };
        // Each stepper's commands with their first step's 64-bit clock,
        // and the steps they must make.
        let mut plans: Vec<Vec<(StepCommand, u64)>> = Vec::new();
        let mut expected: Vec<Vec<(u32, bool)>> = Vec::new();
        for _ in 0..4 {
            let (mut cmds, mut steps) = (Vec::new(), Vec::new());
            let (mut last, mut dir) = (0u64, false);
            for _ in 0..60 {
                if next(3) == 0 {
                    dir = !dir;
                    cmds.push((StepCommand::Dir(dir), last));
                }
                let (interval, count) = (200 + next(2_000_000), 1 + next(200) as u16);
                let add = next(41) as i16 - 20;
                let mut clock = last + u64::from(interval);
                cmds.push((
                    StepCommand::Steps {
                        interval,
                        count,
                        add,
                    },
                    clock,
                ));
                let mut step = interval;
                for k in 0..count {
                    if k > 0 {
                        step = step.wrapping_add(add as u32);
                        clock += u64::from(step);
                    }
                    steps.push((clock as u32, dir));
                }
                last = clock;
            }
            plans.push(cmds);
            expected.push(steps);
        }
        assert!(expected.iter().any(|s| s.len() > 4000), "crosses wraps");
        let mut e = Engine::<Pins, 4, 8, 8>::new(Default::default());
        let mut sent = [0usize; 4];
        let mut now64 = 0u64;
        loop {
            // Fill the outboxes as thread code does, in time order.
            for (i, plan) in plans.iter().enumerate() {
                while let Some(&(cmd, clock)) = plan.get(sent[i]) {
                    if e.push(i, cmd, clock).is_err() {
                        break;
                    }
                    sent[i] += 1;
                }
            }
            for p in e.pins_mut() {
                p.now = now64 as u32;
            }
            match e.run(now64 as u32) {
                Some(at) => now64 += (at.wrapping_sub(now64 as u32) as i32).max(0) as u64,
                None if sent.iter().zip(&plans).all(|(&n, p)| n == p.len()) => break,
                None => {}
            }
        }
        assert_eq!(e.shutdown_reason(), None);
        assert!(now64 > 1 << 32, "ran across a clock wrap");
        for (i, steps) in expected.iter().enumerate() {
            assert_eq!(e.slots[i].pins.steps, *steps, "stepper {i}");
            let position: i64 = steps.iter().map(|s| if s.1 { 1 } else { -1 }).sum();
            assert_eq!(e.position(i), Some(position));
        }
    }

    #[test]
    fn an_endstop_stops_the_steppers_of_its_homing_move_only() {
        let mut e = Engine::<Pins, 3, 8, 8>::new(Default::default());
        // Steppers 0 and 1 home together (a corexy X), at 1000 ticks a
        // step; stepper 2 moves on its own.
        for i in 0..3 {
            e.push(i, StepCommand::Dir(true), 0).expect("room");
            let steps = StepCommand::Steps {
                interval: 1000,
                count: 500,
                add: 0,
            };
            e.push(i, steps, 1000).expect("room");
        }
        e.slots[0].pins.endstop_at = Some(120);
        // Read every 700 ticks; a press must be seen 3 times, 50 apart.
        e.watch_endstop(0, Endstop::home(0, 50, 3, 700), 0b011);
        run_until(&mut e, 1_000_000);
        let (endstop, trigger) = e.take_trigger().expect("triggered");
        assert_eq!(endstop, 0);
        assert_eq!(e.take_trigger(), None, "taken once");
        assert!(!e.is_watching());
        // Pressed at the 120th step (clock 120000): the next reading and
        // two confirmations 50 ticks apart.
        assert!((120_000..=120_800).contains(&trigger), "{trigger}");
        for i in 0..2 {
            let made = e.slots[i].pins.steps.len();
            assert!((120..=121).contains(&made), "stepper {i} made {made}");
            assert!(e.slots[i].pins.steps.iter().all(|s| s.0 <= trigger));
            assert_eq!(e.position(i), Some(made as i64));
        }
        assert_eq!(e.slots[2].pins.steps.len(), 500, "not in the homing move");
        assert_eq!(e.shutdown_reason(), None);
    }

    #[test]
    fn an_endstop_never_pressed_leaves_the_move_whole() {
        let mut e = Engine::<Pins, 2, 8, 8>::new(Default::default());
        e.push(0, StepCommand::Dir(false), 0).expect("room");
        let steps = StepCommand::Steps {
            interval: 1000,
            count: 300,
            add: 0,
        };
        e.push(0, steps, 1000).expect("room");
        e.watch_endstop(0, Endstop::home(0, 50, 3, 700), 0b01);
        run_until(&mut e, 400_000);
        assert_eq!(e.slots[0].pins.steps.len(), 300);
        assert_eq!(e.take_trigger(), None);
        assert!(e.is_watching());
        e.stop_watching();
        assert!(!e.is_watching());
    }

    #[test]
    fn each_tower_endstop_stops_its_own_stepper_and_the_others_go_on() {
        // A delta's towers: each stepper reads its own endstop, pressed at
        // its 100th, 250th and 400th step; each trigger stops that stepper
        // alone.
        let mut e = Engine::<Pins, 4, 8, 8>::new(Default::default());
        let pressed_at = [100, 250, 400];
        for i in 0..4 {
            e.push(i, StepCommand::Dir(true), 0).expect("room");
            let steps = StepCommand::Steps {
                interval: 1000,
                count: 600,
                add: 0,
            };
            e.push(i, steps, 1000).expect("room");
        }
        for (i, &n) in pressed_at.iter().enumerate() {
            e.slots[i].pins.endstop_at = Some(n);
            e.watch_endstop(i, Endstop::home(500, 50, 3, 700), 1 << i);
        }
        assert!(e.is_watching());
        run_until(&mut e, 2_000_000);
        let mut triggers = Vec::new();
        while let Some(t) = e.take_trigger() {
            triggers.push(t);
        }
        assert!(!e.is_watching());
        triggers.sort_by_key(|t| t.1);
        let order: Vec<usize> = triggers.iter().map(|t| t.0).collect();
        assert_eq!(order, [0, 1, 2], "each tower once, in the order pressed");
        for (&(i, trigger), &n) in triggers.iter().zip(&pressed_at) {
            let pressed = n as u32 * 1000;
            assert!(
                (pressed..=pressed + 800).contains(&trigger),
                "tower {i}: {trigger}"
            );
            let made = e.slots[i].pins.steps.len();
            assert!((n..=n + 1).contains(&made), "tower {i} made {made}");
            assert!(e.slots[i].pins.steps.iter().all(|s| s.0 <= trigger));
        }
        // The others went on after the first trigger; stepper 3 (no
        // endstop) made its whole move.
        assert!(e.slots[2].pins.steps.len() > e.slots[0].pins.steps.len());
        assert_eq!(e.slots[3].pins.steps.len(), 600);
        // A stopped stepper drops what comes until its clock is reset.
        let more = StepCommand::Steps {
            interval: 1000,
            count: 5,
            add: 0,
        };
        e.push(0, more, 2_100_000).expect("accepted");
        run_until(&mut e, 2_200_000);
        assert_eq!(e.slots[0].pins.steps.len(), 100, "dropped before a reset");
        e.push(0, StepCommand::ResetClock(2_300_000), 2_300_000)
            .expect("room");
        e.push(0, more, 2_301_000).expect("room");
        run_until(&mut e, 2_400_000);
        assert_eq!(e.slots[0].pins.steps.len(), 105, "steps again after it");
        assert_eq!(e.shutdown_reason(), None);
    }

    #[test]
    fn watches_are_disarmed_together_and_untaken_triggers_stay() {
        let mut e = Engine::<Pins, 3, 8, 8>::new(Default::default());
        for i in 0..2 {
            e.push(i, StepCommand::Dir(true), 0).expect("room");
            let steps = StepCommand::Steps {
                interval: 1000,
                count: 50,
                add: 0,
            };
            e.push(i, steps, 1000).expect("room");
        }
        e.slots[1].pins.endstop_at = Some(10);
        e.watch_endstop(0, Endstop::home(0, 50, 3, 700), 0b01);
        e.watch_endstop(1, Endstop::home(0, 50, 3, 700), 0b10);
        run_until(&mut e, 100_000);
        // Stepper 0's endstop never triggered: its move ran whole.
        assert_eq!(e.slots[0].pins.steps.len(), 50);
        assert!((10..=11).contains(&e.slots[1].pins.steps.len()));
        assert!(e.is_watching());
        e.stop_watching();
        assert!(!e.is_watching());
        let (endstop, _) = e.take_trigger().expect("kept");
        assert_eq!(endstop, 1);
        assert_eq!(e.take_trigger(), None);
    }

    #[test]
    fn a_trigger_from_another_mcu_stops_the_steppers_of_its_mask_until_reset() {
        let mut e = Engine::<Pins, 3, 8, 8>::new(Default::default());
        for i in 0..3 {
            e.push(i, StepCommand::Dir(true), 0).expect("room");
            let steps = StepCommand::Steps {
                interval: 1000,
                count: 500,
                add: 0,
            };
            e.push(i, steps, 1000).expect("room");
        }
        // Stepper 1 waits for its endstop; the trigger comes from elsewhere.
        e.watch_endstop(1, Endstop::home(0, 50, 3, 700), 0b010);
        run_until(&mut e, 100_500);
        e.stop_steppers(0b101);
        run_until(&mut e, 1_000_000);
        for i in [0, 2] {
            assert_eq!(e.slots[i].pins.steps.len(), 100, "stepper {i}");
            assert_eq!(e.position(i), Some(100));
        }
        assert_eq!(e.slots[1].pins.steps.len(), 500, "not in the mask");
        assert!(e.is_watching(), "its endstop is not disarmed");
        assert_eq!(e.take_trigger(), None, "no trigger of its own");
        assert_eq!(e.shutdown_reason(), None);
        // Commands before a reset are dropped; after it they run.
        let one = StepCommand::Steps {
            interval: 1000,
            count: 1,
            add: 0,
        };
        e.push(0, one, 1_001_000).expect("room");
        e.push(0, StepCommand::ResetClock(1_100_000), 1_100_000)
            .expect("room");
        e.push(0, one, 1_101_000).expect("room");
        run_until(&mut e, 1_200_000);
        assert_eq!(e.slots[0].pins.steps.len(), 101);
        assert_eq!(e.slots[0].pins.steps[100].0, 1_101_000);
    }
}
