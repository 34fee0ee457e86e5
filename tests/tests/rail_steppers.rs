//! A rail driven by several steppers (`[stepper_z1]`, as Klipper's
//! `PrinterRail` with extra steppers): each extra stepper follows its
//! rail's kinematics; one with an endstop of its own stops at it alone
//! while the others go on (a racked gantry squared by homing), one without
//! stops with the rail's endstop.

use onechip_host::{Options, Start, Summary};
use onechip_tests::sd_folder;

/// mm per Z step on the shipped machine.
const Z_STEP: f64 = 0.0025;
/// How far the second Z screw starts above the first, mm.
const RACKED: f64 = 1.0;

/// The shipped machine with a second Z stepper on MOTOR_3 (the BTT
/// Octopus Pro's stock `[stepper_z1]` pins) and `endstop` lines, homed and
/// moved from a racked gantry.
fn racked_run(name: &str, endstop: &str) -> Summary {
    let text = sd_folder::shipped_cfg();
    let z = text.find("[stepper_z]").expect("a Z rail");
    let z_steps = "step_pin: PF11";
    let rotation = text[z..]
        .lines()
        .find(|l| l.starts_with("rotation_distance"))
        .expect("rotation_distance");
    let microsteps = text[z..]
        .lines()
        .find(|l| l.starts_with("microsteps"))
        .expect("microsteps");
    assert!(text.contains(z_steps));
    let extra = format!(
        "\n[stepper_z1]\nstep_pin: PG4\ndir_pin: PC1\nenable_pin: !PA2\n{microsteps}\n\
         {rotation}\n{endstop}\n"
    );
    let dir = sd_folder::new(
        &format!("rail-{name}"),
        &(text + &extra),
        Some("G28\nM114\nG1 Z10 F600\nM114\nM400\nM119\n"),
    );
    let s = onechip_host::run_with(
        &dir,
        &Options {
            start: Start::At([50.0, 80.0, 30.0]),
            racked: RACKED,
            ..Options::default()
        },
    )
    .expect("runs");
    std::fs::remove_dir_all(&dir).ok();
    s
}

/// (stepper_z's, stepper_z1's) final positions, steps.
fn z_positions(s: &Summary) -> (i64, i64) {
    let of = |name: &str| {
        s.steppers
            .iter()
            .find(|st| st.name == name)
            .unwrap_or_else(|| panic!("{name}: {:?}", s.steppers))
            .position
    };
    (of("stepper_z"), of("stepper_z1"))
}

#[test]
fn an_extra_stepper_with_its_own_endstop_squares_the_rail_when_homing() {
    let s = racked_run("own", "endstop_pin: PG11");
    assert_eq!(
        (s.errors.as_slice(), s.shutdown.as_ref()),
        (&[][..], None),
        "{s}"
    );
    assert_eq!(s.replies[0].1, "X:0.000 Y:0.000 Z:0.500 E:0.000");
    assert_eq!(s.replies[1].1, "X:0.000 Y:0.000 Z:10.000 E:0.000");
    // Each screw stopped at its own endstop: the second, which started
    // 1 mm higher, made 1 mm more steps down, and both end at Z 10.
    let (z, z1) = z_positions(&s);
    let start = 30.0;
    let real_z = start + z as f64 * Z_STEP;
    let real_z1 = start + RACKED + z1 as f64 * Z_STEP;
    assert!((real_z - 10.0).abs() <= Z_STEP, "stepper_z at {real_z}");
    assert!(
        (real_z1 - 10.0).abs() <= 2.0 * Z_STEP,
        "stepper_z1 at {real_z1}"
    );
    assert!(
        ((z - z1) as f64 * Z_STEP - RACKED).abs() <= 2.0 * Z_STEP,
        "{z} vs {z1}"
    );
}

#[test]
fn an_extra_stepper_without_an_endstop_moves_with_its_rail() {
    for (name, endstop) in [("none", ""), ("shared", "endstop_pin: PG10")] {
        let s = racked_run(name, endstop);
        assert_eq!(
            (s.errors.as_slice(), s.shutdown.as_ref()),
            (&[][..], None),
            "{name}: {s}"
        );
        assert_eq!(s.replies[1].1, "X:0.000 Y:0.000 Z:10.000 E:0.000");
        // Stopped with stepper_z's endstop: the same steps, the gantry
        // still racked.
        let (z, z1) = z_positions(&s);
        assert_eq!(z, z1, "{name}");
    }
}

#[test]
fn a_dead_endstop_on_an_extra_stepper_fails_g28_with_klippers_message() {
    let dir_summary = {
        let extra = "\n[stepper_z1]\nstep_pin: PG4\ndir_pin: PC1\nenable_pin: !PA2\n\
                     microsteps: 16\nrotation_distance: 8\nendstop_pin: PG11\n";
        let dir = sd_folder::new(
            "rail-dead",
            &(sd_folder::shipped_cfg() + extra),
            Some("G28 Z\n"),
        );
        let s = onechip_host::run_with(
            &dir,
            &Options {
                start: Start::At([50.0, 80.0, 30.0]),
                dead_endstop: Some(3),
                ..Options::default()
            },
        )
        .expect("runs");
        std::fs::remove_dir_all(&dir).ok();
        s
    };
    let s = dir_summary;
    assert!(
        s.errors
            .iter()
            .any(|(_, e)| e.contains("No trigger on z1 after full movement")),
        "{:?}",
        s.errors
    );
}
