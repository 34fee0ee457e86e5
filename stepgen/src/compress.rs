//! Step clocks to `(interval, count, add)` sequences, as the MCU executes
//! them: `count` steps, each `interval` ticks after the previous, `interval`
//! growing by `add` after each step.
//!
//! Every step may be scheduled up to `max_error` ticks early, never late
//! (nor earlier than half-way to the previous step), so a compressed step
//! is within `[t - max_error, t]` of its ideal clock `t`. For each sequence
//! the longest run is sought by bisecting on `add`, as Klipper does, over
//! a bounded queue of steps; a run that takes every queued step stays open
//! and the steps that follow join it while they fit (no step is stored
//! for that), so runs are not bounded by the queue. A run that stops at a
//! step it cannot take is ended where its steps had not yet drifted to the
//! early edge of their windows, which leaves the next run a better start.
//! Two filters come first: a step followed within 750 µs by a step back
//! cancels both (step+dir+step), and a step 3·2^28 ticks or more after the
//! last one sent is sent alone, once the steps before it are (the MCU's
//! 32-bit clock wraps; as Klipper does).

/// A step reversed within this time cancels the step before it, s.
pub const SDS_FILTER_TIME: f64 = 0.000_750;
/// Steps this many ticks or more after the last one sent are sent alone.
pub const CLOCK_DIFF_MAX: u64 = 3 << 28;
/// The MCU's limit on steps per sequence.
pub const MAX_COUNT: usize = 0xffff;
/// How early the last step of a run that stops at a step it cannot take
/// may be scheduled, as a fraction (numerator, denominator) of max_error:
/// see [`Compressor::trimmed`].
const END_DRIFT: (i64, i64) = (7, 8);
/// Bound of the add search around a valid add (`(6 + 4√2)·max_error /
/// count²` in theory; 11 is what works in practice).
const QUADRATIC_DEV: i32 = 11;

// What the compressor produces, in order (each with the 64-bit clock of
// its first step); re-exported for the compressor's users.
pub use onechip_sched::step_command::StepCommand;

/// Acceptable range of one step, in ticks after the last sent step: 32
/// bits, as unsent steps lie less than `CLOCK_DIFF_MAX` (3·2^28) ticks
/// after it, and 32-bit arithmetic is native on the MCU.
#[derive(Debug, Clone, Copy)]
struct Window {
    min: i32,
    max: i32,
}

/// Step clocks waiting for compression, contiguous in a buffer of `Q`
/// that holds at most `Q / 2`: sending a sequence from the front moves
/// nothing, and the queue slides back to the buffer's start only when it
/// reaches the end (at most once per `Q / 2` steps appended). A step takes
/// 6 bytes: the low 32 bits of its clock (the steps lie less than
/// [`CLOCK_DIFF_MAX`] after the last one sent, which gives the rest) and
/// its allowed error.
#[derive(Debug, Clone)]
struct Steps<const Q: usize> {
    clocks: [u32; Q],
    /// Each step's allowed error given the step before it, ticks.
    errors: [u16; Q],
    head: usize,
    len: usize,
    /// The newest queued clock, whole (while `len > 0`).
    newest: u64,
}

impl<const Q: usize> Steps<Q> {
    const fn new() -> Self {
        Self {
            clocks: [0; Q],
            errors: [0; Q],
            head: 0,
            len: 0,
            newest: 0,
        }
    }

    fn len(&self) -> usize {
        self.len
    }

    fn is_full(&self) -> bool {
        self.len >= Q / 2
    }

    /// The queued clocks' low 32 bits and their errors, front first.
    fn queued(&self) -> (&[u32], &[u16]) {
        let range = self.head..self.head + self.len;
        (&self.clocks[range.clone()], &self.errors[range])
    }

    /// The low 32 bits of the front clock.
    fn front(&self) -> Option<u32> {
        self.queued().0.first().copied()
    }

    fn last(&self) -> Option<u64> {
        (self.len > 0).then_some(self.newest)
    }

    /// Appends unless full.
    fn push(&mut self, clock: u64, error: u16) {
        if self.is_full() {
            return;
        }
        if self.head + self.len >= Q {
            let range = self.head..Q;
            self.clocks.copy_within(range.clone(), 0);
            self.errors.copy_within(range, 0);
            self.head = 0;
        }
        let at = self.head + self.len;
        if let (Some(c), Some(e)) = (self.clocks.get_mut(at), self.errors.get_mut(at)) {
            (*c, *e) = (clock as u32, error);
            self.len += 1;
            self.newest = clock;
        }
    }

