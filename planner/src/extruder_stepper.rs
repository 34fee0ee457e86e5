//! The steppers that follow an extruder's motion queue, as Klipper's
//! `ExtruderStepper`: the `[extruder]`'s own stepper and every
//! `[extruder_stepper NAME]` (an extra stepper, synced to `extruder` or to
//! nothing), each with its own rotation distance and pressure advance;
//! and their G-code: SET_PRESSURE_ADVANCE, SET_EXTRUDER_ROTATION_DISTANCE
//! and SYNC_EXTRUDER_MOTION, with Klipper's replies and refusals.

use crate::gcode::Extended;
use crate::gcode_move::CommandError;
use crate::machine::{MAX_STEPPERS, Stepper};
use crate::move_sink::{ExtruderStepperMotion, MoveSink};
use crate::reader::{Errors, Read, Reader};
use crate::toolhead::Toolhead;
use core::fmt::Write;
use onechip_config::decimal::Fixed;
use onechip_config::{Bounds, Config};

/// Most steppers following an extruder (the `[extruder]`'s and the
/// `[extruder_stepper]`s): every stepper but the three rails'.
pub const MAX_EXTRUDER_STEPPERS: usize = MAX_STEPPERS - 3;

/// The only motion queue a stepper may follow: the `[extruder]`'s.
pub const EXTRUDER: &str = "extruder";

/// Prefix of the `[extruder_stepper NAME]` sections.
const SECTION_PREFIX: &str = "extruder_stepper ";

/// One stepper following an extruder's motion queue, as configured and
/// as G-code changes it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExtruderStepper<'a> {
    /// Its name in G-code (`EXTRUDER=`): `extruder`, or the NAME of
    /// `[extruder_stepper NAME]`.
    pub name: &'a str,
    /// Its index in [`crate::machine::Machine::steppers`].
    pub stepper: usize,
    /// It follows the `[extruder]`'s motion queue (false: it stands
    /// still).
    pub synced: bool,
    /// pressure_advance, s.
    pub pressure_advance: f64,
    /// pressure_advance_smooth_time, s.
    pub smooth_time: f64,
    /// rotation_distance, mm per turn; negative: the direction configured
    /// is reversed (SET_EXTRUDER_ROTATION_DISTANCE).
    pub rotation_distance: f64,
    /// Microsteps per turn: full_steps_per_rotation × microsteps ×
    /// gear_ratio.
    pub steps_per_rotation: f64,
}

impl ExtruderStepper<'_> {
    /// How its steps follow the queue now.
    pub fn motion(&self) -> ExtruderStepperMotion {
        ExtruderStepperMotion {
            synced: self.synced,
            pressure_advance: self.pressure_advance,
            smooth_time: self.smooth_time,
            step_dist: self.rotation_distance.abs() / self.steps_per_rotation,
            inverted: self.rotation_distance < 0.0,
        }
    }

    /// How far before and after its motion its steps reach, s: half the
    /// smoothing time while it follows a queue with pressure advance.
    fn scan_window(&self) -> f64 {
        if self.synced && self.pressure_advance > 0.0 {
            0.5 * self.smooth_time
        } else {
            0.0
        }
    }
}

/// The step-generation scan window of `steppers`, s (the widest of
/// theirs).
pub fn scan_window(steppers: &[ExtruderStepper<'_>]) -> f64 {
    steppers
        .iter()
        .map(ExtruderStepper::scan_window)
        .fold(0.0, f64::max)
}

/// True for a `[extruder_stepper NAME]` section.
pub fn is_section(name: &str) -> bool {
    name.starts_with(SECTION_PREFIX)
}

/// Reads a stepper section's rotation and pressure advance options
/// (Klipper's defaults and bounds); `name`, `index` (in the machine's
/// steppers) and `synced` as given.
fn read_one<'a>(
    section: &Reader<'_, '_, 'a>,
    name: &'a str,
    index: usize,
    synced: bool,
) -> Read<ExtruderStepper<'a>> {
    let (rotation_distance, steps_per_rotation) = crate::machine::rotation(section)?;
    let pressure_advance = section.float("pressure_advance", 0.0, Bounds::NON_NEGATIVE)?;
    let smooth_time = section.float(
        "pressure_advance_smooth_time",
        0.040,
        Bounds {
            above: Some(0.0),
            maxval: Some(0.200),
            ..Bounds::NONE
        },
    )?;
    Ok(ExtruderStepper {
        name,
        stepper: index,
        synced,
        pressure_advance,
        smooth_time,
        rotation_distance,
        steps_per_rotation,
    })
}

