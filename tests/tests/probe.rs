//! The Z probe in virtual time: the shipped printer with its Z endstop
//! replaced by a probe (`probe:z_virtual_endstop`) over a simulated bed
//! that is a tilted plane. Homing Z stops where the probe touches the bed
//! and sets Z = z_offset; PROBE elsewhere measures the bed's height there
//! (relative to where Z homed); PROBE_ACCURACY reports as Klipper; a probe
//! that never reaches the bed ends with Klipper's error; a BLTouch's servo
//! pulses follow Klipper's timings; PROBE_CALIBRATE finds the z_offset from
//! the nozzle lowered onto the bed; [safe_z_home] and [homing_override]
//! home as Klipper.

use onechip_host::console_printer::ConsolePrinter;
use onechip_host::probe_physics::BltouchFault;
use onechip_host::{Options, Start};
use onechip_planner::bltouch::Command;
use onechip_tests::sd_folder;

/// Z mm per step of the shipped printer.
const Z_STEP: f64 = 0.0025;
/// The probe's offsets from the nozzle, mm.
const OFFSETS: [f64; 3] = [-30.0, 10.0, 1.5];
/// Where Z homes ([safe_z_home] home_xy_position), mm.
const HOME_XY: [f64; 2] = [150.0, 150.0];
/// The bed: 0.3 mm at X = Y = 0, rising 2 µm per mm of X, falling 1 µm
/// per mm of Y.
const BED: [f64; 3] = [0.3, 0.002, -0.001];
/// The shipped printer's clock, Hz.
const FREQ: f64 = 260_000_000.0;

fn bed(x: f64, y: f64, plane: [f64; 3]) -> f64 {
    plane[0] + plane[1] * x + plane[2] * y
}

/// `[safe_z_home]` at [`HOME_XY`], with `extra` options.
fn safe_z_home(extra: &str) -> String {
    let [x, y] = HOME_XY;
    format!("[safe_z_home]\nhome_xy_position: {x}, {y}\nspeed: 100\n{extra}")
}

/// The shipped printer.cfg with Z homing on `probe` (sections), and
/// `[safe_z_home]` at [`HOME_XY`].
fn printer(name: &str, probe: &str, plane: [f64; 3]) -> ConsolePrinter {
    printer_with(name, &format!("{probe}\n{}", safe_z_home("")), plane)
}

/// The shipped printer.cfg with Z homing on a probe, and `sections`.
fn printer_with(name: &str, sections: &str, plane: [f64; 3]) -> ConsolePrinter {
    let z_on_probe = (
        "endstop_pin: PG10\nposition_endstop: 0.5\n",
        "endstop_pin: probe:z_virtual_endstop\nposition_min: -2\n",
    );
    shipped_with(name, z_on_probe, sections, plane)
}

/// The shipped printer.cfg with `replace.0` replaced by `replace.1`, and
/// `sections`.
fn shipped_with(
    name: &str,
    replace: (&str, &str),
    sections: &str,
    plane: [f64; 3],
) -> ConsolePrinter {
    let options = Options {
        start: Start::At([100.0, 120.0, 40.0]),
        bed: plane,
        ..Options::default()
    };
    shipped_with_options(name, replace, sections, options)
}

/// [`shipped_with`], run as `options` say.
fn shipped_with_options(
    name: &str,
    replace: (&str, &str),
    sections: &str,
    options: Options,
) -> ConsolePrinter {
    let cfg = sd_folder::shipped_cfg();
    assert!(cfg.contains(replace.0), "the shipped config changed");
    let cfg = cfg.replace(replace.0, replace.1);
    let cfg = format!("{cfg}\n{sections}\n");
    let dir = sd_folder::new(&format!("probe-{name}"), &cfg, None);
    ConsolePrinter::new(&dir, &options).expect("loads")
}

fn probe_section() -> String {
    let [x, y, z] = OFFSETS;
    format!("[probe]\npin: ^PG10\nx_offset: {x}\ny_offset: {y}\nz_offset: {z}\nspeed: 5\n")
}

