//! The machine as `printer.cfg` describes it: kinematics, limits, steppers
//! and the extruder, read and checked the way Klipper reads them.

use crate::accessories::{self, Accessories};
use crate::extruder_stepper::{self, ExtruderStepper, MAX_EXTRUDER_STEPPERS};
use crate::kinematics::{StepperKinematics, calc_position, delta_tower};
use crate::math::sqrt;
use crate::mcu_section::{self, MAX_SECONDARIES, SecondaryMcu};
use crate::planned_move::Limits;
use crate::probe::{self, ProbeConfig};
use crate::reader::{Errors, Read, Reader};
use crate::safe_home::{self, G28};
use crate::sensor_section::{self, MAX_SENSORS, SensorSection};
use crate::shaper_config::{self, InputShaperConfig};
use crate::temperature_sensor;
use crate::thermal::{self, Fan, Heater, IdleTimeoutConfig};
use crate::tmc::{self, config::TmcDriver};
use crate::toolhead::HomingInfo;
use crate::toolhead::{
    CartesianLimits, DeltaHoming, DeltaLimits, ExtruderLimits, Toolhead, Travel,
};
use core::ptr::addr_of_mut;
use onechip_config::{Bounds, Config, ConfigError, Section, decimal};

/// Most steppers a machine may have.
pub const MAX_STEPPERS: usize = 8;
/// Most unsupported sections reported.
pub const MAX_REPORTED: usize = 32;
/// The longest step_pulse_duration a stepper may set, s (Klipper's
/// bound).
pub const MAX_STEP_PULSE_DURATION: f64 = 0.001;

/// The kinematics of the machine.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kinematics {
    /// Each of X, Y, Z has its own stepper.
    Cartesian,
    /// X and Y belts shared by two steppers (A = X + Y, B = X - Y).
    CoreXY,
    /// X and Z belts shared by two steppers.
    CoreXZ,
    /// Three towers with arms (linear delta).
    Delta,
}

/// One stepper's motion settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stepper<'a> {
    /// Section name (`stepper_x`, `extruder`).
    pub name: &'a str,
    /// Step pin name as written (e.g. `PF13`, `!PF13`).
    pub step_pin: &'a str,
    /// Direction pin name as written.
    pub dir_pin: &'a str,
    /// Driver enable pin name as written, if any.
    pub enable_pin: Option<&'a str>,
    /// Endstop pin name as written (`^PG6`, `probe:z_virtual_endstop`), if
    /// any (rails and towers).
    pub endstop_pin: Option<&'a str>,
    /// Distance per full step times microsteps: mm per step.
    pub step_dist: f64,
    /// position_min, mm (rails).
    pub position_min: f64,
    /// position_max, mm (rails).
    pub position_max: f64,
    /// step_pulse_duration, s, if set (0 to 0.001); without it the
    /// driver decides (see `onechip_app::step_pulse`).
    pub step_pulse_duration: Option<f64>,
}

/// Everything the motion pipeline needs from `printer.cfg`.
#[derive(Debug, Clone)]
pub struct Machine<'a> {
    /// The kinematics.
    pub kinematics: Kinematics,
    /// Toolhead limits.
    pub limits: Limits,
    /// Travel and Z limits.
    pub travel: Travel,
    /// The extruder's limits, if it has one.
    pub extruder: Option<ExtruderLimits>,
    /// The steppers following the extruder's motion queue: the
    /// `[extruder]`'s first, if configured, then each
    /// `[extruder_stepper NAME]` in printer.cfg's order.
    pub extruder_steppers: heapless::Vec<ExtruderStepper<'a>, MAX_EXTRUDER_STEPPERS>,
    /// The steppers: the rails (or towers) in order, then each rail's
    /// extra steppers (`[stepper_z1]`, …; see [`Self::extra_rails`]),
    /// then the extruder, then the `[extruder_stepper]`s.
    pub steppers: heapless::Vec<Stepper<'a>, MAX_STEPPERS>,
    /// The rail (0 = X) of each extra stepper, in order: stepper `3 + i`
    /// moves with rail `extra_rails[i]`.
    pub extra_rails: heapless::Vec<usize, MAX_STEPPERS>,
    /// How the first three steppers follow the toolhead.
    pub stepper_kinematics: [StepperKinematics; 3],
    /// Input shaping ([input_shaper]), applied by step generation.
    pub input_shaper: InputShaperConfig,
    /// The heaters: the extruder's (if it has a heater_pin), then the
    /// bed's.
    pub heaters: heapless::Vec<Heater<'a>, 2>,
    /// The part-cooling fan.
    pub fan: Option<Fan<'a>>,
    /// The `[temperature_sensor NAME]` sections.
    pub sensors: heapless::Vec<SensorSection<'a>, MAX_SENSORS>,
    /// What to do when the printer has been idle (`[idle_timeout]`, with
    /// Klipper's defaults when absent).
    pub idle_timeout: IdleTimeoutConfig<'a>,
    /// The secondary MCUs (`[mcu NAME]`), whose pins are written
    /// `NAME:PIN`.
    pub secondaries: heapless::Vec<SecondaryMcu<'a>, MAX_SECONDARIES>,
    /// The Z probe (`[probe]` or `[bltouch]`), if any.
    pub probe: Option<ProbeConfig<'a>>,
    /// How G28 homes (`[safe_z_home]`, `[homing_override]`).
    pub g28: G28<'a>,
    /// `[screws_tilt_adjust]`, if present.
    pub screws_tilt: Option<crate::screws_tilt::ScrewsTilt<'a>>,
    /// `[bed_screws]`, if present.
    pub bed_screws: Option<crate::bed_screws::BedScrews<'a>>,
    /// Named fans, output pins, board pin aliases, filament sensors.
    pub accessories: Accessories<'a>,
    /// The TMC drivers configured over UART or SPI (`[tmc2209 stepper_x]`).
    pub tmc: heapless::Vec<TmcDriver<'a>, { tmc::config::MAX_DRIVERS }>,
    /// For each stepper, the driver (index into [`Self::tmc`]) whose
    /// virtual endstop its endstop pin names
    /// (`tmc2209_stepper_x:virtual_endstop`: sensorless homing), if any.
    pub stall_homing: [Option<u8>; MAX_STEPPERS],
    /// Sections present that onechip does not support yet.
    pub unsupported: heapless::Vec<&'a str, MAX_REPORTED>,
}

