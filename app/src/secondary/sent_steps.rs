//! What the steppers on a secondary were sent: counts, positions, and the
//! last commands, to place a homing's trigger among their steps.

/// Step commands of one stepper remembered to place a homing's trigger
/// among its steps (those that end before the trigger count whole).
const RECENT_COMMANDS: usize = 32;

/// Calls `step(clock)` for each step of a `queue_step` whose first step
/// is at `clock` (64-bit, ticks): step k+1 comes `interval + (k+1) × add`
/// ticks after step k, as the MCU runs it.
pub fn each_step(clock: u64, interval: u32, count: u16, add: i16, mut step: impl FnMut(u64)) {
    let mut at = clock;
    let mut gap = i64::from(interval);
    for _ in 0..count {
        step(at);
        gap += i64::from(add);
        at = at.saturating_add_signed(gap);
    }
}

/// A `queue_step` sent, as its steps fall: first step's clock (64-bit,
/// ticks), interval, count, add, direction (true: forward).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct SentCommand {
    pub(super) clock: u64,
    pub(super) interval: u32,
    pub(super) count: u16,
    pub(super) add: i16,
    pub(super) forward: bool,
}

/// What a stepper on a secondary was sent, and what it adds up to.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SentSteps {
    /// Steps sent.
    pub count: u64,
    /// Their sum, +1 forward and −1 back.
    pub position: i64,
    /// The direction of the next steps.
    pub(super) forward: bool,
    /// The MCU's position when it last halted (a homing's stop), steps.
    halt: i64,
    /// The sum of the steps sent since.
    since_halt: i64,
    /// The last step commands sent since, oldest first.
    recent: heapless::Deque<SentCommand, RECENT_COMMANDS>,
}

impl SentSteps {
    /// The stepper's position at MCU clock `clock` (ticks, after its last
    /// halt), in steps: the halt's, moved by the steps sent since, less
    /// those of the remembered commands after `clock`.
    pub(super) fn position_at(&self, clock: u64) -> i64 {
        let mut after = 0;
        for c in &self.recent {
            let sign = if c.forward { 1 } else { -1 };
            each_step(c.clock, c.interval, c.count, c.add, |at| {
                if at > clock {
                    after += sign;
                }
            });
        }
        self.halt + self.since_halt - after
    }

    /// A `queue_step` was sent.
    pub(super) fn sent(&mut self, command: SentCommand) {
        if self.recent.is_full() {
            self.recent.pop_front();
        }
        let _ = self.recent.push_back(command);
        let steps = i64::from(command.count) * if command.forward { 1 } else { -1 };
        self.count += u64::from(command.count);
        self.position += steps;
        self.since_halt += steps;
    }

    /// The MCU halted at position `halt` (steps, as it reports it): what
    /// it was sent so far but did not make is forgotten.
    pub(super) fn halted_at(&mut self, halt: i64) {
        self.halt = halt;
        self.since_halt = 0;
        self.recent.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn steps(clock: u64, interval: u32, count: u16, add: i16, forward: bool) -> SentCommand {
        SentCommand {
            clock,
            interval,
            count,
            add,
            forward,
        }
    }

    #[test]
    fn a_trigger_is_placed_among_the_steps_sent_since_the_last_halt() {
        let mut sent = SentSteps::default();
        // 10 steps forward at 100, 110, ..., 190; then 4 back, slowing
        // down: 300, 305, 311, 318.
        sent.sent(steps(100, 10, 10, 0, true));
        sent.sent(steps(300, 4, 4, 1, false));
        assert_eq!((sent.count, sent.position), (14, 6));
        assert_eq!(sent.position_at(145), 5);
        assert_eq!(sent.position_at(305), 8);
        assert_eq!(sent.position_at(1000), 6);
        // Halted at 7: what was sent and not made is forgotten.
        sent.halted_at(7);
        sent.sent(steps(2000, 10, 3, 0, true));
        assert_eq!(sent.position_at(2010), 9);
        // The sum of everything sent goes on from before the halt.
        assert_eq!((sent.count, sent.position), (17, 9));
    }

    #[test]
    fn each_step_adds_add_to_every_interval_after_the_first() {
        let mut clocks = [0u64; 4];
        let mut k = 0;
        each_step(300, 4, 4, 1, |at| {
            clocks[k] = at;
            k += 1;
        });
        assert_eq!(clocks, [300, 305, 311, 318]);
    }
}
