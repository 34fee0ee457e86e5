//! `onechip-sim SD_FOLDER [GCODE] [--plot FILE.svg --from S --to S]`: runs
//! the firmware logic on a folder that plays the SD card and prints a
//! summary; with `--plot`, draws toolhead velocity and step rates over the
//! print-time window `--from`..`--to` (seconds, default the first 10 s).

use onechip_host::Options;
use onechip_host::plot::Window;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

const USAGE: &str = "usage: onechip-sim SD_FOLDER [GCODE] [--plot FILE.svg [--from S] [--to S]]";

fn options(args: &[String]) -> Result<(PathBuf, Options), String> {
    let mut positional = Vec::new();
    let (mut plot, mut from, mut to) = (None, 0.0, 10.0);
    let mut it = args.iter();
    while let Some(arg) = it.next() {
        let mut value = |name: &str| it.next().cloned().ok_or(format!("{name} needs a value"));
        let seconds = |v: String| {
            v.parse::<f64>()
                .map_err(|_| format!("not a time in seconds: {v}"))
        };
        match arg.as_str() {
            "--plot" => plot = Some(PathBuf::from(value("--plot")?)),
            "--from" => from = seconds(value("--from")?)?,
            "--to" => to = seconds(value("--to")?)?,
            other if other.starts_with("--") => return Err(format!("unknown option {other}")),
            other => positional.push(PathBuf::from(other)),
        }
    }
    // Written so that a NaN window is refused too.
    if to.partial_cmp(&from) != Some(std::cmp::Ordering::Greater) {
        return Err("--to must be after --from".into());
    }
    let mut positional = positional.into_iter();
    let sd = positional.next().ok_or(USAGE)?;
    let options = Options {
        gcode: positional.next(),
        plot: plot.map(|p| (p, Window { from, to })),
        ..Options::default()
    };
    Ok((sd, options))
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (sd, options) = match options(&args) {
        Ok(parsed) => parsed,
        Err(e) => {
            eprintln!("onechip-sim: {e}\n{USAGE}");
            return ExitCode::from(2);
        }
    };
    match onechip_host::run_with(Path::new(&sd), &options) {
        Ok(summary) => {
            println!("{summary}");
            if let Some((path, _)) = &options.plot {
                println!("plot:         {}", path.display());
            }
            if summary.errors.is_empty() && summary.shutdown.is_none() {
                ExitCode::SUCCESS
            } else {
                ExitCode::FAILURE
            }
        }
        Err(e) => {
            eprintln!("onechip-sim: {e}");
            ExitCode::FAILURE
        }
    }
}
