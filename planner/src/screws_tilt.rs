//! `[screws_tilt_adjust]`, as Klipper's `screws_tilt_adjust`: the bed's
//! levelling screws probed in turn (Klipper's probe-points helper: up to
//! `horizontal_move_z`, the nozzle over each screw, a probe there), then
//! each screw's turn against the base screw reported as full turns and
//! minutes (1/60 turn) with its direction, from the screw thread's pitch.

use crate::gcode::Extended;
use crate::gcode_move::CommandError;
use crate::move_sink::MoveSink;
use crate::probe::{ProbeConfig, ProbeState, Sampling};
use crate::reader::{Errors, Read, Reader};
use crate::toolhead::{MoveError, Toolhead};
use core::fmt::{self, Write};
use onechip_config::decimal::{Fixed, Shortest};
use onechip_config::{Bounds, Config, decimal};

/// Most screws kept (Klipper reads `screw1` up to `screw99`; printers
/// have 3 to 6).
pub const MAX_SCREWS: usize = 9;

/// `screw_thread`'s choices, as Klipper spells them, with the height one
/// turn moves the bed (mm) and the turn that raises it.
const THREADS: [(&str, f64, bool); 6] = [
    ("CW-M3", 0.5, true),
    ("CCW-M3", 0.5, false),
    ("CW-M4", 0.7, true),
    ("CCW-M4", 0.7, false),
    ("CW-M5", 0.8, true),
    ("CCW-M5", 0.8, false),
];

/// One screw: where the nozzle goes for it (mm) and its name.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Screw<'a> {
    /// X, Y of the nozzle, mm (`screwN`, or a `screwN_fine_adjust`).
    pub at: [f64; 2],
    /// `screwN_name`, if given.
    pub name: Option<&'a str>,
    /// `screwN` (Klipper's default name is `screw at X,Y` of it).
    pub screw: [f64; 2],
}

impl fmt::Display for Screw<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let [x, y] = self.screw;
        match self.name {
            Some(name) => f.write_str(name),
            None => write!(f, "screw at {},{}", Fixed(x, 3), Fixed(y, 3)),
        }
    }
}

/// Screws in order, at most [`MAX_SCREWS`] (in an array, so that the
/// sections holding them stay `Copy`); a slice of them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Screws<'a> {
    list: [Screw<'a>; MAX_SCREWS],
    count: usize,
}

impl<'a> Screws<'a> {
    /// None yet.
    const fn new() -> Self {
        let none = Screw {
            at: [0.0; 2],
            name: None,
            screw: [0.0; 2],
        };
        Self {
            list: [none; MAX_SCREWS],
            count: 0,
        }
    }

    /// Adds `screw` at the end; false if there are [`MAX_SCREWS`] already.
    fn push(&mut self, screw: Screw<'a>) -> bool {
        let Some(slot) = self.list.get_mut(self.count) else {
            return false;
        };
        *slot = screw;
        self.count += 1;
        true
    }
}

impl<'a> core::ops::Deref for Screws<'a> {
    type Target = [Screw<'a>];
    fn deref(&self) -> &Self::Target {
        &self.list[..self.count]
    }
}

/// The `[screws_tilt_adjust]` section.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScrewsTilt<'a> {
    /// The screws ([`Self::screws`]).
    screws: Screws<'a>,
    /// How far one turn moves the bed, mm.
    pub pitch: f64,
    /// A clockwise turn raises the bed (`CW-…` threads).
    pub clockwise_thread: bool,
    /// `horizontal_move_z`: the height moves between screws go at, mm.
    pub horizontal_move_z: f64,
    /// `speed`: those moves' speed, mm/s.
    pub speed: f64,
}

/// Reads `[screws_tilt_adjust]`, if present.
// Out of line: see `Machine::from_config_in`.
#[inline(never)]
pub(crate) fn read<'c, 'a>(
    config: &'c Config<'a>,
    errors: &Errors<'c>,
) -> Read<Option<ScrewsTilt<'a>>> {
    let Some(s) = config.section("screws_tilt_adjust") else {
        return Ok(None);
    };
    let s = Reader::new(s, errors);
    let screws = read_screws(&s, "screws_tilt_adjust: Must have at least three screws")?;
    let names = THREADS.map(|(name, ..)| name);
    let thread = s.get_choice("screw_thread", &names, Some("CW-M3"))?;
    let (_, pitch, clockwise_thread) = THREADS
        .into_iter()
        .find(|(name, ..)| *name == thread)
        .unwrap_or(THREADS[0]);
    Ok(Some(ScrewsTilt {
        screws,
        pitch,
        clockwise_thread,
        horizontal_move_z: s.float("horizontal_move_z", 5.0, Bounds::NONE)?,
        speed: s.float("speed", 50.0, Bounds::POSITIVE)?,
    }))
}