/// The `z=` value of the first reply line starting with `prefix`.
fn z_of(replies: &str, prefix: &str) -> f64 {
    let line = replies
        .lines()
        .find(|l| l.starts_with(prefix))
        .unwrap_or_else(|| panic!("no {prefix:?} in {replies}"));
    line.rsplit("z=")
        .next()
        .and_then(|z| z.trim().parse().ok())
        .expect("z=")
}

#[test]
fn z_homes_on_the_probe_at_the_bed_and_probe_measures_the_bed() {
    let mut p = printer("home", &probe_section(), BED);
    let home = p.send("G28");
    assert!(home.ends_with("ok\n") && !home.contains("!!"), "{home}");
    // Z = z_offset at the trigger, with the probe on the bed at HOME_XY.
    assert_eq!(p.send("M114"), "X:150.000 Y:150.000 Z:1.500 E:0.000\nok\n");
    let probe_at = |x: f64, y: f64| bed(x + OFFSETS[0], y + OFFSETS[1], BED);
    let home_bed = probe_at(HOME_XY[0], HOME_XY[1]);
    let real = p.real_position().expect("physics");
    assert!(
        (real[2] - (home_bed + OFFSETS[2])).abs() <= Z_STEP + 1e-9,
        "nozzle at {real:?}, bed under the probe at {home_bed}"
    );
    let z_triggers = p.triggers().iter().filter(|t| t.0 == 2).count();
    assert_eq!(
        z_triggers, 2,
        "two homing moves of Z, each stopped by the probe"
    );
    // PROBE elsewhere: the bed's height there relative to where Z homed.
    let (x, y) = (60.0, 40.0);
    let r = p.send(&format!("G1 X{x} Y{y} Z8 F6000\nPROBE"));
    let expected = OFFSETS[2] + probe_at(x, y) - home_bed;
    let at = z_of(&r, "// probe at 60.000,40.000 is z=");
    let result = z_of(&r, "// Result is z=");
    assert_eq!(at, result, "one sample: the result is the sample");
    assert!(
        (result - expected).abs() <= Z_STEP + 1e-9,
        "{result} vs {expected}\n{r}"
    );
    // QUERY_PROBE: pressed on the bed, open 2 mm above it.
    assert!(p.send("QUERY_PROBE").starts_with("// probe: TRIGGERED\n"));
    p.send("G1 Z5");
    assert_eq!(p.send("QUERY_PROBE"), "// probe: open\nok\n");
    // G-code position follows the probing: a relative move goes from it.
    assert_eq!(p.send("M114"), "X:60.000 Y:40.000 Z:5.000 E:0.000\nok\n");
}

#[test]
fn probe_accuracy_reports_as_klipper() {
    let mut p = printer("accuracy", &probe_section(), BED);
    p.send("G28");
    let r = p.send("G1 X100 Y100 Z10 F6000\nPROBE_ACCURACY SAMPLES=5 SAMPLE_RETRACT_DIST=1.5");
    let lines: Vec<&str> = r.lines().collect();
    assert!(
        lines.contains(
            &"// PROBE_ACCURACY at X:100.000 Y:100.000 Z:10.000 (samples=5 retract=1.500 \
          speed=5.0 lift_speed=5.0)"
        ),
        "{r}"
    );
    let samples: Vec<f64> = lines
        .iter()
        .filter(|l| l.starts_with("// probe at 100.000,100.000 is z="))
        .map(|l| z_of(l, "// probe at"))
        .collect();
    assert_eq!(samples.len(), 5, "{r}");
    let results = lines
        .iter()
        .find(|l| l.starts_with("// probe accuracy results: "))
        .expect("results line");
    let max = samples.iter().cloned().fold(f64::MIN, f64::max);
    let min = samples.iter().cloned().fold(f64::MAX, f64::min);
    let avg = samples.iter().sum::<f64>() / 5.0;
    let mut sorted = samples.clone();
    sorted.sort_by(f64::total_cmp);
    let sigma = (samples.iter().map(|z| (z - avg).powi(2)).sum::<f64>() / 5.0).sqrt();
    assert_eq!(
        *results,
        format!(
            "// probe accuracy results: maximum {max:.6}, minimum {min:.6}, range {:.6}, \
             average {avg:.6}, median {:.6}, standard deviation {sigma:.6}",
            max - min,
            sorted[2]
        )
    );
    // A simulated probe repeats within a step.
    assert!(max - min <= Z_STEP, "{r}");
    // After the last sample the toolhead is lifted by the retract.
    let last = p.send("M114");
    let z: f64 = last
        .split("Z:")
        .nth(1)
        .and_then(|s| s.split(' ').next())
        .and_then(|z| z.parse().ok())
        .expect("M114 Z");
    assert!((z - (samples[4] + 1.5)).abs() < 0.001, "{last}");
}

