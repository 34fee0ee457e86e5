//! The Klipper golden reference data (`../shared/golden`, described by its
//! README.md) for tests and benches: where it is, which cases it holds, and
//! typed readers for its files.
//!
//! Everything here panics on missing or malformed data, naming the file
//! (and line): a test or bench that reads golden data cannot do anything
//! useful without it, and must not pass by finding nothing.

use onechip_planner::move_sink::TrapqMove;
use std::fmt::Display;
use std::path::{Path, PathBuf};
use std::str::FromStr;

/// The golden data folder: `$ONECHIP_GOLDEN`, or `../shared/golden` beside
/// the checkout.
pub fn golden_dir() -> PathBuf {
    std::env::var_os("ONECHIP_GOLDEN").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/golden"),
        PathBuf::from,
    )
}

/// The bytes of `relative` (a path inside [`golden_dir`]).
pub fn read(relative: impl AsRef<Path>) -> Vec<u8> {
    let path = golden_dir().join(relative);
    std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e} (set ONECHIP_GOLDEN)", path.display()))
}

/// The text of `relative` (a path inside [`golden_dir`]).
pub fn read_string(relative: impl AsRef<Path>) -> String {
    let path = golden_dir().join(relative);
    std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("{}: {e} (set ONECHIP_GOLDEN)", path.display()))
}

/// The names of the case folders (those with a `summary.txt`), sorted.
///
/// # Panics
///
/// If the golden folder cannot be read or holds no case.
pub fn cases() -> Vec<String> {
    let dir = golden_dir();
    let mut cases: Vec<String> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e} (set ONECHIP_GOLDEN)", dir.display()))
        .filter_map(Result::ok)
        .filter(|e| e.path().join("summary.txt").is_file())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    assert!(
        !cases.is_empty(),
        "no golden case (a folder with summary.txt) in {} (set ONECHIP_GOLDEN)",
        dir.display()
    );
    cases.sort();
    cases
}

/// Each machine's case-name prefix, printer.cfg (in `configs/`) and MCU
/// dictionary (in `dicts/`, without `.dict`), as the golden README lists
/// them.
const MACHINES: [(&str, &str, &str); 6] = [
    ("cart", "cartesian.cfg", "stm32f446"),
    ("corexy", "corexy.cfg", "stm32f446"),
    ("delta", "delta.cfg", "stm32f446"),
    ("shaper", "cartesian_shaper.cfg", "stm32f446"),
    ("avr", "cartesian_avr.cfg", "atmega2560"),
    ("h723", "cartesian_h723.cfg", "stm32h723"),
];

/// The [`MACHINES`] entry of `case`, by the prefix of its name.
fn machine(case: &str) -> (&'static str, &'static str, &'static str) {
    let prefix = case.split('_').next();
    MACHINES
        .into_iter()
        .find(|m| Some(m.0) == prefix)
        .unwrap_or_else(|| panic!("golden case {case}: no known machine for its name's prefix"))
}

/// The printer.cfg a case ran with: a file name in `configs/`
/// (e.g. `cartesian.cfg`).
///
/// # Panics
///
/// If the case name's prefix names no known machine.
pub fn config_for(case: &str) -> &'static str {
    machine(case).1
}

/// The MCU data dictionary a case ran against: a name in `dicts/` without
/// `.dict` (e.g. `stm32f446`).
///
/// # Panics
///
/// If the case name's prefix names no known machine.
pub fn dict_for(case: &str) -> &'static str {
    machine(case).2
}

/// The text of `configs/<name>` (`name` includes `.cfg`).
pub fn config(name: &str) -> String {
    read_string(Path::new("configs").join(name))
}

/// The text of `dicts/<name>.dict`.
pub fn dict(name: &str) -> String {
    read_string(Path::new("dicts").join(format!("{name}.dict")))
}

/// The G-code klippy ran for `case` (`gcode/<case>.gcode`).
pub fn gcode(case: &str) -> String {
    read_string(Path::new("gcode").join(format!("{case}.gcode")))
}

/// Which trapq a planned move went to (`moves.tsv` column `trapq`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Trapq {
    /// The cartesian toolhead (XYZ).
    Toolhead,
    /// The extruder (E in `start_x`).
    Extruder,
    /// `FORCE_MOVE` moves of a single stepper (none in the current cases).
    ForceMove,
}

