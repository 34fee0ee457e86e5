//! The MCU role: timer scheduling, the stepper engine that executes
//! `(interval, count, add)` queues, endstops, outputs with safety timeouts,
//! ADC range checks and shutdown (issue #5).
//!
//! Available now:
//! - [`clock`]: rollover-safe arithmetic on the 32-bit hardware clock,
//!   which everything else here is built on;
//! - [`stepper`]: one stepper's engine, executing queued moves from a timer;
//! - [`engine`]: the stepper interrupt's work for all steppers, with far
//!   steps held back until the 32-bit clock can place them;
//! - [`timer`]: which timer fires next;
//! - [`endstop`]: endstop checking during homing;
//! - [`outputs`]: digital outputs with max_duration, ADC range checks;
//! - [`pwm`]: hardware and software PWM with max_duration;
//! - [`mcu`]: all of them together, and shutdown that stops everything;
//! - [`shutdown`]: why everything stopped, in Klipper's words.
#![cfg_attr(not(feature = "std"), no_std)]

pub mod clock;
pub mod endstop;
pub mod engine;
pub mod mcu;
pub mod outputs;
pub mod pwm;
pub mod shutdown;
pub mod stepper;
pub mod timer;
