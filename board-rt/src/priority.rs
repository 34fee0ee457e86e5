//! Interrupt priorities (lower number = more urgent).
//!
//! The stepper engine's timer is alone at the top so that step pulses are
//! never delayed by USB, SD card or the async executor's time driver. The
//! TMC drivers' UART timer comes next: its events are short (62
//! instructions) and run only during an exchange, and each must begin
//! within half a sample (3 µs) of its time, which the heaters' interrupt
//! (11 µs for an SPI temperature chip's reading) could not promise from
//! above it. The heaters' timer follows, so that their safety rules hold
//! however busy the rest is.
//! embassy-time's driver enables its interrupt at priority 0 and must be
//! lowered after `embassy_stm32::init`, which [`apply`] does.

use embassy_stm32::interrupt::{self, InterruptExt, Priority};

/// The stepper engine's timer interrupt (TIM5).
pub const STEPPER: Priority = Priority::P0;
/// The TMC drivers' UART (TIM24): its bit edges and samples, each timed
/// to a few µs (an exchange held off longer is tried again).
pub const TMC_UART: Priority = Priority::P1;
/// The heaters' and fan's timer (TIM2): output edges, thermistor
/// readings, safety timeouts and heater control.
pub const HEATERS: Priority = Priority::P2;
/// A BLTouch's servo signal (TIM23): its pulse edges.
pub const PROBE_SERVO: Priority = Priority::P3;
/// The USART link to secondary MCUs (USART2): it moves bytes between the
/// USART's 16-byte FIFOs and the link's rings. Below the steppers, the
/// TMC UART and the heaters (their timing is tighter), above USB, SDMMC
/// and the executors, whose handlers can run long: at 250,000 bit/s a
/// byte arrives every 40 µs, and the receive FIFO holds 16 (with the shift
/// register, 680 µs before an overrun), which only the three interrupts
/// above could take from it. Its handler is short (a few register reads
/// and ring stores per byte), so the servo's edges at the same level wait
/// at most that.
pub const SECONDARY_LINK: Priority = Priority::P3;
/// embassy-time's timer (TIM4): wakes async tasks.
pub const TIME_DRIVER: Priority = Priority::P3;
/// USB, SDMMC and DMA.
pub const PERIPHERALS: Priority = Priority::P4;
/// The I/O executor (USB console tasks, watchdog, tick): below everything
/// above, above thread code (planning, step generation).
pub const IO_EXECUTOR: Priority = Priority::P5;

/// Sets the priorities of the interrupts that embassy enabled itself.
pub fn apply() {
    interrupt::TIM4.set_priority(TIME_DRIVER);
    interrupt::OTG_HS.set_priority(PERIPHERALS);
    interrupt::SDMMC1.set_priority(PERIPHERALS);
}
