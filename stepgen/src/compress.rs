//! Step clocks to `(interval, count, add)` sequences, as the MCU executes
//! them: `count` steps, each `interval` ticks after the previous, `interval`
//! growing by `add` after each step.
//!
//! Every step may be scheduled up to `max_error` ticks early, never late
//! (nor earlier than half-way to the previous step), so a compressed step
//! is within `[t - max_error, t]` of its ideal clock `t`. For each sequence
//! the longest run is sought by bisecting on `add`, as Klipper does.
//! Two filters come first: a step followed within 750 µs by a step back
//! cancels both (step+dir+step), and a step 3·2^28 ticks or more after the
//! previous one is sent alone (the MCU's 32-bit clock wraps).

/// A step reversed within this time cancels the step before it, s.
pub const SDS_FILTER_TIME: f64 = 0.000_750;
/// Steps this many ticks or more apart are sent as single steps.
pub const CLOCK_DIFF_MAX: u64 = 3 << 28;
/// The MCU's limit on steps per sequence.
pub const MAX_COUNT: usize = 0xffff;
/// Bound of the add search around a valid add (`(6 + 4√2)·max_error /
/// count²` in theory; 11 is what works in practice).
const QUADRATIC_DEV: i32 = 11;

// What the compressor produces, in order (each with the 64-bit clock of
// its first step); re-exported for the compressor's users.
pub use onechip_sched::step_command::StepCommand;

/// Acceptable range of one step, in ticks after the last compressed step:
/// 32 bits, as queued steps are less than `CLOCK_DIFF_MAX` (3·2^28) ticks
/// apart, and 32-bit arithmetic is native on the MCU.
#[derive(Debug, Clone, Copy)]
struct Window {
    min: i32,
    max: i32,
}

/// Step clocks waiting for compression, contiguous in a buffer of `Q`
/// that holds at most `Q / 2`: sending a sequence from the front moves
/// nothing, and the queue slides back to the buffer's start only when it
/// reaches the end (at most once per `Q / 2` steps appended).
#[derive(Debug, Clone)]
struct Steps<const Q: usize> {
    clocks: [u64; Q],
    /// Each step's allowed error given the step before it, ticks.
    errors: [u32; Q],
    head: usize,
    len: usize,
    /// The newest queued clock (while `len > 0`).
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

    fn is_empty(&self) -> bool {
        self.len == 0
    }

    fn is_full(&self) -> bool {
        self.len >= Q / 2
    }

    /// The queued clocks and their errors, front first.
    fn queued(&self) -> (&[u64], &[u32]) {
        let range = self.head..self.head + self.len;
        (&self.clocks[range.clone()], &self.errors[range])
    }

    fn first(&self) -> Option<u64> {
        self.queued().0.first().copied()
    }

    fn last(&self) -> Option<u64> {
        (self.len > 0).then_some(self.newest)
    }

