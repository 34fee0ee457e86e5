//! Klipper's SPI temperature chips end to end through the host build: the
//! simulated chip answers the MCU's register reads with the raw value of
//! the simulated temperature (Klipper's conversion run backwards), the
//! firmware converts it forwards, so a hot end reaches its target only if
//! both agree; the MCU's fault and range checks shut everything down with
//! Klipper's messages.

use onechip_tests::sd_folder;

/// The shipped printer.cfg with the hot end's sensor replaced by `sensor`
/// (chip select PA4 on the board's SPI1) and `extra` appended, running
/// `job` with `options`.
fn run(
    name: &str,
    sensor: &str,
    extra: &str,
    job: &str,
    options: &onechip_host::Options,
) -> onechip_host::Summary {
    let text = sd_folder::shipped_cfg().replace(
        "sensor_pin: PF4\nsensor_type: EPCOS 100K B57560G104F",
        &format!("sensor_pin: PA4\nspi_bus: spi1\n{sensor}"),
    );
    assert!(
        text.contains(sensor),
        "the shipped config's sensor lines moved"
    );
    // A min_temp in `sensor` replaces the hot end's.
    let text = if sensor.contains("min_temp") {
        text.replacen("min_temp: 0\nmax_temp: 250", "max_temp: 250", 1)
    } else {
        text
    };
    let dir = sd_folder::new(&format!("spi-{name}"), &(text + "\n" + extra), Some(job));
    let s = onechip_host::run_with(&dir, options).expect("runs");
    std::fs::remove_dir_all(&dir).ok();
    s
}

#[test]
fn the_hot_end_reaches_200_c_through_every_spi_chip() {
    let cases = [
        ("max6675", "sensor_type: MAX6675"),
        ("max31855", "sensor_type: MAX31855"),
        (
            "max31856",
            "sensor_type: MAX31856\ntc_type: K\ntc_averaging_count: 4",
        ),
        (
            "max31865-pt100",
            "sensor_type: MAX31865\nrtd_num_of_wires: 3",
        ),
        (
            "max31865-pt1000",
            "sensor_type: MAX31865\nrtd_nominal_r: 1000\nrtd_reference_r: 4300",
        ),
    ];
    for (name, sensor) in cases {
        let s = run(
            &format!("heat-{name}"),
            sensor,
            "",
            "M109 S200\nM105\n",
            &onechip_host::Options::default(),
        );
        onechip_tests::assert_held_200(&s, name);
    }
}

#[test]
fn a_thermocouple_fault_shuts_everything_down_with_klippers_message() {
    // From 30 s, the MAX31855 reports an open thermocouple (bit 16, the
    // fault flag, and bit 0): the MCU tolerates three such reads (0.3 s
    // apart), the fourth shuts down.
    for (name, sensor, bits) in [
        ("max31855", "sensor_type: MAX31855", 0x1_0001),
        ("max6675", "sensor_type: MAX6675", 0x04),
        ("max31856", "sensor_type: MAX31856", 0x01),
        ("max31865", "sensor_type: MAX31865", 0x80),
    ] {
        let options = onechip_host::Options {
            spi_fault: Some((30.0, 0, bits)),
            ..onechip_host::Options::default()
        };
        // Each test its own folder (they run in parallel).
        let folder = format!("fault-{name}");
        let s = run(&folder, sensor, "", "M104 S200\nG4 P60000\n", &options);
        assert_eq!(
            s.shutdown.as_deref(),
            Some("Thermocouple reader fault"),
            "{name}: {s}"
        );
        assert!(
            s.heaters.iter().all(|h| !h.on_at_end),
            "{name}: {:?}",
            s.heaters
        );
    }
}

#[test]
fn a_thermocouple_below_min_temp_shuts_everything_down() {
    // min_temp 30 °C in a 25 °C room: the chip's raw value is below the
    // MCU's range from the first read; the fourth such read shuts down.
    let s = run(
        "range",
        "sensor_type: MAX31855\nmin_temp: 30",
        "",
        "G4 P5000\n",
        &onechip_host::Options::default(),
    );
    assert_eq!(
        s.shutdown.as_deref(),
        Some("Thermocouple ADC out of range"),
        "{s}"
    );
}

