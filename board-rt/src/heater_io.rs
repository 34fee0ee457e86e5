//! The heaters and the fan on the board: the MCU role's io with the host
//! role's heater control ([`onechip_app::heaters::Heaters`]) run from
//! TIM2's compare interrupt, below the stepper interrupt and above
//! everything else, on the stepper timer's clock (TIM5's count).
//!
//! The interrupt does every output edge, thermistor reading and timeout
//! due, and each report's control update, so heaters keep their safety
//! rules however busy thread code is (planning, a homing wait). A heater
//! fault stops the steppers; a stepper fault turns the heaters off. The
//! outputs are GPIOs ([`OutPin`]), registered with the panic and fault
//! handlers to be turned off ([`crate::safety`]); the thermistors are read
//! with ADC3 ([`Adc3`]).
//!
//! Thread code reaches the io with TIM2's priority masked (BASEPRI), not
//! every interrupt: the stepper interrupt keeps running. The M105 report
//! copies the heaters under that lock and formats the copy after it.
//!
//! A heater, fan or pin output on a secondary MCU has no pin here: the io
//! runs it as its own and keeps its updates ([`ForwardedOutputs`]) for
//! thread code to send there ([`take_forwarded`]); a thermistor there is
//! sampled there, and its reports come in through [`remote_report`].

use crate::handler_cell::{HandlerCell, mask_of};
use crate::step_pins::OutPin;
use crate::step_timer;
use embassy_stm32::Peri;
use embassy_stm32::adc::AnyAdcChannel;
use embassy_stm32::interrupt;
use embassy_stm32::interrupt::InterruptExt;
use embassy_stm32::pac;
use embassy_stm32::peripherals::ADC3;
use onechip_app::heaters::{
    Heaters, INPUTS, LinearConversion, OUTPUTS, TYPICAL_STM32H7_CAL, ThermalCommand, Wait,
};
use onechip_app::secondary::forwarded::ForwardedOutputs;
use onechip_app::secondary::thermal::Reading;
use onechip_sched::io::Peripherals;
use onechip_sched::outputs::Drive;

/// ADC3's full scale (12 bits).
pub const ADC_MAX: u16 = 4095;

/// Ticks the compare is armed ahead of the count at least (10 µs).
const MIN_AHEAD: u32 = 2_600;
/// Longest time between two runs, ticks (10 ms): the interrupt checks
/// the steppers' state at least this often.
const IDLE_WAKE: u32 = 2_600_000;

/// The outputs and ADC inputs the io drives and reads.
pub struct BoardPeripherals {
    /// Heaters, then the fan, as [`Heaters`] numbers them (None: on a
    /// secondary MCU).
    pub outputs: heapless::Vec<Option<OutPin>, OUTPUTS>,
    /// The updates of the outputs on secondary MCUs.
    pub forwarded: ForwardedOutputs,
    /// ADC3.
    pub adc: Adc3,
    /// Each heater's thermistor, then each temperature sensor's input.
    pub inputs: heapless::Vec<AdcInput, INPUTS>,
}

