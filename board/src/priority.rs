//! Interrupt priorities (lower number = more urgent).
//!
//! The stepper engine's timer is alone at the top so that step pulses are
//! never delayed by USB, SD card or the async executor's time driver.
//! embassy-time's driver enables its interrupt at priority 0 and must be
//! lowered after `embassy_stm32::init`, which [`apply`] does.

use embassy_stm32::interrupt::{self, InterruptExt, Priority};

/// The stepper engine's timer interrupt (TIM5).
pub const STEPPER: Priority = Priority::P0;
/// embassy-time's timer (TIM4): wakes async tasks.
pub const TIME_DRIVER: Priority = Priority::P1;
/// USB, SDMMC and DMA.
pub const PERIPHERALS: Priority = Priority::P2;

/// Sets the priorities of the interrupts that embassy enabled itself.
pub fn apply() {
    interrupt::TIM4.set_priority(TIME_DRIVER);
    interrupt::OTG_HS.set_priority(PERIPHERALS);
    interrupt::SDMMC1.set_priority(PERIPHERALS);
}
