//! `onechip-sim SD_FOLDER [GCODE]`: runs the firmware logic on a folder that
//! plays the SD card and prints a summary.

use std::path::Path;
use std::process::ExitCode;

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(sd) = args.first() else {
        eprintln!("usage: onechip-sim SD_FOLDER [GCODE]");
        return ExitCode::from(2);
    };
    match onechip_host::run(Path::new(sd), args.get(1).map(Path::new)) {
        Ok(summary) => {
            println!("{summary}");
            if summary.errors.is_empty() {
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
