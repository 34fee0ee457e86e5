//! State owned by one interrupt handler (the stepper engine by timer 0's,
//! the heaters by the dual timer's, the console's line queue by the
//! UART's): the handler uses it without a lock, other code only while
//! that handler is masked. The same rule as the board's `HandlerCell`
//! (board-rt/src/handler_cell.rs), written for this machine's priorities
//! (plain NVIC bytes, no embassy).

use core::cell::UnsafeCell;
use core::sync::atomic::{Ordering, compiler_fence};

/// A value owned by one interrupt handler, once installed.
///
/// Invariant: its handler touches it only through [`Self::in_handler`];
/// other code only through [`Self::with`], from thread mode or from a
/// handler the owner cannot preempt (at or below the owner's priority).
pub struct HandlerCell<T> {
    value: UnsafeCell<Option<T>>,
    /// The owner's priority byte; 0 (the top priority, which BASEPRI
    /// cannot mask): every interrupt is masked instead.
    mask: u8,
}

// SAFETY: by the invariant above, no two accesses ever overlap.
unsafe impl<T> Sync for HandlerCell<T> {}

impl<T> HandlerCell<T> {
    /// Empty until [`Self::install`], owned by a handler at priority byte
    /// `owner`.
    pub const fn new(owner: u8) -> Self {
        Self {
            value: UnsafeCell::new(None),
            mask: owner,
        }
    }

    /// Puts `value` in the cell (replacing any earlier one).
    pub fn install(&self, value: T) {
        self.lock(|slot| *slot = Some(value));
    }

    /// Runs `f` on the value with the owner masked; None before it is
    /// installed. Keep `f` short: it delays the owner.
    pub fn with<R>(&self, f: impl FnOnce(&mut T) -> R) -> Option<R> {
        self.lock(|slot| slot.as_mut().map(f))
    }

    /// The owning handler's access, without a lock.
    ///
    /// # Safety
    /// Only from the handler that owns the cell; the reference must not
    /// outlive that run of the handler.
    #[inline(always)]
    #[allow(clippy::mut_from_ref)]
    pub unsafe fn in_handler(&self) -> Option<&mut T> {
        // SAFETY: the caller is the owner, during which nothing else
        // touches the value (invariant above).
        unsafe { &mut *self.value.get() }.as_mut()
    }

    fn lock<R>(&self, f: impl FnOnce(&mut Option<T>) -> R) -> R {
        if self.mask == 0 {
            // SAFETY (inside): every interrupt is masked, so the owner
            // cannot run; this is the only reference.
            critical_section::with(|_| f(unsafe { &mut *self.value.get() }))
        } else {
            let before = cortex_m::register::basepri::read();
            cortex_m::register::basepri_max::write(self.mask);
            compiler_fence(Ordering::SeqCst);
            // SAFETY: BASEPRI holds the owner off and the caller runs at
            // or below it (invariant above); this is the only reference.
            let result = f(unsafe { &mut *self.value.get() });
            compiler_fence(Ordering::SeqCst);
            // SAFETY: restores the mask found on entry.
            unsafe { cortex_m::register::basepri::write(before) };
            result
        }
    }
}
