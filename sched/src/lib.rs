//! The MCU role: timer scheduling, the stepper engine that executes
//! `(interval, count, add)` queues, endstops, outputs with safety timeouts,
//! ADC range checks and shutdown (issue #5).
//!
//! Available now: [`clock`], rollover-safe arithmetic on the 32-bit hardware
//! clock, which everything else here is built on.
#![cfg_attr(not(feature = "std"), no_std)]

pub mod clock;
