//! Why the MCU role stopped everything: Klipper's shutdown reasons, with
//! the message texts Klipper's MCU sends (its `static_string_id` strings),
//! so a user sees the same words.

use core::fmt;

/// A reason to shut down. Once shut down, every output is off and stays
/// off until the printer is restarted; the first reason is kept.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shutdown {
    /// A step command arrived while the stepper's queue was full.
    MoveQueueOverflow,
    /// A stepper's next step was due before it was queued: step
    /// generation fell behind (the queue ran dry mid-move).
    StepperTooFarInPast,
    /// A timer was scheduled for a time already passed.
    TimerTooClose,
    /// An ADC reading left its configured range.
    AdcOutOfRange,
    /// A digital output stayed away from its default past max_duration
    /// without a refresh.
    DigitalOutExpired,
    /// A PWM output stayed away from its default past max_duration
    /// without a refresh.
    PwmExpired,
    /// The host asked for an emergency stop (M112).
    EmergencyStop,
}

impl Shutdown {
    /// Klipper's text for this reason.
    pub fn message(self) -> &'static str {
        match self {
            Self::MoveQueueOverflow => "Move queue overflow",
            Self::StepperTooFarInPast => "Stepper too far in past",
            Self::TimerTooClose => "Timer too close",
            Self::AdcOutOfRange => "ADC out of range",
            Self::DigitalOutExpired => "Missed scheduling of next digital out event",
            Self::PwmExpired => "Missed scheduling of next hard pwm event",
            Self::EmergencyStop => "Shutdown due to M112 command",
        }
    }
}

impl fmt::Display for Shutdown {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.message())
    }
}