/// What one input reads.
pub enum AdcInput {
    /// An SPI temperature chip.
    Spi(crate::spi_sensors::SpiDevice),
    /// A thermistor input's channel (its pin kept in analog mode).
    Pin(AnyAdcChannel<'static, ADC3>),
    /// The internal temperature sensor (ADC3 channel 18, RM0468; Klipper's
    /// `ADC_TEMPERATURE` on the H7).
    Temperature,
    /// An input on a secondary MCU, sampled there (never read here).
    Elsewhere,
}

impl AdcInput {
    /// Its ADC3 channel (none for an SPI chip).
    fn channel(&self) -> u8 {
        match self {
            Self::Spi(_) | Self::Elsewhere => u8::MAX,
            Self::Pin(channel) => channel.get_hw_channel(),
            Self::Temperature => adc3::TEMPERATURE_CHANNEL,
        }
    }
}

/// The internal temperature sensor's factory calibration, read from the
/// chip (TS_CAL1 at 30 °C and TS_CAL2 at 110 °C, 16-bit readings at 3.3 V,
/// in system memory at 0x1FF1E820 and 0x1FF1E840: RM0468, "Temperature
/// sensor"; the addresses Klipper reads on the H7); a typical chip's if
/// the words are blank or do not rise.
pub fn mcu_sensor() -> LinearConversion {
    const TS_CAL1: *const u16 = 0x1FF1_E820 as *const u16;
    const TS_CAL2: *const u16 = 0x1FF1_E840 as *const u16;
    // SAFETY: both are half-words of the always-readable system memory.
    let cal = unsafe { (TS_CAL1.read_volatile(), TS_CAL2.read_volatile()) };
    if cal.0 == 0 || cal.1 == u16::MAX || cal.1 <= cal.0 {
        defmt::warn!("no temperature sensor calibration: a typical chip's");
        return LinearConversion::stm32h7(TYPICAL_STM32H7_CAL);
    }
    LinearConversion::stm32h7(cal)
}

/// ADC3 of the STM32H72x, which is not ADC1/2: a 12-bit ADC laid out like
/// the STM32G4's (RM0468, "ADC3"). embassy-stm32 0.6 drives it as the
/// 16-bit ADC1/2 and writes bits it does not have (CR.BOOST, CR.ADCALLIN,
/// the PCSEL register) and sample-time codes that mean something else
/// here; this driver writes ADC3's own fields only, as raw words, and
/// nothing else of embassy's ADC driver is linked (`cargo xtask image`).
///
/// Its clock is [`crate::clocks::ADC3_HZ`]; each conversion samples for
/// 640.5 ADC clock cycles, as Klipper does on this ADC
/// (`ADC_ATICKS_H723_ADC3`), for 653 cycles in all: 26 µs.
pub struct Adc3 {
    _adc: Peri<'static, ADC3>,
}

/// ADC3's register fields (RM0468, ADC3 registers).
mod adc3 {
    /// CR: enable.
    pub const CR_ADEN: u32 = 1 << 0;
    /// CR: start a regular conversion.
    pub const CR_ADSTART: u32 = 1 << 2;
    /// CR: voltage regulator on (DEEPPWD, bit 29, left 0: out of deep
    /// power-down).
    pub const CR_ADVREGEN: u32 = 1 << 28;
    /// CR: calibrate (ADCALDIF, bit 30, left 0: single-ended).
    pub const CR_ADCAL: u32 = 1 << 31;
    /// ISR: ready.
    pub const ISR_ADRDY: u32 = 1 << 0;
    /// ISR: end of conversion.
    pub const ISR_EOC: u32 = 1 << 2;
    /// ISR: end of sequence.
    pub const ISR_EOS: u32 = 1 << 3;
    /// ISR: overrun.
    pub const ISR_OVR: u32 = 1 << 4;
    /// SQR1: the first conversion's channel (L, bits 0..3, left 0: one
    /// conversion).
    pub const SQR1_SQ1_SHIFT: u32 = 6;
    /// SMPRx field: 640.5 ADC clock cycles.
    pub const SMP_640_5: u32 = 0b111;
    /// SMPR1 holds channels 0..=9, SMPR2 channels 10..=18, three bits each.
    pub const LAST_CHANNEL: u8 = 18;
    /// Common CCR: CKMODE (bits 16..17, 0: the kernel clock) and PRESC
    /// (bits 18..21).
    pub const CCR_CLOCK_MASK: u32 = 0x3f << 16;
    /// Common CCR: PRESC's position.
    pub const CCR_PRESC_SHIFT: u32 = 18;
    /// DR: the 12-bit result, right-aligned (CFGR.RES and ALIGN at reset).
    pub const DR_MASK: u32 = 0xfff;
    /// Common CCR: the temperature sensor's channel on (VSENSEEN).
    pub const CCR_VSENSEEN: u32 = 1 << 23;
    /// The temperature sensor's channel (VSENSE on ADC3_INP18).
    pub const TEMPERATURE_CHANNEL: u8 = 18;
}

/// Polls of an ADC3 status bit before giving up (each poll is several
/// CPU cycles: far beyond the 26 µs a conversion takes).
const ADC3_POLLS: u32 = 20_000;

impl Adc3 {
    /// Resets ADC3, powers it up, calibrates it and enables it, with every
    /// channel's sample time at 640.5 cycles. A step that does not finish
    /// is logged; the readings are then out of range and shut the heaters
    /// down.
    pub fn new(adc: Peri<'static, ADC3>) -> Self {
        use adc3::*;
        use pac::adc::regs::{Cr, Isr, Smpr};
        embassy_stm32::rcc::enable_and_reset::<ADC3>();
        pac::ADC3_COMMON.ccr().modify(|w| {
            w.0 = (w.0 & !CCR_CLOCK_MASK)
                | crate::clocks::ADC3_PRESC << CCR_PRESC_SHIFT
                | CCR_VSENSEEN;
        });
        let regs = pac::ADC3;
        let us = crate::clocks::SYSCLK_HZ / 1_000_000;
        regs.cr().write_value(Cr(CR_ADVREGEN));
        // The regulator's start-up time (Klipper waits 20 µs).
        cortex_m::asm::delay(20 * us);
        regs.cr().write_value(Cr(CR_ADVREGEN | CR_ADCAL));
        let calibrated = poll(|| regs.cr().read().0 & CR_ADCAL == 0);
        // ADEN may be set 4 ADC clock cycles after ADCAL clears.
        cortex_m::asm::delay(us);
        regs.isr().write_value(Isr(ISR_ADRDY));
        regs.cr().write_value(Cr(CR_ADVREGEN | CR_ADEN));
        let ready = poll(|| regs.isr().read().0 & ISR_ADRDY != 0);
        let every = |channels: u32| (0..channels).fold(0, |w, ch| w | SMP_640_5 << (3 * ch));
        regs.smpr(0).write_value(Smpr(every(10)));
        regs.smpr(1)
            .write_value(Smpr(every(u32::from(LAST_CHANNEL) - 9)));
        if !(calibrated && ready) {
            defmt::error!(
                "ADC3 did not start (calibrated: {}, ready: {})",
                calibrated,
                ready
            );
        }
        Self { _adc: adc }
    }