    /// Removes `count` clocks (at most all) from the front.
    fn drop_front(&mut self, count: usize) {
        let count = count.min(self.len);
        self.head += count;
        self.len -= count;
        if self.len == 0 {
            self.head = 0;
        }
    }
}

/// The step+dir+step filter's window on a `freq` Hz clock: the ticks
/// strictly below [`SDS_FILTER_TIME`], the ceiling of it.
fn sds_ticks(freq: f64) -> u64 {
    let sds = SDS_FILTER_TIME * freq;
    let whole = to_clock(sds);
    if (whole as f64) < sds {
        whole + 1
    } else {
        whole
    }
}

/// A run of steps as the MCU executes one sequence: `count` steps after
/// the last sent one, the first `interval` ticks after it, each next gap
/// `add` ticks longer than the one before. Every interval in
/// `[min_interval, max_interval]` keeps each of its steps within its
/// window; it is sent with `max_interval` (its steps as late as allowed).
#[derive(Debug, Clone, Copy)]
struct Run {
    min_interval: i32,
    max_interval: i32,
    /// Steps, 1..=[`MAX_COUNT`].
    count: i32,
    add: i32,
}

impl Run {
    /// Ticks from the last sent step to the run's `k`th step (sent with
    /// `max_interval`).
    fn reach(&self, k: i32) -> i64 {
        let (k, add) = (i64::from(k), i64::from(self.add));
        i64::from(self.max_interval) * k + add * (k * (k - 1) / 2)
    }
}

/// The newest run, compressed but not sent: the steps that follow join it
/// while an interval still keeps each of its steps within its window with
/// the same add, so a run can be far longer than the step queue. There is
/// one only while the queue is empty.
#[derive(Debug, Clone, Copy)]
struct Open {
    run: Run,
    /// `add · count(count-1)/2`: how far the adds move its last step,
    /// ticks.
    adds: i64,
    /// Ideal clocks of its first and last steps.
    first: u64,
    last: u64,
}

impl Open {
    /// Takes the step at ideal clock `clock`, whose window is `w` (ticks
    /// after the last sent step), as the run's next step if it fits: true
    /// if it did.
    fn join(&mut self, clock: u64, w: Window) -> bool {
        let run = &mut self.run;
        if run.count >= MAX_COUNT as i32 {
            return false;
        }
        // The step would be at interval·count + adds after the last sent
        // step (64-bit sums: a misfit's may leave 32 bits).
        let count = run.count + 1;
        let adds = self.adds + i64::from(run.add) * i64::from(run.count);
        let (Ok(lowest), Ok(highest)) = (
            i32::try_from(i64::from(w.min) - adds),
            i32::try_from(i64::from(w.max) - adds),
        ) else {
            return false;
        };
        let (mut min, mut max) = (run.min_interval, run.max_interval);
        if i64::from(min) * i64::from(count) < i64::from(lowest) {
            min = div_ceil(lowest, count);
        }
        if i64::from(max) * i64::from(count) > i64::from(highest) {
            max = highest.div_euclid(count);
        }
        if min > max {
            return false;
        }
        (run.min_interval, run.max_interval, run.count) = (min, max, count);
        (self.adds, self.last) = (adds, clock);
        true
    }
}

/// Compression state of one stepper: up to `Q / 2` queued steps (6 bytes
/// each) and an open run.
///
/// Invariants: there is an open run only while the queue is empty; every
/// step not sent yet lies less than [`CLOCK_DIFF_MAX`] ticks after the last
/// one sent (so its window fits 32 bits).
#[derive(Debug, Clone)]
pub struct Compressor<const Q: usize> {
    /// At most 65535 (25 µs up to a 2.6 GHz clock), ticks.
    max_error: u32,
    freq: f64,
    /// Steps closer than this many ticks to a reversed one are filtered.
    sds_ticks: u64,
    /// Clock of the last step sent (as scheduled), ticks.
    last_step_clock: u64,
    queue: Steps<Q>,
    open: Option<Open>,
    dir: Option<bool>,
    /// The newest step, held back until the next shows it is not reversed.
    held: Option<(u64, bool)>,
}

