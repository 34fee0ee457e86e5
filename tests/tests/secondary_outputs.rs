//! Fans, output pins and stepper enable pins on a secondary MCU, driven
//! as klippy drives them, against stock Klipper firmware (the Linux MCU in
//! `../shared/peers`, whose GPIO shim logs every pin write with its time,
//! and through `tests/peer-shim` the level each pin is set up with):
//! the part fan's software PWM from M106, SET_PIN, a static pin, a heater
//! fan following its heater, an enable pin following its stepper and M84,
//! hardware PWM channels (whose sysfs files the peer-shim logs), and the
//! shutdown values an M112 leaves.

use onechip_host::Options;
use onechip_host::console_printer::ConsolePrinter;
use onechip_tests::peers::{
    Firmware, Peer, extruder_pins, monotonic_now, printer_with_extruder_on,
};
use std::path::Path;
use std::sync::{Mutex, MutexGuard, PoisonError};

/// One peer at a time (they run in real time).
fn one_peer_at_a_time() -> MutexGuard<'static, ()> {
    static PEERS: Mutex<()> = Mutex::new(());
    PEERS.lock().unwrap_or_else(PoisonError::into_inner)
}

/// The part fan's pin on the peer.
const FAN: &str = "gpiochip0/gpio20";
/// An `[output_pin]`'s.
const AUX: &str = "gpiochip0/gpio21";
/// A `[static_digital_output]`'s.
const LIGHT: &str = "gpiochip0/gpio22";
/// A `[heater_fan]`'s (for the extruder, whose heater is the main MCU's).
const HOTEND_FAN: &str = "gpiochip0/gpio23";
/// The output pin's maximum_mcu_duration, s: the MCU shuts down if its
/// value is not sent again within it.
const AUX_MAX_DURATION: f64 = 0.5;
/// The part fan's cycle_time, s (Klipper's default).
const FAN_CYCLE: f64 = 0.010;

/// The shipped printer with its extruder on the Linux MCU `ext` at
/// `serial` and the part fan, an output pin, a static pin and a heater
/// fan there too, written to SD folder `sd`.
fn printer_with_outputs_on_the_peer(sd: &Path, serial: &Path) {
    printer_with_extruder_on(Firmware::Linux, sd, serial, "command", "");
    let cfg = sd.join("printer.cfg");
    let text = std::fs::read_to_string(&cfg).expect("printer.cfg");
    let moved = text.replace("[fan]\npin: PA8", &format!("[fan]\npin: ext:{FAN}"));
    assert!(moved.contains("pin: ext:gpiochip0/gpio20"), "[fan] moved");
    let extra = format!(
        "\n[output_pin aux]\npin: ext:{AUX}\nmaximum_mcu_duration: {AUX_MAX_DURATION}\n\
         \n[static_digital_output light]\npins: ext:{LIGHT}\n\
         \n[heater_fan hotend]\npin: ext:{HOTEND_FAN}\nheater: extruder\n"
    );
    std::fs::write(cfg, moved + &extra).expect("printer.cfg");
}

/// A started printer on a fresh Linux MCU peer.
fn start(test: &str) -> (Peer, ConsolePrinter) {
    start_edited(test, |text| text)
}

/// [`start`] with printer.cfg's text changed by `edit` first.
fn start_edited(test: &str, edit: impl FnOnce(String) -> String) -> (Peer, ConsolePrinter) {
    // Driven: its GPIO shim logs the levels pins are set up with too.
    let peer = Peer::start_driven(test);
    let sd = peer.path.with_file_name("sd");
    printer_with_outputs_on_the_peer(&sd, &peer.path);
    let cfg = sd.join("printer.cfg");
    let text = std::fs::read_to_string(&cfg).expect("printer.cfg");
    std::fs::write(&cfg, edit(text)).expect("printer.cfg");
    let p = ConsolePrinter::new(&sd, &Options::default()).unwrap_or_else(|e| panic!("{e}"));
    (peer, p)
}

/// `pin`'s level at pin log time `t` (s) by its `levels`, if it was
/// written by then.
fn level_at(levels: &[(f64, bool)], t: f64) -> Option<bool> {
    levels
        .iter()
        .take_while(|(at, _)| *at <= t)
        .last()
        .map(|l| l.1)
}

/// Software PWM seen in `levels` between pin log times `from` and `to`
/// (s): the mean period and duty (0..1) of its whole cycles.
fn pwm(levels: &[(f64, bool)], from: f64, to: f64) -> (f64, f64) {
    let rises: Vec<f64> = (levels.iter())
        .filter(|(t, high)| *high && (from..to).contains(t))
        .map(|l| l.0)
        .collect();
    assert!(rises.len() > 10, "{} cycles", rises.len());
    let (first, last) = (rises[0], rises[rises.len() - 1]);
    let mut on = 0.0;
    for pair in levels.windows(2) {
        let ((t0, high), (t1, _)) = (pair[0], pair[1]);
        if high && t0 >= first && t1 <= last {
            on += t1 - t0;
        }
    }
    let period = (last - first) / (rises.len() - 1) as f64;
    (period, on / (last - first))
}

