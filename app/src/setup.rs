//! printer.cfg, read once for both builds: the machine it describes, its
//! pins checked (none twice, none the board keeps), and what a board must
//! wire up for each stepper. The board sees only this, never the
//! planner's types.

use crate::config_files::ConfigFiles;
use crate::pin_check;
use crate::step_pulse::{has_tmc_driver, step_pulse_duration};
use crate::text::cut_text;
use core::mem::MaybeUninit;
pub use onechip_config::Config;
use onechip_planner::machine::{MAX_STEPPERS, Machine};

/// A config error, with its file, line and option, as text (cut to fit; the config it
/// quotes is gone once the machine is built).
pub type SetupError = heapless::String<192>;

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
    /// The endstop pin of a motion stepper (X, Y, Z rail), if any.
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
        let config = Config::parse_files_in(scratch, files).map_err(|e| cut_text(&e))?;
        let machine = Machine::from_config(config).map_err(|e| cut_text(&e))?;
        pin_check::check(&machine, reserved).map_err(|e| {
            // Where the option at fault is, as every config error says.
            let (file, line) = config
                .section(e.at().section)
                .map_or((config.file(), 0), |s| s.locate(e.at().option));
            cut_text(&format_args!("{file}:{line}: {e}"))
        })?;
        let mut step_pulse = [0.0; MAX_STEPPERS];
        for (pulse, stepper) in step_pulse.iter_mut().zip(&machine.steppers) {
            let tmc = has_tmc_driver(config.section_names(), stepper.name);
            *pulse = step_pulse_duration(stepper.step_pulse_duration, tmc);
        }
        Ok(Self {
            machine,
            step_pulse,
        })
    }

    /// The machine, for the session and the heaters.
    pub fn machine(&self) -> &Machine<'a> {
        &self.machine
    }

    /// What to wire for each stepper, in the machine's order.
    pub fn steppers(&self) -> impl Iterator<Item = StepperWiring<'a>> + '_ {
        let rails = self.machine.stepper_kinematics.len();
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
                endstop_pin: s.endstop_pin.filter(|_| i < rails),
                step_pulse,
            })
    }

    /// Sections printer.cfg has that are not supported yet (ignored).
    pub fn unsupported(&self) -> &[&'a str] {
        &self.machine.unsupported
    }

    /// True if there is a heater or a fan to run.
    pub fn has_thermal(&self) -> bool {
        !self.machine.heaters.is_empty() || self.machine.fan.is_some()
    }

    /// For a board without hardware PWM outputs: a fan configured with
    /// `hard_pwm` runs software PWM instead. True if one was changed.
    pub fn without_hard_pwm(&mut self) -> bool {
        match self.machine.fan.as_mut().filter(|f| f.hard_pwm) {
            Some(fan) => {
                fan.hard_pwm = false;
                true
            }
            None => false,
        }
    }
}