impl<const Q: usize> Compressor<Q> {
    /// A compressor for an MCU clock of `freq` Hz with `max_error` ticks
    /// (at most 65535 are used).
    pub fn new(max_error: u32, freq: f64) -> Self {
        Self {
            max_error: max_error.min(u32::from(u16::MAX)),
            freq,
            sds_ticks: sds_ticks(freq),
            last_step_clock: 0,
            queue: Steps::new(),
            open: None,
            dir: None,
            held: None,
        }
    }

    /// Counts time on another clock from now on: `freq` Hz, `max_error`
    /// ticks (a secondary MCU's clock, re-fitted as it drifts). Steps
    /// already appended keep the clocks they were given.
    pub fn set_clock(&mut self, freq: f64, max_error: u32) {
        self.freq = freq;
        self.max_error = max_error;
        self.sds_ticks = sds_ticks(freq);
    }

    /// The clock this compressor counts on, Hz.
    pub fn freq(&self) -> f64 {
        self.freq
    }

    /// The clock of time `time` (s from its clock 0), ticks.
    pub fn clock_at(&self, time: f64) -> u64 {
        to_clock(time * self.freq + 0.5)
    }

    /// Adds a step at print time `time` s in direction `dir`. Commands go
    /// to `out` with the 64-bit clock of their first step (for a direction
    /// change: of the last step before it), which the 32-bit interval of
    /// a far step does not carry.
    #[inline(never)]
    pub fn append(&mut self, time: f64, dir: bool, out: &mut impl FnMut(StepCommand, u64)) {
        let clock = to_clock(time * self.freq + 0.5);
        if let Some((held_clock, held_dir)) = self.held {
            if dir != held_dir && clock.saturating_sub(held_clock) < self.sds_ticks {
                // Step, reverse, step back: neither step is needed.
                self.held = None;
                return;
            }
            self.commit(held_clock, held_dir, out);
        }
        self.held = Some((clock, dir));
    }

    /// Sends the commands of every step before print time `time` (s),
    /// keeping later ones to compress with the steps that follow them (the
    /// last command sent may cover some of those). Every step before print
    /// time `generated` (s), which is later than `time` by more than the
    /// step+dir+step filter's window, has been appended.
    pub fn flush_until(
        &mut self,
        time: f64,
        generated: f64,
        out: &mut impl FnMut(StepCommand, u64),
    ) {
        // The step held back is a step for good once no step can come
        // within the filter's window after it: it may join a run.
        let clock = to_clock(time * self.freq);
        let decided = to_clock(generated * self.freq).saturating_sub(self.sds_ticks);
        if let Some((held_clock, held_dir)) = self.held
            && held_clock < decided.max(clock)
        {
            self.held = None;
            self.commit(held_clock, held_dir, out);
        }
        while self.first_unsent().is_some_and(|c| c < clock) {
            self.send_next(out);
        }
    }

    /// Forgets every step not yet sent (a homing move cut short by its
    /// endstop) and counts the next from `clock`, which the stepper is told
    /// with [`StepCommand::ResetClock`] (its low 32 bits, the MCU's clock),
    /// also sent to `out` with the whole 64-bit `clock`.
    pub fn reset(&mut self, clock: u64, out: &mut impl FnMut(StepCommand, u64)) {
        self.queue.drop_front(self.queue.len());
        self.open = None;
        self.held = None;
        self.dir = None;
        self.last_step_clock = clock;
        out(StepCommand::ResetClock(clock as u32), clock);
    }

    /// Sends every step not sent yet (the end of the motion, or before a
    /// pause).
    pub fn flush(&mut self, out: &mut impl FnMut(StepCommand, u64)) {
        if let Some((clock, dir)) = self.held.take() {
            self.commit(clock, dir, out);
        }
        self.send_all(out);
    }

    /// Takes a step for good: into the open run if it fits, else queued
    /// (or sent alone if far).
    #[inline(always)]
    fn commit(&mut self, clock: u64, dir: bool, out: &mut impl FnMut(StepCommand, u64)) {
        if self.dir != Some(dir) {
            self.send_all(out);
            out(StepCommand::Dir(dir), self.last_step_clock);
            self.dir = Some(dir);
        }
        // Windows are 32-bit offsets from the last sent step: runs go out
        // until it is near enough, or else the step goes alone.
        while clock >= self.last_step_clock + CLOCK_DIFF_MAX && self.first_unsent().is_some() {
            self.send_next(out);
        }
        if clock >= self.last_step_clock + CLOCK_DIFF_MAX {
            self.send_far(clock, out);
            return;
        }
        if self.queue.is_full() {
            self.send_next(out);
        }
        if let Some(open) = self.open {
            // The queue is empty: the step may be the open run's next.
            let window = self.window(clock, open.last);
            if self.open.as_mut().is_some_and(|o| o.join(clock, window)) {
                return;
            }
            self.send_open(out);
        }
        // (For the front step the error is worked out again from the last
        // sent step.)
        let previous = self.queue.last().unwrap_or(self.last_step_clock);
        self.queue.push(clock, self.step_error(clock, previous));
    }

