//! Secondary boards (AVR, SAMD, LPC, STM32) running stock Klipper MCU
//! firmware, driven as Klipper's host drives them: identify, data dictionary,
//! config, clock synchronisation and `queue_step` (issue #6 and after).
//!
//! Available now:
//! - [`step_commands`]: step generation's commands as `queue_step` /
//!   `set_next_step_dir` messages of a given MCU's dictionary, and back.
#![cfg_attr(not(feature = "std"), no_std)]

pub mod step_commands;
