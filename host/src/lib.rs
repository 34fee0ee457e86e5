//! The Linux host build: the firmware's shared logic run against a folder
//! that plays the SD card, so users and tests see what the board would do.
//!
//! It reads `printer.cfg` and a G-code file, plans every move exactly as
//! the firmware does (and as Klipper would), and reports what the printer
//! would do: planned moves, print time, final position and any errors.
//! Step generation and the stepper engine join as issues #4 and #5 land.

use onechip_app::line::{Line, LineAssembler};
use onechip_app::printer::Printer;
use onechip_planner::config::{Config, ConfigFile};
use onechip_planner::machine::{Kinematics, Machine};
use onechip_planner::toolhead::{MoveSink, TrapqMove};
use std::fmt;
use std::path::{Path, PathBuf};

/// Longest G-code line accepted, in bytes (as on the board's USB console).
pub const MAX_LINE: usize = 256;
/// Lookahead capacity of the host build, in moves.
pub const LOOKAHEAD: usize = 4096;

/// What a run of the host build did.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    /// The printer.cfg that was read.
    pub config_path: PathBuf,
    /// The machine's kinematics.
    pub kinematics: Kinematics,
    /// Sections of printer.cfg that onechip does not support yet.
    pub unsupported: Vec<String>,
    /// The input shapers configured, as `axis: type freq`.
    pub input_shaper: Vec<String>,
    /// The G-code file that was run.
    pub gcode_path: PathBuf,
    /// Lines executed (comment-only lines excluded).
    pub lines: usize,
    /// Planned toolhead (XYZ) moves.
    pub toolhead_moves: usize,
    /// Planned extruder moves.
    pub extruder_moves: usize,
    /// Highest planned cruise speed, mm/s.
    pub peak_velocity: f64,
    /// Print time at the end, s.
    pub print_time: f64,
    /// G-code position at the end (X, Y, Z, E), mm.
    pub final_position: [f64; 4],
    /// Replies other than `ok` (Unknown command, M114), by line number.
    pub replies: Vec<(usize, String)>,
    /// Errors (`!!` replies), by line number.
    pub errors: Vec<(usize, String)>,
}

impl fmt::Display for Summary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "config:       {} ({:?})",
            self.config_path.display(),
            self.kinematics
        )?;
        if !self.input_shaper.is_empty() {
            writeln!(
                f,
                "input shaper: {} (applied once step generation lands, #4)",
                self.input_shaper.join(", ")
            )?;
        }
        if !self.unsupported.is_empty() {
            writeln!(
                f,
                "not yet supported (ignored): [{}]",
                self.unsupported.join("], [")
            )?;
        }
        writeln!(
            f,
            "gcode:        {} ({} lines)",
            self.gcode_path.display(),
            self.lines
        )?;
        for (line, reply) in &self.replies {
            writeln!(f, "reply:        line {line}: {reply}")?;
        }
        for (line, error) in &self.errors {
            writeln!(f, "error:        line {line}: {error}")?;
        }
        writeln!(
            f,
            "planned:      {} toolhead moves, {} extruder moves",
            self.toolhead_moves, self.extruder_moves
        )?;
        writeln!(f, "peak speed:   {:.1} mm/s", self.peak_velocity)?;
        writeln!(f, "print time:   {:.3} s", self.print_time)?;
        let p = self.final_position;
        writeln!(
            f,
            "final:        X:{:.3} Y:{:.3} Z:{:.3} E:{:.3}",
            p[0], p[1], p[2], p[3]
        )?;
        writeln!(f, "errors:       {}", self.errors.len())?;
        write!(
            f,
            "steps:        not generated yet (stepgen/sched: issues #4-#5)"
        )
    }
}

/// Why the host build could not run.
#[derive(Debug)]
pub enum RunError {
    /// A file could not be read.
    Read(PathBuf, std::io::Error),
    /// printer.cfg is invalid (the message names file, line and option).
    Config(String),
    /// The SD folder has no G-code file, or several and none was named.
    NoGcode(PathBuf),
}

impl fmt::Display for RunError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Read(path, e) => write!(f, "{}: {e}", path.display()),
            Self::Config(message) => f.write_str(message),
            Self::NoGcode(dir) => write!(
                f,
                "{}: expected exactly one *.gcode file (or name one as the second argument)",
                dir.display()
            ),
        }
    }
}

impl std::error::Error for RunError {}

/// Counts planned moves.
#[derive(Default)]
struct Tally {
    toolhead: usize,
    extruder: usize,
    peak_velocity: f64,
}

impl MoveSink for Tally {
    fn toolhead(&mut self, m: &TrapqMove) {
        self.toolhead += 1;
        self.peak_velocity = self.peak_velocity.max(m.cruise_v);
    }
    fn extruder(&mut self, _: &TrapqMove) {
        self.extruder += 1;
    }
}

