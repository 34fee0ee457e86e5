//! Harness for Cortex-M7 instruction-count benchmarks.
//!
//! Each program in `src/bin` runs on QEMU's mps2-an500 under
//! `shared/tools/m7count`, which counts the guest instructions executed
//! between a call of [`bench_start`] and the next [`bench_stop`]. Build and
//! run one with `cargo m7 --bin NAME` and
//! `../shared/tools/m7count target/thumbv7em-none-eabihf/release/NAME`.
//! Every program measures an empty region first (region 0) to subtract.
#![no_std]

use cortex_m_semihosting::{debug, hprintln};

pub mod stepgen;

/// Marks the start of measured region `id` (the symbol m7count looks for).
#[unsafe(no_mangle)]
#[inline(never)]
pub extern "C" fn bench_start(id: u32) {
    // SAFETY: an empty asm block; it only keeps the call from being removed.
    unsafe { core::arch::asm!("/* {0} */", in(reg) id) }
}

/// Marks the end of measured region `id`.
#[unsafe(no_mangle)]
#[inline(never)]
pub extern "C" fn bench_stop(id: u32) {
    // SAFETY: as above; the nop keeps the two markers distinct.
    unsafe { core::arch::asm!("/* {0} */", "nop", in(reg) id) }
}

/// Runs `work` as measured region `id` and returns its result.
#[inline(always)]
pub fn measure<R>(id: u32, work: impl FnOnce() -> R) -> R {
    bench_start(id);
    let result = work();
    bench_stop(id);
    core::hint::black_box(result)
}

/// Reports a line on the host console through semihosting.
pub fn report(args: core::fmt::Arguments<'_>) {
    hprintln!("{}", args);
}

/// Ends the program successfully (QEMU exits with status 0).
pub fn exit() -> ! {
    debug::exit(debug::EXIT_SUCCESS);
    #[allow(clippy::empty_loop)]
    loop {}
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo<'_>) -> ! {
    hprintln!("panic: {}", info);
    debug::exit(debug::EXIT_FAILURE);
    #[allow(clippy::empty_loop)]
    loop {}
}

/// A small deterministic generator for benchmark inputs (xorshift32).
pub struct Inputs(pub u32);

impl Inputs {
    /// The next pseudo-random value.
    pub fn next_u32(&mut self) -> u32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 17;
        self.0 ^= self.0 << 5;
        self.0
    }

    /// A value in `low..low + span`.
    pub fn between(&mut self, low: i64, span: u32) -> i64 {
        low + i64::from(self.next_u32() % span)
    }
}
