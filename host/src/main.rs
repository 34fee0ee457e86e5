//! `onechip-sim SD_FOLDER [GCODE] [--plot FILE.svg --from S --to S]
//! [--steps DIR] [--summary-json FILE]`: runs the firmware logic on a
//! folder that plays the SD card and prints a summary; with `--plot`,
//! draws toolhead velocity and step rates over the print-time window
//! `--from`..`--to` (seconds, default the first 10 s); `--steps` writes
//! every stepper's steps there, `--summary-json` the summary as JSON.
//!
//! `onechip-sim SD_FOLDER --serial PATH [--speed F]` serves the board's
//! USB console on a pseudo-terminal linked at PATH instead, in real time
//! (or F times faster), until the host closes the port.

use onechip_host::plot::Window;
use onechip_host::serial::Port;
use onechip_host::{Options, SimError, Summary};
use signal_hook::consts::{SIGINT, SIGTERM};
use signal_hook::flag;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

const USAGE: &str = "usage: onechip-sim SD_FOLDER [GCODE] [--plot FILE.svg [--from S] [--to S]] \
                     [--steps DIR] [--summary-json FILE]\n       \
                     onechip-sim SD_FOLDER --serial PATH [--speed F] [--steps DIR] [--summary-json FILE]";

/// What the command line asks for.
struct Command {
    sd: PathBuf,
    options: Options,
    serial: Option<Port>,
    summary_json: Option<PathBuf>,
}

fn command(args: &[String]) -> Result<Command, String> {
    let mut positional = Vec::new();
    let (mut plot, mut from, mut to) = (None, 0.0, 10.0);
    let (mut steps_dir, mut summary_json, mut serial, mut speed) = (None, None, None, None);
    let mut it = args.iter();
    while let Some(arg) = it.next() {
        let mut value = |name: &str| it.next().cloned().ok_or(format!("{name} needs a value"));
        let number = |name: &str, v: String| {
            v.parse::<f64>()
                .map_err(|_| format!("{name}: not a number: {v}"))
        };
        match arg.as_str() {
            "--plot" => plot = Some(PathBuf::from(value("--plot")?)),
            "--from" => from = number("--from", value("--from")?)?,
            "--to" => to = number("--to", value("--to")?)?,
            "--steps" => steps_dir = Some(PathBuf::from(value("--steps")?)),
            "--summary-json" => summary_json = Some(PathBuf::from(value("--summary-json")?)),
            "--serial" => serial = Some(PathBuf::from(value("--serial")?)),
            "--speed" => speed = Some(number("--speed", value("--speed")?)?),
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
    let gcode = positional.next();
    if let Some(extra) = positional.next() {
        return Err(format!("unexpected argument {}", extra.display()));
    }
    let serial = match (serial, speed) {
        (None, Some(_)) => return Err("--speed needs --serial".into()),
        (None, None) => None,
        (Some(path), speed) => {
            let speed = speed.unwrap_or(1.0);
            if !(speed.is_finite() && speed > 0.0) {
                return Err(format!("--speed must be a positive number, not {speed}"));
            }
            if gcode.is_some() {
                return Err("--serial takes its G-code from the port, not a GCODE file".into());
            }
            if plot.is_some() {
                return Err("--plot is for runs of a GCODE file, not --serial".into());
            }
            Some(Port { path, speed })
        }
    };
    Ok(Command {
        sd,
        options: Options {
            gcode,
            steps_dir,
            plot: plot.map(|p| (p, Window { from, to })),
            ..Options::default()
        },
        serial,
        summary_json,
    })
}

/// Runs what `command` asks for and writes its JSON summary if asked.
fn run(command: &Command) -> Result<Summary, SimError> {
    let summary = match &command.serial {
        Some(port) => {
            let ending = Arc::new(AtomicBool::new(false));
            for signal in [SIGINT, SIGTERM] {
                let registered =
                    flag::register_conditional_shutdown(signal, 1, Arc::clone(&ending))
                        .and_then(|_| flag::register(signal, Arc::clone(&ending)));
                registered.map_err(|e| SimError::Serial(port.path.clone(), e))?;
            }
            onechip_host::serial::serve(&command.sd, &command.options, port, &ending, |link| {
                eprintln!(
                    "onechip-sim: serving the console on {} ({}x real time); close the port \
                     or press Ctrl-C to end (twice: at once)",
                    link.display(),
                    port.speed
                );
            })?
        }
        None => onechip_host::run_with(Path::new(&command.sd), &command.options)?,
    };
    if let Some(path) = &command.summary_json {
        let text = format!("{:#}\n", summary.to_json());
        std::fs::write(path, text).map_err(|e| SimError::Read(path.clone(), e))?;
    }
    Ok(summary)
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let command = match command(&args) {
        Ok(parsed) => parsed,
        Err(e) => {
            eprintln!("onechip-sim: {e}\n{USAGE}");
            return ExitCode::from(2);
        }
    };
    match run(&command) {
        Ok(summary) => {
            println!("{summary}");
            if let Some((path, _)) = &command.options.plot {
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