    /// One conversion of ADC3 channel `channel`, 0..=4095; None if there
    /// is no such channel or the conversion does not end.
    pub fn read(&mut self, channel: u8) -> Option<u16> {
        use adc3::*;
        use pac::adc::regs::{Isr, Sqr1};
        if channel > LAST_CHANNEL {
            return None;
        }
        let regs = pac::ADC3;
        regs.sqr1()
            .write_value(Sqr1(u32::from(channel) << SQR1_SQ1_SHIFT));
        regs.isr().write_value(Isr(ISR_EOC | ISR_EOS | ISR_OVR));
        regs.cr().modify(|w| w.0 |= CR_ADSTART);
        if !poll(|| regs.isr().read().0 & ISR_EOC != 0) {
            return None;
        }
        // Reading DR clears EOC.
        Some((regs.dr().read().0 & DR_MASK) as u16)
    }
}

/// Polls `done` up to [`ADC3_POLLS`] times; true once it is.
fn poll(mut done: impl FnMut() -> bool) -> bool {
    (0..ADC3_POLLS).any(|_| done())
}

impl Peripherals for BoardPeripherals {
    fn drive(&mut self, index: usize, drive: Drive) {
        // Only software PWM and steady outputs are configured here (see
        // `install`), so a duty never comes.
        if let (Some(Some(pin)), Drive::Level(on)) = (self.outputs.get(index), drive) {
            pin.set(on);
        }
    }

    fn queued(&mut self, index: usize, clock: u32, value: u32) {
        self.forwarded.queued(index, clock, value);
    }

    fn read_adc(&mut self, index: usize) -> u16 {
        // No channel, or a failed conversion: reads as an open thermistor,
        // which the range check turns into a shutdown.
        self.inputs
            .get(index)
            .and_then(|input| self.adc.read(input.channel()))
            .unwrap_or(ADC_MAX)
    }

