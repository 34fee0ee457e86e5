//! printer.cfg, read once for both builds: the machine it describes, its
//! pins checked (none twice, none the board keeps), and what a board must
//! wire up for each stepper. The board sees only this, never the
//! planner's types.

use crate::config_files::ConfigFiles;
use crate::heaters::input_buses;
use crate::mcu_config::{on_main, pin_ref};
use crate::pin_check::{self, PinUse};
use crate::step_pulse::{has_tmc_driver, step_pulse_duration};
use crate::text::cut_text;
use core::fmt::Write as _;
use core::mem::MaybeUninit;
pub use onechip_config::Config;
use onechip_planner::board_pins::ReservedPin;
use onechip_planner::machine::{MAX_STEPPERS, Machine};
use onechip_planner::spi_temperature::{SpiBus, SpiBusPins};
use onechip_planner::tmc::config::TmcDriver;

/// A config error, with its file, line and option, as text (cut to fit; the config it
/// quotes is gone once the machine is built).
pub type SetupError = heapless::String<192>;

/// The shortest software PWM cycle a `hardware_pwm` output gets on a
/// board without hardware PWM, s.
pub const MIN_SOFTWARE_CYCLE: f64 = 0.001;

/// A pin name with its alias resolved (modifiers, chip and name).
pub type PinText = heapless::String<32>;

/// What a board wires for one stepper.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepperWiring<'a> {
    /// Section name (`stepper_x`).
    pub name: &'a str,
    /// Step pin as written (`PF13`, `!PF13`).
    pub step_pin: &'a str,
    /// Direction pin as written.
    pub dir_pin: &'a str,
    /// Driver enable pin as written, if any.
    pub enable_pin: Option<&'a str>,
    /// The endstop input of a motion stepper (X, Y, Z rail), if any: its
    /// endstop pin, or the DIAG pin of the TMC driver whose virtual
    /// endstop it homes on.
    pub endstop_pin: Option<&'a str>,
    /// Step pulse length, s (`step_pulse_duration`, or Klipper's default
    /// for the stepper's driver).
    pub step_pulse: f64,
}

/// The printer printer.cfg describes.
#[derive(Debug, Clone)]
pub struct PrinterSetup<'a> {
    machine: Machine<'a>,
    /// Each stepper's step pulse length, s.
    step_pulse: [f64; MAX_STEPPERS],
}

impl<'a> PrinterSetup<'a> {
    /// Reads `files` (printer.cfg first, then its includes) into a
    /// machine; its pins must not repeat nor be any in `reserved`. The
    /// config is indexed in `scratch` (tens of KB: a static on a
    /// microcontroller), which the machine no longer needs.
    // The error is text of a fixed size, returned once at start-up: no heap.
    #[allow(clippy::result_large_err)]
    pub fn load(
        files: &ConfigFiles<'a>,
        reserved: &[(&str, &str)],
        scratch: &mut MaybeUninit<Config<'a>>,
    ) -> Result<Self, SetupError> {
        let mut slot = MaybeUninit::uninit();
        Self::load_in(&mut slot, files, reserved, scratch)?;
        // SAFETY: load_in wrote every field on success.
        Ok(unsafe { slot.assume_init() })
    }

