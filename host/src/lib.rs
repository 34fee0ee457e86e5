//! The Linux host build: the firmware's shared logic run against a folder
//! that plays the SD card, so users and tests see what the board would do.
//!
//! Today it loads `printer.cfg` and feeds a G-code file, line by line, to the
//! same console the USB port serves, exactly as a print host would send it.
//! The motion pipeline (planner, stepgen, sched in virtual time) joins as
//! issues #3 to #5 land; until then the summary says that no move is planned.

use onechip_app::console;
use onechip_app::line::{Line, LineAssembler};
use std::fmt;
use std::path::{Path, PathBuf};

/// Longest G-code line accepted, in bytes (as on the board's USB console).
pub const MAX_LINE: usize = 256;

/// What a run of the host build did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Summary {
    /// The printer.cfg that was read.
    pub config_path: PathBuf,
    /// Its size, in bytes.
    pub config_bytes: usize,
    /// Its section names, in file order (`[stepper_x]` -> `stepper_x`).
    pub sections: Vec<String>,
    /// The G-code file that was fed.
    pub gcode_path: PathBuf,
    /// Lines fed to the console.
    pub lines: usize,
    /// `ok` acknowledgements received.
    pub acks: usize,
    /// Error replies (`!! …`) received, with the line number they answered.
    pub errors: Vec<(usize, String)>,
}

impl fmt::Display for Summary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "config:   {} ({} bytes)",
            self.config_path.display(),
            self.config_bytes
        )?;
        writeln!(f, "sections: {}", self.sections.join(", "))?;
        writeln!(
            f,
            "gcode:    {} ({} lines, {} ok)",
            self.gcode_path.display(),
            self.lines,
            self.acks
        )?;
        for (line, error) in &self.errors {
            writeln!(f, "error:    line {line}: {error}")?;
        }
        writeln!(f, "errors:   {}", self.errors.len())?;
        write!(
            f,
            "motion:   not simulated yet (planner/stepgen/sched: issues #3-#5); no moves planned"
        )
    }
}

/// Why the host build could not run.
#[derive(Debug)]
pub enum RunError {
    /// A file could not be read.
    Read(PathBuf, std::io::Error),
    /// The SD folder has no G-code file, or several and none was named.
    NoGcode(PathBuf),
}

impl fmt::Display for RunError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Read(path, e) => write!(f, "{}: {e}", path.display()),
            Self::NoGcode(dir) => write!(
                f,
                "{}: expected exactly one *.gcode file (or name one as the second argument)",
                dir.display()
            ),
        }
    }
}

impl std::error::Error for RunError {}

/// Runs the firmware logic on the SD folder `sd`, with `gcode` or else the
/// folder's only `*.gcode` file.
pub fn run(sd: &Path, gcode: Option<&Path>) -> Result<Summary, RunError> {
    let config_path = sd.join(onechip_app::sdcard::PRINTER_CFG);
    let config = read(&config_path)?;
    let gcode_path = match gcode {
        Some(path) => path.to_path_buf(),
        None => only_gcode_file(sd)?,
    };
    let program = read(&gcode_path)?;
    let (lines, acks, errors) = feed_console(&program);
    Ok(Summary {
        config_bytes: config.len(),
        sections: section_names(&String::from_utf8_lossy(&config)),
        config_path,
        gcode_path,
        lines,
        acks,
        errors,
    })
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

/// Feeds `program` to the console as a print host would (a newline after the
/// last line if missing); returns (lines, oks, errors by line number).
fn feed_console(program: &[u8]) -> (usize, usize, Vec<(usize, String)>) {
    let mut assembler = LineAssembler::<MAX_LINE>::new();
    let (mut lines, mut acks, mut errors) = (0, 0, Vec::new());
    for &byte in program.iter().chain(b"\n") {
        let Some(event) = assembler.push(byte) else {
            continue;
        };
        if let Line::Complete(text) = event
            && is_comment_only(text)
        {
            continue;
        }
        lines += 1;
        let mut reply = String::new();
        // Writing into a String cannot fail.
        let _ = console::answer(&event, &mut reply);
        for answer in reply.lines() {
            match answer.strip_prefix("!! ") {
                Some(error) => errors.push((lines, error.to_string())),
                None if answer == "ok" => acks += 1,
                None => {}
            }
        }
    }
    (lines, acks, errors)
}

/// Print hosts strip comment-only lines before sending; so does the host build.
fn is_comment_only(line: &[u8]) -> bool {
    line.iter()
        .find(|b| !b.is_ascii_whitespace())
        .is_none_or(|&b| b == b';')
}

/// Names of the `[section]` headers of a Klipper config, in order.
fn section_names(config: &str) -> Vec<String> {
    config
        .lines()
        .filter_map(|l| l.trim().strip_prefix('[')?.split(']').next())
        .map(|name| name.trim().to_string())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_line_gets_one_ok_and_overlong_lines_are_errors() {
        let long = "G1 X1 ".repeat(60);
        let program = format!("G28\n; comment\n\n{long}\nM114");
        let (lines, acks, errors) = feed_console(program.as_bytes());
        assert_eq!((lines, acks), (3, 3));
        assert_eq!(
            errors,
            [(2, format!("line too long ({} bytes), ignored", long.len()))]
        );
    }

    #[test]
    fn section_names_keep_file_order_and_ignore_options() {
        let cfg = "[printer]\nkinematics: cartesian\n# [commented]\n[stepper_x]\nstep_pin: PF13\n";
        assert_eq!(section_names(cfg), ["printer", "stepper_x"]);
    }
}