/// One `trapq_append()` klippy made (a line of `moves.tsv`): the moves the
/// planner hands step generation. Times in seconds of print time,
/// positions in mm, velocities in mm/s, accelerations in mm/s².
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrapqAppend {
    /// The trapq the move was appended to.
    pub trapq: Trapq,
    /// Start of the move (s).
    pub print_time: f64,
    /// Duration of the acceleration phase (s).
    pub accel_t: f64,
    /// Duration of the constant-velocity phase (s).
    pub cruise_t: f64,
    /// Duration of the deceleration phase (s).
    pub decel_t: f64,
    /// Start X (mm); for the extruder, the E position (mm of filament).
    pub start_x: f64,
    /// Start Y (mm).
    pub start_y: f64,
    /// Start Z (mm).
    pub start_z: f64,
    /// X component of the unit direction; 1.0 for the extruder.
    pub axes_r_x: f64,
    /// Y component of the unit direction; for the extruder 1.0 if pressure
    /// advance may apply (E > 0 with X/Y motion), else 0.0.
    pub axes_r_y: f64,
    /// Z component of the unit direction.
    pub axes_r_z: f64,
    /// Velocity at the start (mm/s; extruder: along E).
    pub start_v: f64,
    /// Velocity of the cruise phase (mm/s; extruder: along E).
    pub cruise_v: f64,
    /// Acceleration and deceleration (mm/s²; extruder: along E).
    pub accel: f64,
}

impl TrapqAppend {
    /// `[start_x, start_y, start_z]` (mm).
    pub fn start_pos(&self) -> [f64; 3] {
        [self.start_x, self.start_y, self.start_z]
    }

    /// `[axes_r_x, axes_r_y, axes_r_z]`.
    pub fn axes_r(&self) -> [f64; 3] {
        [self.axes_r_x, self.axes_r_y, self.axes_r_z]
    }

    /// Duration of the whole move (s).
    pub fn move_t(&self) -> f64 {
        self.accel_t + self.cruise_t + self.decel_t
    }

    /// Velocity at the end (mm/s): `cruise_v - accel * decel_t`.
    pub fn end_v(&self) -> f64 {
        self.cruise_v - self.accel * self.decel_t
    }

    /// Whether the move ends at rest (end velocity within 1e-9 mm/s of 0).
    pub fn ends_at_rest(&self) -> bool {
        self.end_v().abs() < 1e-9
    }

    /// The move as the planner hands it to step generation.
    pub fn trapq_move(&self) -> TrapqMove {
        TrapqMove {
            print_time: self.print_time,
            accel_t: self.accel_t,
            cruise_t: self.cruise_t,
            decel_t: self.decel_t,
            start_pos: self.start_pos(),
            axes_r: self.axes_r(),
            start_v: self.start_v,
            cruise_v: self.cruise_v,
            accel: self.accel,
        }
    }
}

/// The header line of `moves.tsv`, which fixes its columns.
const MOVES_HEADER: &str = "trapq\tprint_time\taccel_t\tcruise_t\tdecel_t\tstart_x\tstart_y\tstart_z\taxes_r_x\taxes_r_y\taxes_r_z\tstart_v\tcruise_v\taccel";

/// Every move in `case`'s `moves.tsv`, in the order klippy appended them.
///
/// # Panics
///
/// If the file is missing, its header is not the known one, or a line does
/// not parse (naming file and line).
pub fn moves(case: &str) -> Vec<TrapqAppend> {
    let relative = Path::new(case).join("moves.tsv");
    let file = golden_dir().join(&relative);
    let text = read_string(&relative);
    let mut lines = text.lines();
    assert_eq!(
        lines.next(),
        Some(MOVES_HEADER),
        "{}:1: unexpected header",
        file.display()
    );
    lines
        .enumerate()
        .map(|(i, line)| {
            parse_move(line).unwrap_or_else(|e| panic!("{}:{}: {e}: {line}", file.display(), i + 2))
        })
        .collect()
}

/// The moves of `case` that went to `trapq`, in order.
pub fn trapq_moves(case: &str, trapq: Trapq) -> Vec<TrapqAppend> {
    moves(case)
        .into_iter()
        .filter(|m| m.trapq == trapq)
        .collect()
}

/// One data line of `moves.tsv`.
fn parse_move(line: &str) -> Result<TrapqAppend, String> {
    let mut fields = line.split('\t');
    let trapq = match fields.next() {
        Some("toolhead") => Trapq::Toolhead,
        Some("extruder") => Trapq::Extruder,
        Some("force_move") => Trapq::ForceMove,
        other => return Err(format!("unknown trapq {other:?}")),
    };
    // The numeric columns, named by the header, in the order the fields
    // of the literal below take them.
    let mut names = MOVES_HEADER.split('\t').skip(1);
    let mut column = || -> Result<f64, String> {
        let name = names.next().unwrap_or("extra");
        let field = fields.next().ok_or_else(|| format!("no {name} column"))?;
        field.parse().map_err(|e| format!("{name} {field:?}: {e}"))
    };
    let m = TrapqAppend {
        trapq,
        print_time: column()?,
        accel_t: column()?,
        cruise_t: column()?,
        decel_t: column()?,
        start_x: column()?,
        start_y: column()?,
        start_z: column()?,
        axes_r_x: column()?,
        axes_r_y: column()?,
        axes_r_z: column()?,
        start_v: column()?,
        cruise_v: column()?,
        accel: column()?,
    };
    match fields.next() {
        Some(extra) => Err(format!("a column more than the header's: {extra:?}")),
        None => Ok(m),
    }
}

