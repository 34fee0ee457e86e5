//! The 32-bit general-purpose timers the interrupts run on (TIM2, TIM5,
//! TIM23, TIM24): each counts freely at the APB1 timer clock (260 MHz,
//! wrapping every 16.5 s) and interrupts on its compare 1.

use embassy_stm32::pac::timer::TimGp32;

/// Starts `tim` (clocked and reset by the caller) counting from 0 at the
/// timer clock, with its compare-1 interrupt armed at count `first`, or
/// not enabled (None).
pub fn start(tim: TimGp32, first: Option<u32>) {
    tim.psc().write_value(0);
    tim.arr().write_value(u32::MAX);
    tim.egr().write(|w| w.set_ug(true));
    tim.sr().write_value(Default::default());
    if let Some(at) = first {
        tim.ccr(0).write_value(at);
        tim.dier().write(|w| w.set_ccie(0, true));
    }
    tim.cr1().modify(|w| w.set_cen(true));
}

/// Arms `tim`'s compare 1 at count `at` ([`raise_if_passed`]).
#[inline(always)]
pub fn arm(tim: TimGp32, at: u32) {
    tim.ccr(0).write_value(at);
    raise_if_passed(tim, at);
}

/// Raises `tim`'s compare-1 interrupt now if its count has reached `at`
/// already (the interrupt was held off while arming): a compare written
/// at or behind the count matches only after the counter wraps.
#[inline(always)]
pub fn raise_if_passed(tim: TimGp32, at: u32) {
    if !onechip_sched::clock::is_before(tim.cnt().read(), at) {
        tim.egr().write(|w| w.set_ccg(0, true));
    }
}

/// Arms `tim`'s next interrupt for `wake` (a time on the stepper clock,
/// whose count is `now`; None: nothing due): at least `min` ticks and at
/// most `idle` ticks from its own count.
pub fn arm_for(tim: TimGp32, wake: Option<u32>, now: u32, min: u32, idle: u32) {
    let ahead = wake.map_or(idle, |wake| {
        let ahead = wake.wrapping_sub(now) as i32;
        (ahead.max(0) as u32).clamp(min, idle)
    });
    arm(tim, tim.cnt().read().wrapping_add(ahead));
}
