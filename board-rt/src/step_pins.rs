//! Step, direction and enable pins named in printer.cfg, driven through
//! the GPIO registers (the set/reset register, so a write is one store).
//!
//! Each stepper's step pulse lasts its `step_pulse_duration`
//! ([`StepperPins::with_step_pulse`], Klipper's rule in
//! [`onechip_app::step_pulse`]); enable pins made with
//! [`OutPin::new_safe_off`] are turned off by the panic and fault handlers
//! ([`crate::safety`]).

use crate::clocks::SYSCLK_HZ;
use embassy_stm32::pac;
use embassy_stm32::pac::gpio::vals;
use onechip_app::pins::{BadPin, PinName};
use onechip_app::step_pulse;
use onechip_sched::stepper::StepPins;

/// A push-pull output pin, as the two set/reset register words that
/// drive it active and inactive (inversion already applied).
#[derive(Clone, Copy)]
pub struct OutPin {
    port: pac::gpio::Gpio,
    active: u32,
    inactive: u32,
}

impl OutPin {
    /// Configures the pin named `name` as a fast push-pull output, at its
    /// inactive level.
    pub fn new(name: &str) -> Result<Self, BadPin<'_>> {
        let (port, number, parsed) = gpio_pin(name)?;
        let (high, low) = (1 << number, 1 << (number + 16));
        let (active, inactive) = if parsed.inverted {
            (low, high)
        } else {
            (high, low)
        };
        let pin = Self {
            port,
            active,
            inactive,
        };
        pin.set(false);
        port.otyper()
            .modify(|w| w.set_ot(number, vals::Ot::PUSH_PULL));
        port.ospeedr()
            .modify(|w| w.set_ospeedr(number, vals::Ospeedr::VERY_HIGH_SPEED));
        port.moder()
            .modify(|w| w.set_moder(number, vals::Moder::OUTPUT));
        Ok(pin)
    }

    /// [`Self::new`], registered with the panic and fault handlers to be
    /// driven inactive (a driver enable pin: drivers off). A pin the
    /// handlers cannot take is logged, and configured all the same.
    pub fn new_safe_off(name: &str) -> Result<Self, BadPin<'_>> {
        let pin = Self::new(name)?;
        if let Err(e) = pin.register_safe_off() {
            defmt::error!("{}: not turned off on a fault: {}", name, e);
        }
        Ok(pin)
    }

    /// Registers the pin with the panic and fault handlers, which drive it
    /// to its inactive level.
    pub fn register_safe_off(&self) -> Result<(), crate::safety::SafePinError> {
        // The inactive word sets bit n (drive high) or n + 16 (drive low);
        // a pin that drives nothing has none.
        if self.inactive == 0 {
            return Err(crate::safety::SafePinError::NotAPin);
        }
        let bit = self.inactive.trailing_zeros();
        let base = pac::GPIOA.as_ptr() as usize;
        let port = (self.port.as_ptr() as usize).wrapping_sub(base) / crate::gpio::STRIDE;
        crate::safety::register_safe_pin(
            u8::try_from(port).unwrap_or(u8::MAX),
            (bit % 16) as u8,
            bit < 16,
        )
    }

    /// A pin that drives nothing (its writes change no output).
    const fn none() -> Self {
        Self {
            port: pac::GPIOA,
            active: 0,
            inactive: 0,
        }
    }

    /// Drives the signal active (`true`) or inactive: one store.
    #[inline(always)]
    pub fn set(&self, active: bool) {
        let word = if active { self.active } else { self.inactive };
        self.port.bsrr().write_value(pac::gpio::regs::Bsrr(word));
    }
}

/// An input pin (an endstop), as its port's input register bit.
#[derive(Clone, Copy)]
pub struct InPin {
    port: pac::gpio::Gpio,
    mask: u32,
    inverted: bool,
}