#[test]
fn a_probe_that_never_reaches_the_bed_ends_with_klippers_error() {
    // A bed falling 5 mm per 100 mm towards X 0: Z homes (on the probe) at
    // X 150; at X 40 the bed is 5.5 mm lower, beyond position_min (-2)
    // from z_offset (1.5): the probe meets nothing.
    let mut p = printer("no-trigger", &probe_section(), [0.0, 0.05, 0.0]);
    p.send("G28");
    let r = p.send("G1 X40 F6000\nPROBE");
    assert!(
        r.contains("!! No trigger on probe after full movement"),
        "{r}"
    );
    // It went all the way down to position_min.
    assert!(p.send("M114").contains("Z:-2.000"));
    // Before homing, probing is refused as Klipper does.
    let mut p = printer("unhomed", &probe_section(), BED);
    assert!(p.send("PROBE").contains("!! Must home before probe"));
}

/// The sensor test starts once the start-up's pin up has run (0.68 s).
fn close_start(start_up: f64, test: f64) -> bool {
    test >= start_up + 0.68 - 1e-6
}

#[test]
fn bltouch_deploys_probes_and_stows_with_klippers_timings() {
    let [x, y, z] = OFFSETS;
    let section = format!(
        "[bltouch]\nsensor_pin: ^PG10\ncontrol_pin: PB6\nx_offset: {x}\ny_offset: {y}\n\
         z_offset: {z}\n"
    );
    let mut p = printer("bltouch", &section, BED);
    // The simulated BLTouch reads the bed only with its pin down: homing Z
    // works only if the pin is lowered before each homing move.
    let home = p.send("G28");
    assert!(!home.contains("!!"), "{home}");
    let seconds = |log: &[(u64, f64)]| -> Vec<(f64, f64)> {
        log.iter().map(|&(c, w)| (c as f64 / FREQ, w)).collect()
    };
    let homing = seconds(p.probe_servo_log());
    let z_triggers: Vec<f64> = p
        .triggers()
        .iter()
        .filter(|t| t.0 == 2)
        .map(|t| t.2 as f64 / FREQ)
        .collect();
    assert_eq!(z_triggers.len(), 2);
    let (up, touch, down) = (0.001_475, 0.001_165, 0.000_650);
    let widths: Vec<f64> = homing.iter().map(|e| e.1).collect();
    // Start-up (pin up), the sensor test (pin up, touch mode), then for
    // each of Z's two homing moves the pin down before and up after; each
    // command's pulses followed by the signal off.
    assert_eq!(
        widths,
        [
            up, 0.0, up, 0.0, touch, 0.0, down, 0.0, up, 0.0, down, 0.0, up, 0.0
        ],
        "{homing:?}"
    );
    // Start-up: 0.3 s after the first line (Klipper's 0.1 s + 0.2 s).
    assert!(
        homing[0].0 >= 0.3 && close_start(homing[0].0, homing[2].0),
        "{homing:?}"
    );
    let homing = &homing[2..];
    let t = |i: usize| homing[i].0;
    let close = |a: f64, b: f64| (a - b).abs() < 2e-6;
    // pin_move_time 0.68 s: the signal held 0.58 s (whole 20 ms periods
    // past the 0.1 s minimum), the next command after the 0.68 s.
    assert!(
        close(t(1) - t(0), 0.58) && close(t(2) - t(0), 0.68),
        "{homing:?}"
    );
    // Touch mode: held 0.1 s, the next command 0.1 s after it stopped.
    assert!(
        close(t(3) - t(2), 0.10) && close(t(4) - t(3), 0.10),
        "{homing:?}"
    );
    for (k, &trigger) in z_triggers.iter().enumerate() {
        let (pin_down, pin_up) = (t(4 + 4 * k), t(6 + 4 * k));
        assert!(close(t(5 + 4 * k) - pin_down, 0.58), "{homing:?}");
        // The homing move starts once the pin is down; the pin goes up
        // 0.1 s after the trigger.
        assert!(trigger > pin_down + 0.68, "trigger {trigger} vs {homing:?}");
        assert!(
            close(pin_up - trigger, 0.10),
            "trigger {trigger} vs {homing:?}"
        );
        assert!(close(t(7 + 4 * k) - pin_up, 0.58), "{homing:?}");
    }
    // PROBE within TEST_TIME of the test: no new test, pin down, probe,
    // pin up.
    let before = p.probe_servo_log().len();
    let r = p.send("G1 X100 Y100 Z5 F6000\nPROBE");
    assert!(r.contains("// Result is z="), "{r}");
    let probing = seconds(&p.probe_servo_log()[before..]);
    let widths: Vec<f64> = probing.iter().map(|e| e.1).collect();
    assert_eq!(widths, [down, 0.0, up, 0.0], "{probing:?}");
    let trigger = p.triggers().last().expect("probe triggered").2 as f64 / FREQ;
    assert!(trigger > probing[0].0 + 0.68, "{trigger} vs {probing:?}");
    assert!(
        close(probing[2].0 - trigger, 0.10),
        "{trigger} vs {probing:?}"
    );
    // The toolhead waits for the pin: nothing moves before it is up.
    assert!(p.send("M400").ends_with("ok\n"));
}

