//! The stepper engine's timers: CMSDK timer 1 free-running as the step
//! clock (25 MHz, 32 bits), CMSDK timer 0 as its compare, whose interrupt
//! (the highest priority) runs the engine as TIM5's does on the board.
//!
//! A CMSDK timer counts down and interrupts at 0, so the clock is timer
//! 1's count inverted, and a compare at clock `at` is timer 0 loaded with
//! `at - now`. The engine belongs to the interrupt; thread code reaches it
//! with every interrupt masked ([`HandlerCell`]).

use crate::handler_cell::HandlerCell;
use crate::machine::{Irq, TIMER_HZ, TIMER0, TIMER1, priority, read, write};
use crate::pins::StepperPins;
use crate::probe::{self, Context};
use core::sync::atomic::{AtomicU32, Ordering::Relaxed};
use onechip_sched::endstop::Endstop;
use onechip_sched::engine::{Full, StepTimer};
use onechip_sched::shutdown::Shutdown;
use onechip_sched::step_command::StepCommand;
use onechip_sched::stepper::StepPins;

/// CMSDK APB timer registers (byte offsets).
mod reg {
    /// Control: bit 0 enable, bit 3 interrupt enable.
    pub const CTRL: usize = 0x0;
    /// The count, counting down.
    pub const VALUE: usize = 0x4;
    /// Loaded into VALUE when it passes 0.
    pub const RELOAD: usize = 0x8;
    /// Bit 0: the interrupt is pending (write 1 to clear).
    pub const INTSTATUS: usize = 0xc;
    /// CTRL: counting.
    pub const ENABLE: u32 = 1 << 0;
    /// CTRL: interrupt at 0.
    pub const IRQ_ENABLE: u32 = 1 << 3;
}

/// The step clock, Hz.
pub const CLOCK_HZ: f64 = TIMER_HZ as f64;

/// Steppers the engine drives (as the board).
pub const STEPPERS: usize = 8;

/// The stepper engine with the board's queues: 64 moves and 32 waiting
/// commands per stepper.
pub type QemuEngine = onechip_sched::engine::Engine<StepperPins, STEPPERS, 64, 32>;

/// The engine; it belongs to timer 0's handler.
static ENGINE: HandlerCell<QemuEngine> = HandlerCell::new(priority::STEPPER);

/// The clock timer 0 was last armed for (its interrupt's due time).
static ARMED: AtomicU32 = AtomicU32::new(0);
/// The latest any timer interrupt started after its due time, ticks.
static MAX_LATENCY: AtomicU32 = AtomicU32::new(0);
/// Sum of all latencies, ticks, and how many were measured.
static LATENCY_SUM: AtomicU32 = AtomicU32::new(0);
static LATENCY_COUNT: AtomicU32 = AtomicU32::new(0);

/// Timer 0 as the engine's compare.
struct Compare;

impl StepTimer for Compare {
    /// 0.8 µs, as the board's 200 ticks at 260 MHz: a wake closer than
    /// this is served at once.
    const MIN_AHEAD: u32 = 20;

    #[inline(always)]
    fn count(&self) -> u32 {
        now()
    }

    #[inline(always)]
    fn set_compare(&mut self, at: u32) {
        ARMED.store(at, Relaxed);
        write(TIMER0 + reg::VALUE, at.wrapping_sub(now()));
    }
}

/// Starts the clock at 0 and timer 0 with its interrupt (not due for
/// minutes until the engine arms it).
pub fn start() {
    write(TIMER1 + reg::RELOAD, u32::MAX);
    write(TIMER1 + reg::VALUE, u32::MAX);
    write(TIMER1 + reg::CTRL, reg::ENABLE);
    write(TIMER0 + reg::RELOAD, u32::MAX);
    write(TIMER0 + reg::VALUE, u32::MAX);
    write(TIMER0 + reg::CTRL, reg::ENABLE | reg::IRQ_ENABLE);
    crate::machine::enable(Irq::Timer0, priority::STEPPER);
}

