//! The application layer that the STM32H7 firmware and the Linux host build
//! share. Everything here is `no_std`, allocation-free and hardware-free: the
//! boards hand it bytes (USB, SD-card blocks) and get bytes back.
//!
//! - [`line`]: bounded assembly of G-code lines from a byte stream, and
//!   their command word;
//! - [`line_protocol`]: line numbers, checksums and resends;
//! - [`emergency`]: M112 spotted in the byte stream;
//! - [`console`]: what the firmware answers to each line, and SD printing
//!   ([`sd_print`] on a [`card`]);
//! - [`session`]: the printer both builds run;
//! - [`printer`]: G-code lines through the planner to planned moves;
//! - [`heaters`]: heaters and fan, with verify_heater and min_extrude_temp;
//! - [`idle_timeout`]: Klipper's idle timeout (heaters off when idle);
//! - [`tmc`]: TMC stepper drivers over UART/SPI (registers, checks,
//!   SET_TMC_CURRENT, SET_TMC_FIELD, DUMP_TMC, INIT_TMC);
//! - [`pins`]: MCU pin names as printer.cfg writes them;
//! - [`sdcard`]: reading `printer.cfg` from a FAT16/FAT32 SD card;
//! - [`secondary`]: secondary MCUs on stock Klipper firmware, over the
//!   links a build supplies.
#![cfg_attr(not(feature = "std"), no_std)]

pub mod card;
pub mod config_files;
pub mod console;
pub mod emergency;
pub mod filament;
pub mod heaters;
pub mod idle_timeout;
pub mod line;
pub mod line_protocol;
pub mod mcu_config;
pub mod outputs;
pub mod pin_check;
pub mod pins;
pub mod printer;
pub mod probe;
pub mod sd_print;
pub mod sdcard;
pub mod secondary;
pub mod session;
pub mod setup;
pub mod step_pulse;
pub mod text;
pub mod tmc;

/// Firmware name reported to hosts (M115).
pub const FIRMWARE_NAME: &str = "onechip";
/// Firmware version reported to hosts (M115).
pub const FIRMWARE_VERSION: &str = env!("CARGO_PKG_VERSION");
