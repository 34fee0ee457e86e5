//! Homing in virtual time: the toolhead starts somewhere the firmware does
//! not know; each homing move runs until the endstop (at position_endstop)
//! triggers, the steppers stop within one step of it, and the position
//! afterwards is what Klipper sets, which is where the toolhead really is.

use onechip_host::{Options, Start};
use onechip_tests::sd_folder;
use std::path::PathBuf;

fn sd(name: &str, gcode: &str) -> PathBuf {
    sd_folder::new(
        &format!("homing-{name}"),
        &sd_folder::shipped_cfg(),
        Some(gcode),
    )
}

/// The shipped machine: endstops at X 0, Y 0, Z 0.5; 0.0125 mm per X/Y
/// step, 0.0025 per Z step.
const ENDSTOPS: [f64; 3] = [0.0, 0.0, 0.5];
const STEP: [f64; 3] = [0.0125, 0.0125, 0.0025];

#[test]
fn endstops_stop_homing_moves_and_the_position_is_where_the_toolhead_is() {
    let dir = sd("g28", "G28\nM114\nG1 X20.3 Y30.7 Z5 F3000\nM114\n");
    let start = [50.0, 80.0, 30.0];
    let s = onechip_host::run_with(
        &dir,
        &Options {
            start: Start::At(start),
            ..Options::default()
        },
    )
    .expect("runs");
    assert_eq!(s.errors, []);
    assert_eq!(s.shutdown, None);
    // Two homing moves per axis (the second after a retract), X, Y, Z.
    let axes: Vec<usize> = s.endstops.iter().map(|e| e.0).collect();
    assert_eq!(axes, [0, 0, 1, 1, 2, 2]);
    for &(axis, real, time) in &s.endstops {
        let past = (real[axis] - ENDSTOPS[axis]).abs();
        assert!(
            past <= STEP[axis] + 1e-9,
            "axis {axis}: stopped {past} mm from the endstop"
        );
        assert!(time > 0.0);
    }
    // The first X trigger comes after the 50 mm from the start at the
    // homing speed (50 mm/s), not after the whole (352.5 mm) move.
    let first_x = s.endstops[0].2;
    assert!(first_x > 1.0 && first_x < 1.5, "{first_x}");
    // After homing, M114 reports the endstop positions; at the end the
    // firmware's position and the real one agree within a step.
    assert_eq!(s.replies[0].1, "X:0.000 Y:0.000 Z:0.500 E:0.000");
    let real = s.real_position.expect("known start");
    for k in 0..3 {
        assert!(
            (real[k] - s.final_position[k]).abs() <= STEP[k],
            "axis {k}: real {real:?} vs {:?}",
            s.final_position
        );
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn without_a_known_start_homing_runs_to_the_end_as_in_klippy_batch_mode() {
    let dir = sd("ideal", "G28 X\n");
    let s = onechip_host::run_with(
        &dir,
        &Options {
            start: Start::Ideal,
            ..Options::default()
        },
    )
    .expect("runs");
    assert_eq!(s.endstops, []);
    assert_eq!(s.real_position, None);
    std::fs::remove_dir_all(&dir).ok();
}

/// Steps of `stepper` written by a run with `steps_dir`: clock, direction.
fn steps(dir: &std::path::Path, stepper: &str) -> Vec<(u64, bool)> {
    onechip_golden::steps_file(&dir.join(format!("steps-{stepper}.txt")))
}

#[test]
fn homing_from_mid_travel_ends_at_each_trigger_as_in_klipper() {
    let dir = sd("mid", "G28\n");
    let out = dir.join("steps");
    let s = onechip_host::run_with(
        &dir,
        &Options {
            steps_dir: Some(out.clone()),
            ..Options::default()
        },
    )
    .expect("runs");
    assert_eq!((s.errors.len(), s.shutdown.as_ref()), (0, None));
    assert_eq!(s.endstops.len(), 6);
    // Klipper needs about 34 s from mid-travel (Z: 125 mm at 5 mm/s);
    // with the rest of each planned homing move idled away it was 96 s.
    assert!(s.print_time <= 36.0, "G28 took {:.1} s", s.print_time);
    // After each trigger the homed axis moves again (the retract, the
    // second approach, or the next axis) within 50 ms, not after the rest
    // of the planned move (the last trigger ends G28).
    let freq = s.mcu_freq;
    let names = ["stepper_x", "stepper_y", "stepper_z"];
    for (i, pair) in s.endstops.windows(2).enumerate() {
        let ((axis, _, at), next_axis) = (pair[0], pair[1].0);
        let moved = [axis, next_axis].map(|a| {
            steps(&out, names[a])
                .into_iter()
                .map(|(clock, _)| clock as f64 / freq)
                .find(|&t| t > at)
        });
        let next = moved
            .iter()
            .flatten()
            .copied()
            .fold(f64::INFINITY, f64::min);
        assert!(
            next - at < 0.050,
            "trigger {i} (axis {axis}) at {at:.3} s: next step at {next:.3} s"
        );
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn an_endstop_that_never_triggers_fails_g28_with_klippers_message() {
    let dir = sd("dead", "G28 X\nG1 X10 F3000\n");
    let s = onechip_host::run_with(
        &dir,
        &Options {
            start: Start::At([50.0, 80.0, 30.0]),
            dead_endstop: Some(0),
            ..Options::default()
        },
    )
    .expect("runs");
    assert_eq!(s.shutdown, None);
    let errors: Vec<&str> = s.errors.iter().map(|e| e.1.as_str()).collect();
    assert_eq!(errors.len(), 2, "{errors:?}");
    assert_eq!(errors[0], "No trigger on x after full movement");
    // As after Klipper's failed G28 (motors off): X must be homed again.
    assert!(errors[1].starts_with("Must home axis first"), "{errors:?}");
    assert_eq!(s.endstops, []);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_shutdown_while_homing_is_the_error_not_a_missing_trigger() {
    let dir = sd("shutdown", "G28\n");
    let s = onechip_host::run_with(
        &dir,
        &Options {
            start: Start::At([150.0, 150.0, 100.0]),
            // The hot end's thermistor opens 0.5 s in, while X homes.
            open_sensor: Some((0.5, 0)),
            ..Options::default()
        },
    )
    .expect("runs");
    assert!(s.shutdown.is_some(), "{:?}", s.errors);
    assert!(
        s.errors.iter().all(|e| !e.1.contains("No trigger")),
        "{:?}",
        s.errors
    );
    std::fs::remove_dir_all(&dir).ok();
}