/// The G-code position M114 reports (X, Y, Z), mm.
fn m114(p: &mut ConsolePrinter) -> [f64; 3] {
    let r = p.send("M114");
    let mut xyz = [f64::NAN; 3];
    for (k, axis) in ["X:", "Y:", "Z:"].iter().enumerate() {
        xyz[k] = r
            .split(axis)
            .nth(1)
            .and_then(|v| v.split(' ').next())
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("{r}"));
    }
    xyz
}

#[test]
fn safe_z_home_hops_homes_z_over_its_point_and_goes_back() {
    let sections = format!(
        "{}\n{}",
        probe_section(),
        safe_z_home("z_hop: 10\nz_hop_speed: 15\nmove_to_previous: True\n")
    );
    let mut p = printer_with("z-hop", &sections, BED);
    // Z is not homed yet: Z homes only after X and Y.
    let r = p.send("G28 Z");
    assert!(r.contains("!! Must home X and Y axes first"), "{r}");
    let r = p.send("G28");
    assert!(!r.contains("!!"), "{r}");
    // After homing: Z lifted to z_hop, XY back where X and Y homed (0, 0).
    assert_eq!(m114(&mut p), [0.0, 0.0, 10.0]);
    p.send("M400");
    let real = p.real_position().expect("physics");
    assert!(
        real[0].abs() <= 0.0125 && real[1].abs() <= 0.0125,
        "{real:?}"
    );
    let home_bed = bed(HOME_XY[0] + OFFSETS[0], HOME_XY[1] + OFFSETS[1], BED);
    // Z = 10 is 8.5 mm above where the probe triggered (Z = z_offset).
    let expected = home_bed + OFFSETS[2] + (10.0 - OFFSETS[2]);
    assert!(
        (real[2] - expected).abs() <= Z_STEP + 1e-9,
        "{real:?} vs {expected}"
    );
    // The Z triggers happened with the probe over HOME_XY.
    for t in p.triggers().iter().filter(|t| t.0 == 2) {
        assert_eq!([t.1[0], t.1[1]], HOME_XY);
    }
}