/// Options of stepper sections that belong to other parts of the firmware
/// (pins and drivers) or to homing; read so they are not reported unknown.
const STEPPER_OTHER: [&str; 8] = [
    "enable_pin",
    "endstop_pin",
    "homing_speed",
    "homing_retract_dist",
    "homing_retract_speed",
    "second_homing_speed",
    "homing_positive_dir",
    "position_endstop",
];

/// Sections whose options the motion pipeline reads.
const MOTION_SECTIONS: [&str; 18] = [
    "probe",
    "bltouch",
    "safe_z_home",
    "homing_override",
    "printer",
    "stepper_x",
    "stepper_y",
    "stepper_z",
    "stepper_a",
    "stepper_b",
    "stepper_c",
    "extruder",
    "mcu",
    "force_move",
    "input_shaper",
    "heater_bed",
    "fan",
    "idle_timeout",
];

/// Delta tower angles when not configured, degrees.
const DELTA_ANGLES: [f64; 3] = [210.0, 330.0, 90.0];
/// Tower-to-XY motion ratio past which delta moves are slowed.
const SLOW_RATIO: f64 = 3.0;

impl<'a> Machine<'a> {
    /// How many steppers follow the toolhead: the rails (or towers) and
    /// their extra steppers; the extruder comes after them.
    pub fn motion_steppers(&self) -> usize {
        (self.stepper_kinematics.len() + self.extra_rails.len()).min(self.steppers.len())
    }

    /// The rail (0 = X; a delta: the tower) stepper `i` belongs to; None
    /// for the extruder.
    pub fn rail_of(&self, i: usize) -> Option<usize> {
        match i.checked_sub(self.stepper_kinematics.len()) {
            None => (i < self.steppers.len()).then_some(i),
            Some(extra) => self.extra_rails.get(extra).copied(),
        }
    }

    /// How stepper `i` follows the toolhead (an extra stepper as its
    /// rail's); None for the extruder's steppers.
    pub fn kinematics_of(&self, i: usize) -> Option<StepperKinematics> {
        self.rail_of(i).map(|rail| self.stepper_kinematics[rail])
    }