#[test]
fn a_max31855_temperature_sensor_is_reported_by_m105() {
    // As generic-bigtreetech-gtr.cfg's [temperature_sensor k_therm], on
    // this board's SPI1 (the room is 25 °C).
    let s = run(
        "sensor",
        "sensor_type: MAX6675",
        "[temperature_sensor k_therm]\nsensor_type: MAX31855\nsensor_pin: PG12\n\
         spi_bus: spi1\ngcode_id: K\n",
        "G4 P2000\nM400\nM105\n",
        &onechip_host::Options::default(),
    );
    assert_eq!((s.errors.len(), s.shutdown.as_ref()), (0, None), "{s}");
    let (_, report) = s.temperatures.last().expect("M105");
    assert!(report.contains(" K:25.0 /0.0"), "{report}");
}

#[test]
fn the_chips_configuration_is_written_at_start_and_a_max31865_fault_clears_it() {
    use onechip_app::heaters::{Heaters, McuSetup};
    use onechip_host::thermal_plant::{Plant, mcu_sensor};
    // A MAX31856 (J type, 8 samples) on the hot end, a 3-wire MAX31865
    // sensor beside it.
    let text = sd_folder::shipped_cfg().replace(
        "sensor_pin: PF4\nsensor_type: EPCOS 100K B57560G104F",
        "sensor_pin: PA4\nsensor_type: MAX31856\ntc_type: J\ntc_averaging_count: 8",
    ) + "\n[temperature_sensor rtd]\nsensor_type: MAX31865\nsensor_pin: PG12\n\
         rtd_num_of_wires: 3\n";
    let config = onechip_config::Config::parse("printer.cfg", &text).expect("parses");
    let machine = onechip_planner::machine::Machine::from_config(&config).expect("machine");
    let freq = 1_000_000.0;
    let setup = McuSetup::new(&machine, freq, 4095, mcu_sensor(), 0);
    let spi = |i: usize| *setup.inputs[i].1.spi().expect("an SPI query");
    // Klipper's query_thermocouple: every 0.3 s, min_temp..max_temp (0 and
    // 250 °C: 250 × 128 = 32000 counts, << 5) for the hot end; the sensor
    // is unlimited below (clamped to 0) and above (clamped to 2^15 << 1).
    assert_eq!(setup.inputs[0].0, "PA4");
    assert_eq!(
        (
            spi(0).rest_ticks,
            spi(0).min,
            spi(0).max,
            spi(0).max_invalid
        ),
        (300_000, 0, 32_000 << 5, 3)
    );
    assert_eq!((spi(2).min, spi(2).max), (0, 32_768 << 1));
    let mut plant = Plant::new(&machine, freq);
    let mut heaters = Heaters::new(&machine, freq, 4095, mcu_sensor(), 0, &mut plant);
    // CR0 (auto), CR1 (J = 2, 8 samples = 0x30), MASK; then the RTD's
    // configuration: bias, auto, 3-wire, fault clear.
    assert_eq!(
        plant.spi_writes,
        [(0, vec![0x80, 0x80, 0x32, 0x03]), (2, vec![0x80, 0xD2])]
    );
    // The RTD reports a fault: the configuration is written again after
    // each faulted read (Klipper's host does so to clear it); the fourth
    // such read shuts down.
    plant.spi_fault = Some((0, 2, 0x40));
    let mut fault = None;
    while let Some(wake) = heaters.next_wake().filter(|&w| w < 3_000_000) {
        plant.now = u64::from(wake);
        if let Err(reason) = heaters.run(wake, &mut plant) {
            fault = Some(reason);
            break;
        }
    }
    assert_eq!(
        fault.map(|f| f.message()),
        Some("Thermocouple reader fault")
    );
    let rewrites = plant.spi_writes.iter().filter(|(i, _)| *i == 2).count();
    assert_eq!(rewrites, 1 + 4);
    assert_eq!(
        heaters.sensor(0),
        None,
        "a faulted report has no temperature"
    );
}

#[test]
fn a_bus_the_board_lacks_is_a_config_error_naming_file_line_and_option() {
    let text = sd_folder::shipped_cfg();
    let at = text
        .lines()
        .position(|l| l == "sensor_pin: PF4")
        .expect("the hot end's sensor_pin")
        + 1;
    let text = text.replace(
        "sensor_pin: PF4\nsensor_type: EPCOS 100K B57560G104F",
        "sensor_pin: PA4\nsensor_type: MAX31855\nspi_bus: spi2b",
    );
    let dir = sd_folder::new("spi-bus", &text, Some("M105\n"));
    let s = onechip_host::run(&dir, None);
    std::fs::remove_dir_all(&dir).ok();
    let text = match s {
        Ok(s) => format!("{:?}", s.errors),
        Err(e) => e.to_string(),
    };
    let expected = format!(
        "printer.cfg:{}: [extruder] spi_bus spi2b is not on this board",
        at + 2
    );
    assert!(text.contains(&expected), "{text}");
}