/// Runs the firmware logic on the SD folder `sd`, with `gcode` or else the
/// folder's only `*.gcode` file.
pub fn run(sd: &Path, gcode: Option<&Path>) -> Result<Summary, RunError> {
    let config_path = sd.join(onechip_app::sdcard::PRINTER_CFG);
    let texts = config_files(sd, &config_path)?;
    let files: Vec<ConfigFile<'_>> = texts
        .iter()
        .map(|(name, text)| ConfigFile { name, text })
        .collect();
    let config = Config::parse_files(&files).map_err(|e| RunError::Config(e.to_string()))?;
    let machine = Machine::from_config(&config).map_err(|e| RunError::Config(e.to_string()))?;
    let gcode_path = match gcode {
        Some(path) => path.to_path_buf(),
        None => only_gcode_file(sd)?,
    };
    let program = read(&gcode_path)?;
    let mut printer: Box<Printer<LOOKAHEAD>> = Box::new(Printer::new(&machine));
    let mut tally = Tally::default();
    let mut summary = Summary {
        config_path,
        kinematics: machine.kinematics,
        unsupported: machine.unsupported.iter().map(|s| s.to_string()).collect(),
        input_shaper: [("x", machine.input_shaper.x), ("y", machine.input_shaper.y)]
            .iter()
            .filter_map(|(axis, s)| s.map(|s| format!("{axis}: {} {} Hz", s.kind.name(), s.freq)))
            .collect(),
        gcode_path,
        lines: 0,
        toolhead_moves: 0,
        extruder_moves: 0,
        peak_velocity: 0.0,
        print_time: 0.0,
        final_position: [0.0; 4],
        replies: Vec::new(),
        errors: Vec::new(),
    };
    let mut assembler = LineAssembler::<MAX_LINE>::new();
    for &byte in program.iter().chain(b"\n") {
        let Some(event) = assembler.push(byte) else {
            continue;
        };
        summary.lines += 1;
        let text = match event {
            Line::Complete(bytes) => String::from_utf8_lossy(bytes).into_owned(),
            Line::TooLong { len } => {
                summary.errors.push((
                    summary.lines,
                    format!("line too long ({len} bytes), ignored"),
                ));
                continue;
            }
        };
        let mut reply = String::new();
        if let Err(e) = printer.execute(&text, &mut tally, &mut reply) {
            summary.errors.push((summary.lines, e.to_string()));
        }
        summary
            .replies
            .extend(reply.lines().map(|r| (summary.lines, r.to_string())));
    }
    printer.finish(&mut tally);
    summary.toolhead_moves = tally.toolhead;
    summary.extruder_moves = tally.extruder;
    summary.peak_velocity = tally.peak_velocity;
    summary.print_time = printer.print_time();
    summary.final_position = printer.position();
    Ok(summary)
}

/// printer.cfg (first) and every other `.cfg` file under the SD folder,
/// named relative to it, for `[include]` to choose from.
fn config_files(sd: &Path, printer_cfg: &Path) -> Result<Vec<(String, String)>, RunError> {
    let text = |path: &Path| read(path).map(|bytes| String::from_utf8_lossy(&bytes).into_owned());
    let mut files = vec![(printer_cfg.display().to_string(), text(printer_cfg)?)];
    let mut folders = vec![(sd.to_path_buf(), String::new())];
    while let Some((dir, prefix)) = folders.pop() {
        let entries = std::fs::read_dir(&dir).map_err(|e| RunError::Read(dir.clone(), e))?;
        for entry in entries.filter_map(Result::ok) {
            let path = entry.path();
            let name = format!("{prefix}{}", entry.file_name().to_string_lossy());
            if path.is_dir() && prefix.matches('/').count() < 3 {
                folders.push((path, format!("{name}/")));
            } else if path.extension().is_some_and(|x| x == "cfg") && path != printer_cfg {
                files.push((name, text(&path)?));
            }
        }
    }
    Ok(files)
}

fn read(path: &Path) -> Result<Vec<u8>, RunError> {
    std::fs::read(path).map_err(|e| RunError::Read(path.to_path_buf(), e))
}

fn only_gcode_file(sd: &Path) -> Result<PathBuf, RunError> {
    let entries = std::fs::read_dir(sd).map_err(|e| RunError::Read(sd.to_path_buf(), e))?;
    let mut found: Vec<PathBuf> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| {
            p.extension()
                .is_some_and(|x| x.eq_ignore_ascii_case("gcode"))
        })
        .collect();
    match found.len() {
        1 => Ok(found.remove(0)),
        _ => Err(RunError::NoGcode(sd.to_path_buf())),
    }
}
