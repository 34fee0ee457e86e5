//! Every kind of temperature sensor end to end through the host build: the
//! simulated heater is read through the sensor's conversion run backwards
//! (°C to ADC reading), the firmware's heater control through it forwards,
//! so a heater reaches and holds its target only if both agree, and the
//! MCU's range check (from min_temp and max_temp) must hold whichever way
//! the sensor's reading runs with temperature.

use onechip_tests::sd_folder;

/// The shipped printer.cfg with the hot end's sensor lines replaced by
/// `sensor` and `extra` sections appended, heating the hot end to 200 °C
/// and waiting for it.
fn heat_with(name: &str, sensor: &str, extra: &str) -> onechip_host::Summary {
    let text = sd_folder::shipped_cfg().replace("sensor_type: EPCOS 100K B57560G104F", sensor)
        + "\n"
        + extra;
    let dir = sd_folder::new(&format!("sensor-{name}"), &text, Some("M109 S200\nM105\n"));
    let s = onechip_host::run(&dir, None).expect("runs");
    std::fs::remove_dir_all(&dir).ok();
    s
}

#[test]
fn the_hot_end_reaches_its_target_through_every_kind_of_sensor() {
    let cases = [
        ("epcos", "sensor_type: EPCOS 100K B57560G104F", ""),
        ("ad595", "sensor_type: AD595\nadc_voltage: 3.3", ""),
        ("ad8495", "sensor_type: AD8495\nadc_voltage: 5", ""),
        ("pt100", "sensor_type: PT100 INA826\nadc_voltage: 5", ""),
        ("pt1000", "sensor_type: PT1000\npullup_resistor: 4700", ""),
        (
            "custom-thermistor",
            "sensor_type: G2",
            "[thermistor G2]\ntemperature1: 20\nresistance1: 140000\ntemperature2: 195\n\
             resistance2: 593\ntemperature3: 255\nresistance3: 189\n",
        ),
        (
            "custom-table",
            "sensor_type: amp\nadc_voltage: 3.3",
            "[adc_temperature amp]\ntemperature1: 0\nvoltage1: 0.3\ntemperature2: 150\n\
             voltage2: 1.2\ntemperature3: 300\nvoltage3: 2.4\n",
        ),
    ];
    for (name, sensor, extra) in cases {
        let s = heat_with(name, sensor, extra);
        onechip_tests::assert_held_200(&s, name);
    }
}

#[test]
fn a_rising_sensor_read_past_max_temp_shuts_everything_down() {
    // An AD595 on a 3.3 V ADC: a reading stuck at full scale (3.3 V, some
    // 327 °C) is past max_temp (250 °C), so the MCU's range check, whose
    // limits run the other way than a thermistor's, must trip.
    let text = sd_folder::shipped_cfg().replace(
        "sensor_type: EPCOS 100K B57560G104F",
        "sensor_type: AD595\nadc_voltage: 3.3",
    );
    let dir = sd_folder::new("sensor-open", &text, Some("M104 S200\nG4 P60000\n"));
    let options = onechip_host::Options {
        open_sensor: Some((30.0, 0)),
        ..onechip_host::Options::default()
    };
    let s = onechip_host::run_with(&dir, &options).expect("runs");
    std::fs::remove_dir_all(&dir).ok();
    assert_eq!(s.shutdown.as_deref(), Some("ADC out of range"), "{s}");
    assert!(s.heaters.iter().all(|h| !h.on_at_end), "{:?}", s.heaters);
}

/// The shipped printer.cfg with `extra` appended, running `job`.
fn run_with_sections(name: &str, extra: &str, job: &str) -> onechip_host::Summary {
    let dir = sd_folder::new(
        &format!("tsensor-{name}"),
        &(sd_folder::shipped_cfg() + "\n" + extra),
        Some(job),
    );
    let s = onechip_host::run(&dir, None).expect("runs");
    std::fs::remove_dir_all(&dir).ok();
    s
}

/// The value after `label:` in an M105 report.
fn reported(report: &str, label: &str) -> Option<f64> {
    let at = report.find(&format!(" {label}:"))? + label.len() + 2;
    report[at..].split_whitespace().next()?.parse().ok()
}