#[test]
fn the_part_fan_on_a_linux_mcu_makes_software_pwm_from_m106_and_pins_follow_set_pin() {
    let _alone = one_peer_at_a_time();
    let (peer, mut p) = start("outputs-fan");
    p.run_for(0.5);
    // The static pin is on from the config phase; the others are off.
    assert_eq!(peer.levels(LIGHT).last().map(|l| l.1), Some(true));
    assert!(!peer.levels(FAN).iter().any(|l| l.1), "fan on before M106");
    let replies = p.send("M106 S128");
    assert!(!replies.contains("!!"), "{replies}");
    p.run_for(2.0);
    let levels = peer.levels(FAN);
    let started = levels.iter().find(|l| l.1).map(|l| l.0);
    let started = started.unwrap_or_else(|| panic!("the fan never went on: {levels:?}"));
    // After the 0.1 s kick at full power: 128/255 of each 10 ms cycle.
    let (period, duty) = pwm(&levels, started + 0.3, started + 1.5);
    let wanted = 128.0 / 255.0;
    println!(
        "part fan: period {:.4} ms (cycle_time {} ms), duty {:.4} (wanted {wanted:.4})",
        period * 1e3,
        FAN_CYCLE * 1e3,
        duty
    );
    assert!((period - FAN_CYCLE).abs() < 0.000_2, "period {period}");
    assert!((duty - wanted).abs() < 0.03, "duty {duty}");
    // The kick: on for its whole 0.1 s.
    assert_eq!(level_at(&levels, started + 0.09), Some(true));
    let replies = p.send("M107");
    assert!(!replies.contains("!!"), "{replies}");
    p.run_for(0.5);
    let levels = peer.levels(FAN);
    let last = levels.last().copied().unwrap_or((0.0, true));
    assert!(!last.1, "fan on after M107: {last:?}");
    let off_at = last.0;
    // SET_PIN: on for three times its maximum_mcu_duration (its value
    // sent again in time), then off.
    for (value, high) in [(1, true), (0, false)] {
        let replies = p.send(&format!("SET_PIN PIN=aux VALUE={value}"));
        assert!(!replies.contains("!!"), "{replies}");
        p.run_for(3.0 * AUX_MAX_DURATION);
        assert_eq!(
            peer.levels(AUX).last().map(|l| l.1),
            Some(high),
            "VALUE={value}"
        );
    }
    assert_eq!(peer.levels(AUX).iter().filter(|l| l.1).count(), 1);
    let replies = p.send("M105");
    assert!(!replies.contains("!!"), "{replies}");
    // Nothing moved the fan since M107.
    assert_eq!(peer.levels(FAN).last().map(|l| l.0), Some(off_at));
}

/// The enable pin of the main MCU's Y stepper, moved to the peer.
const Y_ENABLE: &str = "gpiochip0/gpio25";

#[test]
fn an_enable_pin_on_a_linux_mcu_follows_its_stepper_on_the_main_mcu() {
    let _alone = one_peer_at_a_time();
    let (peer, mut p) = start_edited("outputs-split-enable", |text| {
        let y = "step_pin: PG0\ndir_pin: PG1\nenable_pin: !PF15\n";
        assert!(text.contains(y), "the shipped [stepper_y] changed");
        let moved = format!("step_pin: PG0\ndir_pin: PG1\nenable_pin: !ext:{Y_ENABLE}\n");
        text.replace(y, &moved)
    });
    p.run_for(0.5);
    // `!` pin: configured high (inactive).
    assert_eq!(peer.levels(Y_ENABLE).last().map(|l| l.1), Some(true));
    let sent = monotonic_now();
    let replies = [p.send("G28 Y"), p.send("G1 Y20 F3000"), p.send("M400")].concat();
    let done = monotonic_now();
    assert!(!replies.contains("!!"), "{replies}");
    let levels = peer.levels(Y_ENABLE);
    let active = levels.iter().find(|l| !l.1).map(|l| l.0);
    println!("Y enable: {levels:?} (G28 sent at {sent:.3}, M400 done at {done:.3})");
    // Active with Y's first move (homing), before the moves were done.
    assert!(
        active.is_some_and(|t| (sent..done).contains(&t)),
        "{levels:?}"
    );
    let replies = p.send("M84");
    assert!(!replies.contains("!!"), "{replies}");
    p.run_for(0.4);
    assert_eq!(peer.levels(Y_ENABLE).last().map(|l| l.1), Some(true));
}

