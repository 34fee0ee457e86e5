//! Arbitrary text as printer.cfg: indexing, typed reads and building the
//! machine must never panic; errors must name a line within the text.
#![no_main]

use libfuzzer_sys::fuzz_target;
use onechip_config::Config;
use onechip_planner::machine::Machine;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let lines = text.lines().count();
    match Config::parse("fuzz.cfg", text) {
        Err(e) => assert!(e.line <= lines + 1),
        Ok(config) => {
            if let Err(e) = Machine::from_config(&config) {
                assert!(e.line <= lines + 1);
                let _ = e.to_string();
            }
        }
    }
});