/// `screw1` .. `screw10` with their `_name` and `_fine_adjust` options
/// (one more screw than kept, so that a tenth is refused rather than
/// ignored).
const SCREW_OPTIONS: [(&str, &str, &str); MAX_SCREWS + 1] = [
    ("screw1", "screw1_name", "screw1_fine_adjust"),
    ("screw2", "screw2_name", "screw2_fine_adjust"),
    ("screw3", "screw3_name", "screw3_fine_adjust"),
    ("screw4", "screw4_name", "screw4_fine_adjust"),
    ("screw5", "screw5_name", "screw5_fine_adjust"),
    ("screw6", "screw6_name", "screw6_fine_adjust"),
    ("screw7", "screw7_name", "screw7_fine_adjust"),
    ("screw8", "screw8_name", "screw8_fine_adjust"),
    ("screw9", "screw9_name", "screw9_fine_adjust"),
    ("screw10", "screw10_name", "screw10_fine_adjust"),
];

/// A section's `screw1`, `screw2`, … (with their names) up to the first
/// missing, at least three (else `too_few`, Klipper's message), as
/// Klipper's screw helpers read them.
pub(crate) fn read_screws<'a>(s: &Reader<'_, '_, 'a>, too_few: &'static str) -> Read<Screws<'a>> {
    let mut screws = Screws::new();
    for (option, name, _) in SCREW_OPTIONS {
        let Some(at) = coordinate(s, option)? else {
            break;
        };
        let screw = Screw {
            at,
            name: s.get_opt(name),
            screw: at,
        };
        if !screws.push(screw) {
            return Err(s.error_for(option, "more screws than onechip keeps (9)"));
        }
    }
    if screws.len() < 3 {
        return Err(s.error_for("screw1", too_few));
    }
    Ok(screws)
}

/// The fine-adjust points of `screws` (`screwN_fine_adjust`, each with
/// its screw's name), in order, for the screws that have one.
pub(crate) fn read_fine_points<'a>(
    s: &Reader<'_, '_, 'a>,
    screws: &Screws<'a>,
) -> Read<Screws<'a>> {
    let mut fine = Screws::new();
    for (screw, (_, _, option)) in screws.iter().zip(SCREW_OPTIONS) {
        if let Some(at) = coordinate(s, option)? {
            // At most one per screw: there is room.
            fine.push(Screw { at, ..*screw });
        }
    }
    Ok(fine)
}

/// Option `option` as an `x, y` coordinate (two finite numbers), if set
/// (Klipper's message if not).
fn coordinate<'c>(s: &Reader<'_, 'c, '_>, option: &'c str) -> Read<Option<[f64; 2]>> {
    let Some(text) = s.get_opt(option) else {
        return Ok(None);
    };
    let mut parts = text.split(',').map(|p| decimal::parse(p.trim()));
    match (parts.next(), parts.next(), parts.next()) {
        (Some(Some(x)), Some(Some(y)), None) if x.is_finite() && y.is_finite() => Ok(Some([x, y])),
        _ => Err(s.error_for(option, "needs to be an x,y coordinate")),
    }
}

/// Marks `[screws_tilt_adjust]` as a section onechip reads.
pub fn is_section(name: &str) -> bool {
    name == "screws_tilt_adjust"
}

/// One screw's adjustment against the base: full turns and minutes
/// (1/60 turn, rounded as Python's `round`), clockwise or not.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Turn {
    /// Clockwise (`CW`) or counter-clockwise (`CCW`).
    pub clockwise: bool,
    /// Whole turns.
    pub turns: u32,
    /// Minutes of a turn (0..=60: Klipper's rounding can give 60).
    pub minutes: u32,
}

impl<'a> ScrewsTilt<'a> {
    /// The screws, in order (the first is the base without DIRECTION).
    pub fn screws(&self) -> &[Screw<'a>] {
        &self.screws
    }

    /// The base screw's index for probed heights `zs` (mm, one per
    /// screw): the first, or with DIRECTION (`clockwise`: CW) the one
    /// that makes every turn go that way (Klipper's choice).
    pub fn base(&self, zs: &[f64], direction: Option<bool>) -> usize {
        let Some(cw) = direction else {
            return 0;
        };
        let use_max = cw == self.clockwise_thread;
        let pick = |best: (usize, f64), (i, &z): (usize, &f64)| {
            let better = if use_max { z > best.1 } else { z < best.1 };
            if better { (i, z) } else { best }
        };
        let first = zs.first().copied().unwrap_or(0.0);
        zs.iter().enumerate().fold((0, first), pick).0
    }