    /// The extruder stepper that is stepper `i`, if it is one (the
    /// `[extruder]`'s or an `[extruder_stepper]`).
    pub fn extruder_stepper(&self, i: usize) -> Option<&ExtruderStepper<'a>> {
        self.extruder_steppers.iter().find(|e| e.stepper == i)
    }

    /// Reads the machine from `config`; every option of the sections it
    /// handles must be valid and known.
    pub fn from_config<'c>(config: &'c Config<'a>) -> Result<Self, ConfigError<'c>> {
        let mut slot = core::mem::MaybeUninit::uninit();
        Self::from_config_in(&mut slot, config)?;
        // SAFETY: from_config_in wrote the machine on success.
        Ok(unsafe { slot.assume_init() })
    }

    /// [`Self::from_config`] written into `slot` (a machine is several KB:
    /// on a microcontroller it goes where it stays, not through the
    /// stack).
    ///
    /// Out of line, as are the section readers it calls: inlined into
    /// one function, every `?` of theirs copies its error through a frame
    /// of tens of KB (5 KiB more flash).
    #[inline(never)]
    pub fn from_config_in<'c, 's>(
        slot: &'s mut core::mem::MaybeUninit<Self>,
        config: &'c Config<'a>,
    ) -> Result<&'s mut Self, ConfigError<'c>> {
        Errors::run(|errors| Self::read_in(slot, config, errors))
    }

    /// [`Self::from_config_in`] into a reading's errors.
    fn read_in<'c, 's>(
        slot: &'s mut core::mem::MaybeUninit<Self>,
        config: &'c Config<'a>,
        errors: &Errors<'c>,
    ) -> Read<&'s mut Self> {
        let section = |section| Reader::new(section, errors);
        let printer = section(errors.check(config.require("printer"))?);
        let kinematics = match printer.get_choice(
            "kinematics",
            &["cartesian", "corexy", "corexz", "delta"],
            None,
        )? {
            "corexy" => Kinematics::CoreXY,
            "corexz" => Kinematics::CoreXZ,
            "delta" => Kinematics::Delta,
            _ => Kinematics::Cartesian,
        };
        let max_velocity = printer.required_float("max_velocity", Bounds::POSITIVE)?;
        let max_accel = printer.required_float("max_accel", Bounds::POSITIVE)?;
        let mut min_cruise_ratio = 0.5;
        if printer
            .get_float_opt("minimum_cruise_ratio", Bounds::NONE)?
            .is_none()
            && let Some(a2d) = printer.get_float_opt("max_accel_to_decel", Bounds::POSITIVE)?
        {
            min_cruise_ratio = 1.0 - (a2d / max_accel).min(1.0);
        }
        let min_cruise_ratio = printer.float(
            "minimum_cruise_ratio",
            min_cruise_ratio,
            Bounds::UNIT_BELOW_ONE,
        )?;
        let scv = printer.float("square_corner_velocity", 5.0, Bounds::NON_NEGATIVE)?;
        let max_z_velocity = printer.float(
            "max_z_velocity",
            max_velocity,
            Bounds {
                above: Some(0.0),
                maxval: Some(max_velocity),
                ..Bounds::NONE
            },
        )?;
        let limits = Limits::new(max_velocity, max_accel, min_cruise_ratio, scv);
        let mut steppers = heapless::Vec::new();
        let mut extra_rails = heapless::Vec::new();
        let probe = probe::read(config, errors)?;
        let g28 = safe_home::read(config, errors)?;
        let screws_tilt = crate::screws_tilt::read(config, errors)?;
        let bed_screws = crate::bed_screws::read(config, errors)?;
        let (travel, stepper_kinematics) = if kinematics == Kinematics::Delta {
            read_delta(config, &printer, &limits, max_z_velocity, &mut steppers)?
        } else {
            read_cartesian(
                config,
                &printer,
                kinematics,
                (max_accel, max_z_velocity),
                &probe,
                (&mut steppers, &mut extra_rails),
            )?
        };

        let mut extruder = None;
        let mut extruder_steppers = heapless::Vec::new();
        let mut heaters = heapless::Vec::new();
        if let Some(section) = config.section("extruder").map(section) {
            extruder = Some(read_extruder(&section, &limits)?);
            let _ =
                extruder_steppers.push(extruder_stepper::read_extruder(&section, steppers.len())?);
            if section.get_opt("heater_pin").is_some() {
                let _ = heaters.push(thermal::read_heater(config, &section)?);
            }
            let _ = steppers.push(read_stepper(&section, StepperKind::Extruder)?);
        }
        extruder_stepper::read_all(
            config,
            errors,
            extruder.is_some(),
            |section| read_stepper(section, StepperKind::Extruder),
            &mut steppers,
            &mut extruder_steppers,
        )?;
        let input_shaper = match config.section("input_shaper").map(section) {
            Some(section) => shaper_config::read(&section)?,
            None => InputShaperConfig::default(),
        };
        if let Some(section) = config.section("heater_bed").map(section) {
            let _ = heaters.push(thermal::read_heater(config, &section)?);
        }
        let fan = config
            .section("fan")
            .map(|s| thermal::read_fan(&section(s)))
            .transpose()?;
        // `[verify_heater NAME]` of a heater onechip drives; one naming
        // any other heater stays unsupported, as that heater is.
        let mut verified = heapless::Vec::<&str, 2>::new();
        for section in config.section_names() {
            let Some(name) = thermal::verify_heater_target(section) else {
                continue;
            };
            let heater = heaters
                .iter_mut()
                .find(|h: &&mut Heater<'_>| h.name == name);
            if let (Some(heater), Some(s)) = (heater, config.section(section))
                && !verified.contains(&section)
            {
                heater.verify = thermal::read_verify_heater(&Reader::new(s, errors), heater.name)?;
                let _ = verified.push(section);
            }
        }
        let idle_timeout = match config.section("idle_timeout").map(section) {
            Some(section) => thermal::read_idle_timeout(&section)?,
            None => IdleTimeoutConfig::default(),
        };
        if let Some(section) = config.section("force_move").map(section) {
            section.get_bool("enable_force_move", false)?;
        }
        let secondaries = mcu_section::read_all(config, errors)?;
        // Sensor types: Klipper reads every definition, used or not.
        temperature_sensor::read_definitions(config, errors)?;
        let heater_names: heapless::Vec<&str, 2> = heaters.iter().map(|h| h.name).collect();
        let stepper_names: heapless::Vec<&str, MAX_STEPPERS> =
            steppers.iter().map(|s| s.name).collect();
        let mut sensors = sensor_section::read_all(config, errors)?;
        let accessories =
            Accessories::read(config, errors, &heater_names, &stepper_names, &mut sensors)?;
        let p = slot.as_mut_ptr();
        // SAFETY: `p` is valid for writes; the field is written before the
        // reference is made. The drivers are read in place: returned, they
        // would cross this frame and read_tmc's (3.5 KB each).
        let tmc = unsafe {
            let field = addr_of_mut!((*p).tmc);
            field.write(heapless::Vec::new());
            &mut *field
        };
        errors.check(read_tmc(config, tmc))?;
        let stall_homing = errors.check(virtual_endstops(config, &steppers, tmc))?;
        let mut unsupported = heapless::Vec::new();
        for name in config.section_names() {
            if !MOTION_SECTIONS.contains(&name)
                && (kinematics == Kinematics::Delta || extra_stepper_rail(name).is_none())
                && !extruder_stepper::is_section(name)
                && !crate::screws_tilt::is_section(name)
                && !crate::bed_screws::is_section(name)
                && !accessories::is_section(name)
                && !name.starts_with("mcu ")
                && !verified.contains(&name)
                && !temperature_sensor::is_definition_section(name)
                && !sensor_section::is_section(name)
                && tmc::DriverKind::of_section(name).is_none()
                && !unsupported.contains(&name)
            {
                let _ = unsupported.push(name);
                config.accept_section(name);
            }
        }
        errors.check(config.check_unused())?;
        // SAFETY: every field but `tmc` (written above) is written here,
        // once, before the slot is taken as initialised.
        unsafe {
            addr_of_mut!((*p).kinematics).write(kinematics);
            addr_of_mut!((*p).limits).write(limits);
            addr_of_mut!((*p).travel).write(travel);
            addr_of_mut!((*p).extra_rails).write(extra_rails);
            addr_of_mut!((*p).extruder).write(extruder);
            addr_of_mut!((*p).extruder_steppers).write(extruder_steppers);
            addr_of_mut!((*p).steppers).write(steppers);
            addr_of_mut!((*p).stepper_kinematics).write(stepper_kinematics);
            addr_of_mut!((*p).input_shaper).write(input_shaper);
            addr_of_mut!((*p).heaters).write(heaters);
            addr_of_mut!((*p).fan).write(fan);
            addr_of_mut!((*p).idle_timeout).write(idle_timeout);
            addr_of_mut!((*p).secondaries).write(secondaries);
            addr_of_mut!((*p).probe).write(probe);
            addr_of_mut!((*p).g28).write(g28);
            addr_of_mut!((*p).screws_tilt).write(screws_tilt);
            addr_of_mut!((*p).bed_screws).write(bed_screws);
            addr_of_mut!((*p).accessories).write(accessories);
            addr_of_mut!((*p).stall_homing).write(stall_homing);
            addr_of_mut!((*p).sensors).write(sensors);
            addr_of_mut!((*p).unsupported).write(unsupported);
            Ok(slot.assume_init_mut())
        }
    }

    /// The TMC driver whose virtual endstop stepper `i` homes on
    /// (sensorless homing), if any.
    pub fn stall_driver(&self, i: usize) -> Option<&TmcDriver<'a>> {
        let k = (*self.stall_homing.get(i)?)?;
        self.tmc.get(usize::from(k))
    }

    /// True if the extruder may extrude before any temperature is known:
    /// it has no heater, or its min_extrude_temp is 0 or less (as
    /// Klipper's `can_extrude` starts).
    pub fn can_extrude_cold(&self) -> bool {
        self.heaters
            .iter()
            .find(|h| h.name == "extruder")
            .is_none_or(|h| h.min_extrude_temp <= 0.0)
    }

    /// The step-generation scan window this machine needs, s: how far
    /// step times can lie before or after the motion causing them
    /// (pressure advance smooths over half its smoothing time each way;
    /// an input shaper's impulses look ahead and behind).
    pub fn scan_delay(&self) -> f64 {
        let pa = extruder_stepper::scan_window(&self.extruder_steppers);
        self.shaper_scan_delay().max(pa)
    }

    /// The input shaper's part of [`Self::scan_delay`], s.
    fn shaper_scan_delay(&self) -> f64 {
        [self.input_shaper.x, self.input_shaper.y]
            .into_iter()
            .flatten()
            .map(|s| s.pulses())
            .fold(0.0, |w, p| w.max(p.lead()).max(p.lag()))
    }

    /// A toolhead for this machine with a lookahead of `N` moves.
    pub fn toolhead<const N: usize>(&self) -> Toolhead<N> {
        let mut toolhead =
            Toolhead::new(self.limits, self.travel, self.extruder, self.scan_delay());
        toolhead.note_other_scan(self.shaper_scan_delay());
        toolhead
    }

    /// [`Self::toolhead`] built in place in `slot`; returns it.
    pub fn toolhead_in<'t, const N: usize>(
        &self,
        slot: &'t mut core::mem::MaybeUninit<Toolhead<N>>,
    ) -> &'t mut Toolhead<N> {
        let toolhead = Toolhead::init_in(
            slot,
            self.limits,
            self.travel,
            self.extruder,
            self.scan_delay(),
        );
        toolhead.note_other_scan(self.shaper_scan_delay());
        toolhead
    }
}

