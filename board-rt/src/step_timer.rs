//! The stepper engine's hardware timer: TIM5, 32 bits, free-running at the
//! timer clock (260 MHz), with its compare-1 interrupt at the highest priority.
//!
//! embassy-time uses TIM4, so TIM5 is ours alone. Its interrupt runs the
//! stepper engine ([`onechip_sched::engine::Engine::on_timer`]): each
//! compare match makes the steps due and re-arms the compare for the next
//! wake. Thread code hands it commands with [`push`].
//!
//! The engine belongs to the interrupt, as Klipper's stepper state belongs
//! to its timer interrupt: thread code reaches it only with interrupts
//! masked, so the interrupt itself takes no lock.

use crate::handler_cell::HandlerCell;
use crate::step_pins::StepperPins;
use embassy_stm32::interrupt;
use embassy_stm32::interrupt::InterruptExt;
use embassy_stm32::pac;
use onechip_sched::engine::{Full, StepTimer};
use onechip_sched::step_command::StepCommand;
use onechip_sched::stepper::StepPins;

/// Timer ticks to the first interrupt after start (1 ms at 260 MHz).
const FIRST_WAKE: u32 = 260_000;

/// The timer's clock, Hz (APB1 timers at twice the 130 MHz bus clock).
pub const TIMER_HZ: f64 = 260_000_000.0;
const _: () = assert!(
    crate::clocks::APB1_TIMER_HZ == TIMER_HZ as u32,
    "TIMER_HZ is not TIM5's clock"
);

/// Steppers the engine drives.
pub const STEPPERS: usize = 8;

/// The stepper engine: 8 steppers, 64 queued moves and 32 waiting
/// commands each.
pub type BoardEngine = onechip_sched::engine::Engine<StepperPins, STEPPERS, 64, 32>;

/// TIM5 as the engine's timer.
struct Tim5;

impl StepTimer for Tim5 {
    /// Compare matches closer than this to the count are served at once
    /// rather than armed (the count could pass the compare before it is
    /// written).
    const MIN_AHEAD: u32 = 200;

    #[inline(always)]
    fn count(&self) -> u32 {
        pac::TIM5.cnt().read()
    }

    #[inline(always)]
    fn set_compare(&mut self, at: u32) {
        pac::TIM5.ccr(0).write_value(at);
    }
}

/// The engine, once installed; it belongs to TIM5's handler. In DTCM
/// (zero wait states, never cached: [`crate::tcm`]), in the section
/// start-up zeroes, which leaves it empty as `new` makes it.
#[unsafe(link_section = ".dtcm_bss.engine")]
static ENGINE: HandlerCell<BoardEngine> = HandlerCell::new();
const _: () = assert!(
    HandlerCell::<BoardEngine>::ZEROED_IS_NEW,
    "ENGINE lives in memory zeroed at boot"
);

/// Runs `f` on the engine with interrupts masked; None before it is
/// installed.
fn with_engine<R>(f: impl FnOnce(&mut BoardEngine) -> R) -> Option<R> {
    ENGINE.with(f)
}

/// Starts TIM5 counting from 0 and arms its first compare interrupt;
/// its handler runs from ITCM, hence the proof that the TCMs are loaded.
pub fn start(_tcm: crate::tcm::Loaded) {
    embassy_stm32::rcc::enable_and_reset::<embassy_stm32::peripherals::TIM5>();
    crate::timer32::start(pac::TIM5, Some(FIRST_WAKE));
    interrupt::TIM5.set_priority(crate::priority::STEPPER);
    // SAFETY: the handler below touches TIM5 and the engine, as the
    // engine's `HandlerCell` allows.
    unsafe { interrupt::TIM5.enable() };
}

/// The timer's current count, in timer ticks (wraps every 16.5 s).
pub fn now() -> u32 {
    pac::TIM5.cnt().read()
}

/// Hands the engine to the interrupt.
pub fn install(engine: BoardEngine) {
    ENGINE.install(engine);
    raise();
}

/// Raises TIM5's interrupt now, so the engine looks at what was pushed.
fn raise() {
    pac::TIM5.egr().write(|w| w.set_ccg(0, true));
}

/// Queues `cmd` for stepper `index` (first step at 64-bit `clock`); Err
/// while its outbox is full (the interrupt is making room) or before the
/// engine is installed.
pub fn push(index: usize, cmd: StepCommand, clock: u64) -> Result<(), Full> {
    let pushed = with_engine(|e| e.push(index, cmd, clock)).unwrap_or(Err(Full));
    raise();
    pushed
}

/// The 64-bit timer clock now, ticks (0 before the engine is installed).
pub fn now64() -> u64 {
    with_engine(|e| e.clock(now())).unwrap_or(0)
}

/// Homing: watches the endstop on stepper `stepper`'s pins (besides those
/// already armed), which stops the steppers in `stops` (bit `i`: stepper
/// `i`) when it triggers.
pub fn watch_endstop(stepper: usize, endstop: onechip_sched::endstop::Endstop, stops: u32) {
    with_engine(|e| e.watch_endstop(stepper, endstop, stops));
    // The interrupt re-arms its compare for the first reading.
    raise();
}

/// Stops watching the armed endstops.
pub fn stop_watching() {
    with_engine(|e| e.stop_watching());
}

/// An endstop trigger not yet taken, if any: the stepper whose pins read
/// that endstop and the trigger's 32-bit clock.
pub fn take_trigger() -> Option<(usize, u32)> {
    with_engine(|e| e.take_trigger()).flatten()
}

/// Stops the steppers in `stops` (bit `i`: stepper `i`) at once, their
/// commands dropped until a step clock reset (another MCU's trsync
/// triggered).
pub fn stop_steppers(stops: u32) {
    with_engine(|e| e.stop_steppers(stops));
}

/// True while stepper `stepper`'s endstop input reads pressed.
pub fn endstop_triggered(stepper: usize) -> bool {
    with_engine(|e| {
        e.pins_mut()
            .nth(stepper)
            .is_some_and(|pins| pins.endstop_triggered())
    })
    .unwrap_or(false)
}

/// Stops every stepper for `reason` (a heater fault).
pub fn stop(reason: onechip_sched::shutdown::Shutdown) {
    with_engine(|e| e.stop(reason));
}

/// Why the engine shut down, if it did.
pub fn shutdown_reason() -> Option<onechip_sched::shutdown::Shutdown> {
    with_engine(|e| e.shutdown_reason()).flatten()
}

/// The stepper interrupt, run from ITCM with the engine's functions it
/// calls (`cargo xtask image` checks both).
#[interrupt]
#[unsafe(link_section = ".itcm_text.TIM5")]
fn TIM5() {
    // Only the compare-1 interrupt is enabled: clear every flag.
    pac::TIM5.sr().write_value(Default::default());
    // SAFETY: this is TIM5's handler, which owns the engine.
    if let Some(engine) = unsafe { ENGINE.in_handler() } {
        engine.on_timer(&mut Tim5);
    }
}
