//! printer.cfg's pins checked against each other and against the pins the
//! board uses itself.

use onechip_app::pin_check::{BOARD_RESERVED, PinConflict, PinUse, check};
use onechip_config::Config;
use onechip_planner::machine::{Machine, Stepper};

/// The printer.cfg shipped for the Octopus Pro.
const SHIPPED: &str = include_str!("../../sdcard-configs/octopus-pro-h723/printer.cfg");

/// The shipped printer.cfg with `from` replaced by `to`, checked against
/// `reserved`: the conflict's message, if any.
fn conflict(from: &str, to: &str, reserved: &[(&'static str, &'static str)]) -> Option<String> {
    assert!(SHIPPED.contains(from), "{from}");
    let text = SHIPPED.replacen(from, to, 1);
    let config = Config::parse("printer.cfg", &text).expect("config");
    let machine = Machine::from_config(&config).expect("machine");
    check(&machine, reserved).err().map(|e| e.to_string())
}

/// Each `(from, to, message)`: the shipped printer.cfg with `from`
/// replaced by `to` is refused with `message` (or passes, if None).
fn expect(cases: &[(&str, &str, Option<&str>)], reserved: &[(&'static str, &'static str)]) {
    for &(from, to, message) in cases {
        assert_eq!(conflict(from, to, reserved).as_deref(), message, "{to}");
    }
}

#[test]
fn the_shipped_config_passes() {
    let config = Config::parse("printer.cfg", SHIPPED).expect("config");
    let machine = Machine::from_config(&config).expect("machine");
    assert_eq!(check(&machine, BOARD_RESERVED), Ok(()));
}

#[test]
fn a_pin_named_twice_is_refused_naming_both_uses() {
    let text = SHIPPED.replacen("heater_pin: PA0", "heater_pin: PF13", 1);
    let config = Config::parse("printer.cfg", &text).expect("config");
    let machine = Machine::from_config(&config).expect("machine");
    let e = check(&machine, &[]).expect_err("PF13 twice");
    assert_eq!(
        e,
        PinConflict::Duplicate {
            first: PinUse {
                section: "stepper_x",
                option: "step_pin",
                pin: "PF13"
            },
            second: PinUse {
                section: "extruder",
                option: "heater_pin",
                pin: "PF13"
            },
        }
    );
    assert_eq!(
        e.to_string(),
        "pin PF13 used by both [stepper_x] step_pin and [extruder] heater_pin"
    );
    // Within one section, and the fan and sensors too.
    expect(
        &[
            (
                "dir_pin: PF12",
                "dir_pin: PF13",
                Some("pin PF13 used by both [stepper_x] step_pin and [stepper_x] dir_pin"),
            ),
            (
                "pin: PA8",
                "pin: PF3",
                Some("pin PF3 used by both [heater_bed] sensor_pin and [fan] pin"),
            ),
        ],
        &[],
    );
}

#[test]
fn modifiers_and_case_do_not_make_another_pin() {
    expect(
        &[
            (
                "endstop_pin: PG9",
                "endstop_pin: ^!pf14",
                Some("pin PF14 used by both [stepper_x] enable_pin and [stepper_y] endstop_pin"),
            ),
            (
                "endstop_pin: PG9",
                "endstop_pin: ~ mcu:PG6",
                Some("pin PG6 used by both [stepper_x] endstop_pin and [stepper_y] endstop_pin"),
            ),
            // A pin of another chip is another pin.
            ("endstop_pin: PG10", "endstop_pin: probe:PG10", None),
        ],
        &[],
    );
}

#[test]
fn steppers_may_share_an_enable_pin_of_one_polarity() {
    expect(
        &[
            ("enable_pin: !PF15", "enable_pin: !PF14", None),
            (
                "enable_pin: !PF15",
                "enable_pin: PF14",
                Some(
                    "pin PF14 shared by [stepper_x] enable_pin and [stepper_y] enable_pin \
                     must have the same polarity (!PF14 vs PF14)",
                ),
            ),
            // Not with anything else, though.
            (
                "heater_pin: PA1",
                "heater_pin: PF14",
                Some("pin PF14 used by both [stepper_x] enable_pin and [heater_bed] heater_pin"),
            ),
        ],
        &[],
    );
}