    /// Appends unless full.
    fn push(&mut self, clock: u64, error: u32) {
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
            (*c, *e) = (clock, error);
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

/// Compression state of one stepper, holding up to `Q` step clocks.
#[derive(Debug, Clone)]
pub struct Compressor<const Q: usize> {
    max_error: u32,
    freq: f64,
    /// Steps closer than this many ticks to a reversed one are filtered.
    sds_ticks: u64,
    last_step_clock: u64,
    queue: Steps<Q>,
    dir: Option<bool>,
    /// The newest step, held back until the next shows it is not reversed.
    held: Option<(u64, bool)>,
}

impl<const Q: usize> Compressor<Q> {
    /// A compressor for an MCU clock of `freq` Hz with `max_error` ticks.
    pub fn new(max_error: u32, freq: f64) -> Self {
        Self {
            max_error,
            freq,
            sds_ticks: sds_ticks(freq),
            last_step_clock: 0,
            queue: Steps::new(),
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

    /// Adds a step at print time `time` s in direction `dir`. Commands go
    /// to `out` with the 64-bit clock of their first step (for a direction
    /// change: of the last step before it), which the 32-bit interval of
    /// a far step does not carry.
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

    /// Sends the commands of the steps before print time `time` (s),
    /// keeping later ones to compress with the steps that follow them.
    /// Steps must have been appended past `time` by more than the
    /// step+dir+step filter's window.
    pub fn flush_until(&mut self, time: f64, out: &mut impl FnMut(StepCommand, u64)) {
        let clock = to_clock(time * self.freq);
        if let Some((held_clock, held_dir)) = self.held
            && held_clock < clock
        {
            self.held = None;
            self.commit(held_clock, held_dir, out);
        }
        while self.queue.first().is_some_and(|c| c < clock) {
            self.compress_some(out);
        }
    }

    /// Forgets every step not yet sent (a homing move cut short by its
    /// endstop) and counts the next from `clock`, which the stepper is told
    /// with [`StepCommand::ResetClock`] (its low 32 bits, the MCU's clock),
    /// also sent to `out` with the whole 64-bit `clock`.
    pub fn reset(&mut self, clock: u64, out: &mut impl FnMut(StepCommand, u64)) {
        self.queue.drop_front(self.queue.len());
        self.held = None;
        self.dir = None;
        self.last_step_clock = clock;
        out(StepCommand::ResetClock(clock as u32), clock);
    }

    /// Sends everything queued (the end of the motion, or before a pause).
    pub fn flush(&mut self, out: &mut impl FnMut(StepCommand, u64)) {
        if let Some((clock, dir)) = self.held.take() {
            self.commit(clock, dir, out);
        }
        self.compress_all(out);
    }

    fn commit(&mut self, clock: u64, dir: bool, out: &mut impl FnMut(StepCommand, u64)) {
        if self.dir != Some(dir) {
            self.compress_all(out);
            out(StepCommand::Dir(dir), self.last_step_clock);
            self.dir = Some(dir);
        }
        let last_queued = self.queue.last().unwrap_or(self.last_step_clock);
        if clock >= last_queued + CLOCK_DIFF_MAX {
            self.compress_all(out);
            out(
                StepCommand::Steps {
                    interval: clock.wrapping_sub(self.last_step_clock) as u32,
                    count: 1,
                    add: 0,
                },
                clock,
            );
            self.last_step_clock = clock;
            return;
        }
        if self.queue.is_full() {
            self.compress_some(out);
        }
        // There is room now: compress_some consumed at least one step. The
        // error a step allows is half its gap to the step before, at most
        // max_error (for the first queued step it is worked out later,
        // from the last compressed step).
        let last_queued = self.queue.last().unwrap_or(self.last_step_clock);
        let error = ((clock.wrapping_sub(last_queued) as u32) / 2).min(self.max_error);
        self.queue.push(clock, error);
    }

    fn compress_all(&mut self, out: &mut impl FnMut(StepCommand, u64)) {
        while !self.queue.is_empty() {
            self.compress_some(out);
        }
    }

    /// Emits one sequence from the front of the queue.
    fn compress_some(&mut self, out: &mut impl FnMut(StepCommand, u64)) {
        let (interval, count, add) = self.best_sequence();
        let count = count.max(1);
        let first = self
            .last_step_clock
            .wrapping_add(u64::from(interval as u32));
        out(
            StepCommand::Steps {
                interval: interval as u32,
                count: count as u16,
                add: add as i16,
            },
            first,
        );
        let (interval, count, add) = (i64::from(interval), i64::from(count), i64::from(add));
        let addfactor = count * (count - 1) / 2;
        self.last_step_clock = self
            .last_step_clock
            .wrapping_add((add * addfactor + interval * count) as u64);
        self.queue.drop_front(count as usize);
    }

    /// The acceptable window of the first queued step.
    fn first_window(&self, clock: u64) -> Window {
        let point = clock.wrapping_sub(self.last_step_clock) as u32;
        let error = (point / 2).min(self.max_error);
        Window {
            min: (point - error) as i32,
            max: point as i32,
        }
    }

    /// The longest `(interval, count, add)` run from the front of the queue.
    fn best_sequence(&self) -> (i32, i32, i32) {
        let (clocks, errors) = self.queue.queued();
        let len = clocks.len().min(MAX_COUNT);
        let (clocks, errors) = (&clocks[..len], &errors[..len]);
        let base = self.last_step_clock;
        // The acceptable window of a queued step after the first.
        let window = |clock: u64, error: u32| {
            let point = clock.wrapping_sub(base) as u32;
            Window {
                min: (point - error) as i32,
                max: point as i32,
            }
        };
        let Some(&front) = clocks.first() else {
            return (0, 0, 0);
        };
        let first = self.first_window(front);
        let (mut outer_min, mut outer_max) = (first.min, first.max);
        let (mut add, mut min_add, mut max_add) = (0i32, -0x8000i32, 0x7fffi32);
        let (mut best_interval, mut best_count, mut best_add, mut best_reach) =
            (0i32, 1i32, 1i32, i32::MIN);
        let (mut zero_interval, mut zero_count) = (0i32, 0i32);
        loop {
            // The longest run with this add.
            let (mut next_min, mut next_max) = (outer_min, outer_max);
            let mut interval = next_max;
            // Steps in the run if the one being tried joins it.
            let mut next_count = 1i32;
            // add · n(n-1)/2 for the step being tried.
            let mut c = 0i32;
            let mut stopped = None;
            // Step k joins as the run's (k+1)th: k < len <= 65535, so the
            // divisions below are by 2..=65535.
            for k in 1..len {
                c += add * k as i32;
                next_count = k as i32 + 1;
                let w = window(clocks[k], errors[k]);
                if next_min * next_count < w.min - c {
                    // C's round-up division (truncating toward zero).
                    next_min = (w.min - c + next_count - 1) / next_count;
                }
                if next_max * next_count > w.max - c {
                    next_max = (w.max - c) / next_count;
                }
                if next_min > next_max {
                    stopped = Some(w);
                    break;
                }
                interval = next_max;
            }
            let Some(next_window) = stopped else {
                // Every queued step joined.
                return (interval, len as i32, add);
            };
            let count = next_count - 1;
            let reach = add * (count * (count - 1) / 2) + interval * count;
            if reach > best_reach || (reach == best_reach && interval > best_interval) {
                (best_interval, best_count, best_add, best_reach) = (interval, count, add, reach);
                if add == 0 {
                    (zero_interval, zero_count) = (interval, count);
                }
                if count > 0x200 {
                    break;
                }
            }
            // Could a larger or smaller add reach further?
            let next_factor = next_count * (next_count - 1) / 2;
            if add * next_factor + interval * next_count < next_window.min {
                min_add = add + 1;
                outer_max = next_max;
            } else {
                max_add = add - 1;
                outer_min = next_min;
            }
            if count > 1 {
                let delta = self.max_error as i32 * QUADRATIC_DEV / (count * count);
                min_add = min_add.max(add - delta);
                max_add = max_add.min(add + delta);
            }
            let c = outer_max * next_count;
            if min_add * next_factor < next_window.min - c {
                min_add = div_ceil(next_window.min - c, next_factor);
            }
            let c = outer_min * next_count;
            if max_add * next_factor > next_window.max - c {
                max_add = (next_window.max - c).div_euclid(next_factor);
            }
            if min_add > max_add {
                break;
            }
            add = max_add - (max_add - min_add) / 4;
        }
        if zero_count + zero_count / 16 >= best_count {
            return (zero_interval, zero_count, 0);
        }
        (best_interval, best_count, best_add)
    }
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
