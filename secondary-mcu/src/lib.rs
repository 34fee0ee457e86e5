//! Secondary boards (AVR, SAMD, LPC, STM32) running stock Klipper MCU
//! firmware, driven as Klipper's host drives them: identify, data dictionary,
//! config, clock synchronisation and `queue_step`.
//!
//! - [`identify`]: the data dictionary, fetched over a fresh link;
//! - [`connection`]: clock sync start-up, config phase, queued commands;
//! - [`clock_sync`]: the MCU's clock against host (print) time;
//! - [`crc32`]: the checksum of the config commands;
//! - [`trsync`]: homing across MCUs (klippy's trsync and trigger
//!   dispatch);
//! - [`step_commands`]: step generation's commands as `queue_step` /
//!   `set_next_step_dir` messages of a given MCU's dictionary, and back.
#![cfg_attr(not(feature = "std"), no_std)]

pub mod clock_sync;
pub mod connection;
pub mod crc32;
pub mod identify;
pub mod step_commands;
pub mod trsync;