#[test]
fn homing_override_runs_its_gcode_for_its_axes() {
    let sections = format!(
        "{}\n[homing_override]\naxes: z\nset_position_z: 0\ngcode:\n  G1 Z5 F600\n  \
         G28 X0 Y0\n  G1 X120 Y130 F6000\n  G28 Z0\n  G1 Z10 F600\n",
        probe_section()
    );
    let mut p = printer_with("override", &sections, BED);
    // G28 X: not one of its axes, X homes as usual.
    assert!(!p.send("G28 X").contains("!!"));
    assert_eq!(m114(&mut p)[0], 0.0);
    // G28: the script (Z may move first: set_position_z marks it homed).
    let r = p.send("G28");
    assert!(!r.contains("!!"), "{r}");
    assert_eq!(m114(&mut p), [120.0, 130.0, 10.0]);
    p.send("M400");
    let real = p.real_position().expect("physics");
    let probe_bed = bed(120.0 + OFFSETS[0], 130.0 + OFFSETS[1], BED);
    let expected = probe_bed + 10.0;
    assert!(
        (real[2] - expected).abs() <= Z_STEP + 1e-9,
        "{real:?} vs {expected}"
    );
}

#[test]
fn probe_calibrate_accepts_the_nozzle_height_as_the_new_z_offset() {
    let mut p = printer("calibrate", &probe_section(), BED);
    p.send("G28");
    let (x, y) = (80.0, 90.0);
    let r = p.send(&format!("G1 X{x} Y{y} Z10 F6000\nPROBE_CALIBRATE"));
    let probed = z_of(&r, "// probe at");
    assert!(r.contains("// Starting manual Z probe."), "{r}");
    // The nozzle is now over the point the probe touched, 5 mm up.
    let at = m114(&mut p);
    assert_eq!([at[0], at[1]], [x + OFFSETS[0], y + OFFSETS[1]]);
    assert!((at[2] - (probed + 5.0)).abs() < 0.001, "{at:?} vs {probed}");
    // Lower it until it touches the bed there (the "paper test"): the bed
    // is at that height in the coordinates Z homed in.
    let home_bed = bed(HOME_XY[0] + OFFSETS[0], HOME_XY[1] + OFFSETS[1], BED);
    let touch = bed(x + OFFSETS[0], y + OFFSETS[1], BED) - home_bed;
    p.send(&format!("TESTZ Z={:.4}", touch - at[2]));
    let r = p.send("ACCEPT");
    // The probe triggers z_offset above the bed: that is what it finds,
    // within the step the trigger is seen in.
    let found: f64 = r
        .strip_prefix("// probe: z_offset: ")
        .and_then(|rest| rest.lines().next())
        .and_then(|z| z.parse().ok())
        .unwrap_or_else(|| panic!("{r}"));
    assert!((found - OFFSETS[2]).abs() <= Z_STEP, "{r}");
    assert!(r.contains("// The SAVE_CONFIG command will update the printer config file\n"));
}

#[test]
fn a_probe_beside_a_z_endstop_probes_on_its_own_input() {
    // Z keeps its switch (at 0.5); the probe is on another pin.
    let keep = (
        "position_max: 250\n\n[extruder]",
        "position_min: -2\nposition_max: 250\n\n[extruder]",
    );
    let section = probe_section().replace("^PG10", "^PG11");
    let mut p = shipped_with("beside", keep, &section, BED);
    p.send("G28");
    assert_eq!(m114(&mut p)[2], 0.5);
    let real = p.real_position().expect("physics");
    assert!((real[2] - 0.5).abs() <= Z_STEP + 1e-9, "{real:?}");
    let (x, y) = (70.0, 110.0);
    let r = p.send(&format!("G1 X{x} Y{y} Z6 F6000\nPROBE"));
    // Z homed on its switch: the result is the bed's own height plus
    // z_offset.
    let expected = bed(x + OFFSETS[0], y + OFFSETS[1], BED) + OFFSETS[2];
    let result = z_of(&r, "// Result is z=");
    assert!(
        (result - expected).abs() <= Z_STEP + 1e-9,
        "{result} vs {expected}\n{r}"
    );
    // M119 reads Z's switch, QUERY_PROBE the probe.
    assert_eq!(p.send("M119"), "x:open y:open z:open\nok\n");
    assert!(p.send("QUERY_PROBE").starts_with("// probe: TRIGGERED"));
}