    /// The turn that brings a screw probed at `z` to `base_z` (mm).
    pub fn turn(&self, base_z: f64, z: f64) -> Turn {
        let diff = base_z - z;
        let adjust = if diff.abs() < 0.001 {
            0.0
        } else {
            diff / self.pitch
        };
        let clockwise = (adjust >= 0.0) == self.clockwise_thread;
        let adjust = adjust.abs();
        let turns = libm::trunc(adjust);
        Turn {
            clockwise,
            turns: turns as u32,
            minutes: libm::rint((adjust - turns) * 60.0) as u32,
        }
    }

    /// Klipper's report of screws probed at `zs` (mm), base chosen by
    /// `direction` (see [`Self::base`]); Err with Klipper's message if a
    /// screw is more than `max_deviation` mm off the base.
    pub fn report(
        &self,
        zs: &[f64],
        direction: Option<bool>,
        max_deviation: Option<f64>,
        out: &mut dyn Write,
    ) -> Result<(), Deviation> {
        let base = self.base(zs, direction);
        let base_z = zs.get(base).copied().unwrap_or(0.0);
        let _ = writeln!(
            out,
            "// 01:20 means 1 full turn and 20 minutes, CW=clockwise, CCW=counter-clockwise"
        );
        let mut worst = 0.0f64;
        for (i, (screw, &z)) in self.screws().iter().zip(zs).enumerate() {
            let [x, y] = screw.at;
            let (x, y, z6) = (Fixed(x, 1), Fixed(y, 1), Fixed(z, 5));
            if i == base {
                let _ = writeln!(out, "// {screw} (base) : x={x}, y={y}, z={z6}");
                continue;
            }
            worst = worst.max((base_z - z).abs());
            let t = self.turn(base_z, z);
            let sign = if t.clockwise { "CW" } else { "CCW" };
            let _ = writeln!(
                out,
                "// {screw} : x={x}, y={y}, z={z6} : adjust {sign} {:02}:{:02}",
                t.turns, t.minutes
            );
        }
        match max_deviation {
            Some(limit) if limit != 0.0 && worst > limit => Err(Deviation(limit)),
            _ => Ok(()),
        }
    }
}

/// A screw more than MAX_DEVIATION (mm) off the base.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Deviation(pub f64);

impl fmt::Display for Deviation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "bed level exceeds configured limits ({}mm)! Adjust screws and restart print.",
            Shortest(self.0)
        )
    }
}

/// SCREWS_TILT_CALCULATE's own parameters: MAX_DEVIATION (mm) and
/// DIRECTION (CW: true); the probe's (SAMPLES, …) are the caller's.
pub fn parameters<'l>(e: &Extended<'l>) -> Result<(Option<f64>, Option<bool>), CommandError<'l>> {
    let max = e.float("MAX_DEVIATION")?;
    let direction = match e.get("DIRECTION")? {
        None => None,
        Some(d) if d.eq_ignore_ascii_case("CW") => Some(true),
        Some(d) if d.eq_ignore_ascii_case("CCW") => Some(false),
        Some(_) => {
            return Err(CommandError::Invalid {
                param: "DIRECTION",
                rule: "must be either CW or CCW",
            });
        }
    };
    Ok((max, direction))
}

