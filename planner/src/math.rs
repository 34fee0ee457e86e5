//! Exact floating-point helpers for `no_std`.
//!
//! `sqrt` must be correctly rounded (the planner reproduces Klipper's
//! numbers): with the `fpu-f64` feature on ARM (a Cortex-M7 with a
//! double-precision FPU, as the STM32H7) it is the FPU's `vsqrt.f64`;
//! elsewhere libm's `sqrt`, which is correctly rounded too, so both give the
//! same bits as Python's `math.sqrt`. (Rust does not expose the FPU's
//! double-precision support to `cfg`, hence the feature.)

/// The correctly rounded square root of `x`.
#[inline]
pub fn sqrt(x: f64) -> f64 {
    #[cfg(all(target_arch = "arm", feature = "fpu-f64"))]
    {
        let out: f64;
        // SAFETY: vsqrt.f64 only reads and writes the given FPU registers.
        unsafe {
            core::arch::asm!("vsqrt.f64 {o}, {i}", o = out(dreg_low16) out, i = in(dreg_low16) x, options(pure, nomem, nostack))
        };
        out
    }
    #[cfg(not(all(target_arch = "arm", feature = "fpu-f64")))]
    {
        libm::sqrt(x)
    }
}

/// `x` limited to `low..=high` (`high` wins if `low > high`; NaN gives
/// `low`). Unlike `f64::clamp` it never panics, and it does not link the
/// float formatting that `f64::clamp`'s assertion message needs.
#[inline]
pub fn clamp(x: f64, low: f64, high: f64) -> f64 {
    x.max(low).min(high)
}

#[cfg(test)]
mod tests {
    use super::sqrt;

    #[test]
    fn exact_on_squares_and_correctly_rounded_elsewhere() {
        for i in 0..10_000u32 {
            let v = f64::from(i);
            assert_eq!(sqrt(v * v), v);
        }
        // sqrt(2) correctly rounded.
        assert_eq!(sqrt(2.0).to_bits(), 0x3ff6_a09e_667f_3bcd);
    }
}