/// A printer homing Z on a BLTouch (with `extra` more of its options)
/// whose simulated sensor has `fault`.
fn bltouch_printer(name: &str, extra: &str, fault: Option<BltouchFault>) -> ConsolePrinter {
    let [x, y, z] = OFFSETS;
    let section = format!(
        "[bltouch]\nsensor_pin: ^PG10\ncontrol_pin: PB6\nx_offset: {x}\ny_offset: {y}\n\
         z_offset: {z}\n{extra}\n{}",
        safe_z_home("")
    );
    let z_on_probe = (
        "endstop_pin: PG10\nposition_endstop: 0.5\n",
        "endstop_pin: probe:z_virtual_endstop\nposition_min: -2\n",
    );
    let options = Options {
        start: Start::At([100.0, 120.0, 40.0]),
        bed: BED,
        bltouch_fault: fault,
        ..Options::default()
    };
    shipped_with_options(name, z_on_probe, &section, options)
}

#[test]
fn a_bltouch_clone_that_cannot_report_touch_mode_fails_klippers_sensor_test() {
    let mut p = bltouch_printer("clone", "", Some(BltouchFault::NoTouchModeReport));
    let r = p.send("G28");
    assert!(
        r.contains("!! BLTouch failed to verify sensor state\n"),
        "{r}"
    );
    // Nothing was probed: the pin never went down.
    let down = Command::PinDown.pulse_width();
    assert!(!p.probe_servo_log().iter().any(|e| e.1 == down));
    // Klipper's advice for such clones: no sensor test, and it homes.
    let mut p = bltouch_printer(
        "clone-untested",
        "pin_up_touch_mode_reports_triggered: False",
        Some(BltouchFault::NoTouchModeReport),
    );
    let r = p.send("G28");
    assert!(!r.contains("!!"), "{r}");
}

#[test]
fn a_bltouch_whose_sensor_stays_triggered_fails_to_raise_after_klippers_three_tries() {
    let mut p = bltouch_printer("stuck", "", Some(BltouchFault::StuckTriggered));
    let r = p.send("G28");
    let retry = "// Failed to verify BLTouch probe is raised; retrying.\n";
    assert_eq!(r.matches(retry).count(), 2, "{r}");
    assert!(r.contains("!! BLTouch failed to raise probe\n"), "{r}");
    // Each retry: a reset for 1 s (its signal held 0.9 s: whole periods
    // past the 0.1 s minimum), then the pin up again.
    let reset = Command::Reset.pulse_width();
    let log: Vec<(f64, f64)> = p
        .probe_servo_log()
        .iter()
        .map(|&(c, w)| (c as f64 / FREQ, w))
        .collect();
    let resets: Vec<usize> = (0..log.len()).filter(|&i| log[i].1 == reset).collect();
    assert_eq!(resets.len(), 2, "{log:?}");
    for &i in &resets {
        let (held, next) = (log[i + 1].0 - log[i].0, log[i + 2]);
        assert!((held - 0.9).abs() < 1e-6, "{log:?}");
        assert!((next.0 - log[i].0 - 1.0).abs() < 1e-6, "{log:?}");
        assert_eq!(next.1, Command::PinUp.pulse_width(), "{log:?}");
    }
    // Unchecked when the BLTouch cannot report it (Klipper's option).
    let mut p = bltouch_printer(
        "stuck-unchecked",
        "pin_up_reports_not_triggered: False",
        Some(BltouchFault::StuckTriggered),
    );
    let r = p.send("G28");
    assert!(!r.contains("!!"), "{r}");
}

