//! The heaters and the fan on the board: the MCU role's io with the host
//! role's heater control ([`onechip_app::heaters::Heaters`]) run from
//! TIM2's compare interrupt, below the stepper interrupt and above
//! everything else, on the stepper timer's clock (TIM5's count).
//!
//! The interrupt does every output edge, thermistor reading and timeout
//! due, and each report's control update, so heaters keep their safety
//! rules however busy thread code is (planning, a homing wait). A heater
//! fault stops the steppers; a stepper fault turns the heaters off.
//! Outputs are GPIOs ([`OutPin`]); thermistors are read with ADC3.

use crate::handler_cell::HandlerCell;
use crate::step_pins::OutPin;
use crate::step_timer;
use embassy_stm32::adc::{Adc, AnyAdcChannel, SampleTime};
use embassy_stm32::interrupt;
use embassy_stm32::interrupt::InterruptExt;
use embassy_stm32::pac;
use embassy_stm32::peripherals::ADC3;
use onechip_app::heaters::{Heaters, MAX_HEATERS, OUTPUTS, ThermalCommand};
use onechip_sched::io::Peripherals;
use onechip_sched::outputs::Drive;

/// ADC3's full scale (12 bits).
pub const ADC_MAX: u16 = 4095;

/// Ticks the compare is armed ahead of the count at least (10 µs).
const MIN_AHEAD: u32 = 2_600;
/// Longest time between two runs, ticks (10 ms): the interrupt checks
/// the steppers' state at least this often.
const IDLE_WAKE: u32 = 2_600_000;

/// The outputs and thermistor channels the io drives.
pub struct BoardPeripherals {
    /// Heaters, then the fan, as [`Heaters`] numbers them.
    pub outputs: heapless::Vec<OutPin, OUTPUTS>,
    /// ADC3.
    pub adc: Adc<'static, ADC3>,
    /// Each heater's thermistor channel.
    pub channels: heapless::Vec<AnyAdcChannel<'static, ADC3>, MAX_HEATERS>,
}

impl Peripherals for BoardPeripherals {
    fn drive(&mut self, index: usize, drive: Drive) {
        // Only software PWM and steady outputs are configured here (see
        // `install`), so a duty never comes.
        if let (Some(pin), Drive::Level(on)) = (self.outputs.get(index), drive) {
            pin.set(on);
        }
    }

    fn read_adc(&mut self, index: usize) -> u16 {
        match self.channels.get_mut(index) {
            Some(channel) => self.adc.blocking_read(channel, SampleTime::CYCLES64_5),
            // No channel: reads as an open thermistor, which the range
            // check turns into a shutdown.
            None => ADC_MAX,
        }
    }
}

/// The io, once installed.
struct Io {
    heaters: Heaters,
    hw: BoardPeripherals,
}

/// The io, once installed; it belongs to TIM2's handler.
static IO: HandlerCell<Io> = HandlerCell::new();

/// Runs `f` on the io with interrupts masked; None before it is
/// installed.
fn with_io<R>(f: impl FnOnce(&mut Io) -> R) -> Option<R> {
    IO.with(f)
}

/// Hands the heaters and their hardware to TIM2's interrupt and starts
/// it.
pub fn install(heaters: Heaters, hw: BoardPeripherals) {
    IO.install(Io { heaters, hw });
    embassy_stm32::rcc::enable_and_reset::<embassy_stm32::peripherals::TIM2>();
    let tim = pac::TIM2;
    tim.psc().write_value(0);
    tim.arr().write_value(u32::MAX);
    tim.egr().write(|w| w.set_ug(true));
    tim.sr().write_value(Default::default());
    tim.ccr(0).write_value(MIN_AHEAD);
    tim.dier().write(|w| w.set_ccie(0, true));
    tim.cr1().modify(|w| w.set_cen(true));
    interrupt::TIM2.set_priority(crate::priority::HEATERS);
    // SAFETY: the handler below touches TIM2 and the io, as the io's
    // `HandlerCell` allows.
    unsafe { interrupt::TIM2.enable() };
}

/// Carries out a heater or fan command now.
pub fn command(command: ThermalCommand) {
    with_io(|io| {
        if let Err(reason) = io.heaters.command(command, step_timer::now(), &mut io.hw) {
            step_timer::stop(reason);
        }
    });
}

/// True while heater `heater` is still reaching its target.
pub fn busy(heater: usize) -> bool {
    with_io(|io| io.heaters.busy(heater) && io.heaters.shutdown_reason().is_none()).unwrap_or(false)
}

/// Writes the M105 report (`T:… /… B:… /…`) to `out`.
pub fn report(out: &mut impl core::fmt::Write) {
    with_io(|io| io.heaters.report(out));
}

#[interrupt]
fn TIM2() {
    pac::TIM2.sr().write_value(Default::default());
    // SAFETY: this is TIM2's handler, which owns the io.
    let Some(io) = (unsafe { IO.in_handler() }) else {
        return;
    };
    let now = step_timer::now();
    if let Err(reason) = io.heaters.run(now, &mut io.hw) {
        step_timer::stop(reason);
    }
    if io.heaters.shutdown_reason().is_none()
        && let Some(reason) = step_timer::shutdown_reason()
    {
        io.heaters.shutdown(reason, &mut io.hw);
    }
    // Arm the compare for the next wake, on TIM2's own count.
    let now = step_timer::now();
    let ahead = io.heaters.next_wake().map_or(IDLE_WAKE, |wake| {
        let ahead = wake.wrapping_sub(now) as i32;
        (ahead.max(0) as u32).clamp(MIN_AHEAD, IDLE_WAKE)
    });
    let tim = pac::TIM2;
    let at = tim.cnt().read().wrapping_add(ahead);
    tim.ccr(0).write_value(at);
    if onechip_sched::clock::is_before(at, tim.cnt().read()) {
        // Passed while arming (a long stepper interrupt): run again now
        // rather than after TIM2 wraps.
        tim.egr().write(|w| w.set_ccg(0, true));
    }
}
