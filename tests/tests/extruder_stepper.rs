//! `[extruder_stepper NAME]`, as Klipper's: an extra stepper that follows
//! the extruder's motion queue with its own rotation distance and
//! pressure advance, or stands still when synced to nothing;
//! SYNC_EXTRUDER_MOTION, SET_EXTRUDER_ROTATION_DISTANCE and
//! SET_PRESSURE_ADVANCE on it, taking effect after the queued moves, with
//! Klipper's replies and refusals. The shipped printer with a second
//! extruder stepper on the Octopus Pro's MOTOR_3 socket, run in virtual
//! time; steps compared from the host's step logs.

use onechip_host::console_printer::ConsolePrinter;
use onechip_host::{Options, Start, Summary};
use onechip_tests::sd_folder;
use std::path::{Path, PathBuf};

/// The extra stepper's section name, as its step log names it.
const E1: &str = "extruder_stepper e1";
/// Step times of two steppers doing the same thing agree within the
/// compressors' max_error (25 µs), s.
const STEP_TOLERANCE: f64 = 25e-6;

/// An SD folder named `name`: the shipped printer.cfg extruding cold,
/// with the extruder's rotation_distance 32 (0.01 mm per step, so that
/// whole millimetres are whole steps) and `[extruder_stepper e1]` with
/// `e1` lines; `gcode` as its job.
fn sd(name: &str, e1: &str, gcode: &str) -> PathBuf {
    let text = sd_folder::shipped_cfg();
    assert!(text.contains("rotation_distance: 33.500\n"));
    let text = text
        .replace("[extruder]\n", "[extruder]\nmin_extrude_temp: 0\n")
        .replace("rotation_distance: 33.500\n", "rotation_distance: 32\n");
    let section = format!(
        "\n[extruder_stepper e1]\nstep_pin: PG4\ndir_pin: PC1\nenable_pin: !PA2\n\
         microsteps: 16\n{e1}\n"
    );
    sd_folder::new(&format!("estep-{name}"), &(text + &section), Some(gcode))
}

/// Runs the folder's job with every step logged; the summary and the
/// step log folder.
fn run(dir: &Path) -> (Summary, PathBuf) {
    let out = dir.join("steps");
    let s = onechip_host::run_with(
        dir,
        &Options {
            start: Start::At([50.0, 80.0, 30.0]),
            steps_dir: Some(out.clone()),
            ..Options::default()
        },
    )
    .expect("runs");
    assert_eq!(
        (s.errors.as_slice(), s.shutdown.as_ref()),
        (&[][..], None),
        "{s}"
    );
    (s, out)
}

/// Every step of `stepper` in a run's step logs: clock, direction.
fn steps(out: &Path, stepper: &str) -> Vec<(u64, bool)> {
    onechip_golden::steps_file(&out.join(format!("steps-{stepper}.txt")))
}

/// Asserts `ours` are `want`'s steps: as many, the same directions, each
/// within [`STEP_TOLERANCE`].
fn assert_same_steps(ours: &[(u64, bool)], want: &[(u64, bool)], freq: f64, what: &str) {
    assert_eq!(ours.len(), want.len(), "{what}: step count");
    let tolerance = (STEP_TOLERANCE * freq) as u64;
    for (k, (a, b)) in ours.iter().zip(want).enumerate() {
        assert_eq!(a.1, b.1, "{what}: direction of step {k}");
        assert!(
            a.0.abs_diff(b.0) <= tolerance,
            "{what}: step {k} at {} vs {} ticks",
            a.0,
            b.0
        );
    }
}

/// A stepper's final position in a summary, steps.
fn position(s: &Summary, name: &str) -> i64 {
    s.steppers
        .iter()
        .find(|st| st.name == name)
        .unwrap_or_else(|| panic!("{name}: {:?}", s.steppers))
        .position
}

/// Extrusion with XY motion (pressure advance applies), a retraction, an
/// extrude-only move and a travel.
const PRINT: &str = "G28\nM83\nG1 X60 Y60 F6000\nG1 X100 Y60 E4 F3000\nG1 X100 Y100 E4\n\
                     G1 E-2 F1800\nG1 X60 Y100 F6000\nG1 E2 F1800\nG1 X60 Y60 E4 F3000\nM400\n";