/// The `[extruder]`'s stepper (the machine's stepper `index`), from its
/// section.
pub(crate) fn read_extruder<'a>(
    section: &Reader<'_, '_, 'a>,
    index: usize,
) -> Read<ExtruderStepper<'a>> {
    read_one(section, EXTRUDER, index, true)
}

/// Reads every `[extruder_stepper NAME]` in printer.cfg's order: each
/// stepper joins `steppers` (`read_stepper` reads its stepper options)
/// and its entry `out`. `has_extruder`: an `[extruder]` is configured
/// (else `extruder: extruder` names nothing).
// Out of line: see `Machine::from_config_in`.
#[inline(never)]
pub(crate) fn read_all<'c, 'a>(
    config: &'c Config<'a>,
    errors: &Errors<'c>,
    has_extruder: bool,
    read_stepper: impl Fn(&Reader<'_, 'c, 'a>) -> Read<Stepper<'a>>,
    steppers: &mut heapless::Vec<Stepper<'a>, MAX_STEPPERS>,
    out: &mut heapless::Vec<ExtruderStepper<'a>, MAX_EXTRUDER_STEPPERS>,
) -> Read<()> {
    for section_name in config.section_names() {
        let Some(section) = config
            .section(section_name)
            .filter(|_| is_section(section_name))
        else {
            continue;
        };
        let section = Reader::new(section, errors);
        let name = section
            .name_in_file()
            .get(SECTION_PREFIX.len()..)
            .unwrap_or_default()
            .trim();
        let synced = match section.get("extruder")?.trim() {
            "" => false,
            EXTRUDER if has_extruder => true,
            _ => {
                return Err(section.error_for(
                    "extruder",
                    "is not a valid extruder: it must name [extruder] or be empty",
                ));
            }
        };
        let stepper = read_stepper(&section)?;
        let index = steppers.len();
        let entry = read_one(&section, name, index, synced)?;
        if out.iter().any(|e| e.name == name) {
            return Err(section.error_for("step_pin", "names an extruder stepper twice"));
        }
        if steppers.push(stepper).is_err() || out.push(entry).is_err() {
            return Err(section.error_for("step_pin", "too many steppers"));
        }
    }
    Ok(())
}

/// Runs `e` if it is one of the extruder steppers' commands
/// (SET_PRESSURE_ADVANCE, SET_EXTRUDER_ROTATION_DISTANCE,
/// SYNC_EXTRUDER_MOTION) on `steppers`; false if it is none of them (or
/// there is no stepper to run it on). A change takes effect after the
/// moves queued so far: step generation is flushed first, as Klipper's.
// Not inlined: see `GcodeMove::traditional`.
#[inline(never)]
pub fn command<'l, const N: usize>(
    steppers: &mut [ExtruderStepper<'_>],
    e: &Extended<'l>,
    toolhead: &mut Toolhead<N>,
    sink: &mut impl MoveSink,
    out: &mut impl Write,
) -> Result<bool, CommandError<'l>> {
    let name = e.name;
    let run = if name.eq_ignore_ascii_case("SET_PRESSURE_ADVANCE") {
        set_pressure_advance
    } else if name.eq_ignore_ascii_case("SET_EXTRUDER_ROTATION_DISTANCE") {
        set_rotation_distance
    } else if name.eq_ignore_ascii_case("SYNC_EXTRUDER_MOTION") {
        sync_motion
    } else {
        return Ok(false);
    };
    if steppers.is_empty() {
        return Ok(false);
    }
    let Some(change) = run(steppers, e, out)? else {
        return Ok(true);
    };
    let sync = change.sync;
    let Some(stepper) = steppers.get_mut(change.index) else {
        return Ok(true);
    };
    *stepper = change.stepper;
    let motion = stepper.motion();
    let index = stepper.stepper;
    let window = scan_window(steppers);
    toolhead.set_extruder_stepper(index, &motion, sync, window, sink);
    Ok(true)
}

/// What a command changes: entry `index` becomes `stepper`; `sync`: it
/// takes the extruder's position as its own (SYNC_EXTRUDER_MOTION).
struct Change<'a> {
    index: usize,
    stepper: ExtruderStepper<'a>,
    sync: bool,
}