/// What a stepper section drives, which decides its options.
#[derive(Clone, Copy, PartialEq, Eq)]
enum StepperKind {
    /// A cartesian axis with a travel range.
    Rail,
    /// A delta tower (no travel range; arm and angle read elsewhere).
    Tower,
    /// Another stepper of a rail (`[stepper_z1]`): pins, step distance
    /// and an optional endstop of its own.
    Extra,
    /// The extruder.
    Extruder,
}

/// A stepper section's distance per step, mm (Klipper's
/// `parse_step_distance`: rotation_distance over full_steps_per_rotation
/// times microsteps times gear_ratio).
pub fn step_distance<'c>(section: &Section<'c, '_>) -> Result<f64, ConfigError<'c>> {
    Errors::run(|errors| read_step_distance(&Reader::new(*section, errors)))
}

/// [`step_distance`] into a reading's errors.
fn read_step_distance(section: &Reader<'_, '_, '_>) -> Read<f64> {
    let (rotation_distance, steps_per_rotation) = rotation(section)?;
    Ok(rotation_distance / steps_per_rotation)
}

/// A stepper section's rotation_distance (mm per turn) and microsteps
/// per turn (full_steps_per_rotation × microsteps × gear_ratio).
pub(crate) fn rotation(section: &Reader<'_, '_, '_>) -> Read<(f64, f64)> {
    let rotation_distance = section.required_float("rotation_distance", Bounds::POSITIVE)?;
    let microsteps = section.get_int("microsteps", None, Some(1))?;
    let full_steps = section.get_int("full_steps_per_rotation", Some(200), Some(1))?;
    if full_steps % 4 != 0 {
        return Err(section.error_for("full_steps_per_rotation", "must be a multiple of 4"));
    }
    let gear_ratio = match section.get_opt("gear_ratio") {
        Some(text) => parse_gear_ratio(text)
            .ok_or_else(|| section.error_for("gear_ratio", "is not a list of 'a:b' ratios"))?,
        None => 1.0,
    };
    Ok((
        rotation_distance,
        full_steps as f64 * microsteps as f64 * gear_ratio,
    ))
}

fn read_stepper<'a>(section: &Reader<'_, '_, 'a>, kind: StepperKind) -> Read<Stepper<'a>> {
    let step_pin = section.get("step_pin")?;
    let dir_pin = section.get("dir_pin")?;
    let enable_pin = section.get_opt("enable_pin");
    let endstop_pin = match kind {
        StepperKind::Extruder => None,
        _ => section.get_opt("endstop_pin"),
    };
    let step_dist = read_step_distance(section)?;
    let step_pulse_duration = section.get_float_opt(
        "step_pulse_duration",
        Bounds {
            minval: Some(0.0),
            maxval: Some(MAX_STEP_PULSE_DURATION),
            ..Bounds::NONE
        },
    )?;
    let (mut position_min, mut position_max) = (0.0, 0.0);
    match kind {
        StepperKind::Rail => {
            position_min = section.float("position_min", 0.0, Bounds::NONE)?;
            position_max = section.required_float(
                "position_max",
                Bounds {
                    above: Some(position_min),
                    ..Bounds::NONE
                },
            )?;
            section.accept(&STEPPER_OTHER);
        }
        StepperKind::Tower => section.accept(&STEPPER_OTHER),
        StepperKind::Extra => section.accept(&["enable_pin", "endstop_pin"]),
        StepperKind::Extruder => section.accept(&["enable_pin"]),
    }
    Ok(Stepper {
        name: section.name_in_file(),
        step_pin,
        dir_pin,
        enable_pin,
        endstop_pin,
        step_dist,
        position_min,
        position_max,
        step_pulse_duration,
    })
}