/// The step clock now, ticks (wraps every 172 s).
#[inline(always)]
pub fn now() -> u32 {
    !read(TIMER1 + reg::VALUE)
}

/// Hands the engine to the interrupt.
pub fn install(engine: QemuEngine) {
    ENGINE.install(engine);
    crate::machine::pend(Irq::Timer0);
}

/// Queues `cmd` for stepper `index`, first step at 64-bit `clock`; Err
/// while its outbox is full or before the engine is installed.
pub fn push(index: usize, cmd: StepCommand, clock: u64) -> Result<(), Full> {
    let pushed = ENGINE
        .with(|e| e.push(index, cmd, clock))
        .unwrap_or(Err(Full));
    crate::machine::pend(Irq::Timer0);
    pushed
}

/// The 64-bit step clock now, ticks (0 before the engine is installed).
pub fn now64() -> u64 {
    ENGINE.with(|e| e.clock(now())).unwrap_or(0)
}

/// Homing: watches `endstop` on stepper `stepper`'s pins; its trigger
/// stops the steppers in `stops`.
pub fn watch_endstop(stepper: usize, endstop: Endstop, stops: u32) {
    ENGINE.with(|e| e.watch_endstop(stepper, endstop, stops));
    crate::machine::pend(Irq::Timer0);
}

/// Stops watching the armed endstops.
pub fn stop_watching() {
    ENGINE.with(|e| e.stop_watching());
}

/// An endstop trigger not yet taken, if any: the stepper whose pins read
/// that endstop and the trigger's 32-bit clock.
pub fn take_trigger() -> Option<(usize, u32)> {
    ENGINE.with(|e| e.take_trigger()).flatten()
}

/// Stops the steppers in `stops` (bit `i`: stepper `i`) at once, their
/// commands dropped until a step clock reset (another MCU's trsync
/// triggered).
pub fn stop_steppers(stops: u32) {
    ENGINE.with(|e| e.stop_steppers(stops));
}

/// True while stepper `stepper`'s endstop reads pressed.
pub fn endstop_triggered(stepper: usize) -> bool {
    ENGINE
        .with(|e| {
            e.pins_mut()
                .nth(stepper)
                .is_some_and(|p| p.endstop_triggered())
        })
        .unwrap_or(false)
}

/// Stops every stepper for `reason`.
pub fn stop(reason: Shutdown) {
    ENGINE.with(|e| e.stop(reason));
}

/// Why the engine shut down, if it did.
pub fn shutdown_reason() -> Option<Shutdown> {
    ENGINE.with(|e| e.shutdown_reason()).flatten()
}

/// Interrupt latency so far: (most, mean) ticks from a compare's due time
/// to its handler reading the clock.
pub fn latency() -> (u32, f64) {
    let count = LATENCY_COUNT.load(Relaxed);
    let mean = f64::from(LATENCY_SUM.load(Relaxed)) / f64::from(count.max(1));
    (MAX_LATENCY.load(Relaxed), mean)
}

/// Records how late the compare's interrupt started (only interrupts the
/// timer raised: a push's pend is not due at any time).
#[inline(always)]
fn measure_latency(now: u32) {
    if read(TIMER0 + reg::INTSTATUS) & 1 != 0 {
        write(TIMER0 + reg::INTSTATUS, 1);
        let late = now.wrapping_sub(ARMED.load(Relaxed));
        if late < TIMER_HZ {
            MAX_LATENCY.fetch_max(late, Relaxed);
            LATENCY_SUM.fetch_add(late, Relaxed);
            LATENCY_COUNT.fetch_add(1, Relaxed);
        }
    }
}

/// Timer 0's handler: the stepper engine.
pub extern "C" fn timer0() {
    probe::within(Context::Stepper, || {
        measure_latency(now());
        // SAFETY: this is timer 0's handler, which owns the engine.
        if let Some(engine) = unsafe { ENGINE.in_handler() } {
            engine.on_timer(&mut Compare);
        }
    });
}
