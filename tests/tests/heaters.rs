//! Heaters and the fan end to end through the host build: G-code targets,
//! Klipper's errors for bad ones, and a failing thermistor shutting the
//! whole printer down.

use onechip_host::Options;
use onechip_tests::sd_folder;
use std::path::PathBuf;

/// A throw-away SD folder with the shipped printer.cfg (edited by `cfg`)
/// and `gcode`.
fn sd_with(name: &str, cfg: impl Fn(String) -> String, gcode: &str) -> PathBuf {
    sd_folder::new(
        &format!("heat-{name}"),
        &cfg(sd_folder::shipped_cfg()),
        Some(gcode),
    )
}

#[test]
fn an_open_thermistor_mid_print_shuts_everything_down() {
    let whole = onechip_host::run(&sd_folder::shipped_dir(), None).expect("runs");
    assert_eq!(whole.shutdown, None);
    // The hot end's thermistor opens 60 s into the print, once it reached
    // 200 °C, while Z homes.
    let options = Options {
        open_sensor: Some((60.0, 0)),
        ..Options::default()
    };
    let s = onechip_host::run_with(&sd_folder::shipped_dir(), &options).expect("runs");
    assert_eq!(s.shutdown.as_deref(), Some("ADC out of range"));
    // Four reports in a row (0.3 s apart) out of range, then every stepper
    // stops and both heaters are off.
    let last = s
        .steppers
        .iter()
        .filter_map(|st| st.last_step)
        .max()
        .expect("steps") as f64
        / s.mcu_freq;
    assert!(last < 60.0 + 4.0 * 0.3 + 0.1, "{last}");
    let steps = |s: &onechip_host::Summary| s.steppers.iter().map(|st| st.steps).sum::<usize>();
    assert!(steps(&s) < steps(&whole));
    assert!(s.heaters.iter().all(|h| !h.on_at_end), "{:?}", s.heaters);
    assert!(s.heaters[0].peak > 150.0, "{:?}", s.heaters);
}

#[test]
fn targets_outside_a_heaters_range_are_refused_with_klippers_message() {
    let dir = sd_with(
        "range",
        |c| c,
        "M104 S300\nM140 S-5\nM104 S180\nM104 T1 S180\nSET_HEATER_TEMPERATURE HEATER=heater_bed TARGET=50\n",
    );
    let s = onechip_host::run(&dir, None).expect("runs");
    let errors: Vec<(usize, &str)> = s.errors.iter().map(|(n, e)| (*n, e.as_str())).collect();
    assert_eq!(
        errors,
        [
            (1, "Requested temperature (300.0) out of range (0.0:250.0)"),
            (2, "Requested temperature (-5.0) out of range (0.0:130.0)"),
            (4, "No such heater configured"),
        ]
    );
    assert_eq!((s.heaters[0].target, s.heaters[1].target), (180.0, 50.0));
    // Nothing waited, so the hot end is still on its way up.
    assert_eq!(s.heat_wait, 0.0);
    assert!(s.heaters[0].on_at_end);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn without_a_fan_section_fan_commands_are_unknown() {
    let dir = sd_with(
        "nofan",
        |c| c.replace("[fan]\npin: PA8", ""),
        "M106 S128\nM107\n",
    );
    let s = onechip_host::run(&dir, None).expect("runs");
    let replies: Vec<&str> = s.replies.iter().map(|(_, r)| r.as_str()).collect();
    assert_eq!(
        replies,
        ["Unknown command:\"M106\"", "Unknown command:\"M107\""]
    );
    assert_eq!(s.fan_speed, None);
    let _ = std::fs::remove_dir_all(&dir);
}