/// The rail (0 = X) of an extra stepper section's name: `stepper_z1`
/// (`stepper_x2`, …) is rail Z's.
pub fn extra_stepper_rail(section: &str) -> Option<usize> {
    let rest = section.strip_prefix("stepper_")?;
    let (axis, number) = rest.split_at_checked(1)?;
    let rail = ["x", "y", "z"].iter().position(|a| *a == axis)?;
    (!number.is_empty() && number.bytes().all(|b| b.is_ascii_digit())).then_some(rail)
}

/// An extra stepper section's axis and number (`stepper_z1`: 2, 1).
fn extra_stepper_name(section: &str) -> Option<(u8, u8)> {
    let axis = extra_stepper_rail(section)?;
    let number = section.get("stepper_x".len()..)?.parse().ok()?;
    Some((axis as u8, number))
}

/// Reads every `[stepper_x1]`, `[stepper_z1]`, … (in printer.cfg's
/// order) after the rails; `rails` gets each one's rail.
fn read_extra_steppers<'c, 'a>(
    config: &'c Config<'a>,
    errors: &Errors<'c>,
    steppers: &mut heapless::Vec<Stepper<'a>, MAX_STEPPERS>,
    rails: &mut heapless::Vec<usize, MAX_STEPPERS>,
) -> Read<()> {
    for name in config.section_names() {
        let (Some(rail), Some(section)) = (extra_stepper_rail(name), config.section(name)) else {
            continue;
        };
        let section = Reader::new(section, errors);
        let stepper = read_stepper(&section, StepperKind::Extra)?;
        // Room for the extruder after it.
        if steppers.len() + 1 >= MAX_STEPPERS {
            return Err(section.error_for("step_pin", "too many steppers"));
        }
        let _ = steppers.push(stepper);
        let _ = rails.push(rail);
    }
    Ok(())
}

/// The TMC drivers of `config` into `drivers` ([`tmc::config::read_all`]),
/// out of line (see [`Machine::from_config_in`]).
#[inline(never)]
fn read_tmc<'c, 'a>(
    config: &'c Config<'a>,
    drivers: &mut heapless::Vec<TmcDriver<'a>, { tmc::config::MAX_DRIVERS }>,
) -> Result<(), ConfigError<'c>> {
    tmc::config::read_all(config, step_distance, drivers)
}

/// For each of `steppers`, the driver of `drivers` (its index) whose
/// virtual endstop its endstop pin names
/// (`tmc2209_stepper_x:virtual_endstop`); an endstop pin naming one no
/// driver can give is refused with Klipper's message.
#[inline(never)]
fn virtual_endstops<'c, 'a: 'c>(
    config: &'c Config<'a>,
    steppers: &[Stepper<'a>],
    drivers: &[tmc::config::TmcDriver<'a>],
) -> Result<[Option<u8>; MAX_STEPPERS], ConfigError<'c>> {
    let mut found = [None; MAX_STEPPERS];
    for (slot, stepper) in found.iter_mut().zip(steppers) {
        let Some(pin) = stepper.endstop_pin else {
            continue;
        };
        match tmc::sensorless::virtual_endstop(drivers, pin) {
            Ok(driver) => *slot = driver,
            Err(e) => {
                let section = config.require(stepper.name)?;
                let (message, name) = e.message();
                return Err(section.pin_error("endstop_pin", message, name));
            }
        }
    }
    Ok(found)
}

/// For a rail homing on `probe:z_virtual_endstop`: the probe's z_offset
/// (its position_endstop, as in Klipper), or why it cannot.
fn probe_z(
    stepper: &Stepper<'_>,
    axis: usize,
    probe: &Option<ProbeConfig<'_>>,
) -> Result<Option<f64>, &'static str> {
    match stepper.endstop_pin.map(str::trim) {
        Some(pin) if pin.eq_ignore_ascii_case(probe::VIRTUAL_ENDSTOP) => match probe {
            Some(p) if axis == 2 => Ok(Some(p.offsets[2])),
            Some(_) => Err("probe:z_virtual_endstop can only home Z"),
            None => Err("names chip 'probe': add a [probe] or [bltouch] section"),
        },
        Some(pin)
            if pin
                .trim_start_matches(['^', '~', '!', ' '])
                .eq_ignore_ascii_case(probe::VIRTUAL_ENDSTOP) =>
        {
            Err("probe:z_virtual_endstop can not be inverted or pulled up")
        }
        _ => Ok(None),
    }
}

/// Reads how a rail homes, with Klipper's defaults; `probe_z` is the
/// probe's z_offset if the rail homes on it (then position_endstop is not
/// read).
fn read_homing(
    section: &Reader<'_, '_, '_>,
    (min, max): (f64, f64),
    probe_z: Result<Option<f64>, &'static str>,
) -> Read<HomingInfo> {
    let probe_z = probe_z.map_err(|reason| section.error_for("endstop_pin", reason))?;
    let position_endstop = match probe_z {
        Some(z) => z,
        None => section.required_float("position_endstop", Bounds::NONE)?,
    };
    read_homing_from(section, position_endstop, (min, max), probe_z.is_some())
}

/// [`read_homing`] with position_endstop known (mm): the speeds, the
/// retract and the direction, checked against the travel `(min, max)`.
fn read_homing_from(
    section: &Reader<'_, '_, '_>,
    position_endstop: f64,
    (min, max): (f64, f64),
    probe: bool,
) -> Read<HomingInfo> {
    if position_endstop < min || position_endstop > max {
        return Err(section.error_for(
            "position_endstop",
            "must be between position_min and position_max",
        ));
    }
    let speed = section.float("homing_speed", 5.0, Bounds::POSITIVE)?;
    let second_speed = section.float("second_homing_speed", speed / 2.0, Bounds::POSITIVE)?;
    let retract_speed = section.float("homing_retract_speed", speed, Bounds::POSITIVE)?;
    let retract_dist = section.float("homing_retract_dist", 5.0, Bounds::NON_NEGATIVE)?;
    let positive_dir = match section.get_opt("homing_positive_dir") {
        Some(_) => section.get_bool("homing_positive_dir", false)?,
        None => {
            let quarter = (max - min) / 4.0;
            if position_endstop <= min + quarter {
                false
            } else if position_endstop >= max - quarter {
                true
            } else {
                return Err(
                    section.error_for("position_endstop", "is mid-travel: set homing_positive_dir")
                );
            }
        }
    };
    Ok(HomingInfo {
        position_endstop,
        positive_dir,
        speed,
        second_speed,
        retract_dist,
        retract_speed,
        range: (min, max),
        probe,
    })
}

