//! Klipper's heater safety end to end through the host build: a heater
//! that does not heat as expected shuts the printer down (verify_heater),
//! a normal heat-up never does, and the extruder refuses to move while
//! cold (min_extrude_temp) or further than max_extrude_only_distance
//! without XY motion, with Klipper's messages.

use onechip_host::{Options, Summary};
use onechip_tests::sd_folder;
use std::path::PathBuf;

/// A throw-away SD folder with the shipped printer.cfg plus `extra` and
/// `gcode`.
fn sd_with(name: &str, extra: &str, gcode: &str) -> PathBuf {
    sd_folder::new(
        &format!("safety-{name}"),
        &(sd_folder::shipped_cfg() + extra),
        Some(gcode),
    )
}

/// Runs `gcode` on the shipped printer (plus `extra` config) with heater
/// `weak.0`'s element giving `weak.1` of its power.
fn run(name: &str, extra: &str, gcode: &str, weak: Option<(usize, f64)>) -> Summary {
    let dir = sd_with(name, extra, gcode);
    let options = Options {
        weak_heater: weak,
        ..Options::default()
    };
    let s = onechip_host::run_with(&dir, &options).expect("runs");
    let _ = std::fs::remove_dir_all(&dir);
    s
}

/// Every heater is off at the end.
fn all_stopped(s: &Summary) {
    assert!(s.heaters.iter().all(|h| !h.on_at_end), "{:?}", s.heaters);
}

#[test]
fn a_heater_that_cannot_heat_shuts_the_printer_down_with_klippers_message() {
    // The hot end's element is dead. M109 sets 200 °C at 0 s and waits;
    // the first check (the first temperature report, 0.2 s) starts the
    // approach, which ends without the 2 °C gain after check_gain_time
    // (20 checks, one a second); the next check finds the accumulated
    // error (about 170 °C·s a second) past max_error (120): the fault is
    // due 0.2 + 20 + 1 = 21.2 s after the target was set.
    let s = run("dead", "", "M109 S200\nG28\n", Some((0, 0.0)));
    assert_eq!(
        s.shutdown.as_deref(),
        Some("Heater extruder not heating at expected rate")
    );
    // M109 waited until the shutdown.
    assert!((21.2..21.5).contains(&s.heat_wait), "{}", s.heat_wait);
    assert!(s.heaters[0].peak < 25.5, "{:?}", s.heaters);
    all_stopped(&s);
    // Nothing moved: the shutdown came first, G28 never ran.
    assert!(s.steppers.iter().all(|st| st.steps == 0));

    // [verify_heater extruder] overrides the defaults: 40 s to gain.
    let s = run(
        "dead-40",
        "\n[verify_heater extruder]\ncheck_gain_time: 40\n",
        "M109 S200\n",
        Some((0, 0.0)),
    );
    assert_eq!(
        s.shutdown.as_deref(),
        Some("Heater extruder not heating at expected rate")
    );
    assert!((41.2..41.5).contains(&s.heat_wait), "{}", s.heat_wait);
    assert_eq!(s.unsupported, Vec::<String>::new());
}

#[test]
fn a_weak_heater_that_stalls_below_its_target_shuts_the_printer_down() {
    // A quarter of the 40 W: the hot end settles near 106 °C (time
    // constant 60 s), far below 200 °C. It heats well at first: each 2 °C
    // gained restarts the 20 s window (and clears the error). From about
    // 147 s on it gains less than 2 °C in 20 s (81 °C × e^(-t/60 s) ×
    // (1 − e^(-20/60)) < 2 °C), so the window that starts with the first
    // gain after 147 s (at most 20 s later) runs out 20 s on, and the
    // next check finds the error (about 90 °C·s a second) past 120:
    // between 168 and 188 s (plus up to a report, 0.3 s, and the first
    // report's 0.2 s).
    let s = run("weak", "", "M109 S200\n", Some((0, 0.25)));
    assert_eq!(
        s.shutdown.as_deref(),
        Some("Heater extruder not heating at expected rate")
    );
    assert!((167.0..189.5).contains(&s.heat_wait), "{}", s.heat_wait);
    let hot_end = &s.heaters[0];
    assert!((95.0..107.0).contains(&hot_end.peak), "{hot_end:?}");
    all_stopped(&s);

    // A bed at a fifth of its 250 W settles near 48 °C (time constant
    // 300 s): short of 55 °C (60 − hysteresis). From about 221 s on it
    // gains less than 2 °C per check_gain_time (60 s for the bed: 23 °C ×
    // e^(-t/300 s) × (1 − e^(-60/300)) < 2 °C); the window that starts
    // with the first gain after that runs out 60 s on, and the next check
    // faults (the error grows about 15 °C·s a second): between 282 and
    // 342 s.
    let s = run("weak-bed", "", "M190 S60\n", Some((1, 0.2)));
    assert_eq!(
        s.shutdown.as_deref(),
        Some("Heater heater_bed not heating at expected rate")
    );
    assert!((281.0..342.5).contains(&s.heat_wait), "{}", s.heat_wait);
    all_stopped(&s);
}