    /// Sends the step at `clock`, [`CLOCK_DIFF_MAX`] or more after the last
    /// one sent, alone; its 32-bit interval is the gap's low bits.
    fn send_far(&mut self, clock: u64, out: &mut impl FnMut(StepCommand, u64)) {
        out(
            StepCommand::Steps {
                interval: clock.wrapping_sub(self.last_step_clock) as u32,
                count: 1,
                add: 0,
            },
            clock,
        );
        self.last_step_clock = clock;
    }

    /// The error allowed to a step at `clock` after one at `previous`
    /// (less than [`CLOCK_DIFF_MAX`] before it): half their gap, at most
    /// max_error, ticks.
    fn step_error(&self, clock: u64, previous: u64) -> u16 {
        ((clock.wrapping_sub(previous) as u32) / 2).min(self.max_error) as u16
    }

    /// The acceptable window of a step at `clock` after one at `previous`,
    /// in ticks after the last sent step.
    fn window(&self, clock: u64, previous: u64) -> Window {
        let point = clock.wrapping_sub(self.last_step_clock) as u32;
        Window {
            min: (point - u32::from(self.step_error(clock, previous))) as i32,
            max: point as i32,
        }
    }

    /// The acceptable window of the front queued step (its error is half
    /// its gap to the last sent step, at most max_error).
    fn first_window(&self) -> Window {
        let base = self.last_step_clock as u32;
        let point = self.queue.front().map_or(0, |low| low.wrapping_sub(base));
        let error = (point / 2).min(self.max_error);
        Window {
            min: (point - error) as i32,
            max: point as i32,
        }
    }

    /// The ideal clock of the first step not sent yet (the open run's or
    /// the front queued step's).
    fn first_unsent(&self) -> Option<u64> {
        match &self.open {
            Some(open) => Some(open.first),
            None => self.queue.front().map(|low| {
                let base = self.last_step_clock;
                base + u64::from(low.wrapping_sub(base as u32))
            }),
        }
    }

    fn send_all(&mut self, out: &mut impl FnMut(StepCommand, u64)) {
        while self.first_unsent().is_some() {
            self.send_next(out);
        }
    }

    /// Sends the next run: the open one, else the longest from the front
    /// of the queue, which instead stays open if it took every queued
    /// step.
    fn send_next(&mut self, out: &mut impl FnMut(StepCommand, u64)) {
        if self.open.is_some() {
            self.send_open(out);
            return;
        }
        let (Some(first), Some(last)) = (self.first_unsent(), self.queue.last()) else {
            return;
        };
        let run = self.best_run();
        if run.count as usize >= self.queue.len() {
            let c = i64::from(run.count);
            self.open = Some(Open {
                run,
                adds: i64::from(run.add) * (c * (c - 1) / 2),
                first,
                last,
            });
            self.queue.drop_front(self.queue.len());
        } else {
            let run = self.trimmed(run);
            self.send(&run, out);
            self.queue.drop_front(run.count as usize);
        }
    }

    /// `run`, which stopped at a queued step it could not take, ended at
    /// its last step scheduled at most [`END_DRIFT`] of max_error early, if
    /// that leaves at least three quarters of it: the steps of a run that
    /// ends where its steps drifted to the early edge of their windows
    /// leave the next run starting out of step, and shorter.
    fn trimmed(&self, run: Run) -> Run {
        let (clocks, _) = self.queue.queued();
        let base = self.last_step_clock as u32;
        let limit = i64::from(self.max_error) * END_DRIFT.0 / END_DRIFT.1;
        let shortest = run.count - run.count / 4;
        let mut count = run.count;
        while count > shortest {
            let ideal = clocks
                .get(count as usize - 1)
                .map_or(0, |c| i64::from(c.wrapping_sub(base)));
            if ideal - run.reach(count) <= limit {
                return Run { count, ..run };
            }
            count -= 1;
        }
        run
    }