#[test]
fn temperature_sensors_are_read_and_those_with_a_gcode_id_reported_by_m105() {
    // A thermistor on a free thermistor input in a 25 °C room, and the
    // MCU's own sensor (the simulated die at 40 °C, read through the
    // chip's factory calibration).
    let s = run_with_sections(
        "m105",
        "[temperature_sensor chamber]\nsensor_type: EPCOS 100K B57560G104F\nsensor_pin: PF5\n\
         gcode_id: C\n\
         [temperature_sensor mcu_temp]\nsensor_type: temperature_mcu\nmin_temp: 0\nmax_temp: 100\n\
         gcode_id: MCU\n\
         [temperature_sensor unlabelled]\nsensor_type: temperature_mcu\n",
        "G4 P2000\nM400\nM105\n",
    );
    assert_eq!((s.errors.len(), s.shutdown.as_ref()), (0, None), "{s}");
    let (_, report) = s.temperatures.last().expect("M105");
    let chamber = reported(report, "C").unwrap_or_else(|| panic!("C in M105: {report}"));
    let mcu = reported(report, "MCU").expect("MCU in M105");
    assert!((chamber - 25.0).abs() < 0.5, "{report}");
    assert!((mcu - 40.0).abs() < 1.0, "{report}");
    assert!(
        report.contains("/0.0 MCU:"),
        "a sensor's target is 0: {report}"
    );
    assert_eq!(
        report.matches(':').count(),
        6,
        "T, B, C, MCU, @, B@: {report}"
    );
}

#[test]
fn a_temperature_sensor_past_its_max_temp_shuts_everything_down() {
    // The die (40 °C) is past this max_temp: the MCU's range check trips,
    // as it does for a heater's thermistor.
    let s = run_with_sections(
        "range",
        "[temperature_sensor mcu_temp]\nsensor_type: temperature_mcu\nmax_temp: 35\n",
        "G4 P3000\nM400\n",
    );
    assert_eq!(s.shutdown.as_deref(), Some("ADC out of range"), "{s}");
}

#[test]
fn temperature_wait_waits_for_a_heater_or_a_sensor_as_klipper() {
    let sensor = "[temperature_sensor chamber]\nsensor_type: EPCOS 100K B57560G104F\n\
                  sensor_pin: PF5\ngcode_id: C\n";
    // The hot end heated to 200 °C, waited for only until 150 °C: the
    // wait ends on the way up, well before M109 would.
    let s = run_with_sections(
        "wait-heater",
        sensor,
        "M104 S200\nTEMPERATURE_WAIT SENSOR=extruder MINIMUM=150\nM105\n",
    );
    assert_eq!((s.errors.len(), s.shutdown.as_ref()), (0, None), "{s}");
    let (_, report) = s.temperatures.last().expect("M105");
    let hot_end: f64 = report[2..]
        .split_whitespace()
        .next()
        .and_then(|t| t.parse().ok())
        .expect("T");
    assert!((150.0..165.0).contains(&hot_end), "{report}");
    assert!(s.heat_wait > 5.0, "waited {} s", s.heat_wait);
    // A temperature sensor already in range: no wait; the bed's range
    // (MAXIMUM only) also met at once.
    let s = run_with_sections(
        "wait-sensor",
        sensor,
        "TEMPERATURE_WAIT SENSOR=\"temperature_sensor chamber\" MINIMUM=20 MAXIMUM=30\n\
         TEMPERATURE_WAIT SENSOR=heater_bed MAXIMUM=40\nM105\n",
    );
    assert_eq!((s.errors.len(), s.shutdown.as_ref()), (0, None), "{s}");
    assert!(s.heat_wait < 1.0, "waited {} s", s.heat_wait);
    // Klipper's refusals.
    let s = run_with_sections(
        "wait-errors",
        sensor,
        "TEMPERATURE_WAIT SENSOR=chamber MINIMUM=20\nTEMPERATURE_WAIT SENSOR=extruder\n\
         TEMPERATURE_WAIT SENSOR=extruder MINIMUM=50 MAXIMUM=40\n",
    );
    let errors: Vec<&str> = s.errors.iter().map(|(_, e)| e.as_str()).collect();
    assert_eq!(
        errors,
        [
            "Unknown sensor 'chamber'",
            "Error on 'TEMPERATURE_WAIT': missing MINIMUM or MAXIMUM.",
            "Error on 'TEMPERATURE_WAIT': MAXIMUM must be above 50.000",
        ],
        "{s}"
    );
}
