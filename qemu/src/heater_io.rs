//! The heaters and the fan: [`Heaters`] run from the dual timer's
//! interrupt, below the stepper engine's, on the step clock, as TIM2's
//! interrupt runs them on the board.
//!
//! This machine has no temperature sensors: each heater's ADC input reads what
//! its sensor would read at [`ROOM`] °C (an SPI chip answers with its raw
//! value there), so the heaters' control, reports and safety checks run
//! (and cost what they cost) but nothing heats.
//! Outputs are pins ([`OutPin`]) the plugin logs like the steppers'. As on
//! the board, an output on a secondary MCU has no pin here (its updates
//! are forwarded, [`take_forwarded`]) and an input there is sampled there
//! ([`remote_report`]).

use crate::handler_cell::HandlerCell;
use crate::machine::{DUALTIMER, Irq, priority, write};
use crate::pins::OutPin;
use crate::probe::{self, Context};
use crate::step_timer;
use onechip_app::heaters::{Heaters, INPUTS, OUTPUTS, SpiSensor, ThermalCommand, Wait};
use onechip_app::secondary::forwarded::ForwardedOutputs;
use onechip_app::secondary::thermal::Reading;
use onechip_sched::io::Peripherals;
use onechip_sched::outputs::Drive;
use onechip_sched::shutdown::Shutdown;

/// The ADC's full scale the heaters are configured for (12 bits, as the
/// H723's ADC3).
pub const ADC_MAX: u16 = 4095;
/// The temperature every thermistor reads, °C.
pub const ROOM: f64 = 25.0;

/// Ticks the wake is armed ahead at least (10 µs).
const MIN_AHEAD: u32 = 250;
/// Longest time between two runs, ticks (10 ms).
const IDLE_WAKE: u32 = 250_000;

/// CMSDK dual timer, timer 1 (byte offsets and CONTROL bits).
mod reg {
    /// Loaded into the count at once.
    pub const LOAD: usize = 0x00;
    /// CONTROL: bit 0 one-shot, bit 1 32-bit, bit 5 interrupt, bit 7 on.
    pub const CONTROL: usize = 0x08;
    /// Write: clears the interrupt.
    pub const INTCLR: usize = 0x0c;
    /// One-shot 32-bit counter with its interrupt, running.
    pub const ONE_SHOT: u32 = 1 | 1 << 1 | 1 << 5 | 1 << 7;
}

/// The outputs and thermistor readings the heaters use.
pub struct QemuPeripherals {
    /// Heaters, then the fan, as [`Heaters`] numbers them (None: on a
    /// secondary MCU).
    pub outputs: heapless::Vec<Option<OutPin>, OUTPUTS>,
    /// The updates of the outputs on secondary MCUs.
    pub forwarded: ForwardedOutputs,
    /// What each heater's ADC input reads.
    pub readings: heapless::Vec<u16, INPUTS>,
    /// Each input's SPI chip, if it is one.
    pub chips: heapless::Vec<Option<SpiSensor>, INPUTS>,
}

impl Peripherals for QemuPeripherals {
    fn drive(&mut self, index: usize, drive: Drive) {
        // Software PWM and steady outputs only, as the board.
        if let (Some(Some(pin)), Drive::Level(on)) = (self.outputs.get(index), drive) {
            pin.set(on);
        }
    }

    fn queued(&mut self, index: usize, clock: u32, value: u32) {
        self.forwarded.queued(index, clock, value);
    }

    fn read_adc(&mut self, index: usize) -> u16 {
        // No such input reads as an open thermistor (a range error).
        self.readings.get(index).copied().unwrap_or(ADC_MAX)
    }

    fn spi_transfer(&mut self, index: usize, data: &mut [u8]) {
        // No such chip reads zeros (out of range for a heater).
        match self.chips.get(index).copied().flatten() {
            Some(chip) => {
                let _ = chip.simulate_reply(ROOM, 0, data);
            }
            None => data.fill(0),
        }
    }
}