/// The entry `EXTRUDER=` names, as Klipper's mux commands find it
/// (names compared as written): its index and a copy; without the
/// parameter, the `[extruder]`'s if `default_extruder` (the bool: the
/// parameter was given).
fn named<'a, 'l>(
    steppers: &[ExtruderStepper<'a>],
    e: &Extended<'l>,
    default_extruder: bool,
) -> Result<(usize, ExtruderStepper<'a>, bool), CommandError<'l>> {
    let wanted = match e.get("EXTRUDER")? {
        Some(name) => Some(name),
        None if default_extruder => None,
        None => return Err(crate::gcode::GcodeError::Missing("EXTRUDER").into()),
    };
    let name = wanted.unwrap_or(EXTRUDER);
    (steppers.iter().enumerate())
        .find(|(_, s)| s.name == name)
        .map(|(index, s)| (index, *s, wanted.is_some()))
        .ok_or(CommandError::NotValidFor {
            key: "EXTRUDER",
            value: wanted,
        })
}

/// SET_PRESSURE_ADVANCE [EXTRUDER=] [ADVANCE=] [SMOOTH_TIME=]: the values
/// not given stay; both are reported. Without EXTRUDER, the `[extruder]`'s
/// stepper, which must follow its queue.
fn set_pressure_advance<'a, 'l>(
    steppers: &[ExtruderStepper<'a>],
    e: &Extended<'l>,
    out: &mut impl Write,
) -> Result<Option<Change<'a>>, CommandError<'l>> {
    let (index, mut stepper, given) = named(steppers, e, true)?;
    if !given && !stepper.synced {
        return Err(CommandError::Refused(
            "Unable to infer active extruder stepper",
        ));
    }
    let advance = e.float("ADVANCE")?.unwrap_or(stepper.pressure_advance);
    let smooth_time = e.float("SMOOTH_TIME")?.unwrap_or(stepper.smooth_time);
    if advance < 0.0 {
        return Err(CommandError::Invalid {
            param: "ADVANCE",
            rule: "must not be negative",
        });
    }
    if !(0.0..=0.200).contains(&smooth_time) {
        return Err(CommandError::Invalid {
            param: "SMOOTH_TIME",
            rule: "must be between 0 and 0.2",
        });
    }
    (stepper.pressure_advance, stepper.smooth_time) = (advance, smooth_time);
    let _ = writeln!(
        out,
        "// pressure_advance: {}\n// pressure_advance_smooth_time: {}",
        Fixed(advance, 6),
        Fixed(smooth_time, 6)
    );
    Ok(Some(Change {
        index,
        stepper,
        sync: false,
    }))
}

/// SET_EXTRUDER_ROTATION_DISTANCE EXTRUDER= [DISTANCE=]: a new distance
/// (negative: the configured direction reversed), or none to report it.
fn set_rotation_distance<'a, 'l>(
    steppers: &[ExtruderStepper<'a>],
    e: &Extended<'l>,
    out: &mut impl Write,
) -> Result<Option<Change<'a>>, CommandError<'l>> {
    let (index, mut stepper, _) = named(steppers, e, false)?;
    let distance = e.float("DISTANCE")?;
    if distance == Some(0.0) {
        return Err(CommandError::Refused("Rotation distance can not be zero"));
    }
    if let Some(distance) = distance {
        stepper.rotation_distance = distance;
    }
    let _ = writeln!(
        out,
        "// Extruder '{}' rotation distance set to {}",
        stepper.name,
        Fixed(stepper.rotation_distance, 6)
    );
    Ok(distance.map(|_| Change {
        index,
        stepper,
        sync: false,
    }))
}

/// SYNC_EXTRUDER_MOTION EXTRUDER= MOTION_QUEUE=: the stepper follows the
/// `[extruder]`'s queue from the extruder's position, or (empty) nothing.
fn sync_motion<'a, 'l>(
    steppers: &[ExtruderStepper<'a>],
    e: &Extended<'l>,
    out: &mut impl Write,
) -> Result<Option<Change<'a>>, CommandError<'l>> {
    let (index, mut stepper, _) = named(steppers, e, false)?;
    let queue = e
        .get("MOTION_QUEUE")?
        .ok_or(crate::gcode::GcodeError::Missing("MOTION_QUEUE"))?;
    stepper.synced = match queue {
        "" => false,
        EXTRUDER if steppers.iter().any(|s| s.name == EXTRUDER) => true,
        other => return Err(CommandError::NotAnExtruder(other)),
    };
    let _ = writeln!(
        out,
        "// Extruder '{}' now syncing with '{queue}'",
        stepper.name
    );
    Ok(Some(Change {
        index,
        stepper,
        sync: stepper.synced,
    }))
}

#[cfg(test)]
mod tests {
    extern crate std;
    use crate::machine::Machine;
    use std::string::{String, ToString};

    /// A cartesian printer with an extruder and `extra` sections.
    fn machine(extra: &str) -> Result<Machine<'static>, String> {
        let text = std::format!(
            concat!(cartesian_printer!(), "pressure_advance: 0.05\n{extra}"),
            extra = extra
        );
        // Leaked: the machine borrows the text (a test only).
        let text: &'static str = std::boxed::Box::leak(text.into_boxed_str());
        let config = std::boxed::Box::leak(std::boxed::Box::new(
            onechip_config::Config::parse("printer.cfg", text).map_err(|e| e.to_string())?,
        ));
        Machine::from_config(config).map_err(|e| e.to_string())
    }

    /// An `[extruder_stepper NAME]` section with `options`.
    fn section(name: &str, options: &str) -> String {
        std::format!(
            "[extruder_stepper {name}]\nstep_pin: PG4\ndir_pin: PC1\nmicrosteps: 16\n\
             rotation_distance: 8\ngear_ratio: 3:1\n{options}\n"
        )
    }

    #[test]
    fn extruder_steppers_follow_the_extruders_stepper_with_klippers_defaults() {
        let extra = section("e1", "extruder: extruder")
            + &section("belt", "extruder:\npressure_advance: 0.1")
                .replace("PG4", "PE2")
                .replace("PC1", "PE3");
        let m = machine(&extra).expect("machine");
        assert!(m.unsupported.is_empty(), "{:?}", m.unsupported);
        let names: std::vec::Vec<_> = m.steppers.iter().map(|s| s.name).collect();
        assert_eq!(
            names,
            [
                "stepper_x",
                "stepper_y",
                "stepper_z",
                "extruder",
                "extruder_stepper e1",
                "extruder_stepper belt"
            ]
        );
        let [extruder, e1, belt] = [3, 4, 5].map(|i| *m.extruder_stepper(i).expect("follows"));
        assert_eq!((extruder.name, extruder.synced), ("extruder", true));
        assert_eq!((e1.name, e1.synced, e1.stepper), ("e1", true, 4));
        assert_eq!((belt.name, belt.synced), ("belt", false));
        // Klipper's defaults: no advance, 40 ms smoothing.
        assert_eq!((e1.pressure_advance, e1.smooth_time), (0.0, 0.040));
        assert_eq!(extruder.pressure_advance, 0.05);
        // gear_ratio counts in the steps per turn.
        assert_eq!(e1.steps_per_rotation, 200.0 * 16.0 * 3.0);
        let motion = e1.motion();
        assert_eq!(motion.step_dist, m.steppers[4].step_dist);
        assert!(!motion.inverted);
        assert!(m.extruder_stepper(2).is_none());
        // The scan window: the extruder's (e1 has no advance; belt's is
        // not followed).
        assert_eq!(m.scan_delay(), 0.020);
    }

    #[test]
    fn bad_extruder_stepper_sections_are_refused() {
        let cases = [
            (
                section("e1", "extruder: extruder1"),
                "is not a valid extruder",
            ),
            (
                section("e1", ""),
                "'extruder' in section 'extruder_stepper e1' must be",
            ),
            (
                section("extruder", "extruder: extruder"),
                "names an extruder stepper twice",
            ),
            (
                section("e1", "extruder:\npressure_advance: -0.1"),
                "'pressure_advance'",
            ),
            (
                section("e1", "extruder:\nposition_max: 10"),
                "'position_max' is not valid",
            ),
        ];
        for (extra, want) in cases {
            let e = machine(&extra).expect_err(&extra);
            assert!(e.contains(want), "{extra}: {e}");
            assert!(e.starts_with("printer.cfg:"), "{e}");
        }
        // Every stepper slot taken: the fifth extruder stepper is one too
        // many.
        let pins = ["PA1", "PA2", "PA3", "PA4", "PA5"];
        let extra: String = pins
            .iter()
            .enumerate()
            .map(|(k, pin)| {
                section(&std::format!("e{k}"), "extruder:")
                    .replace("PG4", pin)
                    .replace("PC1", &std::format!("PB{k}"))
            })
            .collect();
        let e = machine(&extra).expect_err("too many");
        assert!(e.contains("too many steppers"), "{e}");
    }
}
