//! The README's main command, on the shipped default SD folder and on bad
//! input, end to end through the host build.

use onechip_planner::machine::Kinematics;
use onechip_tests::sd_folder;
use std::path::PathBuf;

/// A throw-away SD folder with the shipped printer.cfg and `gcode`.
fn sd_with(name: &str, gcode: &str) -> PathBuf {
    sd_folder::new(name, &sd_folder::shipped_cfg(), Some(gcode))
}

#[test]
fn the_shipped_default_plans_cleanly() {
    let s = onechip_host::run(&sd_folder::shipped_dir(), None).expect("runs");
    assert!(s.gcode_path.ends_with("first-layer-square.gcode"));
    assert_eq!(s.kinematics, Kinematics::Cartesian);
    assert_eq!(s.errors, []);
    assert_eq!(s.unsupported, Vec::<String>::new());
    // Homing (3 moves per axis), 4 square sides, travel, z moves and the
    // final nudge; E on 7 of them.
    assert_eq!((s.toolhead_moves, s.extruder_moves), (20, 7));
    assert_eq!(s.final_position, [122.5, 117.5, 10.0, 6.86]);
    assert_eq!(
        s.replies,
        [(30, "X:122.500 Y:117.500 Z:10.000 E:6.860".to_string())]
    );
    // M190 and M109 report temperatures every second while they wait;
    // M105 (line 29) reports once more.
    let (last_line, last) = s.temperatures.last().expect("reports");
    assert!(*last_line == 29 && last.starts_with("T:"), "{last}");
    assert!(s.temperatures.len() as f64 >= s.heat_wait - 2.0);
    // The bed (watermark, 60 °C) and the hot end (PID, 200 °C) heat while
    // homing; M190 and M109 then wait until both have settled, and the
    // print ends with both targets 0 and the fan off.
    let [extruder, bed] = &s.heaters[..] else {
        panic!("{:?}", s.heaters)
    };
    assert!((200.0..205.0).contains(&extruder.peak), "{extruder:?}");
    assert!((60.0..63.0).contains(&bed.peak), "{bed:?}");
    assert_eq!((extruder.target, bed.target), (0.0, 0.0));
    assert!(s.heat_wait > 1.0 && s.heat_wait < 120.0, "{}", s.heat_wait);
    assert_eq!(s.fan_speed, Some(0.0));
    // Every stepper moved, and nothing shut down; X and Y end where homing
    // and the moves put them relative to where they started.
    assert_eq!(s.shutdown, None);
    let steps: Vec<usize> = s.steppers.iter().map(|st| st.steps).collect();
    assert!(steps.iter().all(|&n| n > 0), "{steps:?}");
    // Homing from mid-travel ends at the endstops (~34 s, Z at 5 mm/s
    // from Z=125), then about 9 s of printing.
    assert!(
        s.print_time - s.heat_wait > 40.0 && s.print_time - s.heat_wait < 46.0,
        "{} {}",
        s.print_time,
        s.heat_wait
    );
}

#[test]
fn bad_lines_are_reported_with_their_number_and_the_rest_still_runs() {
    let dir = sd_with(
        "bad-gcode",
        "SET_KINEMATIC_POSITION X=0 Y=0 Z=0\nG1 X10 F6000\nG1 X1.2.3\nG1 X500\nN7 G1 Y10*99\nM999\nG1 Y10\n",
    );
    let s = onechip_host::run(&dir, None).expect("runs");
    let lines: Vec<usize> = s.errors.iter().map(|(n, _)| *n).collect();
    assert_eq!(lines, [3, 4], "{:?}", s.errors);
    assert!(
        s.errors[0].1.contains("unable to parse X=1.2.3"),
        "{:?}",
        s.errors
    );
    assert!(
        s.errors[1].1.starts_with("Move out of range: 500.000"),
        "{:?}",
        s.errors
    );
    // A bad checksum is not run, and the host is asked to resend (Marlin's
    // words); M999 without a shutdown does nothing.
    assert_eq!(
        s.replies,
        [
            (5, "Error:checksum mismatch, Last Line: 0".to_string()),
            (5, "Resend: 1".to_string())
        ]
    );
    assert_eq!(s.toolhead_moves, 2);
    assert_eq!(s.final_position[..2], [10.0, 10.0]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_bad_config_names_file_line_and_option() {
    let dir = sd_with("bad-cfg", "G1 X1\n");
    let cfg = std::fs::read_to_string(dir.join("printer.cfg")).expect("cfg");
    std::fs::write(
        dir.join("printer.cfg"),
        cfg.replace("max_accel: 3000", "max_accel: fast"),
    )
    .expect("write");
    let err = onechip_host::run(&dir, None)
        .expect_err("bad config")
        .to_string();
    assert!(
        err.ends_with("option 'max_accel' in section 'printer' is not a number"),
        "{err}"
    );
    assert!(err.contains("printer.cfg:15:"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn includes_are_read_from_the_sd_folder() {
    let dir = sd_with("include", "G28\nG1 X10 Y10 F6000\n");
    let cfg = std::fs::read_to_string(dir.join("printer.cfg")).expect("cfg");
    std::fs::create_dir_all(dir.join("extras")).expect("dir");
    std::fs::write(
        dir.join("extras/speed.cfg"),
        "[printer]\nmax_velocity: 120\n",
    )
    .expect("write");
    std::fs::write(
        dir.join("printer.cfg"),
        format!("{cfg}\n[include extras/*.cfg]\n"),
    )
    .expect("write");
    let s = onechip_host::run(&dir, None).expect("runs");
    assert_eq!(s.errors, []);
    std::fs::write(
        dir.join("extras/speed.cfg"),
        "[printer]\nmax_velocity: fast\n",
    )
    .expect("write");
    let err = onechip_host::run(&dir, None)
        .expect_err("bad include")
        .to_string();
    assert!(
        err.starts_with("extras/speed.cfg:2: option 'max_velocity'"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_missing_gcode_file_is_a_clear_error() {
    let dir = sd_with("no-gcode", "");
    std::fs::remove_file(dir.join("job.gcode")).expect("remove");
    let err = onechip_host::run(&dir, None).expect_err("no gcode");
    assert!(
        err.to_string()
            .contains("expected exactly one *.gcode file"),
        "{err}"
    );
    let err = onechip_host::run(&dir, Some(&dir.join("missing.gcode"))).expect_err("missing");
    assert!(err.to_string().contains("missing.gcode"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_plot_of_a_window_is_written_as_svg() {
    let out = std::env::temp_dir().join(format!("onechip-plot-{}.svg", std::process::id()));
    let window = onechip_host::plot::Window {
        from: 95.0,
        to: 104.5,
    };
    let s = onechip_host::run_with(
        &sd_folder::shipped_dir(),
        &onechip_host::Options {
            plot: Some((out.clone(), window)),
            ..onechip_host::Options::default()
        },
    )
    .expect("runs");
    let svg = std::fs::read_to_string(&out).expect("plot written");
    assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
    // The velocity line and one per stepper.
    assert_eq!(svg.matches("<polyline").count(), 1 + s.steppers.len());
    assert!(s.steppers.iter().all(|st| svg.contains(&st.name)));
    std::fs::remove_file(&out).ok();
}