/// Reads a cartesian (or corexy, corexz) machine's rails, their extra
/// steppers into `steppers` (and `extra_rails`), and its travel limits.
#[inline(never)]
fn read_cartesian<'c, 'a>(
    config: &'c Config<'a>,
    printer: &Reader<'_, 'c, 'a>,
    kinematics: Kinematics,
    (max_accel, max_z_velocity): (f64, f64),
    probe: &Option<ProbeConfig<'_>>,
    (steppers, extra_rails): (
        &mut heapless::Vec<Stepper<'a>, MAX_STEPPERS>,
        &mut heapless::Vec<usize, MAX_STEPPERS>,
    ),
) -> Read<(Travel, [StepperKinematics; 3])> {
    let errors = printer.errors();
    let max_z_accel = printer.float(
        "max_z_accel",
        max_accel,
        Bounds {
            above: Some(0.0),
            maxval: Some(max_accel),
            ..Bounds::NONE
        },
    )?;
    let mut ranges = [(0.0, 0.0); 3];
    let mut homing = [None; 3];
    for (i, name) in ["stepper_x", "stepper_y", "stepper_z"].iter().enumerate() {
        let section = Reader::new(errors.check(config.require(name))?, errors);
        let stepper = read_stepper(&section, StepperKind::Rail)?;
        ranges[i] = (stepper.position_min, stepper.position_max);
        homing[i] = Some(read_homing(
            &section,
            ranges[i],
            probe_z(&stepper, i, probe),
        )?);
        let _ = steppers.push(stepper);
    }
    read_extra_steppers(config, errors, steppers, extra_rails)?;
    let mut travel = CartesianLimits::new(ranges, max_z_velocity, max_z_accel);
    travel.homing = homing;
    for (named, stepper) in travel.extra_steppers.iter_mut().zip(&steppers[3..]) {
        *named = extra_stepper_name(stepper.name);
    }
    use StepperKinematics::{Axis, Difference, Sum};
    let kin = match kinematics {
        Kinematics::CoreXY => [Sum(0, 1), Difference(0, 1), Axis(2)],
        Kinematics::CoreXZ => [Sum(0, 2), Axis(1), Difference(0, 2)],
        _ => [Axis(0), Axis(1), Axis(2)],
    };
    Ok((Travel::Cartesian(travel), kin))
}

/// Reads a linear delta's towers and derives its travel limits.
// Out of line: see `Machine::from_config_in`.
#[inline(never)]
fn read_delta<'c, 'a>(
    config: &'c Config<'a>,
    printer: &Reader<'_, 'c, 'a>,
    limits: &Limits,
    max_z_velocity: f64,
    steppers: &mut heapless::Vec<Stepper<'a>, MAX_STEPPERS>,
) -> Read<(Travel, [StepperKinematics; 3])> {
    let radius = printer.required_float("delta_radius", Bounds::POSITIVE)?;
    let print_radius = printer.float("print_radius", radius, Bounds::POSITIVE)?;
    let errors = printer.errors();
    let tower = |name| Ok(Reader::new(errors.check(config.require(name))?, errors));
    let towers = [
        tower("stepper_a")?,
        tower("stepper_b")?,
        tower("stepper_c")?,
    ];
    let above_radius = Bounds {
        above: Some(radius),
        ..Bounds::NONE
    };
    let arm_a = towers[0].required_float("arm_length", above_radius)?;
    let endstop_a = towers[0].required_float("position_endstop", Bounds::NONE)?;
    let (mut max_z, mut limit_z, mut min_arm, mut min_step_dist) =
        (f64::MAX, f64::MAX, f64::MAX, f64::MAX);
    let mut kinematics = [StepperKinematics::Axis(0); 3];
    let (mut abs_endstops, mut max_arm2) = ([0.0; 3], 0.0f64);
    let mut homing_a = None;
    for (k, ((tower, default_angle), kin)) in towers
        .iter()
        .zip(DELTA_ANGLES)
        .zip(kinematics.iter_mut())
        .enumerate()
    {
        let arm = tower.float("arm_length", arm_a, above_radius)?;
        let endstop = tower.float("position_endstop", endstop_a, Bounds::NONE)?;
        // As Klipper's rails without a travel range: 0 to the endstop.
        let homing = read_homing_from(tower, endstop, (0.0, endstop), false)?;
        homing_a.get_or_insert(homing);
        let angle = tower.float("angle", default_angle, Bounds::NONE)?;
        *kin = StepperKinematics::DeltaTower {
            arm2: arm * arm,
            tower: delta_tower(angle, radius),
        };
        let abs_endstop = endstop + sqrt(arm * arm - radius * radius);
        abs_endstops[k] = abs_endstop;
        max_arm2 = max_arm2.max(arm * arm);
        max_z = max_z.min(endstop);
        limit_z = limit_z.min(abs_endstop - arm);
        min_arm = min_arm.min(arm);
        let stepper = read_stepper(tower, StepperKind::Tower)?;
        min_step_dist = min_step_dist.min(stepper.step_dist);
        let _ = steppers.push(stepper);
    }
    let min_z = printer.float(
        "minimum_z_position",
        0.0,
        Bounds {
            maxval: Some(max_z),
            ..Bounds::NONE
        },
    )?;
    let half_step = min_step_dist * 0.5;
    let ratio_to_xy = |ratio: f64| {
        ratio * sqrt(min_arm * min_arm / (ratio * ratio + 1.0) - half_step * half_step) + half_step
            - radius
    };
    let slow = ratio_to_xy(SLOW_RATIO);
    let very_slow = ratio_to_xy(2.0 * SLOW_RATIO);
    let max_xy = print_radius
        .min(min_arm - radius)
        .min(ratio_to_xy(4.0 * SLOW_RATIO));
    let mut travel = DeltaLimits::new(
        max_xy * max_xy,
        slow * slow,
        very_slow * very_slow,
        max_z,
        min_z,
        limit_z,
        limits.max_velocity,
        limits.max_accel,
        max_z_velocity,
    );
    travel.homing = homing_a.map(|info| DeltaHoming {
        info,
        home: calc_position(&kinematics, abs_endstops),
        force_z: -1.5 * sqrt(max_arm2 - max_xy * max_xy),
    });
    Ok((Travel::Delta(travel), kinematics))
}

