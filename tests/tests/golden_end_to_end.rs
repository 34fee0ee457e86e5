//! Every golden case end to end through the host build: printer.cfg and
//! G-code in an SD folder, planned, step-generated and run through the
//! MCU role's stepper engine in virtual time, its `steps-*.txt` output
//! compared with klippy's: the same step count, direction sequence and
//! final position per stepper, every step within max_error_ticks; also with
//! the MCU clock starting just before its 32-bit wrap.
//!
//! Klippy's batch mode took two timing decisions from its own processing
//! speed, not from the G-code: where its priming timer had expired between
//! input chunks (in the circle cases, mid-file) and when it restarted from
//! rest (in the circles, and after homing in cart_move_g28). The run
//! replays them (`KlippyBatch`), read from klippy's planned moves: which
//! moves it ended at rest and when it started moves from rest.

mod klippy_batch;

use klippy_batch::KlippyBatch;
use onechip_host::{Options, Start};
use onechip_tests::{golden_dir, summary_value};
use std::path::Path;

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

/// Klippy's batch-mode timing decisions in `case`, from its planned
/// toolhead moves (`moves.tsv`).
fn klippy_batch(case: &str, origin: f64) -> KlippyBatch {
    let moves = onechip_golden::trapq_moves(case, onechip_golden::Trapq::Toolhead);
    KlippyBatch {
        // Ends at rest: cruise_v - accel * decel_t = 0.
        stops: (0..moves.len())
            .filter(|&i| moves[i].ends_at_rest())
            .collect(),
        starts: (0..moves.len())
            .filter(|&i| moves[i].start_v == 0.0)
            .map(|i| (i, moves[i].print_time))
            .collect(),
        origin,
    }
}

/// Runs `case` on `config` from MCU clock `origin`; compares every stepper.
fn check(case: &str, config: &str, origin: u64) {
    check_edited(case, config, origin, |cfg| cfg, "");
}

/// [`check`] with printer.cfg passed through `edit` and `prefix` put
/// before the G-code.
fn check_edited(
    case: &str,
    config: &str,
    origin: u64,
    edit: impl FnOnce(String) -> String,
    prefix: &str,
) {
    let work = std::env::temp_dir().join(format!(
        "onechip-e2e-{case}-{origin}-{}-{}",
        prefix.len(),
        std::process::id()
    ));
    let sd = work.join("sd");
    std::fs::create_dir_all(&sd).expect("sd folder");
    let read = |path: std::path::PathBuf| {
        std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
    };
    let cfg = read(golden_dir().join("configs").join(config));
    std::fs::write(sd.join("printer.cfg"), edit(cfg)).expect("cfg");
    let gcode = read(golden_dir().join("gcode").join(format!("{case}.gcode")));
    std::fs::write(sd.join(format!("{case}.gcode")), format!("{prefix}{gcode}")).expect("gcode");
    let freq = summary_value(case, "clock_freq");
    let max_error = summary_value(case, "max_error_ticks") as u64;
    let out = work.join("steps");
    let mut replay = klippy_batch(case, origin as f64 / freq);
    let summary = onechip_host::run_replaying::<{ onechip_host::KLIPPY_LOOKAHEAD }>(
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
        Some(&mut replay),
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
            assert!(
                o.1 == g.1 && o.0.abs_diff(g.0 + origin) <= max_error,
                "{case} {name}: step {i} ours {o:?} golden {g:?} (+{origin})"
            );
        }
    }
    std::fs::remove_dir_all(&work).ok();
}

fn both(case: &str, config: &str) {
    check(case, config, 0);
    let freq = summary_value(case, "clock_freq") as u64;
    check(case, config, (1 << 32) - freq / 2);
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
fn pressure_advance_set_by_gcode_steps_as_when_configured() {
    // corexy_extrude's machine has pressure_advance 0.04 (smoothed over
    // 40 ms) in printer.cfg; here printer.cfg has none and the G-code
    // sets it first: klippy's steps all the same.
    let without = |cfg: String| {
        assert!(
            cfg.contains("pressure_advance: 0.04\n"),
            "the golden config's PA"
        );
        cfg.replace("pressure_advance: 0.04\n", "pressure_advance: 0\n")
    };
    let prefix = "SET_PRESSURE_ADVANCE ADVANCE=0.04 SMOOTH_TIME=0.040\n";
    check_edited("corexy_extrude", "corexy.cfg", 0, without, prefix);
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
fn circles() {
    both("cart_circle", "cartesian.cfg");
    both("corexy_circle", "corexy.cfg");
    both("delta_circle", "delta.cfg");
    both("shaper_circle", "cartesian_shaper.cfg");
}

#[test]
fn homing_in_batch_mode() {
    both("cart_move_g28", "cartesian.cfg");
}
