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
    /// An SPI temperature chip's value left its configured range.
    ThermocoupleOutOfRange,
    /// An SPI temperature chip reported a fault.
    ThermocoupleFault,
    /// A digital output stayed away from its default past max_duration
    /// without a refresh.
    DigitalOutExpired,
    /// A PWM output stayed away from its default past max_duration
    /// without a refresh.
    PwmExpired,
    /// The host asked for an emergency stop (M112).
    EmergencyStop,
    /// A TMC driver reported an error flag (overtemperature, a short,
    /// undervoltage) or stopped answering, as Klipper's periodic driver
    /// check shuts down; the console said which driver and which flags.
    TmcError,
    /// A heater did not heat at the rate its `[verify_heater]` checks
    /// expect (in Klipper a host-side check; here the MCU role runs it).
    NotHeating(Heater),
    /// A secondary MCU (`[mcu NAME]`) shut down with its own message.
    Secondary {
        /// Its name.
        mcu: &'static str,
        /// Its shutdown message.
        reason: &'static str,
    },
    /// A secondary MCU stopped answering its clock queries.
    LostCommunication {
        /// Its name.
        mcu: &'static str,
    },
    /// A secondary MCU could not be brought back by FIRMWARE_RESTART:
    /// Klipper's message, which names it (`Failed automated reset of MCU
    /// 'ext'`).
    SecondaryNotReady {
        /// The message.
        message: &'static str,
    },
}

/// The heaters a shutdown can name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Heater {
    /// `[extruder]`'s heater.
    Extruder,
    /// `[heater_bed]`.
    Bed,
}

impl Heater {
    /// The heater's name in printer.cfg.
    pub fn name(self) -> &'static str {
        match self {
            Self::Extruder => "extruder",
            Self::Bed => "heater_bed",
        }
    }
}

/// The lines Klipper adds under a verify_heater shutdown's message.
const HINT_THERMAL: &[&str] = &[
    "See the 'verify_heater' section in docs/Config_Reference.md",
    "for the parameters that control this check.",
];

impl Shutdown {
    /// Klipper's text for this reason (for a secondary MCU, its own
    /// message; [`Shutdown`]'s `Display` names the MCU as Klipper does).
    pub fn message(self) -> &'static str {
        match self {
            Self::Secondary { reason, .. } => reason,
            Self::LostCommunication { .. } => "Lost communication with MCU",
            Self::SecondaryNotReady { message } => message,
            Self::MoveQueueOverflow => "Move queue overflow",
            Self::StepperTooFarInPast => "Stepper too far in past",
            Self::TimerTooClose => "Timer too close",
            Self::AdcOutOfRange => "ADC out of range",
            Self::ThermocoupleOutOfRange => "Thermocouple ADC out of range",
            Self::ThermocoupleFault => "Thermocouple reader fault",
            Self::DigitalOutExpired => "Missed scheduling of next digital out event",
            Self::PwmExpired => "Missed scheduling of next hard pwm event",
            Self::EmergencyStop => "Shutdown due to M112 command",
            Self::TmcError => "TMC driver error (see the message above)",
            Self::NotHeating(Heater::Extruder) => "Heater extruder not heating at expected rate",
            Self::NotHeating(Heater::Bed) => "Heater heater_bed not heating at expected rate",
        }
    }

    /// The lines Klipper prints under the message (each to be shown as a
    /// `// ` line), if any: where to read about the check that fired.
    pub fn hint(self) -> &'static [&'static str] {
        match self {
            Self::NotHeating(_) => HINT_THERMAL,
            _ => &[],
        }
    }
}

impl fmt::Display for Shutdown {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Secondary { mcu, reason } => write!(f, "MCU '{mcu}' shutdown: {reason}"),
            Self::LostCommunication { mcu } => write!(f, "Lost communication with MCU '{mcu}'"),
            _ => f.write_str(self.message()),
        }
    }
}