#[test]
fn a_synced_extruder_stepper_makes_the_extruders_steps() {
    // The same rotation distance and pressure advance as the extruder.
    let dir = sd(
        "same",
        "extruder: extruder\nrotation_distance: 32\npressure_advance: 0.04",
        PRINT,
    );
    let (s, out) = run(&dir);
    let extruder = steps(&out, "extruder");
    // 12 mm of filament at 100 steps/mm, with the retraction's 2 mm back
    // and forth (and pressure advance's).
    assert!(extruder.len() >= 1200 + 400, "{}", extruder.len());
    assert_eq!(position(&s, "extruder"), 1200);
    assert_same_steps(&steps(&out, E1), &extruder, s.mcu_freq, "e1");
    assert_eq!(position(&s, E1), 1200);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn an_extruder_stepper_has_its_own_pressure_advance_and_rotation_distance() {
    // No pressure advance on e1: the same filament, other step times.
    let dir = sd("pa", "extruder: extruder\nrotation_distance: 32", PRINT);
    let (s, out) = run(&dir);
    let (extruder, e1) = (steps(&out, "extruder"), steps(&out, E1));
    assert_eq!(position(&s, E1), position(&s, "extruder"));
    let tolerance = (STEP_TOLERANCE * s.mcu_freq) as u64;
    let first_apart = e1
        .iter()
        .zip(&extruder)
        .position(|(a, b)| a.0.abs_diff(b.0) > tolerance);
    assert!(
        first_apart.is_some(),
        "e1 stepped with the extruder's advance"
    );
    std::fs::remove_dir_all(&dir).ok();
    // Half the rotation distance: twice the steps; a negative one steps
    // the other way.
    for (rotation, want) in [("16", 2400), ("-32", -1200)] {
        let dir = sd(
            "rd",
            "extruder: extruder\nrotation_distance: 32\npressure_advance: 0.04",
            &format!("SET_EXTRUDER_ROTATION_DISTANCE EXTRUDER=e1 DISTANCE={rotation}\n{PRINT}"),
        );
        let (s, out) = run(&dir);
        assert_eq!(position(&s, E1), want, "rotation_distance {rotation}");
        let (extruder, e1) = (steps(&out, "extruder"), steps(&out, E1));
        if rotation == "-32" {
            let reversed: Vec<_> = extruder.iter().map(|&(t, d)| (t, !d)).collect();
            assert_same_steps(&e1, &reversed, s.mcu_freq, "e1 reversed");
        }
        std::fs::remove_dir_all(&dir).ok();
    }
}

#[test]
fn a_rotation_distance_set_mid_print_changes_the_moves_after_it() {
    // Without pressure advance, so that each move's steps are its own.
    let dir = sd(
        "mid",
        "extruder: extruder\nrotation_distance: 32",
        "SET_PRESSURE_ADVANCE ADVANCE=0\nG28\nM83\nG1 X60 Y60 F6000\nG1 X100 Y60 E4 F3000\n\
         SET_EXTRUDER_ROTATION_DISTANCE EXTRUDER=e1 DISTANCE=-32\n\
         G1 X100 Y100 E3\nG1 E-1 F1800\n\
         SET_EXTRUDER_ROTATION_DISTANCE EXTRUDER=e1 DISTANCE=16\nG1 X60 Y100 E2 F3000\nM400\n",
    );
    let (s, out) = run(&dir);
    let (extruder, e1) = (steps(&out, "extruder"), steps(&out, E1));
    assert_eq!(position(&s, "extruder"), 800);
    // The first move as the extruder, the next two reversed, the last at
    // twice the steps.
    assert_eq!(position(&s, E1), 400 - 300 + 100 + 400);
    assert_same_steps(&e1[..400], &extruder[..400], s.mcu_freq, "e1 before");
    let reversed: Vec<_> = extruder[400..800].iter().map(|&(t, d)| (t, !d)).collect();
    assert_same_steps(&e1[400..800], &reversed, s.mcu_freq, "e1 reversed");
    assert_eq!(e1.len(), 800 + 400);
    assert!(e1[800..].iter().all(|&(t, d)| d && t > extruder[799].0));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn an_unsynced_extruder_stepper_stands_still_until_synced_mid_print() {
    // Without pressure advance, so that each move's steps are its own.
    let dir = sd(
        "sync",
        "extruder:\nrotation_distance: 32",
        "SET_PRESSURE_ADVANCE ADVANCE=0\nG28\nM83\nG1 X60 Y60 F6000\nG1 X100 Y60 E4 F3000\n\
         SYNC_EXTRUDER_MOTION EXTRUDER=e1 MOTION_QUEUE=extruder\n\
         G1 X100 Y100 E3\nG1 X60 Y100 E2\n\
         SYNC_EXTRUDER_MOTION EXTRUDER=e1 MOTION_QUEUE=\n\
         G1 X60 Y60 E5\nM400\n",
    );
    let (s, out) = run(&dir);
    assert_eq!(position(&s, "extruder"), 1400);
    // Only the two moves between the commands moved e1: its steps are
    // the extruder's from the 400th to the 900th.
    let (extruder, e1) = (steps(&out, "extruder"), steps(&out, E1));
    assert_eq!(position(&s, E1), 500);
    assert_same_steps(&e1, &extruder[400..900], s.mcu_freq, "e1 while synced");
    std::fs::remove_dir_all(&dir).ok();
    // Synced to nothing from the start: no step at all.
    let dir = sd("none", "extruder:\nrotation_distance: 32", PRINT);
    let (s, out) = run(&dir);
    assert_eq!(position(&s, "extruder"), 1200);
    assert_eq!(steps(&out, E1), []);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn the_geeetech_301s_extruder_steppers_follow_the_extruder_once_synced() {
    // Klipper's stock config for the Geeetech A30 / 301 (three filaments
    // into one nozzle: `[extruder_stepper e1]` and `e2` synced to
    // nothing), extruding cold; the G-code syncs one, then the other.
    let stock = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/klipper-configs/printer-geeetech-301-2019.cfg");
    let text = std::fs::read_to_string(stock).expect("stock config");
    let dir = sd_folder::new(
        "estep-301",
        &(text + "\n[extruder]\nmin_extrude_temp: 0\n"),
        Some(
            "G28\nG1 Z150 F6000\nM83\nG1 X10 E1 F1200\n\
             SYNC_EXTRUDER_MOTION EXTRUDER=e1 MOTION_QUEUE=extruder\nG1 Y10 E1\n\
             SYNC_EXTRUDER_MOTION EXTRUDER=e1 MOTION_QUEUE=\n\
             SYNC_EXTRUDER_MOTION EXTRUDER=e2 MOTION_QUEUE=extruder\nG1 X-10 E2\nM400\n",
        ),
    );
    let s = onechip_host::run_with(
        &dir,
        &Options {
            start: Start::At([0.0, 0.0, 150.0]),
            board_pins: false,
            ..Options::default()
        },
    )
    .expect("runs");
    assert_eq!(
        (s.errors.as_slice(), s.shutdown.as_ref()),
        (&[][..], None),
        "{s}"
    );
    assert!(
        s.unsupported
            .iter()
            .all(|u| !u.starts_with("extruder_stepper"))
    );
    // 0.01 mm of filament per step on each.
    assert_eq!(position(&s, "extruder"), 400);
    assert_eq!(position(&s, "extruder_stepper e1"), 100);
    assert_eq!(position(&s, "extruder_stepper e2"), 200);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn an_extruder_steppers_tmc_driver_is_configured_and_answers_to_its_short_name() {
    // As Klipper: `[tmc2209 extruder_stepper e1]`, STEPPER=e1 in G-code.
    let dir = sd(
        "tmc",
        "extruder: extruder\nrotation_distance: 32\n\n\
         [tmc2209 extruder_stepper e1]\nuart_pin: PC7\nrun_current: 0.8",
        "",
    );
    let mut p = ConsolePrinter::new(&dir, &Options::default()).expect("printer");
    p.send("G4 P10");
    // Written over its UART at start: IHOLD_IRUN as configured (0.8 A:
    // 25), the simulated driver holding what the session wrote.
    let written: Vec<(u8, u32)> = (p.tmc().registers(E1).expect("driver").iter()).collect();
    let sim = p.tmc_drivers().driver(E1).expect("simulated");
    assert_eq!(sim.field("irun"), Some(25));
    assert!(written.iter().all(|&(addr, v)| sim.register(addr) == v));
    assert_eq!(
        p.send("SET_TMC_CURRENT STEPPER=e1 CURRENT=0.5"),
        "// Run Current: 0.49A Hold Current: 0.49A\nok\n"
    );
    assert_eq!(
        p.send("SET_TMC_CURRENT STEPPER=extruder_stepper CURRENT=0.5"),
        "!! The value 'extruder_stepper' is not valid for STEPPER\nok\n"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn the_commands_reply_and_refuse_as_klipper() {
    let dir = sd(
        "console",
        "extruder:\nrotation_distance: 32\npressure_advance: 0.02",
        "",
    );
    let mut p = ConsolePrinter::new(
        &dir,
        &Options {
            start: Start::At([50.0, 80.0, 30.0]),
            ..Options::default()
        },
    )
    .expect("printer");
    let cases = [
        (
            "SYNC_EXTRUDER_MOTION EXTRUDER=e1 MOTION_QUEUE=extruder",
            "// Extruder 'e1' now syncing with 'extruder'\nok\n",
        ),
        (
            "SYNC_EXTRUDER_MOTION EXTRUDER=e1 MOTION_QUEUE=",
            "// Extruder 'e1' now syncing with ''\nok\n",
        ),
        (
            "SYNC_EXTRUDER_MOTION EXTRUDER=e2 MOTION_QUEUE=extruder",
            "!! The value 'e2' is not valid for EXTRUDER\nok\n",
        ),
        (
            "SYNC_EXTRUDER_MOTION EXTRUDER=e1 MOTION_QUEUE=e1",
            "!! 'e1' is not a valid extruder.\nok\n",
        ),
        (
            "SET_EXTRUDER_ROTATION_DISTANCE EXTRUDER=e1",
            "// Extruder 'e1' rotation distance set to 32.000000\nok\n",
        ),
        (
            "SET_EXTRUDER_ROTATION_DISTANCE EXTRUDER=e1 DISTANCE=-22.5",
            "// Extruder 'e1' rotation distance set to -22.500000\nok\n",
        ),
        (
            "SET_EXTRUDER_ROTATION_DISTANCE EXTRUDER=e1 DISTANCE=0",
            "!! Rotation distance can not be zero\nok\n",
        ),
        (
            "SET_EXTRUDER_ROTATION_DISTANCE EXTRUDER=extruder",
            "// Extruder 'extruder' rotation distance set to 32.000000\nok\n",
        ),
        (
            "SET_PRESSURE_ADVANCE EXTRUDER=e1",
            "// pressure_advance: 0.020000\n// pressure_advance_smooth_time: 0.040000\nok\n",
        ),
        (
            "SET_PRESSURE_ADVANCE EXTRUDER=e1 ADVANCE=0.05 SMOOTH_TIME=0.02",
            "// pressure_advance: 0.050000\n// pressure_advance_smooth_time: 0.020000\nok\n",
        ),
        // Without EXTRUDER: the extruder's own, unchanged by e1's.
        (
            "SET_PRESSURE_ADVANCE",
            "// pressure_advance: 0.040000\n// pressure_advance_smooth_time: 0.040000\nok\n",
        ),
        (
            "SET_PRESSURE_ADVANCE EXTRUDER=E1",
            "!! The value 'E1' is not valid for EXTRUDER\nok\n",
        ),
        // The extruder's own stepper synced to nothing: the default
        // SET_PRESSURE_ADVANCE cannot tell which stepper is meant.
        (
            "SYNC_EXTRUDER_MOTION EXTRUDER=extruder MOTION_QUEUE=",
            "// Extruder 'extruder' now syncing with ''\nok\n",
        ),
        (
            "SET_PRESSURE_ADVANCE",
            "!! Unable to infer active extruder stepper\nok\n",
        ),
    ];
    for (line, want) in cases {
        assert_eq!(p.send(line), want, "{line}");
    }
    for (line, missing) in [
        ("SET_EXTRUDER_ROTATION_DISTANCE DISTANCE=3", "EXTRUDER"),
        ("SYNC_EXTRUDER_MOTION EXTRUDER=e1", "MOTION_QUEUE"),
    ] {
        let reply = p.send(line);
        assert!(
            reply.starts_with("!! ") && reply.contains(&format!("missing {missing}")),
            "{line}: {reply}"
        );
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_extruder_stepper_sections_are_refused_naming_file_line_and_option() {
    for (name, e1, want) in [
        (
            "bad-extruder",
            "extruder: extruder1\nrotation_distance: 32",
            "option 'extruder' in section 'extruder_stepper e1' is not a valid extruder",
        ),
        (
            "no-extruder",
            "rotation_distance: 32",
            "option 'extruder' in section 'extruder_stepper e1' must be specified",
        ),
        (
            "bad-pa",
            "extruder: extruder\nrotation_distance: 32\npressure_advance_smooth_time: 0.3",
            "option 'pressure_advance_smooth_time' in section 'extruder_stepper e1'",
        ),
        (
            "endstop",
            "extruder: extruder\nrotation_distance: 32\nendstop_pin: PG11",
            "option 'endstop_pin' is not valid in section 'extruder_stepper e1'",
        ),
    ] {
        let dir = sd(name, e1, "M400\n");
        let s = onechip_host::run_with(&dir, &Options::default());
        let e = match s {
            Ok(s) => panic!("{name}: loaded: {s}"),
            Err(e) => e.to_string(),
        };
        assert!(e.contains(want), "{name}: {e}");
        // The file and the line of the option (or of the section).
        assert!(e.contains("printer.cfg:"), "{name}: {e}");
        std::fs::remove_dir_all(&dir).ok();
    }
}

#[test]
fn a_secondary_mcu_gets_an_extruder_steppers_config_where_klippy_creates_it() {
    // Klipper's cartesian golden machine with an extruder stepper whose
    // enable line is the extruder's: klippy creates it with the other
    // extra sections, before the toolhead's rails and extruder, so its
    // stepper takes object id 0 and its config comes first; the shared
    // enable pin is configured once, with the first stepper.
    use onechip_app::heaters::McuSetup;
    use onechip_app::mcu_config::{ConfigTarget, MAIN, write_config};
    let text = onechip_golden::config("cartesian.cfg")
        + "\n[extruder_stepper e1]\nextruder: extruder\nstep_pin: PE2\ndir_pin: PE3\n\
           enable_pin: !PA0\nmicrosteps: 16\nrotation_distance: 33.5\n";
    let config = onechip_config::Config::parse("printer.cfg", &text).expect("config");
    let machine = onechip_planner::machine::Machine::from_config(&config).expect("machine");
    let freq = 180e6;
    let setup = McuSetup::new(
        &machine,
        freq,
        4095,
        onechip_host::thermal_plant::mcu_sensor(),
        0,
    );
    let mut lines = Vec::new();
    let main = ConfigTarget {
        mcu: MAIN,
        pwm_max: 255,
        spi_bus: "spi",
    };
    let oids = write_config(&machine, &setup, main, &|_| 360, &mut |l| {
        lines.push(l.to_string())
    });
    // 16 objects as klippy's golden session, and e1's stepper.
    assert_eq!(oids.count, 17);
    assert_eq!(oids.steppers[4], Some(0));
    assert_eq!(
        oids.steppers[0],
        Some(3),
        "stepper_x after its endstop and trsync"
    );
    assert_eq!(oids.steppers[3], Some(10), "the extruder's last");
    assert_eq!(oids.enables[4], oids.enables[3]);
    assert_eq!(
        &lines[1..3],
        [
            "config_stepper oid=0 step_pin=PE2 dir_pin=PE3 invert_step=0 step_pulse_ticks=360",
            "config_digital_out oid=11 pin=PA0 value=1 default_value=1 max_duration=0",
        ]
    );
    assert!(
        lines[3].starts_with("config_endstop oid=1 pin=PG6"),
        "{lines:?}"
    );
    // The extruder's stepper keeps its place after its heater, sharing
    // e1's enable output.
    let extruder = lines
        .iter()
        .position(|l| l.contains("step_pin=PG4"))
        .expect("the extruder's stepper");
    assert!(lines[extruder - 1].starts_with("set_digital_out_pwm_cycle"));
    assert!(!lines[extruder + 1..].iter().any(|l| l.contains("pin=PA0")));
}
