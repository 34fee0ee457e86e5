//! The MCU role: the stepper engine that executes `(interval, count, add)`
//! queues from a timer, endstops, outputs with safety timeouts, ADC range
//! checks and shutdown (issue #5).
//!
//! - [`clock`]: rollover-safe arithmetic on the 32-bit hardware clock,
//!   which everything else here is built on;
//! - [`stepper`]: one stepper's engine, executing queued moves from a timer;
//! - [`engine`]: the stepper interrupt's work for all steppers, with far
//!   steps held back until the 32-bit clock can place them;
//! - [`endstop`]: endstop checking during homing;
//! - [`outputs`]: digital outputs, software and hardware PWM, with
//!   max_duration;
//! - [`adc`]: ADC sampling with range checks;
//! - [`thermocouple`]: SPI temperature chips read with Klipper's range
//!   and fault checks;
//! - [`io`]: outputs and ADC inputs run from a timer, behind the
//!   [`io::Peripherals`] hardware trait;
//! - [`tmc_uart`]: the TMC2208/TMC2209 single-wire UART, bit-banged from
//!   a timer;
//! - [`serial`]: a USART link's byte rings and baud-rate divisor;
//! - [`shutdown`]: why everything stopped, in Klipper's words;
//! - [`step_command`]: the step command, as step generation produces it
//!   and the engine executes it.
#![cfg_attr(not(feature = "std"), no_std)]

pub mod adc;
pub mod clock;
pub mod endstop;
pub mod engine;
pub mod io;
pub mod outputs;
pub mod serial;
pub mod shutdown;
pub mod step_command;
pub mod stepper;
pub mod thermocouple;
pub mod tmc_uart;
