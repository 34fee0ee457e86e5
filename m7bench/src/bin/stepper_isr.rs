//! Instructions per step on the stepper interrupt's common path on a
//! Cortex-M7: the board's timer interrupt body ([`Engine::on_timer`]:
//! acknowledge, run the engine over 4 steppers, one stepping and three
//! idle, arm the compare) called once per step, over long queued moves
//! (the path of all but a move's last step). Region 2 runs a bare
//! interrupt body (acknowledge, re-arm) in the same loop: the difference
//! is what the engine adds to an interrupt. Region 3 runs the loop around
//! an empty function: region 1 less region 3 is the interrupt's own path.
#![no_std]
#![no_main]

use cortex_m_rt::entry;
use onechip_m7bench::{exit, measure, report};
use onechip_sched::engine::{Engine, StepTimer};
use onechip_sched::step_command::StepCommand;
use onechip_sched::stepper::StepPins;

/// Stands in for a GPIO set/reset register.
#[derive(Default)]
struct Pins {
    bsrr: u32,
}

impl StepPins for Pins {
    fn set_dir(&mut self, positive: bool) {
        // SAFETY: a write to a field, kept by the volatile access.
        unsafe {
            core::ptr::write_volatile(&mut self.bsrr, if positive { 1 << 4 } else { 1 << 20 })
        }
    }

    #[inline(always)]
    fn step(&mut self) {
        // Step pin high, then low.
        // SAFETY: as above.
        unsafe {
            core::ptr::write_volatile(&mut self.bsrr, 1 << 3);
            core::ptr::write_volatile(&mut self.bsrr, 1 << 19);
        }
    }
}

const STEPS: u32 = 10_000;

type BenchEngine = Engine<Pins, 4, 64, 32>;

/// Stands in for the hardware timer's registers.
#[derive(Default)]
struct Timer {
    status: u32,
    count: u32,
    compare: u32,
}

impl StepTimer for Timer {
    const MIN_AHEAD: u32 = 200;

    fn count(&self) -> u32 {
        // SAFETY: a read of a field, kept by the volatile access.
        unsafe { core::ptr::read_volatile(&self.count) }
    }

    fn set_compare(&mut self, at: u32) {
        // SAFETY: a write to a field, kept by the volatile access.
        unsafe { core::ptr::write_volatile(&mut self.compare, at) }
    }
}

/// The timer interrupt handler's body, as the board's: acknowledges the
/// interrupt, runs the engine and arms the compare.
#[inline(never)]
fn timer_interrupt(engine: &mut BenchEngine, timer: &mut Timer) {
    // SAFETY: as above.
    unsafe { core::ptr::write_volatile(&mut timer.status, 0) };
    engine.on_timer(timer);
}

/// The least any timer interrupt does, to measure the loop around the
/// handler: acknowledge and re-arm.
#[inline(never)]
fn bare_interrupt(timer: &mut Timer) {
    // SAFETY: as above.
    unsafe { core::ptr::write_volatile(&mut timer.status, 0) };
    let next = timer.count().wrapping_add(30_000);
    timer.set_compare(next);
}

/// Nothing, called as the handlers are: the benchmark loop's own cost
/// (which a real interrupt does not have: the hardware enters it).
#[inline(never)]
fn no_interrupt(timer: &mut Timer) {
    // SAFETY: an empty asm block; it only keeps the call.
    unsafe { core::arch::asm!("/* {0} */", in(reg) timer, options(nostack)) }
}

#[entry]
fn main() -> ! {
    let mut engine = BenchEngine::new(Default::default());
    // Accelerating: the interval shrinks by 1 tick a step, from 30000.
    let steps = StepCommand::Steps {
        interval: 30_000,
        count: 10_000,
        add: -1,
    };
    for cmd in [StepCommand::Dir(true), steps, steps] {
        if engine.push(0, cmd, 30_000).is_err() {
            panic!("push")
        }
    }
    // Release the moves and arm the first step (outside the measurement).
    let mut timer = Timer::default();
    timer_interrupt(&mut engine, &mut timer);
    measure(0, || 0u32);
    measure(1, || {
        for _ in 0..STEPS {
            // The interrupt comes at the compare time.
            timer.count = timer.compare;
            timer_interrupt(&mut engine, &mut timer);
        }
    });
    let mut bare = Timer::default();
    measure(2, || {
        for _ in 0..STEPS {
            bare.count = bare.compare;
            bare_interrupt(&mut bare);
        }
    });
    let mut idle = Timer::default();
    measure(3, || {
        for _ in 0..STEPS {
            idle.count = idle.compare;
            no_interrupt(&mut idle);
        }
    });
    report(format_args!(
        "stepper_isr: region 1 makes {STEPS} steps (position {:?}); \
         in the same loop {STEPS} times, region 2 runs a bare interrupt \
         (acknowledge, re-arm) and region 3 calls an empty function",
        engine.position(0)
    ));
    exit()
}
