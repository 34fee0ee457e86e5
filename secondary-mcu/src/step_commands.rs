//! Step commands for a secondary MCU: the compressor's output as Klipper's
//! `queue_step oid interval count add`, `set_next_step_dir oid dir` and
//! `reset_step_clock oid clock` messages, encoded with that MCU's data
//! dictionary, and decoded back.

use onechip_protocol::codec::{EncodeError, Encoder};
use onechip_protocol::dictionary::Dictionary;
use onechip_stepgen::compress::StepCommand;

/// Encodes one stepper's commands for the MCU that owns it.
#[derive(Debug, Clone, Copy)]
pub struct StepCommandEncoder<'d> {
    queue_step: Encoder<'d>,
    set_dir: Encoder<'d>,
    reset_clock: Encoder<'d>,
    oid: u8,
    invert_dir: bool,
}

impl<'d> StepCommandEncoder<'d> {
    /// For the stepper configured as `oid` on the MCU described by `dict`;
    /// `invert_dir` as the stepper's `dir_pin` (`!` prefix).
    pub fn new(
        dict: &'d Dictionary<'d>,
        oid: u8,
        invert_dir: bool,
    ) -> Result<Self, EncodeError<'d>> {
        Ok(Self {
            queue_step: Encoder::new(dict, "queue_step")?,
            set_dir: Encoder::new(dict, "set_next_step_dir")?,
            reset_clock: Encoder::new(dict, "reset_step_clock")?,
            oid,
            invert_dir,
        })
    }

    /// Writes `cmd` as a message into `out`; returns its length in bytes.
    /// Fails only if `out` is too small (every [`StepCommand`] is within
    /// the MCU's limits by its types).
    pub fn encode(&self, cmd: &StepCommand, out: &mut [u8]) -> Result<usize, EncodeError<'d>> {
        let oid = i64::from(self.oid);
        match *cmd {
            StepCommand::Dir(positive) => {
                let dir = i64::from(positive != self.invert_dir);
                self.set_dir.encode_ints(&[oid, dir], out)
            }
            StepCommand::ResetClock(clock) => {
                self.reset_clock.encode_ints(&[oid, i64::from(clock)], out)
            }
            StepCommand::Steps {
                interval,
                count,
                add,
            } => self.queue_step.encode_ints(
                &[oid, i64::from(interval), i64::from(count), i64::from(add)],
                out,
            ),
        }
    }

    /// Reads a step command for this stepper from the front of `payload`:
    /// the command and its length in bytes, or None if the message there
    /// is something else (or for another oid, or malformed).
    pub fn decode(&self, dict: &Dictionary<'_>, payload: &[u8]) -> Option<(StepCommand, usize)> {
        let (msg, len) = dict.decode(payload).ok()?;
        if msg.int("oid")? != i64::from(self.oid) {
            return None;
        }
        let cmd = if msg.message.id == self.reset_clock.id() {
            StepCommand::ResetClock(u32::try_from(msg.int("clock")?).ok()?)
        } else if msg.message.id == self.set_dir.id() {
            StepCommand::Dir((msg.int("dir")? != 0) != self.invert_dir)
        } else if msg.message.id == self.queue_step.id() {
            StepCommand::Steps {
                interval: u32::try_from(msg.int("interval")?).ok()?,
                count: u16::try_from(msg.int("count")?).ok()?,
                add: i16::try_from(msg.int("add")?).ok()?,
            }
        } else {
            return None;
        };
        Some((cmd, len))
    }
}