// Out of line: see `Machine::from_config_in`.
#[inline(never)]
fn read_extruder(section: &Reader<'_, '_, '_>, limits: &Limits) -> Read<ExtruderLimits> {
    let nozzle_diameter = section.required_float("nozzle_diameter", Bounds::POSITIVE)?;
    let filament_diameter = section.required_float(
        "filament_diameter",
        Bounds {
            minval: Some(nozzle_diameter),
            ..Bounds::NONE
        },
    )?;
    let filament_area =
        core::f64::consts::PI * (filament_diameter * 0.5) * (filament_diameter * 0.5);
    let def_max_cross_section = 4.0 * nozzle_diameter * nozzle_diameter;
    let def_max_extrude_ratio = def_max_cross_section / filament_area;
    let max_cross_section = section.float(
        "max_extrude_cross_section",
        def_max_cross_section,
        Bounds::POSITIVE,
    )?;
    Ok(ExtruderLimits {
        nozzle_diameter,
        filament_area,
        max_extrude_ratio: max_cross_section / filament_area,
        max_e_velocity: section.float(
            "max_extrude_only_velocity",
            limits.max_velocity * def_max_extrude_ratio,
            Bounds::POSITIVE,
        )?,
        max_e_accel: section.float(
            "max_extrude_only_accel",
            limits.max_accel * def_max_extrude_ratio,
            Bounds::POSITIVE,
        )?,
        max_e_dist: section.float("max_extrude_only_distance", 50.0, Bounds::NON_NEGATIVE)?,
        instant_corner_v: section.float(
            "instantaneous_corner_velocity",
            1.0,
            Bounds::NON_NEGATIVE,
        )?,
    })
}

