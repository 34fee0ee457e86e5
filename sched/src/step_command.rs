//! The step command: one stepper's instruction as Klipper's wire protocol
//! carries it (`set_next_step_dir`, `queue_step`, `reset_step_clock`).
//! Step generation's compressor produces it, the stepper engine
//! ([`crate::engine::Engine::push`]) executes it, and a secondary MCU's
//! link encodes it as a message.

/// A step command for one stepper, as on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StepCommand {
    /// `set_next_step_dir`: the direction of the following steps (true:
    /// positive).
    Dir(bool),
    /// `queue_step`: `count` steps, the first `interval` ticks after the
    /// previous step.
    Steps {
        /// Ticks to the first step.
        interval: u32,
        /// Number of steps.
        count: u16,
        /// Change of the interval after each step.
        add: i16,
    },
    /// `reset_step_clock`: the next step's interval counts from this clock
    /// (the MCU's 32-bit clock; after a homing move was cut short).
    ResetClock(u32),
}
