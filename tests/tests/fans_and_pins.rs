//! Fans and pins besides the heaters, end to end on the simulated shipped
//! printer in virtual time: a heater fan following its heater, a
//! controller fan following the motors, SET_PIN and SET_FAN_SPEED seen on
//! the simulated outputs, shutdown values after M112, board pin aliases
//! resolved (and reserved ones refused), and a filament runout pausing a
//! print from the card.

use onechip_host::console_printer::ConsolePrinter;
use onechip_host::{Options, Start};
use onechip_tests::sd_folder;
use std::path::{Path, PathBuf};

/// Sections added to the shipped printer.cfg.
const EXTRAS: &str = "
[board_pins]
aliases: EXP1_1=PE8, EXP1_2=PE7, EXP1_9=<GND>
[heater_fan hotend_fan]
pin: PE5
heater: extruder
heater_temp: 50.0
[controller_fan drivers]
pin: PD12
idle_speed: 0.5
idle_timeout: 5
[fan_generic aux]
pin: PD13
max_power: 0.8
[output_pin led]
pin: PD14
pwm: True
scale: 10
value: 2
shutdown_value: 5
cycle_time: 0.010
[output_pin beeper]
pin: EXP1_1
[static_digital_output enables]
pins: PD15, !PB1
[filament_switch_sensor runout]
switch_pin: ^PG12
";

/// A short job from the card: home, then a long slow square.
const JOB: &str = "G28\nG90\nG1 Z5 F600\nG1 X20 Y20 F6000\nG1 X200 Y20 F600\nG1 X200 Y200\nG1 X20 Y200\nG1 X20 Y20\nM400\n";

/// A throw-away SD folder: the shipped printer.cfg with `extras`, and
/// the job.
fn sd(name: &str, extras: &str) -> PathBuf {
    sd_folder::new(
        &format!("pins-{name}"),
        &(sd_folder::shipped_cfg() + extras),
        Some(JOB),
    )
}

fn printer(dir: &Path) -> ConsolePrinter {
    let options = Options {
        start: Start::At([50.0, 80.0, 30.0]),
        ..Options::default()
    };
    ConsolePrinter::new(dir, &options).expect("printer")
}

/// Output `pin`'s value now (0..1 of full scale).
fn output(p: &mut ConsolePrinter, pin: &str) -> f64 {
    p.outputs()
        .into_iter()
        .find(|(name, _)| *name == pin)
        .unwrap_or_else(|| panic!("no output {pin}"))
        .1
}

/// The hot end's temperature in an M105 reply, °C.
fn hot_end(p: &mut ConsolePrinter) -> f64 {
    let reply = p.send("M105");
    let t = reply.split("T:").nth(1).expect("T:");
    t.split_whitespace()
        .next()
        .and_then(|v| v.parse().ok())
        .expect("a temperature")
}

