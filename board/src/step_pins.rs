//! Step, direction and enable pins named in printer.cfg, driven through
//! the GPIO registers (the set/reset register, so a write is one store).

use embassy_stm32::pac;
use embassy_stm32::pac::gpio::vals;
use onechip_app::pins::{BadPin, PinName};
use onechip_sched::stepper::StepPins;

/// A push-pull output pin.
#[derive(Clone, Copy)]
pub struct OutPin {
    port: pac::gpio::Gpio,
    number: usize,
    inverted: bool,
}

impl OutPin {
    /// Configures the pin named `name` as a fast push-pull output, at its
    /// inactive level.
    pub fn new(name: &str) -> Result<Self, BadPin<'_>> {
        let PinName {
            port,
            number,
            inverted,
            ..
        } = onechip_app::pins::parse(name)?;
        let port = gpio(port).ok_or(BadPin(name))?;
        let pin = Self {
            port,
            number: usize::from(number),
            inverted,
        };
        pin.set(false);
        port.otyper()
            .modify(|w| w.set_ot(pin.number, vals::Ot::PUSH_PULL));
        port.ospeedr()
            .modify(|w| w.set_ospeedr(pin.number, vals::Ospeedr::VERY_HIGH_SPEED));
        port.moder()
            .modify(|w| w.set_moder(pin.number, vals::Moder::OUTPUT));
        Ok(pin)
    }

    /// Drives the signal active (`true`) or inactive.
    #[inline(always)]
    pub fn set(&self, active: bool) {
        let high = active != self.inverted;
        self.port.bsrr().write(|w| {
            if high {
                w.set_bs(self.number, true);
            } else {
                w.set_br(self.number, true);
            }
        });
    }
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

/// One stepper's step and direction pins.
#[derive(Clone, Copy)]
pub struct StepperPins {
    step: OutPin,
    dir: OutPin,
}

impl StepperPins {
    /// The pins named `step` and `dir`, configured as outputs.
    pub fn new<'a>(step: &'a str, dir: &'a str) -> Result<Self, BadPin<'a>> {
        Ok(Self {
            step: OutPin::new(step)?,
            dir: OutPin::new(dir)?,
        })
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
}

/// A stepper slot of the engine: the pins of a configured stepper, or
/// nothing for an unused slot.
#[derive(Clone, Copy, Default)]
pub struct Slot(pub Option<StepperPins>);

impl StepPins for Slot {
    fn set_dir(&mut self, positive: bool) {
        if let Some(pins) = &mut self.0 {
            pins.set_dir(positive);
        }
    }

    #[inline(always)]
    fn step(&mut self) {
        if let Some(pins) = &mut self.0 {
            pins.step();
        }
    }
}
