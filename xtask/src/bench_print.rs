//! The host build's benchmark print: the golden cartesian machine and a
//! print of a given length made of the golden extrusion case's body
//! repeated.

use std::io::{self, BufWriter, Write as _};
use std::path::{Path, PathBuf};

/// Repetitions of the golden extrusion body (15.4 s of print each) in an
/// hour of print.
const HOUR_REPEATS: f64 = 234.0;

/// Lines of the golden extrusion case before its body (position, modes),
/// written once.
const PROLOGUE_LINES: usize = 5;

/// The G-code file's name in the SD folder.
const GCODE: &str = "hour.gcode";

/// `cargo xtask hour-print DIR [--hours N]`: the folder and the print's
/// length, h (1 by default).
pub fn parse_args(args: &[String]) -> Result<(PathBuf, f64), String> {
    const USAGE: &str = "usage: cargo xtask hour-print DIR [--hours N]";
    let (mut dir, mut hours) = (None, 1.0);
    let mut it = args.iter();
    while let Some(arg) = it.next() {
        match arg.as_str() {
            "--hours" => {
                let value = it.next().ok_or(USAGE)?;
                hours = value
                    .parse::<f64>()
                    .ok()
                    .filter(|h| h.is_finite() && *h > 0.0)
                    .ok_or(format!("--hours: not a positive number of hours: {value}"))?;
            }
            other if other.starts_with("--") || dir.is_some() => return Err(USAGE.into()),
            other => dir = Some(PathBuf::from(other)),
        }
    }
    Ok((dir.ok_or(USAGE)?, hours))
}

/// Writes a benchmark print of about `hours` h into `dir` (printer.cfg
/// and hour.gcode), from the golden data next to the workspace `root`.
pub fn write(root: &Path, dir: &Path, hours: f64) -> Result<(), String> {
    let golden = root.join("../shared/golden");
    let read = |p: PathBuf| std::fs::read_to_string(&p).map_err(at(&p));
    let config = read(golden.join("configs/cartesian.cfg"))?;
    let gcode = read(golden.join("gcode/cart_extrude.gcode"))?;
    let lines: Vec<&str> = gcode.lines().collect();
    let (prologue, body) = lines.split_at(PROLOGUE_LINES.min(lines.len()));
    let repeats = (hours * HOUR_REPEATS).round().max(1.0) as usize;
    std::fs::create_dir_all(dir).map_err(at(dir))?;
    let path = dir.join("printer.cfg");
    std::fs::write(&path, config).map_err(at(&path))?;
    let path = dir.join(GCODE);
    write_gcode(&path, prologue, body, repeats).map_err(at(&path))
}

/// Writes `prologue` once, then `body` `repeats` times, to `path`.
fn write_gcode(path: &Path, prologue: &[&str], body: &[&str], repeats: usize) -> io::Result<()> {
    let mut out = BufWriter::new(std::fs::File::create(path)?);
    let bodies = std::iter::repeat_n(body, repeats);
    for line in std::iter::once(prologue).chain(bodies).flatten() {
        writeln!(out, "{line}")?;
    }
    out.flush()
}

/// An io error at `path`, as a message.
fn at(path: &Path) -> impl FnOnce(io::Error) -> String + '_ {
    move |e| format!("{}: {e}", path.display())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(list: &[&str]) -> Vec<String> {
        list.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn hours_default_to_one() {
        assert_eq!(
            parse_args(&args(&["/tmp/hour"])),
            Ok((PathBuf::from("/tmp/hour"), 1.0))
        );
        assert_eq!(
            parse_args(&args(&["--hours", "24", "/tmp/day"])),
            Ok((PathBuf::from("/tmp/day"), 24.0))
        );
    }

    #[test]
    fn a_print_needs_a_folder_and_a_positive_length() {
        for bad in [
            &[][..],
            &["a", "b"],
            &["a", "--hours"],
            &["a", "--hours", "0"],
        ] {
            assert!(parse_args(&args(bad)).is_err(), "{bad:?}");
        }
    }
}
