//! Instructions per step on the stepper interrupt's common path on a
//! Cortex-M7: the engine's step (pulse, position, next interval) plus the
//! GPIO writes of the pulse and the timer compare write for the next step,
//! over long queued moves (the path taken by all but a move's last step).
#![no_std]
#![no_main]

use cortex_m_rt::entry;
use onechip_m7bench::{exit, measure, report};
use onechip_sched::stepper::{StepPins, Stepper};

/// Stands in for the GPIO set/reset register and the timer compare register.
struct Registers {
    bsrr: u32,
    compare: u32,
}

impl StepPins for &mut Registers {
    fn set_dir(&mut self, positive: bool) {
        // SAFETY: a write to a local, kept by the volatile access.
        unsafe {
            core::ptr::write_volatile(&mut self.bsrr, if positive { 1 << 4 } else { 1 << 20 })
        }
    }

    #[inline(always)]
    fn step(&mut self) {
        // Step pin high, then low: the pulse (min width is met by the
        // instructions between the writes on a 520 MHz part).
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
    let mut stepper = Stepper::<4>::new();
    stepper.set_next_dir(true);
    let mut regs = Registers {
        bsrr: 0,
        compare: 0,
    };
    // Long moves with a changing interval, as accelerations produce.
    for _ in 0..2 {
        if stepper.queue(2000, 60_000, -1, 0).is_err() {
            panic!("queue");
        }
    }
    // Load the first move (the uncommon path), outside the measurement.
    let Some(first) = stepper.next_step() else {
        panic!("no step")
    };
    regs.compare = first;
    measure(0, || 0u32);
    measure(1, || {
        for _ in 0..STEPS {
            let mut pins = &mut regs;
            match stepper.step(&mut pins) {
                // SAFETY: as above.
                Some(next) => unsafe { core::ptr::write_volatile(&mut regs.compare, next) },
                None => break,
            }
        }
    });
    report(format_args!(
        "stepper_isr: region 1 makes {STEPS} steps (position {})",
        stepper.position()
    ));
    exit()
}
