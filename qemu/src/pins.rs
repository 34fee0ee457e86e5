//! Step, direction, enable and heater pins named in printer.cfg (STM32
//! names, `PF13`), on this machine's pin ports.
//!
//! QEMU's plugin API (7.2) reports a store's address but not its value,
//! so a pin's level is in the address, as the STM32's BSRR puts it in the
//! bit position: port `p` (0 = A) occupies [`PORT_STRIDE`] bytes from
//! [`PINS`], and a store to word `n` drives pin `n` low, to word
//! `16 + n` high. One store per write, as on the board. Input pins read
//! word 32, which reads 0 (QEMU has no device there): endstops never
//! trigger on this machine.

use crate::machine::{CPU_HZ, PINS, PORT_STRIDE, PORTS, read, write};
use onechip_app::pins::{BadPin, PinName};
use onechip_app::step_pulse;
use onechip_sched::stepper::StepPins;

/// Turns of `cortex_m::asm::delay`'s loop (`subs`, `bne`: two
/// instructions) per second on QEMU. The board counts its delay in CPU
/// cycles, which the M7 takes one to two of per turn; here a pulse lasts
/// what printer.cfg asks for.
const DELAY_HZ: f64 = CPU_HZ as f64 / 2.0;

/// The port past the last: writes there drive nothing.
const NOWHERE: usize = PINS + PORTS as usize * PORT_STRIDE;

/// The address of pin `number` of port `port` driven to `high`.
const fn pin_word(port: u8, number: u8, high: bool) -> usize {
    PINS + port as usize * PORT_STRIDE + 4 * (number as usize + 16 * high as usize)
}

/// The port and pin of the pin named `name`, with its modifiers.
fn parse(name: &str) -> Result<PinName, BadPin<'_>> {
    let pin = onechip_app::pins::parse(name)?;
    if pin.port >= PORTS || pin.number > 15 {
        return Err(BadPin(name));
    }
    Ok(pin)
}

/// An output pin, as the two addresses that drive it active and inactive
/// (inversion applied).
#[derive(Clone, Copy)]
pub struct OutPin {
    active: usize,
    inactive: usize,
}

impl OutPin {
    /// The pin named `name`, driven to its inactive level.
    pub fn new(name: &str) -> Result<Self, BadPin<'_>> {
        let pin = parse(name)?;
        let (high, low) = (
            pin_word(pin.port, pin.number, true),
            pin_word(pin.port, pin.number, false),
        );
        let (active, inactive) = if pin.inverted {
            (low, high)
        } else {
            (high, low)
        };
        let pin = Self { active, inactive };
        pin.set(false);
        Ok(pin)
    }

    /// A pin that drives nothing.
    const fn none() -> Self {
        Self {
            active: NOWHERE,
            inactive: NOWHERE,
        }
    }

    /// Drives the signal active (`true`) or inactive: one store.
    #[inline(always)]
    pub fn set(&self, active: bool) {
        write(if active { self.active } else { self.inactive }, 0);
    }
}

/// An input pin (an endstop).
#[derive(Clone, Copy)]
pub struct InPin {
    address: usize,
    mask: u32,
    inverted: bool,
}

impl InPin {
    /// The pin named `name`.
    pub fn new(name: &str) -> Result<Self, BadPin<'_>> {
        let pin = parse(name)?;
        Ok(Self {
            address: pin_word(pin.port, 0, false) + 4 * 32,
            mask: 1 << pin.number,
            inverted: pin.inverted,
        })
    }

    /// A pin that never reads active.
    const fn none() -> Self {
        Self {
            address: NOWHERE,
            mask: 0,
            inverted: false,
        }
    }

    /// True while the signal is active.
    #[inline(always)]
    pub fn is_active(&self) -> bool {
        (read(self.address) & self.mask != 0) != self.inverted
    }
}

/// One stepper's step and direction pins, step pulse and endstop; the
/// default drives nothing (an unused slot of the engine).
#[derive(Clone, Copy)]
pub struct StepperPins {
    step: OutPin,
    dir: OutPin,
    /// Turns of `cortex_m::asm::delay`'s loop the step pulse lasts (and
    /// the least time between a step and a direction change): its loop is
    /// two instructions a turn, 4 ns here, so [`DELAY_HZ`] turns a second.
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
    /// The pins named `step` and `dir` with a step pulse of `pulse`
    /// seconds (the stepper's `step_pulse_duration`, as the board).
    pub fn new<'a>(step: &'a str, dir: &'a str, pulse: f64) -> Result<Self, BadPin<'a>> {
        let max = step_pulse::pulse_ticks(step_pulse::MAX, DELAY_HZ);
        Ok(Self {
            step: OutPin::new(step)?,
            dir: OutPin::new(dir)?,
            pulse_cycles: step_pulse::pulse_ticks(pulse, DELAY_HZ).min(max),
            endstop: InPin::none(),
        })
    }

    /// The same pins with `endstop` as the rail's endstop.
    pub fn with_endstop(self, endstop: InPin) -> Self {
        Self { endstop, ..self }
    }
}

impl StepPins for StepperPins {
    /// Holds the direction for the pulse duration on both sides of the
    /// change, as the board.
    fn set_dir(&mut self, positive: bool) {
        cortex_m::asm::delay(self.pulse_cycles);
        self.dir.set(positive);
        cortex_m::asm::delay(self.pulse_cycles);
    }

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
