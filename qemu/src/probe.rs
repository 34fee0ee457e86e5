//! Marks for the TCG plugin's CPU-time accounting: one store to
//! [`crate::machine::PROBE`] when an interrupt handler or a wait starts
//! and ends. The plugin keeps a stack of these contexts (the stepper
//! interrupt preempts the heaters', either preempts a wait) and charges
//! every instruction to the one on top; instructions outside any are
//! thread code. A mark costs two instructions.

use crate::machine::{PROBE, write};

/// What the CPU is doing between two marks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum Context {
    /// The stepper engine's interrupt.
    Stepper = 0,
    /// The heaters' interrupt.
    Heaters = 1,
    /// The console UART's receive interrupt.
    Console = 2,
    /// Thread code waiting (`wfe`): idle.
    Idle = 3,
}

/// Marks the start of `context`.
#[inline(always)]
pub fn enter(context: Context) {
    write(PROBE + 8 * context as usize, 0);
}

/// Marks the end of `context`.
#[inline(always)]
pub fn leave(context: Context) {
    write(PROBE + 8 * context as usize + 4, 0);
}

/// Runs `f` marked as `context`; an interrupt handler's run also counts
/// as an event for thread code's wait ([`crate::machine::sleep`]).
#[inline(always)]
pub fn within<R>(context: Context, f: impl FnOnce() -> R) -> R {
    if context != Context::Idle {
        crate::machine::interrupt_ran();
    }
    enter(context);
    let result = f();
    leave(context);
    result
}