impl<const N: usize> Toolhead<N> {
    /// Klipper's probe-points helper, automatic probing: up to
    /// `horizontal_move_z` (the first time at `speed`, then at the probe's
    /// lift speed), the nozzle to each of `points` at `speed` (mm/s),
    /// a probe there with `sampling`; then up again. The probed height
    /// of each point (mm) goes to `each`. The probe stays deployed from
    /// the first point to the last where its options allow.
    #[allow(clippy::too_many_arguments)]
    pub fn probe_points(
        &mut self,
        probe: &ProbeConfig<'_>,
        state: &mut ProbeState,
        sampling: &Sampling,
        points: &[[f64; 2]],
        (horizontal_move_z, speed): (f64, f64),
        now: f64,
        sink: &mut impl MoveSink,
        out: &mut impl Write,
        each: &mut dyn FnMut(usize, f64),
    ) -> Result<(), MoveError> {
        state.begin_multi();
        let probed = (|| {
            for (i, point) in points.iter().enumerate() {
                let mut at = self.position();
                at[2] = horizontal_move_z;
                self.move_to(at, if i == 0 { speed } else { sampling.lift_speed }, sink)?;
                at[0] = point[0];
                at[1] = point[1];
                self.move_to(at, speed, sink)?;
                let z = self.probe_samples(probe, state, sampling, now, sink, out)?[2];
                each(i, z);
            }
            let mut at = self.position();
            at[2] = horizontal_move_z;
            self.move_to(at, sampling.lift_speed, sink)
        })();
        let raised = self.end_multi_probe(probe, state, now, sink, out);
        probed?;
        raised
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::string::{String, ToString};

    /// Three screws with `thread`, read from a config leaked for the
    /// test's lifetime.
    fn tilt(thread: &str) -> ScrewsTilt<'static> {
        let text = std::format!(
            "[screws_tilt_adjust]\nscrew1: 20,30\nscrew1_name: front left\n\
             screw2: 200, 30\nscrew3: 200,230\nscrew_thread: {thread}\n"
        );
        let text: &'static str = std::boxed::Box::leak(text.into_boxed_str());
        let config = Config::parse("printer.cfg", text).expect("parses");
        let config: &'static Config<'static> = std::boxed::Box::leak(std::boxed::Box::new(config));
        Errors::run(|errors| read(config, errors))
            .expect("reads")
            .expect("present")
    }

    #[test]
    fn turns_and_minutes_as_klipper_computes_them() {
        let t = tilt("CW-M4");
        let options = (t.pitch, t.clockwise_thread, t.horizontal_move_z, t.speed);
        assert_eq!(options, (0.7, true, 5.0, 50.0));
        let turn = |clockwise, turns, minutes| Turn {
            clockwise,
            turns,
            minutes,
        };
        // 0.35 mm low: half a turn of an M4 (0.7 mm) clockwise.
        assert_eq!(t.turn(2.0, 1.65), turn(true, 0, 30));
        // 1.05 mm high: one and a half turns counter-clockwise.
        assert_eq!(t.turn(2.0, 3.05), turn(false, 1, 30));
        // Within a micron: no turn.
        assert_eq!(t.turn(2.0, 2.0009), turn(true, 0, 0));
        // A counter-clockwise thread turns the other way.
        assert!(!tilt("CCW-M3").turn(2.0, 1.75).clockwise);
    }

    #[test]
    fn the_report_reads_as_klippers() {
        let t = tilt("CW-M3");
        let zs = [2.4875, 2.36, 2.61];
        let mut out = String::new();
        t.report(&zs, None, None, &mut out).expect("no limit");
        assert_eq!(
            out,
            "// 01:20 means 1 full turn and 20 minutes, CW=clockwise, CCW=counter-clockwise\n\
             // front left (base) : x=20.0, y=30.0, z=2.48750\n\
             // screw at 200.000,30.000 : x=200.0, y=30.0, z=2.36000 : adjust CW 00:15\n\
             // screw at 200.000,230.000 : x=200.0, y=230.0, z=2.61000 : adjust CCW 00:15\n"
        );
        // DIRECTION=CW with a clockwise thread: the highest screw is the
        // base, every other turns clockwise; CCW: the lowest.
        assert_eq!(t.base(&zs, Some(true)), 2);
        assert_eq!(t.base(&zs, Some(false)), 1);
        let err = t.report(&zs, None, Some(0.1), &mut out);
        assert_eq!(
            err.map_err(|e| e.to_string()),
            Err(
                "bed level exceeds configured limits (0.1mm)! Adjust screws and restart print."
                    .into()
            )
        );
    }

    #[test]
    fn fewer_than_three_screws_or_a_bad_thread_are_refused() {
        let two = "[screws_tilt_adjust]\nscrew1: 1,2\nscrew2: 3,4\n";
        let config = Config::parse("printer.cfg", two).expect("parses");
        let e = Errors::run(|errors| read(&config, errors))
            .expect_err("two screws")
            .to_string();
        assert!(e.contains("Must have at least three screws"), "{e}");
        let bad = "[screws_tilt_adjust]\nscrew1: 1,2\nscrew2: 3,4\nscrew3: 5,6\nscrew_thread: M3\n";
        let config = Config::parse("printer.cfg", bad).expect("parses");
        let e = Errors::run(|errors| read(&config, errors))
            .expect_err("bad thread")
            .to_string();
        assert!(e.contains("screw_thread"), "{e}");
    }
}