/// `"57:11, 2:1"` -> 57/11 * 2/1.
fn parse_gear_ratio(text: &str) -> Option<f64> {
    text.split(',').try_fold(1.0, |ratio, pair| {
        let (a, b) = pair.split_once(':')?;
        let (a, b) = (decimal::parse(a.trim())?, decimal::parse(b.trim())?);
        (a > 0.0 && b > 0.0).then_some(ratio * a / b)
    })
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::string::ToString;

    #[test]
    fn pins_are_kept_as_written() {
        let text = "[printer]\nkinematics: cartesian\nmax_velocity: 300\nmax_accel: 3000\n\
            [stepper_x]\nstep_pin: PF13\ndir_pin: !PF12\nenable_pin: !PF14\nendstop_pin: ^PG6\n\
            microsteps: 16\nrotation_distance: 40\nposition_endstop: 0\nposition_max: 200\n\
            [stepper_y]\nstep_pin: PG0\ndir_pin: PG1\n\
            microsteps: 16\nrotation_distance: 40\nposition_endstop: 0\nposition_max: 200\n\
            [stepper_z]\nstep_pin: PF11\ndir_pin: PG3\nmicrosteps: 16\nrotation_distance: 8\n\
            endstop_pin: probe:z_virtual_endstop\nposition_max: 200\n\
            [probe]\npin: ^PG10\nz_offset: 1.25\n";
        let config = onechip_config::Config::parse("printer.cfg", text).expect("config");
        let machine = Machine::from_config(&config).expect("machine");
        let x = &machine.steppers[0];
        assert_eq!((x.step_pin, x.dir_pin), ("PF13", "!PF12"));
        assert_eq!((x.enable_pin, x.endstop_pin), (Some("!PF14"), Some("^PG6")));
        assert_eq!(machine.steppers[1].endstop_pin, None);
        assert_eq!(
            machine.steppers[2].endstop_pin,
            Some("probe:z_virtual_endstop")
        );
        // Z homes on the probe: its position_endstop is the z_offset.
        let z = machine.travel.homing_info(2).expect("z homes");
        assert!(z.probe && z.position_endstop == 1.25);
    }

    #[test]
    fn step_pulse_duration_is_read_per_stepper() {
        let text = |x_pulse: &str, e_pulse: &str| {
            std::format!(
                "[printer]\nkinematics: cartesian\nmax_velocity: 300\nmax_accel: 3000\n\
                [stepper_x]\nstep_pin: PF13\ndir_pin: PF12\nendstop_pin: PG6\n\
                microsteps: 16\nrotation_distance: 40\nposition_endstop: 0\nposition_max: 200\n\
                {x_pulse}\n\
                [stepper_y]\nstep_pin: PG0\ndir_pin: PG1\nendstop_pin: PG9\n\
                microsteps: 16\nrotation_distance: 40\nposition_endstop: 0\nposition_max: 200\n\
                [stepper_z]\nstep_pin: PF11\ndir_pin: PG3\nendstop_pin: PG10\nmicrosteps: 16\n\
                rotation_distance: 8\nposition_endstop: 0\nposition_max: 200\n\
                [extruder]\nstep_pin: PG4\ndir_pin: PC1\nmicrosteps: 16\n\
                rotation_distance: 33.5\nnozzle_diameter: 0.4\nfilament_diameter: 1.75\n\
                {e_pulse}\n"
            )
        };
        let pulses = |x_pulse: &str, e_pulse: &str| {
            let text = text(x_pulse, e_pulse);
            let config = onechip_config::Config::parse("printer.cfg", &text).expect("config");
            Machine::from_config(&config)
                .map(|m| m.steppers.iter().map(|s| s.step_pulse_duration).collect())
                .map_err(|e| std::string::ToString::to_string(&e))
        };
        let read: std::vec::Vec<_> =
            pulses("step_pulse_duration: 0.000005", "step_pulse_duration: 0").expect("machine");
        assert_eq!(read, [Some(0.000_005), None, None, Some(0.0)]);
        // Klipper's bounds: 0 to 1 ms.
        for bad in ["0.0011", "-0.000001", "fast"] {
            let e =
                pulses(&std::format!("step_pulse_duration: {bad}"), "").expect_err("out of bounds");
            assert!(e.contains("step_pulse_duration"), "{e}");
        }
        assert!(pulses("", "step_pulse_duration: 0.001").is_ok());
    }

    /// A cartesian printer with a heated extruder and bed, and `extra`.
    fn with_heaters(extra: &str) -> Result<Machine<'static>, std::string::String> {
        let text = std::format!(
            concat!(
                cartesian_printer!(),
                "heater_pin: PA0\nsensor_pin: PF4\n\
            sensor_type: EPCOS 100K B57560G104F\ncontrol: watermark\nmin_temp: 0\nmax_temp: 250\n\
            [heater_bed]\nheater_pin: PA1\nsensor_pin: PF3\nsensor_type: Generic 3950\n\
            control: watermark\nmin_temp: 0\nmax_temp: 130\n{extra}"
            ),
            extra = extra
        );
        // Leaked: the machine borrows the text (a test only).
        let text: &'static str = std::boxed::Box::leak(text.into_boxed_str());
        let config = std::boxed::Box::leak(std::boxed::Box::new(
            onechip_config::Config::parse("printer.cfg", text).map_err(|e| e.to_string())?,
        ));
        Machine::from_config(config).map_err(|e| e.to_string())
    }

    #[test]
    fn every_heater_is_verified_with_klippers_defaults_unless_its_section_says_otherwise() {
        let m = with_heaters("").expect("machine");
        let defaults = |gain_time| crate::thermal::VerifyHeater {
            max_error: 120.0,
            check_gain_time: gain_time,
            hysteresis: 5.0,
            heating_gain: 2.0,
        };
        assert_eq!(m.heaters[0].verify, defaults(20.0));
        assert_eq!(m.heaters[1].verify, defaults(60.0));
        assert_eq!(m.heaters[0].min_extrude_temp, 170.0);
        assert!(!m.can_extrude_cold());
        let m = with_heaters(
            "[verify_heater extruder]\nmax_error: 60\ncheck_gain_time: 30\nhysteresis: 3\n\
            heating_gain: 1\n[verify_heater heater_bed]\ncheck_gain_time: 90\n",
        )
        .expect("machine");
        assert_eq!(
            m.heaters[0].verify,
            crate::thermal::VerifyHeater {
                max_error: 60.0,
                check_gain_time: 30.0,
                hysteresis: 3.0,
                heating_gain: 1.0,
            }
        );
        assert_eq!(m.heaters[1].verify, defaults(90.0));
        assert!(m.unsupported.is_empty(), "{:?}", m.unsupported);
        // A heater onechip does not drive: unsupported, as the heater is.
        let m = with_heaters("[verify_heater extruder1]\nmax_error: 5\n").expect("machine");
        assert_eq!(&m.unsupported[..], ["verify_heater extruder1"]);
        // Klipper's bounds, and unknown options.
        let e =
            with_heaters("[verify_heater extruder]\ncheck_gain_time: 0.5\n").expect_err("bound");
        assert!(e.contains("'check_gain_time'"), "{e}");
        let e = with_heaters("[verify_heater extruder]\nheating_gain: 0\n").expect_err("bound");
        assert!(e.contains("'heating_gain'"), "{e}");
        let e = with_heaters("[verify_heater extruder]\nmax_eror: 5\n").expect_err("typo");
        assert!(e.contains("'max_eror' is not valid"), "{e}");
        // min_extrude_temp 0: extrusion is never refused.
        let m = with_heaters("[extruder]\nmin_extrude_temp: 0\n").expect("machine");
        assert!(m.can_extrude_cold());
    }

    #[test]
    fn the_idle_timeout_is_klippers_unless_configured() {
        let m = with_heaters("").expect("machine");
        assert_eq!(m.idle_timeout.timeout, 600.0);
        assert_eq!(m.idle_timeout.gcode, "TURN_OFF_HEATERS\nM84");
        let m = with_heaters("[idle_timeout]\ntimeout: 1800\ngcode:\n  M104 S0\n  M140 S0\n")
            .expect("machine");
        assert_eq!(m.idle_timeout.timeout, 1800.0);
        assert_eq!(m.idle_timeout.gcode.lines().count(), 2);
        assert!(m.unsupported.is_empty(), "{:?}", m.unsupported);
        let e = with_heaters("[idle_timeout]\ntimeout: 0\n").expect_err("bound");
        assert!(e.contains("'timeout'"), "{e}");
        let e = with_heaters(
            "[idle_timeout]\ngcode:\n  {% if 'heaters' in printer %}\n  TURN_OFF_HEATERS\n  {% endif %}\n",
        )
        .expect_err("template");
        assert!(e.contains("template"), "{e}");
    }

    #[test]
    fn gear_ratios_multiply() {
        assert_eq!(parse_gear_ratio("3:1"), Some(3.0));
        assert_eq!(parse_gear_ratio("57:11, 2:1"), Some(57.0 / 11.0 * 2.0));
        assert_eq!(parse_gear_ratio("3"), None);
        assert_eq!(parse_gear_ratio("0:1"), None);
    }
}
