//! Every golden case end to end through the host build: printer.cfg and
//! G-code in an SD folder, planned, step-generated and run through the
//! MCU role's stepper engine in virtual time, its `steps-*.txt` output
//! compared with klippy's: the same step count, direction sequence and
//! final position per stepper, every step within max_error_ticks; also with
//! the MCU clock starting just before its 32-bit wrap.
//!
//! Five cases carry timing that klippy's batch mode takes from its own
//! processing speed, not from the G-code (see the planner's golden test):
//! in the circle cases its priming timer fired mid-file, and its flush
//! timer delayed restarts from rest (circles, and after homing in
//! cart_move_g28). A run of the G-code cannot reproduce those times, so for
//! these cases the step counts, direction sequences and final positions are
//! compared; their step times are checked against golden by the step
//! generation test, which starts from klippy's planned moves.

use onechip_host::{Options, Start};
use std::path::{Path, PathBuf};

fn golden_dir() -> PathBuf {
    std::env::var_os("ONECHIP_GOLDEN").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/golden"),
        PathBuf::from,
    )
}

fn summary_value(case: &str, key: &str) -> f64 {
    let text =
        std::fs::read_to_string(golden_dir().join(case).join("summary.txt")).expect("summary");
    text.lines()
        .find_map(|l| l.strip_prefix(&format!("{key} ")))
        .expect("key")
        .trim()
        .parse()
        .expect("number")
}

fn steps(path: &Path) -> Vec<(u64, bool)> {
    std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .lines()
        .map(|l| {
            let (c, d) = l.split_once(' ').expect("clock dir");
            (c.parse().expect("clock"), d == "1")
        })
        .collect()
}

/// How closely a case must match.
#[derive(Clone, Copy, PartialEq)]
enum Compare {
    /// Every step's time too.
    Times,
    /// Counts, directions and final positions.
    Path,
}

/// Runs `case` on `config` from MCU clock `origin`; compares every stepper.
fn check(case: &str, config: &str, origin: u64, compare: Compare) {
    let work = std::env::temp_dir().join(format!(
        "onechip-e2e-{case}-{origin}-{}",
        std::process::id()
    ));
    let sd = work.join("sd");
    std::fs::create_dir_all(&sd).expect("sd folder");
    std::fs::copy(
        golden_dir().join("configs").join(config),
        sd.join("printer.cfg"),
    )
    .expect("cfg");
    std::fs::copy(
        golden_dir().join("gcode").join(format!("{case}.gcode")),
        sd.join(format!("{case}.gcode")),
    )
    .expect("gcode");
    let freq = summary_value(case, "clock_freq");
    let max_error = summary_value(case, "max_error_ticks") as u64;
    let out = work.join("steps");
    let summary = onechip_host::run_with(
        &sd,
        &Options {
            steps_dir: Some(out.clone()),
            mcu_freq: freq,
            clock_origin: origin,
            // Klipper's batch mode has no endstops: homing moves run to
            // their end.
            start: Start::Ideal,
            ..Options::default()
        },
    )
    .expect("runs");
    assert_eq!(summary.shutdown, None, "{case}");
    for stepper in &summary.steppers {
        let name = &stepper.name;
        let ours = steps(&out.join(format!("steps-{name}.txt")));
        let golden = steps(&golden_dir().join(case).join(format!("steps-{name}.txt")));
        assert_eq!(ours.len(), golden.len(), "{case} {name}: step count");
        let position =
            |s: &[(u64, bool)]| s.iter().map(|x| if x.1 { 1i64 } else { -1 }).sum::<i64>();
        assert_eq!(
            stepper.position,
            position(&golden),
            "{case} {name}: final position"
        );
        for (i, (o, g)) in ours.iter().zip(&golden).enumerate() {
            let on_time = compare == Compare::Path || o.0.abs_diff(g.0 + origin) <= max_error;
            assert!(
                o.1 == g.1 && on_time,
                "{case} {name}: step {i} ours {o:?} golden {g:?} (+{origin})"
            );
        }
    }
    std::fs::remove_dir_all(&work).ok();
}

fn both(case: &str, config: &str) {
    check(case, config, 0, Compare::Times);
    let freq = summary_value(case, "clock_freq") as u64;
    check(case, config, (1 << 32) - freq / 2, Compare::Times);
}

#[test]
fn cartesian() {
    both("cart_square", "cartesian.cfg");
    both("cart_extrude", "cartesian.cfg");
}

#[test]
fn corexy() {
    both("corexy_square", "corexy.cfg");
    both("corexy_extrude", "corexy.cfg");
}

#[test]
fn delta() {
    both("delta_square", "delta.cfg");
    both("delta_extrude", "delta.cfg");
}

#[test]
fn input_shaping() {
    both("shaper_square", "cartesian_shaper.cfg");
    both("shaper_extrude", "cartesian_shaper.cfg");
}

#[test]
fn avr_and_h723_clocks() {
    both("avr_cart_extrude", "cartesian_avr.cfg");
    both("h723_cart_extrude", "cartesian_h723.cfg");
}

#[test]
fn cases_with_klippy_batch_timing() {
    for (case, config) in [
        ("cart_circle", "cartesian.cfg"),
        ("corexy_circle", "corexy.cfg"),
        ("delta_circle", "delta.cfg"),
        ("shaper_circle", "cartesian_shaper.cfg"),
        ("cart_move_g28", "cartesian.cfg"),
    ] {
        check(case, config, 0, Compare::Path);
    }
}
