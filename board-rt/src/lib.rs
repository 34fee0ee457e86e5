//! The interrupt-driven half of the onechip firmware on the BTT Octopus
//! Pro v1.1 (STM32H723ZE): the hardware the MCU role runs on, compiled for
//! speed (opt-level 2), while the firmware crate that boots the board and
//! runs thread code (console, card, USB, the session) is compiled for
//! size. Generic code takes the opt-level of the crate that instantiates
//! it: the stepper engine is instantiated here.
//!
//! - [`step_timer`]: the stepper engine in TIM5's interrupt (from ITCM,
//!   its state in DTCM: [`tcm`]), [`step_pins`] its GPIOs;
//! - [`heater_io`]: heaters, fans and thermistors in TIM2's interrupt,
//!   [`spi_sensors`] the SPI temperature chips it reads;
//! - [`probe_servo`]: a BLTouch's servo signal from TIM23;
//! - [`tmc_link`]: the TMC drivers' UART (TIM24) and SPI;
//! - [`usart_link`]: the USART link to secondary MCUs (USART2);
//! - [`safety`]: the watchdog and the fault handlers that turn every
//!   registered output off;
//! - [`clocks`], [`priority`], [`gpio`], [`handler_cell`], [`timer32`]:
//!   the clock tree, the interrupt priorities, the ports, state owned by
//!   one interrupt, and the timers the interrupts run on.
#![no_std]

pub mod clocks;
pub mod gpio;
pub mod handler_cell;
pub mod heater_io;
pub mod priority;
pub mod probe_servo;
pub mod safety;
pub mod spi_sensors;
pub mod step_pins;
pub mod step_timer;
pub mod tcm;
pub mod timer32;
pub mod tmc_link;
pub mod usart_link;