    fn spi_transfer(&mut self, index: usize, data: &mut [u8]) {
        // An input that is no SPI chip reads zeros (out of range).
        match self.inputs.get_mut(index) {
            Some(AdcInput::Spi(chip)) => chip.transfer(data),
            _ => data.fill(0),
        }
    }
}

/// The io, once installed.
struct Io {
    heaters: Heaters,
    hw: BoardPeripherals,
}

/// The io, once installed; it belongs to TIM2's handler, and thread code
/// reaches it with TIM2's priority masked.
static IO: HandlerCell<Io, { mask_of(crate::priority::HEATERS) }> = HandlerCell::new();

/// Runs `f` on the io with TIM2 (and everything below it) masked; None
/// before it is installed.
fn with_io<R>(f: impl FnOnce(&mut Io) -> R) -> Option<R> {
    IO.with(f)
}

/// Hands the heaters and their hardware to TIM2's interrupt and starts
/// it. Every output is registered to be turned off by the panic and fault
/// handlers, and the watchdog from now on resets the chip if TIM2's
/// interrupt stops running.
pub fn install(heaters: Heaters, hw: BoardPeripherals) {
    for pin in hw.outputs.iter().flatten() {
        if let Err(e) = pin.register_safe_off() {
            defmt::error!("heater/fan output not turned off on a fault: {}", e);
        }
    }
    IO.install(Io { heaters, hw });
    embassy_stm32::rcc::enable_and_reset::<embassy_stm32::peripherals::TIM2>();
    crate::timer32::start(pac::TIM2, Some(MIN_AHEAD));
    interrupt::TIM2.set_priority(crate::priority::HEATERS);
    // SAFETY: the handler below touches TIM2 and the io, as the io's
    // `HandlerCell` allows.
    unsafe { interrupt::TIM2.enable() };
    crate::safety::watch_heaters();
}

/// Carries out a heater or fan command now.
pub fn command(command: ThermalCommand) {
    with_io(|io| {
        if let Err(reason) = io.heaters.command(command, step_timer::now(), &mut io.hw) {
            step_timer::stop(reason);
        }
    });
}

/// The oldest update of an output on a secondary MCU not taken yet:
/// (output, clock, value), the clock 32-bit on the stepper timer.
pub fn take_forwarded() -> Option<(usize, u32, u32)> {
    with_io(|io| io.hw.forwarded.take()).flatten()
}

/// A report of an input on a secondary MCU, for the heaters' control and
/// checks as this board's own (a fault stops everything). TIM2's
/// interrupt is then pended, to arm its next wake for what the report
/// queued.
pub fn remote_report(reading: Reading) {
    with_io(|io| {
        let now = step_timer::now();
        let hz = step_timer::TIMER_HZ;
        if let Err(reason) = io.heaters.remote_reading(&reading, hz, now, &mut io.hw) {
            step_timer::stop(reason);
        }
    });
    cortex_m::peripheral::NVIC::pend(interrupt::TIM2);
}

/// Every heater and fan output off at once, for `reason` (M112); they stay
/// off until the board restarts.
pub fn shutdown(reason: onechip_sched::shutdown::Shutdown) {
    with_io(|io| io.heaters.shutdown(reason, &mut io.hw));
}

/// True while `wait` is not over (and the heaters have not shut down).
pub fn waiting(wait: Wait) -> bool {
    with_io(|io| io.heaters.waiting(wait) && io.heaters.shutdown_reason().is_none())
        .unwrap_or(false)
}

/// True if the extruder is hot enough to extrude (false before the
/// heaters are installed).
pub fn can_extrude() -> bool {
    with_io(|io| io.heaters.can_extrude()).unwrap_or(false)
}

/// Writes the M105 report (`T:… /… B:… /…`) to `out`: the temperatures
/// are copied under the lock (which holds off TIM2 only), and formatted
/// after it (formatting floats takes far longer than the copy; TIM2 must
/// not wait for it).
pub fn report(out: &mut impl core::fmt::Write) {
    if let Some(temperatures) = IO.with(|io| io.heaters.temperatures()) {
        let _ = write!(out, "{temperatures}");
    }
}

#[interrupt]
fn TIM2() {
    pac::TIM2.sr().write_value(Default::default());
    crate::safety::heaters_ran();
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
    let wake = io.heaters.next_wake();
    crate::timer32::arm_for(pac::TIM2, wake, step_timer::now(), MIN_AHEAD, IDLE_WAKE);
}