#[test]
fn only_one_rails_steppers_share_an_endstop_pin() {
    let config = Config::parse("printer.cfg", SHIPPED).expect("config");
    let mut machine = Machine::from_config(&config).expect("machine");
    let z = machine.steppers[2];
    assert_eq!(z.name, "stepper_z");
    let z1 = Stepper {
        name: "stepper_z1",
        step_pin: "PG4",
        dir_pin: "PC1",
        enable_pin: Some("!PA2"),
        endstop_pin: Some("PG10"),
        ..z
    };
    machine.steppers.push(z1).expect("room");
    assert_eq!(check(&machine, BOARD_RESERVED), Ok(()));
    // With the same modifiers only.
    machine.steppers[4].endstop_pin = Some("^PG10");
    let e = check(&machine, BOARD_RESERVED).expect_err("pull-up differs");
    assert!(matches!(e, PinConflict::Modifiers { .. }), "{e}");
    // Another rail's endstop is another switch.
    machine.steppers[4].name = "stepper_y1";
    machine.steppers[4].endstop_pin = Some("PG10");
    assert_eq!(
        check(&machine, BOARD_RESERVED).map_err(|e| e.to_string()),
        Err("pin PG10 used by both [stepper_z] endstop_pin and [stepper_y1] endstop_pin".into())
    );
}

#[test]
fn pins_the_board_uses_are_refused() {
    expect(
        &[
            (
                "step_pin: PF13",
                "step_pin: PA11",
                Some("pin PA11 of [stepper_x] step_pin is used by the board (USB D-)"),
            ),
            (
                "heater_pin: PA1",
                "heater_pin: !pd2",
                Some("pin pd2 of [heater_bed] heater_pin is used by the board (SD card CMD)"),
            ),
            (
                "pin: PA8",
                "pin: ph0",
                Some("pin ph0 of [fan] pin is used by the board (crystal)"),
            ),
            (
                "step_pin: PF13",
                "step_pin: PH1",
                Some("pin PH1 of [stepper_x] step_pin is used by the board (crystal)"),
            ),
            (
                "endstop_pin: PG6",
                "endstop_pin: ^PA13",
                Some("pin PA13 of [stepper_x] endstop_pin is used by the board (SWD)"),
            ),
            (
                "enable_pin: !PF14",
                "enable_pin: !PA14",
                Some("pin PA14 of [stepper_x] enable_pin is used by the board (SWD)"),
            ),
        ],
        BOARD_RESERVED,
    );
    for (pin, _) in BOARD_RESERVED {
        let cfg = format!("pin: {pin}");
        assert!(
            conflict("pin: PA8", &cfg, BOARD_RESERVED).is_some(),
            "{pin}"
        );
        assert_eq!(conflict("pin: PA8", &cfg, &[]), None, "{pin}");
    }
}

#[test]
fn a_software_spi_bus_is_shared_by_its_chips_and_by_nothing_else() {
    // Two MAX6675s on one software bus (as the Flashforge Creator Pro's
    // two hot ends): the clock and data pins are shared, the chip selects
    // not; a bus pin that is also a heater's is refused.
    let bus = "spi_software_sclk_pin: PE2\nspi_software_miso_pin: PE5\n\
        spi_software_mosi_pin: PE6";
    let hot_end = format!("sensor_pin: PE3\nsensor_type: MAX6675\n{bus}");
    let sensor = format!(
        "[temperature_sensor chamber]\nsensor_type: MAX6675\nsensor_pin: PE4\n{bus}\n\n[fan]"
    );
    let both = SHIPPED
        .replacen(
            "sensor_pin: PF4\nsensor_type: EPCOS 100K B57560G104F",
            &hot_end,
            1,
        )
        .replacen("[fan]", &sensor, 1);
    let config = Config::parse("printer.cfg", &both).expect("config");
    let machine = Machine::from_config(&config).expect("machine");
    assert_eq!(check(&machine, BOARD_RESERVED), Ok(()));
    let clash = both.replacen("heater_pin: PA1", "heater_pin: PE5", 1);
    let config = Config::parse("printer.cfg", &clash).expect("config");
    let machine = Machine::from_config(&config).expect("machine");
    assert_eq!(
        check(&machine, &[]).map_err(|e| e.to_string()),
        Err(
            "pin PE5 used by both [heater_bed] heater_pin and [extruder] spi_software_miso_pin"
                .to_string()
        )
    );
}

#[test]
fn an_spi_sensor_on_a_bus_the_board_lacks_is_refused_with_the_boards_pins() {
    let from = "sensor_pin: PF4\nsensor_type: EPCOS 100K B57560G104F";
    let on = |bus: &str| format!("sensor_pin: PA4\nsensor_type: MAX31855\nspi_bus: {bus}");
    expect(
        &[
            (from, &on("spi1"), None),
            (
                from,
                &on("spi2b"),
                Some(
                    "[extruder] spi_bus spi2b is not on this board (its SPI is spi1: \
                     PA5 SCK, PA6 MISO, PA7 MOSI)",
                ),
            ),
        ],
        BOARD_RESERVED,
    );
    // Without the board's pins (a config for another board), any bus.
    expect(&[(from, &on("spi2b"), None)], &[]);
}