#[test]
fn a_normal_heat_up_never_trips_verify_heater() {
    // The shipped job: bed and hot end heat while homing, then print.
    let s = onechip_host::run(&sd_folder::shipped_dir(), None).expect("runs");
    assert_eq!(s.shutdown, None);
    assert_eq!(s.errors, []);
    // Hotter, and held for five minutes: the bed to 110 °C (its simulated
    // 250 W settle at 140 °C; the last 5 °C take minutes, yet gain more
    // than 2 °C a minute), the hot end to 245 °C, then down to 150 °C and
    // back up.
    let gcode = "M140 S110\nM104 S245\nM190 S110\nM109 S245\nG4 P300000\n\
                 M104 S150\nG4 P60000\nM109 S245\nG4 P60000\nM105\n";
    let s = run("hot", "", gcode, None);
    assert_eq!(s.shutdown, None, "{}", s.transcript);
    assert_eq!(s.errors, []);
    let [hot_end, bed] = &s.heaters[..] else {
        panic!("{:?}", s.heaters)
    };
    assert!((245.0..249.0).contains(&hot_end.peak), "{hot_end:?}");
    assert!((110.0..113.0).contains(&bed.peak), "{bed:?}");
    assert!(s.heat_wait > 300.0, "{}", s.heat_wait);
}

#[test]
fn a_cold_extruder_refuses_to_move_with_klippers_message() {
    let gcode = "SET_KINEMATIC_POSITION X=100 Y=100 Z=10\n\
                 G1 X110 E1 F1200\n\
                 G1 E5 F300\n\
                 G1 E-1 F300\n\
                 M114\n\
                 M109 S200\n\
                 G1 X110 E1 F1200\n\
                 M114\n";
    let s = run("cold", "", gcode, None);
    let errors: Vec<(usize, &str)> = s.errors.iter().map(|(n, e)| (*n, e.as_str())).collect();
    let cold = "Extrude below minimum temp";
    assert_eq!(errors, [(2, cold), (3, cold), (4, cold)]);
    // Klipper's reply to each: the message with its hint as `// ` lines,
    // then `!! ` with the first line, then `ok`.
    let refusal = "// Extrude below minimum temp\n\
                   // See the 'min_extrude_temp' config option for details\n\
                   !! Extrude below minimum temp\nok\n";
    assert_eq!(s.transcript.matches(refusal).count(), 3, "{}", s.transcript);
    // Nothing moved while cold; after M109 the same move runs.
    let positions: Vec<(usize, &str)> = s
        .replies
        .iter()
        .filter(|(_, r)| r.starts_with("X:"))
        .map(|(n, r)| (*n, r.as_str()))
        .collect();
    assert_eq!(
        positions,
        [
            (5, "X:100.000 Y:100.000 Z:10.000 E:0.000"),
            (8, "X:110.000 Y:100.000 Z:10.000 E:1.000")
        ]
    );
    assert_eq!((s.toolhead_moves, s.extruder_moves), (1, 1));
    // The extruder ends 1 mm on (steps of 0.0105 mm; pressure advance
    // adds a few steps back and forth).
    let extruder = s.steppers.iter().find(|st| st.name == "extruder");
    let extruder = extruder.expect("extruder");
    assert_eq!(extruder.position, 96);
    assert_eq!(s.shutdown, None);
}

#[test]
fn an_extrude_only_move_longer_than_max_extrude_only_distance_is_refused() {
    // Absolute E: the third move retracts from 49 to -2, 51 mm.
    let gcode = "M109 S200\nG1 E60 F300\nG1 E49 F300\nG1 E-2 F300\nM114\n";
    let s = run("too-long", "", gcode, None);
    let errors: Vec<(usize, &str)> = s.errors.iter().map(|(n, e)| (*n, e.as_str())).collect();
    assert_eq!(
        errors,
        [
            (2, "Extrude only move too long (60.000mm vs 50.000mm)"),
            (4, "Extrude only move too long (-51.000mm vs 50.000mm)")
        ]
    );
    assert!(
        s.transcript.contains(
            "// Extrude only move too long (60.000mm vs 50.000mm)\n\
             // See the 'max_extrude_only_distance' config option for details\n\
             !! Extrude only move too long (60.000mm vs 50.000mm)\n"
        ),
        "{}",
        s.transcript
    );
    assert_eq!(s.final_position, [0.0, 0.0, 0.0, 49.0]);
    assert_eq!(s.extruder_moves, 1);
    // A max_extrude_only_distance of 100 lets all three through.
    let s = run(
        "longer",
        "\n[extruder]\nmax_extrude_only_distance: 100\n",
        gcode,
        None,
    );
    assert_eq!(s.errors.len(), 0, "{:?}", s.errors);
    assert_eq!(s.final_position, [0.0, 0.0, 0.0, -2.0]);
}