/// `[screws_tilt_adjust]` over four screws, with `thread`.
fn screws_section(thread: &str) -> String {
    format!(
        "[screws_tilt_adjust]\nscrew1: 50, 50\nscrew1_name: front left screw\n\
         screw2: 200, 50\nscrew2_name: front right screw\nscrew3: 200, 200\n\
         screw3_name: rear right screw\nscrew4: 50, 200\nscrew4_name: rear left screw\n\
         horizontal_move_z: 10\nspeed: 100\nscrew_thread: {thread}\n"
    )
}

/// Turns and minutes (and CW) Klipper gives a screw `diff` mm low
/// against the base with a thread of `pitch` mm, clockwise-raising if
/// `cw_thread`: diff / pitch turns, the fraction in sixtieths rounded.
fn klipper_turn(diff: f64, pitch: f64, cw_thread: bool) -> String {
    let adjust = if diff.abs() < 0.001 {
        0.0
    } else {
        diff / pitch
    };
    let cw = (adjust >= 0.0) == cw_thread;
    let turns = adjust.abs().trunc();
    let minutes = ((adjust.abs() - turns) * 60.0).round_ties_even();
    format!(
        "{} {:02}:{:02}",
        if cw { "CW" } else { "CCW" },
        turns,
        minutes
    )
}

#[test]
fn screws_tilt_calculate_probes_each_screw_and_reports_klippers_turns() {
    let sections = format!("{}\n{}", probe_section(), screws_section("CW-M4"));
    // A bed tilted 2 µm/mm along X and -1 µm/mm along Y: 0.3 mm from the
    // left screws to the right ones, 0.15 mm front to back.
    let mut p = printer_with("screws", &format!("{sections}\n{}", safe_z_home("")), BED);
    assert!(p.send("G28").ends_with("ok\n"));
    let r = p.send("SCREWS_TILT_CALCULATE");
    assert!(r.ends_with("ok\n") && !r.contains("!!"), "{r}");
    println!("{r}");
    let lines: Vec<&str> = r.lines().filter(|l| l.contains(" : x=")).collect();
    assert_eq!(lines.len(), 4, "{r}");
    assert!(r.contains(
        "// 01:20 means 1 full turn and 20 minutes, CW=clockwise, CCW=counter-clockwise\n"
    ));
    // Each screw probed where the nozzle is over it: the probe, offset
    // from the nozzle, finds the bed beside the screw.
    let screws = [(50.0, 50.0), (200.0, 50.0), (200.0, 200.0), (50.0, 200.0)];
    let z: Vec<f64> = (lines.iter())
        .map(|l| {
            let z = l.split("z=").nth(1).and_then(|z| z.split(' ').next());
            z.and_then(|z| z.parse().ok()).expect("z=")
        })
        .collect();
    let bed_at = |(x, y): (f64, f64)| bed(x + OFFSETS[0], y + OFFSETS[1], BED);
    for (i, &screw) in screws.iter().enumerate() {
        let measured = z[i] - z[0];
        let real = bed_at(screw) - bed_at(screws[0]);
        assert!(
            (measured - real).abs() <= Z_STEP + 1e-9,
            "screw {i}: {measured} vs {real}"
        );
    }
    assert!(
        lines[0].starts_with("// front left screw (base) : x=50.0, y=50.0, z="),
        "{}",
        lines[0]
    );
    for (i, line) in lines.iter().enumerate().skip(1) {
        let expected = klipper_turn(z[0] - z[i], 0.7, true);
        assert!(
            line.ends_with(&format!(" : adjust {expected}")),
            "{line} vs {expected}"
        );
    }
    // The front right screw is 0.3 mm high: 0.3 / 0.7 of a turn, about
    // 26 minutes, counter-clockwise.
    assert!(lines[1].ends_with("adjust CCW 00:26"), "{}", lines[1]);
    // Probing ended at horizontal_move_z over the last screw.
    assert_eq!(p.send("M114"), "X:50.000 Y:200.000 Z:10.000 E:0.000\nok\n");
    // DIRECTION=CW: the highest screw is the base, every turn clockwise.
    let r = p.send("SCREWS_TILT_CALCULATE DIRECTION=CW");
    let adjusted: Vec<&str> = r.lines().filter(|l| l.contains(": adjust ")).collect();
    assert!(r.contains("front right screw (base)"), "{r}");
    assert!(adjusted.iter().all(|l| l.contains("adjust CW ")), "{r}");
    // MAX_DEVIATION: Klipper's error past it.
    let r = p.send("SCREWS_TILT_CALCULATE MAX_DEVIATION=0.1");
    assert!(
        r.contains(
            "!! bed level exceeds configured limits (0.1mm)! Adjust screws and restart print.\n"
        ),
        "{r}"
    );
    let r = p.send("SCREWS_TILT_CALCULATE DIRECTION=UP");
    assert!(
        r.contains("!! ") && r.contains("DIRECTION must be either CW or CCW"),
        "{r}"
    );
}