    fn send_open(&mut self, out: &mut impl FnMut(StepCommand, u64)) {
        if let Some(open) = self.open.take() {
            self.send(&open.run, out);
        }
    }

    /// Sends `run` as one command.
    fn send(&mut self, run: &Run, out: &mut impl FnMut(StepCommand, u64)) {
        let interval = run.max_interval as u32;
        out(
            StepCommand::Steps {
                interval,
                count: run.count as u16,
                add: run.add as i16,
            },
            self.last_step_clock.wrapping_add(u64::from(interval)),
        );
        let reach = run.reach(run.count) as u64;
        self.last_step_clock = self.last_step_clock.wrapping_add(reach);
    }

    /// How far a run with `add` gets from the front of the queue, its
    /// interval within `[min, max]` (the front step's window, or within it).
    fn scan(&self, add: i32, min: i32, max: i32) -> Scan {
        let (clocks, errors) = self.queue.queued();
        let len = clocks.len().min(MAX_COUNT);
        let (clocks, errors) = (&clocks[..len], &errors[..len]);
        let base = self.last_step_clock as u32;
        let (mut next_min, mut next_max) = (min, max);
        let mut interval = next_max;
        // add · k(k+1)/2 for step k.
        let mut c = 0i32;
        // Step k joins as the run's (k+1)th: k < len <= 65535, so the
        // divisions below are by 2..=65535.
        for k in 1..len {
            c += add * k as i32;
            let count = k as i32 + 1;
            let point = clocks[k].wrapping_sub(base);
            let w = Window {
                min: (point - u32::from(errors[k])) as i32,
                max: point as i32,
            };
            if next_min * count < w.min - c {
                // C's round-up division (truncating toward zero).
                next_min = (w.min - c + count - 1) / count;
            }
            if next_max * count > w.max - c {
                next_max = (w.max - c) / count;
            }
            if next_min > next_max {
                return Scan {
                    run: Run {
                        min_interval: interval,
                        max_interval: interval,
                        count: count - 1,
                        add,
                    },
                    stop: Some(Stop {
                        window: w,
                        min: next_min,
                        max: next_max,
                    }),
                };
            }
            interval = next_max;
        }
        Scan {
            run: Run {
                min_interval: next_min,
                max_interval: interval,
                count: len as i32,
                add,
            },
            stop: None,
        }
    }

    /// The longest run from the front of the queue (at least one step;
    /// the queue must not be empty), found by bisecting on its add as
    /// Klipper does.
    fn best_run(&self) -> Run {
        let first = self.first_window();
        let (mut outer_min, mut outer_max) = (first.min, first.max);
        let (mut add, mut min_add, mut max_add) = (0i32, -0x8000i32, 0x7fffi32);
        let mut best = Run {
            min_interval: 0,
            max_interval: 0,
            count: 1,
            add: 1,
        };
        let mut best_reach = i32::MIN;
        let mut zero: Option<Run> = None;
        loop {
            let Scan { run, stop } = self.scan(add, outer_min, outer_max);
            let Some(stop) = stop else {
                // Every queued step joined.
                return run;
            };
            let (interval, count) = (run.max_interval, run.count);
            let reach = add * (count * (count - 1) / 2) + interval * count;
            if reach > best_reach || (reach == best_reach && interval > best.max_interval) {
                (best, best_reach) = (run, reach);
                if add == 0 {
                    zero = Some(run);
                }
                if count > 0x200 {
                    break;
                }
            }
            // Could a larger or smaller add reach further?
            let next_count = count + 1;
            let next_factor = next_count * (next_count - 1) / 2;
            if add * next_factor + interval * next_count < stop.window.min {
                min_add = add + 1;
                outer_max = stop.max;
            } else {
                max_add = add - 1;
                outer_min = stop.min;
            }
            if count > 1 {
                let delta = self.max_error as i32 * QUADRATIC_DEV / (count * count);
                min_add = min_add.max(add - delta);
                max_add = max_add.min(add + delta);
            }
            let c = outer_max * next_count;
            if min_add * next_factor < stop.window.min - c {
                min_add = div_ceil(stop.window.min - c, next_factor);
            }
            let c = outer_min * next_count;
            if max_add * next_factor > stop.window.max - c {
                max_add = (stop.window.max - c).div_euclid(next_factor);
            }
            if min_add > max_add {
                break;
            }
            add = max_add - (max_add - min_add) / 4;
        }
        // Add 0 if it reaches nearly as far.
        match zero {
            Some(zero) if zero.count + zero.count / 16 >= best.count => zero,
            _ => best,
        }
    }
}