    /// [`Self::load`] written into `slot`: the setup is several KB, which
    /// on a microcontroller go where they stay (a static), not through
    /// the stack.
    #[allow(clippy::result_large_err)]
    // Not inlined: its error exits and locals stay out of the caller's
    // frame.
    #[inline(never)]
    pub fn load_in<'s>(
        slot: &'s mut MaybeUninit<Self>,
        files: &ConfigFiles<'a>,
        reserved: &[(&str, &str)],
        scratch: &mut MaybeUninit<Config<'a>>,
    ) -> Result<&'s mut Self, SetupError> {
        let config = Config::parse_files_in(scratch, files).map_err(|e| cut_text(&e))?;
        let p = slot.as_mut_ptr();
        // SAFETY: a field of the slot, written before it is read.
        let machine_slot = unsafe {
            &mut *core::ptr::addr_of_mut!((*p).machine).cast::<MaybeUninit<Machine<'a>>>()
        };
        let machine = Machine::from_config_in(machine_slot, config).map_err(|e| cut_text(&e))?;
        // Where an option at fault is, as every config error says.
        let at = |used: PinUse<'_>| {
            (config.section(used.section)).map_or((config.file(), 0), |s| s.locate(used.option))
        };
        pin_check::check(machine, reserved).map_err(|e| {
            let (file, line) = at(e.at());
            cut_text(&format_args!("{file}:{line}: {e}"))
        })?;
        if let Some((used, why)) = unsupported_on_secondary(machine) {
            let (file, line) = at(used);
            let pin = used.pin.trim();
            return Err(cut_text(&format_args!(
                "{file}:{line}: {used}: pin '{pin}' {why}"
            )));
        }
        let mut step_pulse = [0.0; MAX_STEPPERS];
        for (pulse, stepper) in step_pulse.iter_mut().zip(&machine.steppers) {
            let tmc = has_tmc_driver(config.section_names(), stepper.name);
            *pulse = step_pulse_duration(stepper.step_pulse_duration, tmc);
        }
        // SAFETY: the other field; with the machine written above, the
        // whole setup is initialised.
        unsafe {
            core::ptr::addr_of_mut!((*p).step_pulse).write(step_pulse);
            Ok(slot.assume_init_mut())
        }
    }

    /// The machine, for the session and the heaters.
    pub fn machine(&self) -> &Machine<'a> {
        &self.machine
    }

    /// For a build that has no links to secondary MCUs (the board's, so
    /// far; QEMU's): an `[mcu NAME]` section is refused, naming its
    /// `serial` option, rather than its pins taken for this MCU's.
    #[allow(clippy::result_large_err)]
    pub fn without_secondaries(&self) -> Result<(), SetupError> {
        match self.machine.secondaries.first() {
            Some(mcu) => {
                let (file, line) = mcu.serial_at;
                Err(cut_text(&format_args!(
                    "{file}:{line}: option 'serial' in section 'mcu {}': this board does not \
                     drive secondary MCUs yet (the simulator does)",
                    mcu.name
                )))
            }
            None => Ok(()),
        }
    }

    /// What to wire for each stepper, in the machine's order.
    pub fn steppers(&self) -> impl Iterator<Item = StepperWiring<'a>> + '_ {
        let rails = self.machine.motion_steppers();
        self.machine
            .steppers
            .iter()
            .zip(self.step_pulse)
            .enumerate()
            .map(move |(i, (s, step_pulse))| StepperWiring {
                name: s.name,
                step_pin: s.step_pin,
                dir_pin: s.dir_pin,
                enable_pin: s.enable_pin,
                // A rail homing on the probe reads the probe's slot; one
                // homing on a TMC driver's virtual endstop, its DIAG pin.
                endstop_pin: s
                    .endstop_pin
                    .filter(|p| i < rails && !crate::probe::is_virtual_endstop(p))
                    .map(|p| match self.machine.stall_driver(i) {
                        Some(TmcDriver {
                            diag: Some((diag, _)),
                            ..
                        }) => diag,
                        _ => p,
                    }),
                step_pulse,
            })
    }

    /// `pin` as printer.cfg writes it, with its `[board_pins]` alias
    /// resolved (`!EXP1_1` → `!PE8`); an alias reserved with `<NAME>` is
    /// an error (the pin check refused those already). A name too long
    /// for [`PinText`] is cut (and then names no pin).
    pub fn resolve_pin(&self, pin: &'a str) -> Result<PinText, ReservedPin<'a>> {
        let resolved = self.machine.accessories.board_pins.resolve(pin)?;
        let mut text = PinText::new();
        let _ = write!(text, "{resolved}");
        Ok(text)
    }

    /// Sections printer.cfg has that are not supported yet (ignored).
    pub fn unsupported(&self) -> &[&'a str] {
        &self.machine.unsupported
    }

    /// True if there is a heater, a fan or a pin to run.
    pub fn has_thermal(&self) -> bool {
        !self.machine.heaters.is_empty()
            || !self.machine.sensors.is_empty()
            || self.machine.fan.is_some()
            || self.machine.accessories.output_count() > 0
    }

    /// For a board without hardware PWM outputs: a fan or output pin on
    /// the main MCU configured with `hardware_pwm` runs software PWM
    /// instead, of its cycle_time but at least [`MIN_SOFTWARE_CYCLE`] (a
    /// hardware cycle of tens of µs would have the heaters' interrupt run
    /// at every edge). One on a secondary keeps its hardware channel.
    /// True if one was changed.
    pub fn without_hard_pwm(&mut self) -> bool {
        let accessories = &mut self.machine.accessories;
        let fans = self
            .machine
            .fan
            .iter_mut()
            .chain(accessories.fans.iter_mut().map(|f| &mut f.fan));
        let mut changed = false;
        for fan in fans.filter(|f| f.hard_pwm && on_main(f.pin)) {
            fan.hard_pwm = false;
            fan.cycle_time = fan.cycle_time.max(MIN_SOFTWARE_CYCLE);
            changed = true;
        }
        for pin in accessories
            .output_pins
            .iter_mut()
            .filter(|p| p.hardware_pwm && on_main(p.pin))
        {
            pin.hardware_pwm = false;
            pin.cycle_time = pin.cycle_time.max(MIN_SOFTWARE_CYCLE);
            changed = true;
        }
        changed
    }
}

