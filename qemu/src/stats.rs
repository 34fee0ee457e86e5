//! What the firmware measures of itself, printed over semihosting (QEMU's
//! standard output, apart from the console's UART) once a second of step
//! clock: interrupt latency, stack high-water mark and static RAM.
//!
//! The stack is painted at boot; its high-water mark is the lowest word
//! no longer holding the paint. The lowest word of the stack region is
//! its guard: `guard=touched` means the stack reached the statics.

use crate::step_timer;
use core::fmt::Write;
use cortex_m_semihosting::hio::{self, HostStream};

/// What unused stack holds.
const PAINT: u32 = 0x5AC4_5AC4;
/// Bytes below the stack pointer left unpainted at boot (the painting
/// function's own frame and what it calls).
const MARGIN: usize = 512;

unsafe extern "C" {
    /// The end of the statics: the stack's lowest address (cortex-m-rt).
    static __sheap: u32;
    /// The stack's start, its highest address (cortex-m-rt).
    static _stack_start: u32;
}

/// The lowest and highest address of the stack region.
fn stack_region() -> (usize, usize) {
    // Only the symbols' addresses are taken.
    (
        core::ptr::addr_of!(__sheap) as usize,
        core::ptr::addr_of!(_stack_start) as usize,
    )
}

/// Bytes of RAM the statics take (data and bss).
pub fn static_ram() -> usize {
    stack_region().0 - 0x2000_0000
}

/// Paints the unused stack (to call once, early in `main`).
#[inline(never)]
pub fn paint_stack() {
    let (bottom, _) = stack_region();
    let sp = cortex_m::register::msp::read() as usize;
    let mut at = bottom;
    while at + MARGIN < sp {
        // SAFETY: between the statics and the live stack: unused RAM.
        unsafe { core::ptr::write_volatile(at as *mut u32, PAINT) };
        at += 4;
    }
}

/// Bytes of stack ever used, and whether the guard word was touched.
pub fn stack_used() -> (usize, bool) {
    let (bottom, top) = stack_region();
    // SAFETY: reads of the stack region's unused part.
    let painted = |at: usize| unsafe { core::ptr::read_volatile(at as *const u32) } == PAINT;
    let mut at = bottom;
    while at < top && painted(at) {
        at += 4;
    }
    (top - at, !painted(bottom))
}

/// The periodic report.
pub struct Reporter {
    out: Option<HostStream>,
    next: u64,
}

impl Reporter {
    /// A reporter on semihosting's standard output; prints the static
    /// RAM at once.
    pub fn new() -> Self {
        let mut reporter = Self {
            out: hio::hstdout().ok(),
            next: 0,
        };
        reporter.print(format_args!("onechip-qemu: static_ram={}", static_ram()));
        reporter
    }

    /// Prints the figures if a second has passed since the last time.
    pub fn poll(&mut self, now: u64) {
        if now < self.next {
            return;
        }
        self.next = now + step_timer::CLOCK_HZ as u64;
        let (max, mean) = step_timer::latency();
        let (stack, touched) = stack_used();
        self.print(format_args!(
            "stats clock={now} latency_max_ticks={max} latency_mean_ticks={mean:.2} \
             stack_used={stack} guard={} uart1_overruns={}",
            if touched { "touched" } else { "intact" },
            crate::uart_link::overruns()
        ));
    }

    /// Writes one line, formatted before the semihosting call.
    pub fn print(&mut self, args: core::fmt::Arguments<'_>) {
        let mut line = heapless::String::<192>::new();
        let _ = line.write_fmt(args);
        let _ = line.push('\n');
        if let Some(out) = &mut self.out {
            let _ = out.write_all(line.as_bytes());
        }
    }
}