/// How far a run with one add gets from the front of the queue.
struct Scan {
    /// The run up to the first step that does not fit (or of every queued
    /// step).
    run: Run,
    /// That step, if any.
    stop: Option<Stop>,
}

/// The first queued step that does not fit a run.
struct Stop {
    /// Its window.
    window: Window,
    /// The interval bounds it and the steps before it need (`min > max`).
    min: i32,
    max: i32,
}

fn div_ceil(n: i32, d: i32) -> i32 {
    -(-n).div_euclid(d)
}

/// `x` (ticks, non-negative, below 2^53) truncated to an integer; negative
/// values give 0. Two 32-bit conversions, which the Cortex-M7's FPU does in
/// hardware (a direct 64-bit conversion is a library call).
#[inline]
fn to_clock(x: f64) -> u64 {
    const TWO_32: f64 = 4_294_967_296.0;
    let high = (x * (1.0 / TWO_32)) as u32;
    let low = (x - f64::from(high) * TWO_32) as u32;
    (u64::from(high) << 32) | u64::from(low)
}

/// Expands commands back into step clocks and directions (the MCU's view,
/// from clock 0). A reset carries the 32-bit clock: it is taken as the
/// 64-bit clock with those low bits nearest the last step's (but not
/// before 0).
pub fn expand(commands: &[StepCommand], mut emit: impl FnMut(u64, bool)) {
    let (mut clock, mut dir) = (0u64, true);
    for cmd in commands {
        match *cmd {
            StepCommand::Dir(d) => dir = d,
            StepCommand::ResetClock(at) => {
                let back = u64::from((clock as u32).wrapping_sub(at));
                clock = if back <= i32::MAX as u64 && back <= clock {
                    clock - back
                } else {
                    clock + u64::from(at.wrapping_sub(clock as u32))
                };
            }
            StepCommand::Steps {
                interval,
                count,
                add,
            } => {
                let mut interval = interval;
                for _ in 0..count {
                    clock += u64::from(interval);
                    emit(clock, dir);
                    interval = interval.wrapping_add(add as u32);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec::Vec;

    fn expanded(commands: &[StepCommand]) -> Vec<u64> {
        let mut clocks = Vec::new();
        expand(commands, |clock, _| clocks.push(clock));
        clocks
    }

    const MAX_ERROR: u32 = 4500;

    /// Forward steps at `times` (s, ascending) through a compressor of `Q`
    /// at `freq` Hz, `flushes` (time, generated) made once the steps before
    /// their `generated` are appended, then everything; checks that the
    /// commands run every step within its window and returns their step
    /// sequences.
    fn compressed<const Q: usize>(
        times: &[f64],
        freq: f64,
        flushes: &[(f64, f64)],
    ) -> Vec<StepCommand> {
        let mut compressor = Compressor::<Q>::new(MAX_ERROR, freq);
        let mut commands = Vec::new();
        let mut out = |cmd, _| commands.push(cmd);
        let mut flushes = flushes.iter().peekable();
        for &time in times {
            while let Some(&&(until, generated)) = flushes.peek()
                && generated <= time
            {
                compressor.flush_until(until, generated, &mut out);
                flushes.next();
            }
            compressor.append(time, true, &mut out);
        }
        for &(until, generated) in flushes {
            compressor.flush_until(until, generated, &mut out);
        }
        compressor.flush(&mut out);
        let ideal: Vec<u64> = times.iter().map(|t| to_clock(t * freq + 0.5)).collect();
        let steps = expanded(&commands);
        assert_eq!(steps.len(), ideal.len());
        for (i, (&step, &clock)) in steps.iter().zip(&ideal).enumerate() {
            let gap = clock - i.checked_sub(1).map_or(0, |p| ideal[p]);
            let error = (gap / 2).min(u64::from(MAX_ERROR));
            assert!(
                step <= clock && clock - step <= error,
                "step {i} at {step}, ideal {clock}"
            );
        }
        commands.retain(|c| matches!(c, StepCommand::Steps { .. }));
        commands
    }

    /// Steps of a move from rest to rest: 3000 mm/s² up to 100 mm/s, at
    /// 0.0125 mm a step, starting at `start` s; `steps` of them.
    fn trapezoid(start: f64, steps: usize) -> Vec<f64> {
        let (accel, cruise, step) = (3000.0, 100.0, 0.0125);
        let ramp = cruise * cruise / (2.0 * accel);
        let length = steps as f64 * step;
        let cruise_end = length - ramp;
        let ramp_time = cruise / accel;
        let cruise_time = (cruise_end - ramp) / cruise;
        (0..steps)
            .map(|k| {
                let x = (k as f64 + 0.5) * step;
                start
                    + if x < ramp {
                        (2.0 * x / accel).sqrt()
                    } else if x < cruise_end {
                        ramp_time + (x - ramp) / cruise
                    } else {
                        let left = length - x;
                        2.0 * ramp_time + cruise_time - (2.0 * left / accel).sqrt()
                    }
            })
            .collect()
    }

    #[test]
    fn a_constant_rate_command_outgrows_the_queue() {
        // 1000 steps 36054 ticks apart, with room for 8 in the queue.
        let times: Vec<f64> = (1..=1000).map(|k| k as f64 * 200.3e-6).collect();
        let commands = compressed::<16>(&times, 180e6, &[]);
        assert!(
            matches!(
                commands[..],
                [StepCommand::Steps {
                    count: 1000,
                    add: 0,
                    ..
                }]
            ),
            "{commands:?}"
        );
    }

    #[test]
    fn a_tiny_queue_keeps_every_step_of_a_move_in_its_window() {
        let times = trapezoid(0.01, 4000);
        let end = times.last().copied().unwrap_or_default();
        // Flushed as motion does: every 50 ms, 250 ms behind generation.
        let flushes: Vec<(f64, f64)> = (1..)
            .map(|k| k as f64 * 0.05)
            .take_while(|&t| t < end)
            .map(|t| (t - 0.25, t))
            .collect();
        for commands in [
            compressed::<8>(&times, 180e6, &flushes),
            compressed::<1024>(&times, 180e6, &flushes),
        ] {
            assert!(commands.len() < times.len() / 50, "{commands:?}");
        }
    }

    #[test]
    fn steps_far_after_the_last_sent_one_are_sent_before_windows_leave_32_bits() {
        // Steps 1 s apart at 520 MHz: each within CLOCK_DIFF_MAX of the one
        // before, but not of the one 2 s before.
        let times: Vec<f64> = (1..=6).map(f64::from).collect();
        let commands = compressed::<16>(&times, 520e6, &[]);
        assert!(commands.len() > 1, "{commands:?}");
    }

    #[test]
    fn the_last_step_before_a_pause_joins_its_command_once_it_cannot_be_reversed() {
        // 100 steps 1 ms apart, then nothing: flushed to 50 ms, with steps
        // generated through 200 ms (or only just past the last step).
        let times: Vec<f64> = (1..=100).map(|k| k as f64 * 0.001).collect();
        let decided = compressed::<256>(&times, 180e6, &[(0.05, 0.2)]);
        assert_eq!(decided.len(), 1, "{decided:?}");
        let undecided = compressed::<256>(&times, 180e6, &[(0.05, 0.1005)]);
        assert_eq!(undecided.len(), 2, "{undecided:?}");
    }

    #[test]
    fn a_reset_is_placed_near_the_last_step() {
        let step = |interval| StepCommand::Steps {
            interval,
            count: 1,
            add: 0,
        };
        let top = u32::MAX - 9;
        // From clock 0, forward.
        let first = [StepCommand::ResetClock(top), step(20)];
        assert_eq!(expanded(&first), [(1 << 32) + 10]);
        // After steps past the 32-bit range, back a little (a homing move
        // cut short before its last steps) and forward.
        let back = [step(3_000_000_000), step(3_000_000_000)];
        let last = 6_000_000_000u64;
        let earlier = (last - 100) as u32;
        let mut cmds = Vec::from(back);
        cmds.extend([StepCommand::ResetClock(earlier), step(1)]);
        assert_eq!(expanded(&cmds)[2], last - 99);
        cmds.truncate(2);
        cmds.extend([StepCommand::ResetClock((last + 100) as u32), step(1)]);
        assert_eq!(expanded(&cmds)[2], last + 101);
    }
}