/// Why a pin on a secondary MCU is refused: nothing drives it there yet.
const NOT_DRIVEN_THERE: &str = "is on a secondary MCU, where onechip drives only steppers, \
    endstops, heaters, sensors, fans and pins so far";

/// The first pin that no build drives where printer.cfg puts it, and
/// why, if any. Every build drives steppers, their endstops and enable
/// pins, heaters, temperature sensors (on ADC pins, or SPI chips on a
/// hardware bus), fans, output pins and static pins on a secondary MCU;
/// anything else there (a probe, a TMC driver's wires, a filament sensor,
/// an SPI chip on a bit-banged bus, ...) is refused. A stepper's
/// direction pin must be on its step pin's MCU (as Klipper requires); its
/// enable pin may be on any.
fn unsupported_on_secondary<'a>(machine: &Machine<'a>) -> Option<(PinUse<'a>, &'static str)> {
    const SUPPORTED: [&str; 8] = [
        "step_pin",
        "dir_pin",
        "enable_pin",
        "endstop_pin",
        "heater_pin",
        "sensor_pin",
        "pin",
        "pins",
    ];
    fn mcu(pin: &str) -> &str {
        pin_ref(pin).mcu
    }
    let split = (machine.steppers.iter()).find(|s| mcu(s.dir_pin) != mcu(s.step_pin));
    if let Some(s) = split {
        let used = PinUse {
            section: s.name,
            option: "dir_pin",
            pin: s.dir_pin,
        };
        return Some((used, "must be on the same MCU as step_pin"));
    }
    let on_secondary = |pin: &str| (machine.secondaries.iter()).any(|s| s.name == mcu(pin));
    let probe = machine.probe.as_ref().map(|p| p.section);
    // The chip select (its sensor_pin; a pin has one use) of an SPI
    // sensor on a bit-banged bus.
    let spi_chip = |pin: &str| {
        let software = |bus: &SpiBus<'_>| matches!(bus.pins, SpiBusPins::Software { .. });
        (input_buses(machine).flatten()).any(|bus| bus.cs_pin == pin && software(&bus))
    };
    pin_check::uses(machine)
        .find(|used| {
            on_secondary(used.pin)
                && (!SUPPORTED.contains(&used.option)
                    || Some(used.section) == probe
                    || spi_chip(used.pin))
        })
        .map(|used| (used, NOT_DRIVEN_THERE))
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use onechip_config::ConfigFile;
    use std::boxed::Box;
    use std::format;
    use std::string::{String, ToString};

    /// The shipped printer.cfg with `extra` appended, read as the board
    /// reads it.
    fn with_shipped(extra: &str, check: impl FnOnce(&PrinterSetup<'_>)) {
        load_shipped_then(extra, |setup| check(&setup.expect("loads")));
    }

    /// The shipped printer.cfg with `extra` appended: loaded, or why not.
    fn load_shipped(extra: &str) -> Result<(), String> {
        load_shipped_then(extra, |setup| setup.map(|_| ()).map_err(|e| e.to_string()))
    }

    fn load_shipped_then<R>(
        extra: &str,
        then: impl FnOnce(Result<PrinterSetup<'_>, SetupError>) -> R,
    ) -> R {
        let text = format!("{SHIPPED}{extra}");
        let mut files = ConfigFiles::new();
        let file = ConfigFile {
            name: "printer.cfg",
            text: &text,
        };
        files.push(file).expect("one file");
        let mut scratch = Box::new(MaybeUninit::uninit());
        then(PrinterSetup::load(
            &files,
            pin_check::BOARD_RESERVED,
            &mut scratch,
        ))
    }

    /// The shipped printer.cfg.
    const SHIPPED: &str = include_str!("../../sdcard-configs/octopus-pro-h723/printer.cfg");

    /// Lines in the shipped printer.cfg.
    fn shipped_lines() -> usize {
        SHIPPED.lines().count()
    }

    #[test]
    fn a_build_without_secondary_links_refuses_an_mcu_section_naming_its_serial_option() {
        with_shipped("", |setup| assert_eq!(setup.without_secondaries(), Ok(())));
        let lines = include_str!("../../sdcard-configs/octopus-pro-h723/printer.cfg")
            .lines()
            .count();
        with_shipped("\n[mcu ext]\nserial: /dev/ttyUSB1\n", |setup| {
            let expected = std::format!(
                "printer.cfg:{}: option 'serial' in section 'mcu ext': this board does not drive \
                 secondary MCUs yet (the simulator does)",
                lines + 3
            );
            assert_eq!(
                setup.without_secondaries().map_err(|e| e.to_string()),
                Err(expected)
            );
        });
    }

    #[test]
    fn steppers_heaters_and_fans_may_be_on_a_secondary_and_other_pins_are_refused_by_option() {
        let ext = "\n[mcu ext]\nserial: usart2\n";
        let fan = "\n[fan_generic exhaust]\npin: ext:PB1\n";
        with_shipped(&(ext.to_string() + fan), |_| {});
        let sensor = "\n[filament_switch_sensor runout]\nswitch_pin: ext:PB2\n";
        let refused = load_shipped(&(ext.to_string() + sensor)).expect_err("refused");
        let line = shipped_lines() + 6;
        assert_eq!(
            refused,
            format!(
                "printer.cfg:{line}: [filament_switch_sensor runout] switch_pin: pin 'ext:PB2' \
                 is on a secondary MCU, where onechip drives only steppers, endstops, heaters, \
                 sensors, fans and pins so far"
            )
        );
        // A stepper's pins on two MCUs: its direction pin is refused (as
        // Klipper does); its enable pin may be on any MCU.
        let split = "\n[stepper_x]\nstep_pin: ext:PB0\n";
        let refused = load_shipped(&(ext.to_string() + split)).expect_err("refused");
        assert!(
            refused.contains("[stepper_x] dir_pin: pin '")
                && refused.ends_with("must be on the same MCU as step_pin"),
            "{refused}"
        );
        let split = "\n[stepper_x]\nenable_pin: !ext:PB0\n";
        assert!(load_shipped(&(ext.to_string() + split)).is_ok());
        let probe = "\n[probe]\npin: ext:PB3\nz_offset: 1\n";
        let refused = load_shipped(&(ext.to_string() + probe)).expect_err("refused");
        let line = shipped_lines() + 6;
        assert!(
            refused.starts_with(&format!("printer.cfg:{line}: [probe] pin: pin 'ext:PB3'")),
            "{refused}"
        );
    }
}
