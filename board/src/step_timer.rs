//! The stepper engine's hardware timer: TIM5, 32 bits, free-running at the
//! timer clock (260 MHz), with its compare-1 interrupt at the highest priority.
//!
//! embassy-time uses TIM4, so TIM5 is ours alone. Its interrupt runs the
//! stepper engine ([`onechip_sched::engine::Engine`]): each compare match
//! makes the steps due and re-arms the compare for the next one, or for a
//! heartbeat at most 1 ms away (which also keeps the 64-bit clock
//! extended). Thread code hands it commands with [`push`].

use crate::step_pins::Slot;
use core::cell::RefCell;
use core::sync::atomic::{AtomicU32, Ordering};
use critical_section::Mutex;
use embassy_stm32::interrupt;
use embassy_stm32::interrupt::InterruptExt;
use embassy_stm32::pac;

/// Timer ticks between heartbeat interrupts (1 ms at 260 MHz).
const HEARTBEAT_TICKS: u32 = 260_000;

/// The timer's clock, Hz (APB1 timers at twice the 130 MHz bus clock).
pub const TIMER_HZ: f64 = 260_000_000.0;

/// Steppers the engine drives.
pub const STEPPERS: usize = 8;

/// The stepper engine: 8 steppers, 64 queued moves and 32 waiting
/// commands each.
pub type BoardEngine = onechip_sched::engine::Engine<Slot, STEPPERS, 64, 32>;

/// Compare matches closer than this to the count are handled at once
/// rather than armed (the compare could be passed before it is written).
const MIN_AHEAD: u32 = 200;

static ENGINE: Mutex<RefCell<Option<BoardEngine>>> = Mutex::new(RefCell::new(None));

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

/// Hands the engine to the interrupt.
pub fn install(engine: BoardEngine) {
    critical_section::with(|cs| *ENGINE.borrow_ref_mut(cs) = Some(engine));
}

/// Queues `cmd` for stepper `index` (first step at 64-bit `clock`); Err
/// while its outbox is full (the interrupt is making room) or before the
/// engine is installed.
pub fn push(
    index: usize,
    cmd: onechip_sched::engine::Command,
    clock: u64,
) -> Result<(), onechip_sched::engine::Full> {
    let pushed = critical_section::with(|cs| {
        ENGINE
            .borrow_ref_mut(cs)
            .as_mut()
            .map_or(Err(onechip_sched::engine::Full), |e| {
                e.push(index, cmd, clock)
            })
    });
    // Let the interrupt look at it now rather than at its next wake.
    pac::TIM5.egr().write(|w| w.set_ccg(0, true));
    pushed
}

/// The 64-bit timer clock now, ticks (0 before the engine is installed).
pub fn now64() -> u64 {
    critical_section::with(|cs| {
        ENGINE
            .borrow_ref_mut(cs)
            .as_mut()
            .map_or(0, |e| e.clock(now()))
    })
}

/// Why the engine shut down, if it did.
pub fn shutdown_reason() -> Option<onechip_sched::shutdown::Shutdown> {
    critical_section::with(|cs| {
        ENGINE
            .borrow_ref(cs)
            .as_ref()
            .and_then(|e| e.shutdown_reason())
    })
}

/// Compare interrupts served so far.
pub fn irq_count() -> u32 {
    IRQ_COUNT.load(Ordering::Relaxed)
}

#[interrupt]
fn TIM5() {
    let tim = pac::TIM5;
    tim.sr().modify(|w| w.set_ccif(0, false));
    IRQ_COUNT.fetch_add(1, Ordering::Relaxed);
    critical_section::with(|cs| {
        let mut engine = ENGINE.borrow_ref_mut(cs);
        loop {
            let now = tim.cnt().read();
            let heartbeat = now.wrapping_add(HEARTBEAT_TICKS);
            let wake = engine.as_mut().and_then(|e| e.run(now));
            let at = match wake {
                Some(at) if onechip_sched::clock::is_before(at, heartbeat) => at,
                _ => heartbeat,
            };
            if onechip_sched::clock::is_before(at, tim.cnt().read().wrapping_add(MIN_AHEAD)) {
                continue;
            }
            tim.ccr(0).write_value(at);
            break;
        }
    });
}
