//! Arbitrary text as a G-code line: parsing and reading every parameter
//! must never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use onechip_planner::gcode::{Command, parse};

fuzz_target!(|data: &[u8]| {
    let Ok(line) = std::str::from_utf8(data) else { return };
    let Ok(parsed) = parse(line) else { return };
    match parsed.command {
        Command::Empty => {}
        Command::Traditional(t) => {
            let _ = t.raw_params();
            for p in t.params() {
                let _ = t.float(p.key);
            }
        }
        Command::Extended(e) => {
            for p in e.params() {
                if let Ok((key, _)) = p {
                    let _ = e.float(key);
                }
            }
        }
    }
});
