//! Step, direction and enable pins named in printer.cfg, driven through
//! the GPIO registers (the set/reset register, so a write is one store).

use embassy_stm32::pac;
use embassy_stm32::pac::gpio::vals;
use onechip_app::pins::{BadPin, PinName};
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
fn gpio_pin(name: &str) -> Result<(pac::gpio::Gpio, usize, PinName), BadPin<'_>> {
    let pin = onechip_app::pins::parse(name)?;
    let port = gpio(pin.port).ok_or(BadPin(name))?;
    let number = usize::from(pin.number);
    if number > 15 {
        return Err(BadPin(name));
    }
    Ok((port, number, pin))
}

/// The GPIO port with index `port` (0 = A).
fn gpio(port: u8) -> Option<pac::gpio::Gpio> {
    Some(match port {
        0 => pac::GPIOA,
        1 => pac::GPIOB,
        2 => pac::GPIOC,
        3 => pac::GPIOD,
        4 => pac::GPIOE,
        5 => pac::GPIOF,
        6 => pac::GPIOG,
        7 => pac::GPIOH,
        _ => return None,
    })
}

/// One stepper's step and direction pins and its rail's endstop; the
/// default drives nothing and never triggers (an unused slot of the
/// engine).
#[derive(Clone, Copy)]
pub struct StepperPins {
    step: OutPin,
    dir: OutPin,
    endstop: InPin,
}

impl Default for StepperPins {
    fn default() -> Self {
        Self {
            step: OutPin::none(),
            dir: OutPin::none(),
            endstop: InPin::none(),
        }
    }
}

impl StepperPins {
    /// The pins named `step` and `dir`, configured as outputs.
    pub fn new<'a>(step: &'a str, dir: &'a str) -> Result<Self, BadPin<'a>> {
        Ok(Self {
            step: OutPin::new(step)?,
            dir: OutPin::new(dir)?,
            endstop: InPin::none(),
        })
    }

    /// The same pins with `endstop` as the rail's endstop.
    pub fn with_endstop(self, endstop: InPin) -> Self {
        Self { endstop, ..self }
    }
}

/// CPU cycles the step pulse stays high (about 100 ns at 520 MHz, what
/// Klipper gives TMC drivers).
const PULSE_CYCLES: u32 = 52;

impl StepPins for StepperPins {
    fn set_dir(&mut self, positive: bool) {
        self.dir.set(positive);
    }

    #[inline(always)]
    fn step(&mut self) {
        self.step.set(true);
        cortex_m::asm::delay(PULSE_CYCLES);
        self.step.set(false);
    }

    fn endstop_triggered(&mut self) -> bool {
        self.endstop.is_active()
    }
}