impl InPin {
    /// Configures the pin named `name` as an input, with its pull-up if
    /// the name asks for one (`^`).
    pub fn new(name: &str) -> Result<Self, BadPin<'_>> {
        let (port, number, parsed) = gpio_pin(name)?;
        let pull = if parsed.pull_up {
            vals::Pupdr::PULL_UP
        } else {
            vals::Pupdr::FLOATING
        };
        port.pupdr().modify(|w| w.set_pupdr(number, pull));
        port.moder()
            .modify(|w| w.set_moder(number, vals::Moder::INPUT));
        Ok(Self {
            port,
            mask: 1 << number,
            inverted: parsed.inverted,
        })
    }

    /// A pin that never reads active.
    const fn none() -> Self {
        Self {
            port: pac::GPIOA,
            mask: 0,
            inverted: false,
        }
    }

    /// True while the signal is active (high, or low if inverted `!`).
    #[inline(always)]
    pub fn is_active(&self) -> bool {
        (self.port.idr().read().0 & self.mask != 0) != self.inverted
    }
}

/// The port and pin number (0..=15) of the GPIO named `name`, with its
/// modifiers.
pub fn gpio_pin(name: &str) -> Result<(pac::gpio::Gpio, usize, PinName), BadPin<'_>> {
    let pin = onechip_app::pins::parse(name)?;
    let port = crate::gpio::port(pin.port).ok_or(BadPin(name))?;
    let number = usize::from(pin.number);
    if number > 15 {
        return Err(BadPin(name));
    }
    Ok((port, number, pin))
}

/// One stepper's step and direction pins, its step pulse and its rail's
/// endstop; the default drives nothing and never triggers (an unused slot
/// of the engine).
#[derive(Clone, Copy)]
pub struct StepperPins {
    step: OutPin,
    dir: OutPin,
    /// CPU cycles the step pulse lasts, and the least time between a step
    /// and a direction change.
    pulse_cycles: u32,
    endstop: InPin,
}

impl Default for StepperPins {
    fn default() -> Self {
        Self {
            step: OutPin::none(),
            dir: OutPin::none(),
            pulse_cycles: 0,
            endstop: InPin::none(),
        }
    }
}

impl StepperPins {
    /// The pins named `step` and `dir`, configured as outputs, with
    /// Klipper's default pulse for a driver without a `[tmcXXXX]` section
    /// (2 µs) until [`Self::with_step_pulse`] says otherwise.
    pub fn new<'a>(step: &'a str, dir: &'a str) -> Result<Self, BadPin<'a>> {
        Ok(Self {
            step: OutPin::new(step)?,
            dir: OutPin::new(dir)?,
            pulse_cycles: pulse_cycles(step_pulse::DEFAULT),
            endstop: InPin::none(),
        })
    }

    /// The same pins with a step pulse of `seconds` (the stepper's
    /// `step_pulse_duration`, see [`step_pulse::step_pulse_duration`]),
    /// rounded up to whole CPU cycles.
    pub fn with_step_pulse(self, seconds: f64) -> Self {
        Self {
            pulse_cycles: pulse_cycles(seconds),
            ..self
        }
    }

    /// The same pins with `endstop` as the rail's endstop.
    pub fn with_endstop(self, endstop: InPin) -> Self {
        Self { endstop, ..self }
    }
}

/// `seconds` in CPU cycles, rounded up, at most [`step_pulse::MAX`]'s.
fn pulse_cycles(seconds: f64) -> u32 {
    let max = step_pulse::pulse_ticks(step_pulse::MAX, f64::from(SYSCLK_HZ));
    step_pulse::pulse_ticks(seconds, f64::from(SYSCLK_HZ)).min(max)
}

impl StepPins for StepperPins {
    /// Holds the direction pin for the pulse duration on both sides of the
    /// change (Klipper: the step pulse is also the least time between a
    /// step and a direction change); direction changes are rare.
    fn set_dir(&mut self, positive: bool) {
        cortex_m::asm::delay(self.pulse_cycles);
        self.dir.set(positive);
        cortex_m::asm::delay(self.pulse_cycles);
    }

    /// The step pin high for at least the pulse duration (the delay loop
    /// takes at least a cycle per count on the Cortex-M7).
    #[inline(always)]
    fn step(&mut self) {
        self.step.set(true);
        cortex_m::asm::delay(self.pulse_cycles);
        self.step.set(false);
    }

    fn endstop_triggered(&mut self) -> bool {
        self.endstop.is_active()
    }
}