#[test]
fn bed_screws_adjust_walks_the_screws_as_klippers_tool() {
    let sections = "[bed_screws]\nscrew1: 30,30\nscrew1_name: front left\n\
                    screw1_fine_adjust: 40,40\nscrew2: 200,30\nscrew2_name: front right\n\
                    screw3: 115,200\nscrew3_fine_adjust: 115,190\n\
                    horizontal_move_z: 8\nprobe_height: 0.2\n";
    // The shipped printer as it is (Z on its endstop), with the section.
    let mut p = shipped_with("bed-screws", ("[printer]", "[printer]"), sections, BED);
    assert!(p.send("G28").ends_with("ok\n"));
    let prompt = |name: &str| {
        format!(
            "// Adjust {name}. Then run ACCEPT, ADJUSTED, or ABORT\n\
             // Use ADJUSTED if a significant screw adjustment is made\nok\n"
        )
    };
    let step = |p: &mut ConsolePrinter, command: &str, name: &str, at: [f64; 2]| {
        let r = p.send(command);
        // Without the host protocol's keep-alive lines.
        let r: String = r
            .lines()
            .filter(|l| !l.starts_with("echo:busy"))
            .map(|l| format!("{l}\n"))
            .collect();
        assert!(r.ends_with(&prompt(name)), "{command}: {r}");
        assert_eq!(
            p.send("M114"),
            format!("X:{:.3} Y:{:.3} Z:0.200 E:0.000\nok\n", at[0], at[1]),
            "after {command}"
        );
    };
    step(&mut p, "BED_SCREWS_ADJUST", "front left", [30.0, 30.0]);
    let again = p.send("BED_SCREWS_ADJUST");
    assert!(
        again.contains("!! Already in bed_screws helper; use ABORT to exit"),
        "{again}"
    );
    step(&mut p, "ACCEPT", "front right", [200.0, 30.0]);
    // A notable adjustment: the coarse round runs again after this one.
    step(
        &mut p,
        "ADJUSTED",
        "screw at 115.000,200.000",
        [115.0, 200.0],
    );
    step(&mut p, "ACCEPT", "front left", [30.0, 30.0]);
    step(&mut p, "ACCEPT", "front right", [200.0, 30.0]);
    step(&mut p, "ACCEPT", "screw at 115.000,200.000", [115.0, 200.0]);
    // Then the fine round, at the fine-adjust points.
    step(&mut p, "ACCEPT", "front left", [40.0, 40.0]);
    step(&mut p, "ACCEPT", "screw at 115.000,200.000", [115.0, 190.0]);
    let done = p.send("ACCEPT");
    assert!(
        done.starts_with("// Bed screws tool completed successfully\n"),
        "{done}"
    );
    assert_eq!(p.send("M114"), "X:115.000 Y:190.000 Z:8.000 E:0.000\nok\n");
    // Done: ACCEPT means nothing any more; ABORT ends a tool midway.
    assert!(p.send("ACCEPT").contains("Unknown command:\"ACCEPT\""));
    step(&mut p, "BED_SCREWS_ADJUST", "front left", [30.0, 30.0]);
    assert_eq!(p.send("ABORT"), "ok\n");
    assert!(p.send("ADJUSTED").contains("Unknown command:\"ADJUSTED\""));
}