/// The words after `key` on the line of `case`'s `summary.txt` that starts
/// with it, each parsed as a number (e.g. `toolhead_final_position`: X, Y,
/// Z, E).
///
/// # Panics
///
/// If there is no such line or a word is not a number.
pub fn summary_values(case: &str, key: &str) -> Vec<f64> {
    let relative = Path::new(case).join("summary.txt");
    let file = golden_dir().join(&relative);
    let text = read_string(&relative);
    let (i, rest) = text
        .lines()
        .enumerate()
        .find_map(|(i, l)| Some((i, l.strip_prefix(key)?.strip_prefix(' ')?)))
        .unwrap_or_else(|| panic!("{}: no {key} line", file.display()));
    rest.split_whitespace()
        .map(|w| {
            w.parse()
                .unwrap_or_else(|e| panic!("{}:{}: {key} {w:?}: {e}", file.display(), i + 1))
        })
        .collect()
}

/// The number after `key` in `case`'s `summary.txt` (e.g. `clock_freq`,
/// `max_error_ticks`).
///
/// # Panics
///
/// If there is no such line or it holds other than one number.
pub fn summary_value(case: &str, key: &str) -> f64 {
    match summary_values(case, key)[..] {
        [value] => value,
        ref values => panic!("{case}/summary.txt: {key} has {values:?}, not one number"),
    }
}

/// A `stepper` line of `summary.txt`: what klippy reports for one stepper
/// at the end of the case.
#[derive(Debug, Clone, PartialEq)]
pub struct StepperSummary {
    /// Stepper name (`stepper_x`, `stepper_a`, `extruder`, ...).
    pub name: String,
    /// The MCU object id of the stepper.
    pub oid: u32,
    /// Distance of one step (mm).
    pub step_dist: f64,
    /// Whether the dir pin is inverted.
    pub invert_dir: bool,
    /// Number of commands in its `queue-<stepper>.txt` (`queue_step`,
    /// `set_next_step_dir`, `reset_step_clock`).
    pub queue_cmds: u64,
    /// Total number of steps.
    pub steps: u64,
    /// Sum of +1/-1 steps (stepcompress position, starts at 0).
    pub final_mcu_pos: i64,
    /// klippy's `get_mcu_position()`.
    pub klippy_mcu_position: i64,
    /// Where itersolve last placed the stepper (mm).
    pub commanded_pos: f64,
    /// Clock of the last step (MCU ticks).
    pub last_step_clock: u64,
    /// Time of the last step (s).
    pub last_step_time: f64,
}

/// The `stepper` lines of `case`'s `summary.txt`, in file order.
///
/// # Panics
///
/// If a stepper line lacks a field or a value does not parse.
pub fn summary_steppers(case: &str) -> Vec<StepperSummary> {
    let relative = Path::new(case).join("summary.txt");
    let file = golden_dir().join(&relative);
    read_string(&relative)
        .lines()
        .enumerate()
        .filter_map(|(i, l)| Some((i, l.strip_prefix("stepper ")?)))
        .map(|(i, rest)| {
            let words: Vec<&str> = rest.split_whitespace().collect();
            let at = format!("{}:{}", file.display(), i + 1);
            StepperSummary {
                name: words
                    .first()
                    .map_or_else(|| panic!("{at}: no name"), |n| (*n).to_string()),
                oid: summary_field(&words, "oid", &at),
                step_dist: summary_field(&words, "step_dist", &at),
                invert_dir: summary_field::<u8>(&words, "invert_dir", &at) != 0,
                queue_cmds: summary_field(&words, "queue_cmds", &at),
                steps: summary_field(&words, "steps", &at),
                final_mcu_pos: summary_field(&words, "final_mcu_pos", &at),
                klippy_mcu_position: summary_field(&words, "klippy_mcu_position", &at),
                commanded_pos: summary_field(&words, "commanded_pos", &at),
                last_step_clock: summary_field(&words, "last_step_clock", &at),
                last_step_time: summary_field(&words, "last_step_time", &at),
            }
        })
        .collect()
}

