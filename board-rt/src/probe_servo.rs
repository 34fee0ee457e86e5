//! A BLTouch's control pin on the board: the servo signal (a pulse of the
//! command's width every 20 ms, `onechip_planner::bltouch`) as software
//! PWM on a GPIO, from TIM23's compare interrupt on the stepper timer's
//! clock (TIM5's count), as the heaters' outputs run from TIM2's. Each
//! command is queued at its clock ([`Output::queue`]); a command whose
//! clock has passed is dropped (logged): the BLTouch then misses it, as a
//! late servo command would on Klipper's MCU.

use crate::handler_cell::{HandlerCell, mask_of};
use crate::step_pins::OutPin;
use crate::step_timer;
use embassy_stm32::interrupt;
use embassy_stm32::interrupt::InterruptExt;
use embassy_stm32::pac;
use onechip_app::probe::SIGNAL_PERIOD;
use onechip_sched::outputs::{Drive, Output, OutputConfig, OutputKind};

/// Ticks the compare is armed ahead of the count at least (10 µs).
const MIN_AHEAD: u32 = 2_600;
/// Longest time between two runs, ticks (10 ms).
const IDLE_WAKE: u32 = 2_600_000;

/// The signal and its pin.
struct Servo {
    output: Output,
    pin: OutPin,
}

/// The servo, once installed; it belongs to TIM23's handler, and thread
/// code reaches it with TIM23's priority masked.
static SERVO: HandlerCell<Servo, { mask_of(crate::priority::PROBE_SERVO) }> = HandlerCell::new();

/// Drives `pin` as the control pin (signal off until the first command)
/// and starts TIM23's interrupt. The pin is turned off by the panic and
/// fault handlers.
pub fn install(pin: OutPin) {
    let config = OutputConfig {
        kind: OutputKind::Digital {
            cycle_ticks: (SIGNAL_PERIOD * step_timer::TIMER_HZ) as u32,
        },
        value: 0,
        default: 0,
        max_duration: 0,
    };
    pin.set(false);
    SERVO.install(Servo {
        output: Output::new(config),
        pin,
    });
    embassy_stm32::rcc::enable_and_reset::<embassy_stm32::peripherals::TIM23>();
    crate::timer32::start(pac::TIM23, Some(MIN_AHEAD));
    interrupt::TIM23.set_priority(crate::priority::PROBE_SERVO);
    // SAFETY: the handler below touches TIM23 and the servo, as the
    // servo's `HandlerCell` allows.
    unsafe { interrupt::TIM23.enable() };
}

/// From 64-bit clock `clock` on, pulses of `pulse_width` s every 20 ms
/// (0: signal off).
pub fn set(clock: u64, pulse_width: f64) {
    let on_ticks = (pulse_width.max(0.0) * step_timer::TIMER_HZ) as u32;
    let queued = SERVO.with(|s| s.output.queue(clock as u32, on_ticks, step_timer::now()));
    if let Some(Err(e)) = queued {
        defmt::warn!("BLTouch command dropped: {}", defmt::Debug2Format(&e));
    }
    // Run the handler now: it arms the compare for the new command.
    pac::TIM23.egr().write(|w| w.set_ccg(0, true));
}

#[interrupt]
fn TIM23() {
    pac::TIM23.sr().write_value(Default::default());
    // SAFETY: this is TIM23's handler, which owns the servo.
    let Some(servo) = (unsafe { SERVO.in_handler() }) else {
        return;
    };
    let now = step_timer::now();
    match servo.output.run(now) {
        Ok(Some(Drive::Level(on))) => servo.pin.set(on),
        Ok(_) => {}
        // No max_duration is set: a timeout never comes; off if it did.
        Err(_) => servo.pin.set(false),
    }
    let wake = servo.output.next_event();
    crate::timer32::arm_for(pac::TIM23, wake, step_timer::now(), MIN_AHEAD, IDLE_WAKE);
}