#[test]
fn a_heater_fan_follows_its_heater_through_m104_m109_and_cooling() {
    let dir = sd("heater-fan", EXTRAS);
    let mut p = printer(&dir);
    p.run_for(3.0);
    assert_eq!(output(&mut p, "PE5"), 0.0, "cold, no target: off");
    // A target turns it on at the next check (once a second) + 0.1 s.
    p.send("M104 S200");
    p.run_for(1.2);
    assert_eq!(output(&mut p, "PE5"), 1.0);
    p.send("M109 S200");
    assert!(hot_end(&mut p) > 190.0);
    assert_eq!(output(&mut p, "PE5"), 1.0);
    // Target off: it stays on while the hot end is above heater_temp, and
    // goes off within a check of it cooling below.
    p.send("M104 S0");
    let mut trace = Vec::new();
    for second in 0..400 {
        p.run_for(1.0);
        trace.push((hot_end(&mut p), output(&mut p, "PE5")));
        if trace.last().is_some_and(|&(_, fan)| fan == 0.0) {
            break;
        }
        assert!(second < 399, "never cooled: {trace:?}");
    }
    let off = trace.len() - 1;
    assert!(off > 60, "cooling takes minutes, not {off} s");
    assert!(trace[off].0 <= 50.0, "{:?}", &trace[off - 3..]);
    // Checked once a second, set 0.1 s later: off within about a second
    // of crossing (cooling 0.4 °C/s there).
    assert!(trace[off - 1].0 > 49.4, "{:?}", &trace[off - 3..]);
    assert!(trace[..off].iter().all(|&(_, fan)| fan == 1.0));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_controller_fan_runs_while_the_motors_are_on_then_idles_down() {
    let dir = sd("controller", EXTRAS);
    let mut p = printer(&dir);
    p.run_for(2.0);
    assert_eq!(output(&mut p, "PD12"), 0.0);
    p.send("G28");
    p.run_for(1.2);
    assert_eq!(output(&mut p, "PD12"), 1.0);
    // Motors off: idle_speed for idle_timeout (5 checks), then off.
    p.send("M84");
    let mut speeds = Vec::new();
    for _ in 0..8 {
        p.run_for(1.0);
        speeds.push(output(&mut p, "PD12"));
    }
    let idle = speeds.iter().filter(|&&s| s == 0.5).count();
    assert!((4..=5).contains(&idle), "{speeds:?}");
    assert_eq!(speeds.last(), Some(&0.0), "{speeds:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn set_pin_and_set_fan_speed_reach_the_simulated_outputs() {
    let dir = sd("set-pin", EXTRAS);
    let mut p = printer(&dir);
    p.run_for(1.0);
    // Start-up values: value 2 of scale 10; static pins on (! is active
    // low: the value is the logical one).
    assert_eq!(output(&mut p, "PD14"), 0.2);
    assert_eq!((output(&mut p, "PD15"), output(&mut p, "!PB1")), (1.0, 1.0));
    assert_eq!(p.send("SET_PIN PIN=led VALUE=7.5"), "ok\n");
    assert_eq!(p.send("SET_PIN PIN=beeper VALUE=1"), "ok\n");
    assert_eq!(p.send("SET_FAN_SPEED FAN=aux SPEED=0.5"), "ok\n");
    p.run_for(0.5);
    assert_eq!(output(&mut p, "PD14"), 0.75);
    assert_eq!(output(&mut p, "EXP1_1"), 1.0);
    // 0.5 of max_power 0.8, after a kick at full (max_power) for 0.1 s.
    assert!((output(&mut p, "PD13") - 0.4).abs() < 1e-3);
    assert_eq!(p.send("SET_FAN_SPEED FAN=aux SPEED=0"), "ok\n");
    p.run_for(0.5);
    assert_eq!(output(&mut p, "PD13"), 0.0);
    // Klipper's refusals.
    let refused = [
        (
            "SET_PIN PIN=led VALUE=11",
            "VALUE must have maximum of 10.000000",
        ),
        ("SET_PIN PIN=beeper VALUE=0.5", "Invalid pin value"),
        (
            "SET_PIN PIN=nope VALUE=1",
            "The value 'nope' is not valid for PIN",
        ),
        (
            "SET_FAN_SPEED FAN=nope SPEED=1",
            "The value 'nope' is not valid for FAN",
        ),
    ];
    for (line, message) in refused {
        let reply = p.send(line);
        assert!(
            reply.starts_with("!! ") && reply.contains(message),
            "{line}: {reply}"
        );
    }
    assert_eq!(
        output(&mut p, "PD14"),
        0.75,
        "a refused line changes nothing"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_shutdown_sets_every_output_to_its_shutdown_value() {
    let dir = sd("shutdown", EXTRAS);
    let mut p = printer(&dir);
    p.send("SET_PIN PIN=led VALUE=9");
    p.send("SET_PIN PIN=beeper VALUE=1");
    p.send("SET_FAN_SPEED FAN=aux SPEED=1");
    p.run_for(1.0);
    assert_eq!(output(&mut p, "PD14"), 0.9);
    assert_eq!(output(&mut p, "PE5"), 0.0);
    p.receive(b"M112\n");
    p.run_for(0.5);
    // The led's shutdown_value (5 of 10), a heater fan at full speed,
    // everything else off; static pins as they were.
    assert_eq!(output(&mut p, "PD14"), 0.5);
    assert_eq!(output(&mut p, "PE5"), 1.0);
    assert_eq!(output(&mut p, "PD13"), 0.0);
    assert_eq!(output(&mut p, "EXP1_1"), 0.0);
    assert_eq!(output(&mut p, "PD15"), 1.0);
    assert_eq!(output(&mut p, "PA8"), 0.0);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn board_pin_aliases_resolve_and_reserved_ones_are_refused() {
    // EXP1_1 is PE8: naming PE8 again is the same pin.
    let twice = format!("{EXTRAS}[output_pin again]\npin: PE8\n");
    let dir = sd("alias-twice", &twice);
    let options = Options::default();
    let message = match ConsolePrinter::new(&dir, &options) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("PE8 used twice through an alias"),
    };
    assert!(
        message
            .contains("pin EXP1_1 used by both [output_pin beeper] pin and [output_pin again] pin"),
        "{message}"
    );
    // EXP1_9 is reserved (<GND>).
    let reserved = format!("{EXTRAS}[output_pin gnd]\npin: EXP1_9\n");
    let dir2 = sd("alias-reserved", &reserved);
    let message = match ConsolePrinter::new(&dir2, &options) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("a reserved alias used"),
    };
    assert!(
        message.contains("printer.cfg:") && message.contains("pin EXP1_9 is reserved for <GND>"),
        "{message}"
    );
    // A bad alias names its file and line.
    let bad = "\n[board_pins]\naliases: EXP1_1\n";
    let dir3 = sd("alias-bad", bad);
    let message = match ConsolePrinter::new(&dir3, &options) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("a bad alias accepted"),
    };
    assert!(
        message.contains("aliases") && message.contains("NAME=PIN"),
        "{message}"
    );
    for d in [dir, dir2, dir3] {
        let _ = std::fs::remove_dir_all(&d);
    }
}

#[test]
fn a_filament_runout_pauses_a_print_from_the_card() {
    let dir = sd("runout", EXTRAS);
    let mut p = printer(&dir);
    p.run_for(3.0);
    assert_eq!(
        p.send("QUERY_FILAMENT_SENSOR SENSOR=runout"),
        "// Filament Sensor runout: filament detected\nok\n"
    );
    p.send("M23 job.gcode");
    p.send("M24");
    p.run_for(5.0);
    assert!(p.is_printing());
    p.set_filament(0, false);
    p.run_for(1.0);
    assert!(!p.is_printing(), "paused on runout");
    let paused = p.send("M27");
    p.run_for(5.0);
    assert_eq!(p.send("M27"), paused, "no line runs while paused");
    assert_eq!(
        p.send("QUERY_FILAMENT_SENSOR SENSOR=runout"),
        "// Filament Sensor runout: filament not detected\nok\n"
    );
    // Filament back, RESUME: the print runs to its end.
    p.set_filament(0, true);
    p.run_for(1.0);
    assert_eq!(p.send("RESUME"), "ok\n");
    let mut out = String::new();
    for _ in 0..300 {
        out += &p.run_for(1.0);
        if out.contains("Done printing file") {
            break;
        }
    }
    assert!(out.contains("Done printing file"), "{out}");
    assert_eq!(p.position()[..2], [20.0, 20.0]);
    // With the sensor disabled, a runout does nothing.
    p.send("SET_FILAMENT_SENSOR SENSOR=runout ENABLE=0");
    p.send("M23 job.gcode");
    p.send("M24");
    p.run_for(3.0);
    p.set_filament(0, false);
    p.run_for(2.0);
    assert!(p.is_printing());
    let _ = std::fs::remove_dir_all(&dir);
}

/// The value after `label:` in an M105 reply, and its target.
fn reported(reply: &str, label: &str) -> (f64, f64) {
    let at = reply
        .find(&format!(" {label}:"))
        .unwrap_or_else(|| panic!("{label} in {reply}"));
    let mut words = reply[at + label.len() + 2..].split_whitespace();
    let temp = words.next().and_then(|t| t.parse().ok()).expect("temp");
    let target = words
        .next()
        .and_then(|t| t.trim_start_matches('/').parse().ok())
        .expect("target");
    (temp, target)
}

/// A temperature fan cooling the simulated electronics (45 °C with the
/// fan off, 25 °C at full speed) on a thermistor input.
fn cooling(control: &str) -> String {
    format!(
        "\n[temperature_fan board]\npin: PD12\nsensor_type: EPCOS 100K B57560G104F\n\
         sensor_pin: PF5\nmin_temp: 0\nmax_temp: 100\ntarget_temp: 35\ngcode_id: BRD\n{control}\n"
    )
}

#[test]
fn a_watermark_temperature_fan_holds_its_target_within_max_delta() {
    let dir = sd(
        "tfan-watermark",
        &cooling("control: watermark\nmax_delta: 2"),
    );
    let mut p = printer(&dir);
    let (mut temps, mut speeds) = (Vec::new(), Vec::new());
    for _ in 0..240 {
        p.run_for(0.5);
        let (temp, target) = reported(&p.send("M105"), "BRD");
        assert_eq!(target, 35.0);
        temps.push(temp);
        speeds.push(output(&mut p, "PD12"));
    }
    // Hot at first: full speed from the first report on (0.2 s, set
    // 0.3 s later), down to 33 °C; then off until 37 °C, on again: the
    // temperature cycles within the band (a report's lag and a 0.5 s
    // sample apart).
    assert_eq!(speeds[1], 1.0, "{speeds:?}");
    let switches = speeds.windows(2).filter(|w| w[0] != w[1]).count();
    assert!(switches >= 4, "{switches} switches: {speeds:?}");
    assert!(speeds.iter().all(|&s| s == 0.0 || s == 1.0));
    let settled = &temps[temps.iter().position(|&t| t < 35.0).expect("cooled")..];
    let (low, high) = settled
        .iter()
        .fold((f64::MAX, f64::MIN), |(l, h), &t| (l.min(t), h.max(t)));
    assert!(low > 32.0 && high < 38.0, "{low}..{high}: {temps:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_pid_temperature_fan_settles_at_its_target_and_set_temperature_fan_target_moves_it() {
    let pid = "control: pid\npid_Kp: 40\npid_Ki: 2\npid_Kd: 0\nmin_speed: 0.1";
    let dir = sd("tfan-pid", &cooling(pid));
    let mut p = printer(&dir);
    p.run_for(240.0);
    let (temp, _) = reported(&p.send("M105"), "BRD");
    let speed = output(&mut p, "PD12");
    assert!((temp - 35.0).abs() < 1.0, "{temp} °C at speed {speed}");
    // 35 °C needs half the cooling between 45 and 25 °C.
    assert!((0.35..0.65).contains(&speed), "{speed}");
    // A lower target takes more cooling; the range and speeds are checked
    // as Klipper does.
    assert_eq!(
        p.send("SET_TEMPERATURE_FAN_TARGET TEMPERATURE_FAN=board TARGET=30"),
        "ok\n"
    );
    p.run_for(240.0);
    let (temp, target) = reported(&p.send("M105"), "BRD");
    assert_eq!(target, 30.0);
    assert!((temp - 30.0).abs() < 1.0, "{temp}");
    assert!(output(&mut p, "PD12") > speed);
    for (line, error) in [
        (
            "SET_TEMPERATURE_FAN_TARGET TEMPERATURE_FAN=board TARGET=150",
            "Requested temperature (150.0) out of range (0.0:100.0)",
        ),
        (
            "SET_TEMPERATURE_FAN_TARGET TEMPERATURE_FAN=board MIN_SPEED=0.8 MAX_SPEED=0.5",
            "Requested min speed (0.8) is greater than max speed (0.5)",
        ),
        (
            "SET_TEMPERATURE_FAN_TARGET TEMPERATURE_FAN=nope",
            "The value 'nope' is not valid for TEMPERATURE_FAN",
        ),
    ] {
        let reply = p.send(line);
        assert!(reply.contains(error), "{line}: {reply}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