/// The value after the word `key` in a summary line's `words`; `at` names
/// the file and line for the panic.
fn summary_field<T: FromStr>(words: &[&str], key: &str, at: &str) -> T
where
    T::Err: Display,
{
    let value = words
        .iter()
        .position(|w| *w == key)
        .and_then(|k| words.get(k + 1))
        .unwrap_or_else(|| panic!("{at}: no {key}"));
    value
        .parse()
        .unwrap_or_else(|e| panic!("{at}: {key} {value:?}: {e}"))
}

/// Every step of `stepper` in `case` (`steps-<stepper>.txt`): (absolute
/// 64-bit MCU clock, positive direction), in order.
///
/// # Panics
///
/// If the file is missing or a line does not parse (naming file and line).
pub fn steps(case: &str, stepper: &str) -> Vec<(u64, bool)> {
    let relative = Path::new(case).join(format!("steps-{stepper}.txt"));
    parse_steps(&read_string(&relative), &golden_dir().join(relative))
}

/// The steps in any file of the `steps-*.txt` format (`<clock> <dir>`
/// lines), such as the host build writes: (clock, positive direction).
///
/// # Panics
///
/// If the file cannot be read or a line does not parse (naming file and
/// line).
pub fn steps_file(path: &Path) -> Vec<(u64, bool)> {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    parse_steps(&text, path)
}

/// The steps in `text`, the contents of `file`.
fn parse_steps(text: &str, file: &Path) -> Vec<(u64, bool)> {
    text.lines()
        .enumerate()
        .map(|(i, line)| {
            let step = line.split_once(' ').and_then(|(clock, dir)| {
                let dir = match dir {
                    "1" => true,
                    "0" => false,
                    _ => return None,
                };
                Some((clock.parse().ok()?, dir))
            });
            step.unwrap_or_else(|| {
                panic!("{}:{}: not `<clock> <dir>`: {line}", file.display(), i + 1)
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_case_reads() {
        let cases = cases();
        assert_eq!(cases.len(), 15, "{cases:?}");
        for case in &cases {
            let moves = moves(case);
            assert!(!moves.is_empty(), "{case}");
            assert!(moves.iter().all(|m| m.move_t() >= -1e-12), "{case}");
            let freq = summary_value(case, "clock_freq");
            assert!(freq >= 16e6, "{case}: {freq}");
            let steppers = summary_steppers(case);
            assert_eq!(steppers.len(), 4, "{case}");
            for s in &steppers {
                let steps = steps(case, &s.name);
                assert_eq!(steps.len() as u64, s.steps, "{case} {}", s.name);
                let pos: i64 = steps.iter().map(|&(_, d)| if d { 1 } else { -1 }).sum();
                assert_eq!(pos, s.final_mcu_pos, "{case} {}", s.name);
                assert_eq!(steps.last().map_or(0, |s| s.0), s.last_step_clock);
                let queue = read_string(format!("{case}/queue-{}.txt", s.name));
                let commands = queue.lines().filter(|l| !l.starts_with('#')).count();
                assert_eq!(commands as u64, s.queue_cmds, "{case} {}", s.name);
            }
            assert_eq!(summary_values(case, "toolhead_final_position").len(), 4);
            config(config_for(case));
            dict(dict_for(case));
            gcode(case);
        }
    }

    #[test]
    #[should_panic(expected = "no known machine")]
    fn a_case_of_an_unknown_machine_panics() {
        config_for("scara_square");
    }

    #[test]
    fn a_move_line_parses_into_named_columns() {
        let line =
            "toolhead\t0.25\t0.1\t0.2\t0.3\t1.0\t2.0\t3.0\t0.6\t0.8\t0.0\t0.0\t100.0\t3000.0";
        let m = parse_move(line).expect("parses");
        assert_eq!(m.trapq, Trapq::Toolhead);
        assert_eq!(m.start_pos(), [1.0, 2.0, 3.0]);
        assert_eq!(m.axes_r(), [0.6, 0.8, 0.0]);
        assert_eq!((m.print_time, m.cruise_v, m.accel), (0.25, 100.0, 3000.0));
        assert!((m.move_t() - 0.6).abs() < 1e-12);
        assert!((m.end_v() - -800.0).abs() < 1e-9);
        assert!(parse_move("toolhead\t1.0").is_err());
        assert!(parse_move(&format!("{line}\t1.0")).is_err());
        assert!(parse_move(&line.replace("toolhead", "bed")).is_err());
        assert!(parse_move(&line.replace("100.0", "fast")).is_err());
    }
}
