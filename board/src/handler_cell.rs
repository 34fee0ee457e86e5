//! State that belongs to one interrupt handler, as the stepper engine
//! belongs to TIM5's and the heaters to TIM2's: the handler uses it
//! without a lock, thread code only with interrupts masked.

use core::cell::UnsafeCell;

/// A value owned by one interrupt handler, once installed.
///
/// Invariant: only its handler touches it outside a critical section
/// (through [`Self::in_handler`]); thread code and other handlers touch it
/// only inside one (interrupts masked, so the handler cannot run
/// meanwhile); the handler does not preempt itself.
pub struct HandlerCell<T>(UnsafeCell<Option<T>>);

// SAFETY: by the invariant above, no two accesses ever overlap.
unsafe impl<T> Sync for HandlerCell<T> {}

impl<T> HandlerCell<T> {
    /// Empty until [`Self::install`].
    pub const fn new() -> Self {
        Self(UnsafeCell::new(None))
    }

    /// Puts `value` in the cell (replacing any earlier one).
    pub fn install(&self, value: T) {
        critical_section::with(|_| {
            // SAFETY: interrupts are masked (invariant above).
            unsafe { *self.0.get() = Some(value) };
        });
    }

    /// Runs `f` on the value with interrupts masked; None before it is
    /// installed.
    pub fn with<R>(&self, f: impl FnOnce(&mut T) -> R) -> Option<R> {
        critical_section::with(|_| {
            // SAFETY: interrupts are masked, so the handler is not running
            // and cannot start; this is the only reference (invariant
            // above).
            let value = unsafe { &mut *self.0.get() };
            value.as_mut().map(f)
        })
    }

    /// The handler's own access, without a lock.
    ///
    /// # Safety
    /// Only from the one interrupt handler that owns the cell, and the
    /// reference must not outlive that run of the handler.
    #[inline(always)]
    #[allow(clippy::mut_from_ref)]
    pub unsafe fn in_handler(&self) -> Option<&mut T> {
        // SAFETY: the caller is the owning handler, which nothing else
        // runs during (invariant above).
        unsafe { &mut *self.0.get() }.as_mut()
    }
}
