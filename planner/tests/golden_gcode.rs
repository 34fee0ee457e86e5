//! Every line of the G-code files klippy ran for the golden cases parses,
//! into the commands those files use (the planner's input set for #3).

use onechip_planner::gcode::{Command, parse};
use std::collections::BTreeMap;

#[test]
fn all_golden_gcode_parses() {
    let mut seen: BTreeMap<String, usize> = BTreeMap::new();
    let cases = onechip_golden::cases();
    for case in &cases {
        let text = onechip_golden::gcode(case);
        let path = format!("gcode/{case}.gcode");
        for (number, line) in text.lines().enumerate() {
            let parsed =
                parse(line).unwrap_or_else(|e| panic!("{path}:{}: {e}: {line}", number + 1));
            let name = match parsed.command {
                Command::Empty => continue,
                Command::Traditional(t) => {
                    for p in t.params() {
                        if p.key.len() == 1 && !p.value.is_empty() {
                            t.float(p.key)
                                .unwrap_or_else(|e| panic!("{path}:{}: {e}", number + 1));
                        }
                    }
                    format!("{}{}", t.letter as char, t.number)
                }
                Command::Extended(e) => {
                    for p in e.params() {
                        p.unwrap_or_else(|err| panic!("{path}:{}: {err}", number + 1));
                    }
                    e.name.to_ascii_uppercase()
                }
            };
            *seen.entry(name).or_default() += 1;
        }
    }
    assert_eq!(cases.len(), 15, "{cases:?}");
    for expected in [
        "G1", "G4", "G90", "G91", "G92", "M82", "M83", "M204", "M220", "M221", "M400", "G28",
    ] {
        assert!(seen.contains_key(expected), "no {expected} in {seen:?}");
    }
    for expected in ["SET_KINEMATIC_POSITION", "SET_VELOCITY_LIMIT"] {
        assert!(seen.contains_key(expected), "no {expected} in {seen:?}");
    }
    assert!(seen["G1"] > 5_000, "{seen:?}");
}
