//! State that belongs to one interrupt handler, as the stepper engine
//! belongs to TIM5's and the heaters to TIM2's: the handler uses it
//! without a lock, other code only while that handler is masked.
//!
//! The lock masks no more than it must: a cell owned by a handler below
//! the top priority (`MASK`, its priority as BASEPRI writes it) raises
//! BASEPRI to the owner's priority, which holds off the owner and everything at or below
//! it while interrupts above it (the stepper timer) keep running; a cell
//! owned by a top-priority handler (`MASK` 0) masks every
//! interrupt (BASEPRI cannot mask priority 0). The STM32H7's Cortex-M7 is
//! r1p1 or later, so BASEPRI needs no erratum 837070 workaround.

use core::cell::UnsafeCell;
use core::mem::MaybeUninit;
use core::sync::atomic::{Ordering, compiler_fence};
use cortex_m::peripheral::{NVIC, SCB};
use embassy_stm32::interrupt::Priority;

/// A value owned by one interrupt handler, once installed.
///
/// Invariant: only its handler touches it outside the cell's lock (through
/// [`Self::in_handler`]); other code touches it only inside the lock
/// ([`Self::with`]), which holds the handler off, and
/// only from thread mode or a handler that the owner cannot preempt
/// (priority at or below the owner's; checked); the handler does not
/// preempt itself.
///
/// The owner's priority is in the type (`MASK`, as BASEPRI writes it; 0:
/// the top priority, every interrupt masked), so an empty cell is all
/// zero bytes, the same as [`Self::new`] ([`Self::ZEROED_IS_NEW`],
/// checked at compile time): a cell lives in memory zeroed at boot (the
/// stepper engine's in DTCM), and takes no flash for initial contents.
pub struct HandlerCell<T, const MASK: u8 = 0> {
    slot: UnsafeCell<Slot<T>>,
}

/// The value, once installed.
struct Slot<T> {
    /// True once `value` holds a value.
    installed: bool,
    value: MaybeUninit<T>,
}

impl<T> Slot<T> {
    /// The value, if installed.
    #[inline(always)]
    fn get_mut(&mut self) -> Option<&mut T> {
        // SAFETY: `installed` says `value` is initialised.
        self.installed
            .then(|| unsafe { self.value.assume_init_mut() })
    }

    /// Installs `value`, dropping any earlier one.
    fn put(&mut self, value: T) {
        if self.installed {
            // SAFETY: `installed` says `value` is initialised; it is
            // overwritten next.
            unsafe { self.value.assume_init_drop() };
        }
        self.value.write(value);
        self.installed = true;
    }
}

// SAFETY: by the invariant above, no two accesses ever overlap.
unsafe impl<T, const MASK: u8> Sync for HandlerCell<T, MASK> {}

/// `MASK` for a cell owned by a handler at `owner` priority: the lock
/// masks that priority and below only.
pub const fn mask_of(owner: Priority) -> u8 {
    owner as u8
}

impl<T, const MASK: u8> Default for HandlerCell<T, MASK> {
    fn default() -> Self {
        Self::new()
    }
}

impl<T, const MASK: u8> HandlerCell<T, MASK> {
    /// Empty until [`Self::install`].
    pub const fn new() -> Self {
        Self {
            slot: UnsafeCell::new(Slot {
                installed: false,
                value: MaybeUninit::uninit(),
            }),
        }
    }

    /// True: a cell of all-zero bytes is empty, as [`Self::new`] makes
    /// it. Evaluated at compile time (an invalid all-zero value would fail
    /// the build).
    pub const ZEROED_IS_NEW: bool = {
        // SAFETY: every field takes zero bytes: `MaybeUninit` any bytes,
        // `bool` false.
        let zeroed: Self = unsafe { core::mem::zeroed() };
        !zeroed.slot.into_inner().installed
    };

    /// Puts `value` in the cell (replacing any earlier one).
    pub fn install(&self, value: T) {
        self.lock(|slot| slot.put(value));
    }

    /// Runs `f` on the value with the owner masked; None before it is
    /// installed. Keep `f` short: it delays the owner and everything
    /// below it.
    pub fn with<R>(&self, f: impl FnOnce(&mut T) -> R) -> Option<R> {
        self.lock(|slot| slot.get_mut().map(f))
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
        unsafe { &mut *self.slot.get() }.get_mut()
    }

    /// Runs `f` on the slot with the owner held off.
    fn lock<R>(&self, f: impl FnOnce(&mut Slot<T>) -> R) -> R {
        assert!(
            caller_below(MASK),
            "HandlerCell locked from above its owner's priority"
        );
        // SAFETY: the owner's priority is masked and the caller runs at
        // or below it (checked above), so the owner is not running and
        // cannot start; this is the only reference (invariant above).
        masked(MASK, || f(unsafe { &mut *self.slot.get() }))
    }
}

/// Runs `f` with the interrupts at priority `mask` (as BASEPRI writes it)
/// and below held off, those above still running; `mask` 0 holds off
/// every interrupt (BASEPRI cannot mask priority 0). Keep `f` short.
pub fn masked<R>(mask: u8, f: impl FnOnce() -> R) -> R {
    if mask == 0 {
        return critical_section::with(|_| f());
    }
    let before = cortex_m::register::basepri::read();
    // Raises the mask only (never lowers one already stricter).
    cortex_m::register::basepri_max::write(mask);
    compiler_fence(Ordering::SeqCst);
    let result = f();
    compiler_fence(Ordering::SeqCst);
    // SAFETY: restores the mask this function found.
    unsafe { cortex_m::register::basepri::write(before) };
    result
}

/// True if the code running now cannot be preempted by a handler at
/// priority `mask` (0: the top priority): thread mode, or an interrupt at
/// that priority or below. System exceptions (faults, NMI) never lock.
fn caller_below(mask: u8) -> bool {
    // SAFETY: a read of ICSR, which has no side effects.
    let active = unsafe { (*SCB::PTR).icsr.read() } & 0x1ff;
    match active {
        0 => true,
        1..=15 => false,
        vector => {
            // SAFETY: a read of the interrupt's priority byte.
            let priority = unsafe { (*NVIC::PTR).ipr[(vector - 16) as usize].read() };
            priority >= mask
        }
    }
}
