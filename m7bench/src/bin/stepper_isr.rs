//! Instructions per step on the stepper interrupt's common path on a
//! Cortex-M7: what the board's TIM5 handler runs for each wake —
//! [`Engine::run`] over 4 steppers (one stepping, three idle) making the
//! step due (pulse, position, next interval) and finding the next wake,
//! plus the timer compare write — over long queued moves (the path of all
//! but a move's last step).
#![no_std]
#![no_main]

use cortex_m_rt::entry;
use onechip_m7bench::{exit, measure, report};
use onechip_sched::engine::{Command, Engine};
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

#[entry]
fn main() -> ! {
    let mut engine = Engine::<Pins, 4, 64, 32>::new(Default::default());
    // Accelerating: the interval shrinks by 1 tick a step, from 30000.
    let steps = Command::Steps {
        interval: 30_000,
        count: 10_000,
        add: -1,
    };
    for cmd in [Command::Dir(true), steps, steps] {
        if engine.push(0, cmd, 30_000).is_err() {
            panic!("push")
        }
    }
    // Release the moves and arm the first step (outside the measurement).
    let Some(mut wake) = engine.run(0) else {
        panic!("no step")
    };
    let mut compare = 0u32;
    measure(0, || 0u32);
    measure(1, || {
        for _ in 0..STEPS {
            match engine.run(wake) {
                Some(next) => {
                    wake = next;
                    // SAFETY: a write to a local, as to the compare register.
                    unsafe { core::ptr::write_volatile(&mut compare, next) };
                }
                None => break,
            }
        }
    });
    report(format_args!(
        "stepper_isr: region 1 makes {STEPS} steps (position {:?})",
        engine.position(0)
    ));
    exit()
}