#[test]
fn a_linux_mcu_that_kept_its_config_gets_its_steady_outputs_back_at_their_start_levels() {
    let _alone = one_peer_at_a_time();
    let (peer, mut p) = start("outputs-kept");
    let pins = extruder_pins(Firmware::Linux);
    p.run_for(0.5);
    let replies = [p.send("M83"), p.send("G1 E1 F300"), p.send("M400")].concat();
    assert!(!replies.contains("!!"), "{replies}");
    p.run_for(0.2);
    // The extruder's `!` enable pin is active (low) when the host goes.
    assert_eq!(peer.levels(pins.enable).last().map(|l| l.1), Some(false));
    drop(p);
    // The same printer.cfg again: the MCU holds its config (same CRC),
    // so none is sent; klippy's restart commands put the enable pin back
    // to inactive.
    let sd = peer.path.with_file_name("sd");
    let mut p = ConsolePrinter::new(&sd, &Options::default()).unwrap_or_else(|e| panic!("{e}"));
    p.run_for(0.5);
    let enable = peer.levels(pins.enable);
    assert_eq!(enable.last().map(|l| l.1), Some(true), "{enable:?}");
    let replies = p.send("M105");
    assert!(!replies.contains("!!"), "{replies}");
}

#[test]
fn a_heater_fan_and_an_enable_pin_on_a_linux_mcu_follow_their_heater_and_stepper() {
    let _alone = one_peer_at_a_time();
    let (peer, mut p) = start("outputs-enable");
    let pins = extruder_pins(Firmware::Linux);
    p.run_for(0.5);
    // `!` enable pin: configured high (inactive).
    assert_eq!(peer.levels(pins.enable).last().map(|l| l.1), Some(true));
    let replies = [p.send("M83"), p.send("G1 E1 F300"), p.send("M400")].concat();
    assert!(!replies.contains("!!"), "{replies}");
    p.run_for(0.2);
    let steps = peer.rising_edges(pins.step);
    assert!(steps.len() > 10, "{} steps", steps.len());
    let enable = peer.levels(pins.enable);
    let active = enable.iter().find(|l| !l.1).map(|l| l.0);
    let active = active.unwrap_or_else(|| panic!("enable never active: {enable:?}"));
    println!(
        "enable active {:.3} ms before the first step",
        (steps[0] - active) * 1e3
    );
    assert!(
        active < steps[0],
        "enable at {active}, first step {}",
        steps[0]
    );
    let replies = p.send("M84");
    assert!(!replies.contains("!!"), "{replies}");
    p.run_for(0.4);
    let enable = peer.levels(pins.enable);
    assert_eq!(enable.last().map(|l| l.1), Some(true), "{enable:?}");
    assert!(
        enable.last().is_some_and(|l| l.0 > steps[steps.len() - 1]),
        "disabled before the last step: {enable:?}"
    );
    // The heater fan: on (steady at full speed) within its 1 s checks of
    // the heater getting a target.
    assert!(!peer.levels(HOTEND_FAN).iter().any(|l| l.1));
    let replies = p.send("M104 S150");
    assert!(!replies.contains("!!"), "{replies}");
    p.run_for(1.5);
    assert_eq!(peer.levels(HOTEND_FAN).last().map(|l| l.1), Some(true));
    // Off again with the heater (still below its heater_temp, 50 °C).
    p.send("M104 S0");
    p.run_for(1.5);
    assert_eq!(peer.levels(HOTEND_FAN).last().map(|l| l.1), Some(false));
    // M112: the MCU puts every output at its shutdown value: the part
    // fan off (shutdown_speed 0), the heater fan on (1), the enable pin
    // inactive (mid-move).
    p.send("M106 S255");
    p.run_for(0.5);
    assert_eq!(peer.levels(FAN).last().map(|l| l.1), Some(true));
    // 2 s of extrusion; M112 comes mid-move.
    p.send("G1 E10 F300");
    p.run_for(0.6);
    assert_eq!(peer.levels(pins.enable).last().map(|l| l.1), Some(false));
    let stopped = p.send("M112");
    assert!(stopped.contains("M112"), "{stopped}");
    // The MCU acts on `emergency_stop` by itself: real time passes.
    std::thread::sleep(std::time::Duration::from_millis(300));
    assert_eq!(peer.levels(FAN).last().map(|l| l.1), Some(false));
    assert_eq!(peer.levels(HOTEND_FAN).last().map(|l| l.1), Some(true));
    assert_eq!(peer.levels(pins.enable).last().map(|l| l.1), Some(true));
}

/// Two hardware PWM channels of the peer (its driven shim logs each
/// write to their sysfs files).
const FAN_CHANNEL: &str = "pwmchip0/pwm0";
const TOOL_CHANNEL: &str = "pwmchip1/pwm0";
/// The Linux MCU's PWM_MAX (its dictionary).
const LINUX_PWM_MAX: f64 = 32768.0;

