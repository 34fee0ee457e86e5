//! The stepper engine's hardware timer: TIM5, 32 bits, free-running at the
//! timer clock (260 MHz), with its compare-1 interrupt at the highest priority.
//!
//! embassy-time uses TIM4, so TIM5 is ours alone. The interrupt handler is the
//! entry point of the stepper engine (issue #5); until that lands it keeps a
//! fixed heartbeat cadence so its timing can be observed.

use core::sync::atomic::{AtomicU32, Ordering};
use embassy_stm32::interrupt;
use embassy_stm32::interrupt::InterruptExt;
use embassy_stm32::pac;

/// Timer ticks between heartbeat interrupts (1 ms at 260 MHz).
const HEARTBEAT_TICKS: u32 = 260_000;

/// Number of TIM5 compare interrupts served since start.
static IRQ_COUNT: AtomicU32 = AtomicU32::new(0);

/// Starts TIM5 counting from 0 and arms its first compare interrupt.
pub fn start() {
    embassy_stm32::rcc::enable_and_reset::<embassy_stm32::peripherals::TIM5>();
    let tim = pac::TIM5;
    tim.psc().write_value(0);
    tim.arr().write_value(u32::MAX);
    tim.egr().write(|w| w.set_ug(true));
    tim.sr().write_value(Default::default());
    tim.ccr(0).write_value(HEARTBEAT_TICKS);
    tim.dier().write(|w| w.set_ccie(0, true));
    tim.cr1().modify(|w| w.set_cen(true));
    interrupt::TIM5.set_priority(crate::priority::STEPPER);
    // SAFETY: the handler below only touches TIM5 and an atomic counter.
    unsafe { interrupt::TIM5.enable() };
}

/// The timer's current count, in timer ticks (wraps every 16.5 s).
pub fn now() -> u32 {
    pac::TIM5.cnt().read()
}

/// Compare interrupts served so far.
pub fn irq_count() -> u32 {
    IRQ_COUNT.load(Ordering::Relaxed)
}

#[interrupt]
fn TIM5() {
    let tim = pac::TIM5;
    tim.sr().modify(|w| w.set_ccif(0, false));
    let next = tim.ccr(0).read().wrapping_add(HEARTBEAT_TICKS);
    tim.ccr(0).write_value(next);
    IRQ_COUNT.fetch_add(1, Ordering::Relaxed);
}