struct Io {
    heaters: Heaters,
    hw: QemuPeripherals,
}

/// The heaters; they belong to the dual timer's handler.
static IO: HandlerCell<Io> = HandlerCell::new(priority::HEATERS);

/// Hands the heaters and their pins to the dual timer's interrupt and
/// starts it.
pub fn install(heaters: Heaters, hw: QemuPeripherals) {
    IO.install(Io { heaters, hw });
    arm(MIN_AHEAD);
    crate::machine::enable(Irq::DualTimer, priority::HEATERS);
}

/// Raises the interrupt `ahead` ticks from now.
fn arm(ahead: u32) {
    write(DUALTIMER + reg::CONTROL, 0);
    write(DUALTIMER + reg::LOAD, ahead);
    write(DUALTIMER + reg::CONTROL, reg::ONE_SHOT);
}

/// Carries out a heater or fan command now.
pub fn command(command: ThermalCommand) {
    IO.with(|io| {
        if let Err(reason) = io.heaters.command(command, step_timer::now(), &mut io.hw) {
            step_timer::stop(reason);
        }
    });
}

/// The oldest update of an output on a secondary MCU not taken yet:
/// (output, clock, value), the clock 32-bit on the step clock.
pub fn take_forwarded() -> Option<(usize, u32, u32)> {
    IO.with(|io| io.hw.forwarded.take()).flatten()
}

/// A report of an input on a secondary MCU, for the heaters' control and
/// checks as this machine's own (a fault stops everything); the timer
/// then runs the heaters at once, to wake next for what the report
/// queued.
pub fn remote_report(reading: Reading) {
    IO.with(|io| {
        let now = step_timer::now();
        let hz = step_timer::CLOCK_HZ;
        if let Err(reason) = io.heaters.remote_reading(&reading, hz, now, &mut io.hw) {
            step_timer::stop(reason);
        }
        arm(MIN_AHEAD);
    });
}

/// Every heater and fan output off for `reason`.
pub fn shutdown(reason: Shutdown) {
    IO.with(|io| io.heaters.shutdown(reason, &mut io.hw));
}

/// True while `wait` is not over (and the heaters have not shut down).
pub fn waiting(wait: Wait) -> bool {
    IO.with(|io| io.heaters.waiting(wait) && io.heaters.shutdown_reason().is_none())
        .unwrap_or(false)
}

/// True if the extruder is hot enough to extrude.
pub fn can_extrude() -> bool {
    IO.with(|io| io.heaters.can_extrude()).unwrap_or(false)
}

/// Writes the M105 report: copied under the lock, formatted after it.
pub fn report(out: &mut impl core::fmt::Write) {
    if let Some(temperatures) = IO.with(|io| io.heaters.temperatures()) {
        let _ = write!(out, "{temperatures}");
    }
}

/// The dual timer's handler: the heaters' events due, then the next wake.
pub extern "C" fn dualtimer() {
    probe::within(Context::Heaters, || {
        write(DUALTIMER + reg::INTCLR, 1);
        // SAFETY: this is the dual timer's handler, which owns the io.
        let Some(io) = (unsafe { IO.in_handler() }) else {
            return;
        };
        if let Err(reason) = io.heaters.run(step_timer::now(), &mut io.hw) {
            step_timer::stop(reason);
        }
        if io.heaters.shutdown_reason().is_none()
            && let Some(reason) = step_timer::shutdown_reason()
        {
            io.heaters.shutdown(reason, &mut io.hw);
        }
        let now = step_timer::now();
        let ahead = io.heaters.next_wake().map_or(IDLE_WAKE, |wake| {
            (wake.wrapping_sub(now) as i32).max(0).unsigned_abs()
        });
        arm(ahead.clamp(MIN_AHEAD, IDLE_WAKE));
    });
}