/// The duty cycles (ns) `channel` had so far, as the Linux MCU sets
/// them: a duty_cycle write, then enable 1; or enable 0 alone (duty 0).
fn duties(peer: &Peer, channel: &str) -> Vec<u64> {
    let file = |name: &str| peer.values(&format!("{channel}/{name}"));
    let mut writes: Vec<(f64, bool, u64)> = (file("duty_cycle").into_iter())
        .map(|(t, v)| (t, true, v))
        .chain(file("enable").into_iter().map(|(t, v)| (t, false, v)))
        .collect();
    writes.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut duty = 0;
    let mut duties = Vec::new();
    for (_, is_duty, value) in writes {
        match (is_duty, value) {
            (true, ns) => duty = ns,
            (false, 0) => duties.push(0),
            (false, _) => duties.push(duty),
        }
    }
    duties
}

/// Asserts `duty` (ns) is what the Linux MCU writes for `level` (0..1)
/// of a `period` ns channel as klippy sets it: `int(level * PWM_MAX +
/// 0.5)`, then `period * value / PWM_MAX`.
fn assert_duty(duty: u64, level: f64, period: u64) {
    let value = (level * LINUX_PWM_MAX + 0.5) as u64;
    let wanted = period * value / LINUX_PWM_MAX as u64;
    assert_eq!(duty, wanted, "level {level} of {period} ns");
}

#[test]
fn hardware_pwm_on_a_linux_mcu_is_configured_as_klippys_pwm_out_and_follows_m106_and_set_pin() {
    let _alone = one_peer_at_a_time();
    let fan = format!(
        "[fan]\npin: ext:{FAN_CHANNEL}\nhardware_pwm: True\ncycle_time: 0.001\nshutdown_speed: 0.5"
    );
    let tool = format!(
        "\n[output_pin tool]\npin: !ext:{TOOL_CHANNEL}\npwm: True\nhardware_pwm: True\n\
         cycle_time: 0.0002\nvalue: 0.25\nshutdown_value: 0\n"
    );
    let (peer, mut p) = start_edited("outputs-hard-pwm", |text| {
        text.replace(&format!("[fan]\npin: ext:{FAN}"), &fan) + &tool
    });
    p.run_for(0.5);
    // config_pwm_out: each channel's period (its cycle_time in 50 MHz
    // ticks, 20 ns each), then its start duty.
    let period = |channel: &str| peer.values(&format!("{channel}/period"));
    let (fan_period, tool_period) = (1_000_000, 200_000);
    assert_eq!(
        period(FAN_CHANNEL).iter().map(|v| v.1).collect::<Vec<_>>(),
        [fan_period]
    );
    assert_eq!(
        period(TOOL_CHANNEL).iter().map(|v| v.1).collect::<Vec<_>>(),
        [tool_period]
    );
    assert_eq!(duties(&peer, FAN_CHANNEL), [0]);
    // The tool's `!` pin: 0.25 is 0.75 on the channel.
    assert_eq!(duties(&peer, TOOL_CHANNEL), [150_000]);
    // M106: the kick at full power, then 128/255.
    let replies = p.send("M106 S128");
    assert!(!replies.contains("!!"), "{replies}");
    p.run_for(1.0);
    let fan = duties(&peer, FAN_CHANNEL);
    println!("fan duty cycles (ns): {fan:?}");
    assert_eq!(fan[..2], [0, fan_period], "the kick");
    assert_eq!(fan.len(), 3, "{fan:?}");
    assert_duty(fan[2], 128.0 / 255.0, fan_period);
    p.send("M107");
    p.run_for(0.5);
    assert_eq!(duties(&peer, FAN_CHANNEL).last(), Some(&0));
    let replies = p.send("SET_PIN PIN=tool VALUE=0.6");
    assert!(!replies.contains("!!"), "{replies}");
    p.run_for(0.5);
    let tool = duties(&peer, TOOL_CHANNEL);
    assert_eq!(tool.len(), 2, "{tool:?}");
    assert_duty(tool[1], 0.4, tool_period);
    // M112: the MCU sets each channel to its shutdown value: the fan's
    // shutdown_speed, the tool's 0 (full duty on its `!` pin).
    let stopped = p.send("M112");
    assert!(stopped.contains("M112"), "{stopped}");
    std::thread::sleep(std::time::Duration::from_millis(300));
    assert_duty(
        *duties(&peer, FAN_CHANNEL).last().unwrap_or(&0),
        0.5,
        fan_period,
    );
    assert_eq!(duties(&peer, TOOL_CHANNEL).last(), Some(&tool_period));
}
