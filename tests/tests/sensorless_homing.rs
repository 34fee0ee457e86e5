//! Sensorless homing as Klipper does it (`endstop_pin:
//! tmc2209_stepper_x:virtual_endstop`): the rail's endstop is the driver's
//! DIAG pin, the driver's registers are set up for stall detection for
//! each homing move and put back after it, with Klipper's writes
//! (`klippy/extras/tmc.py`, `TMCVirtualPinHelper`), and the simulated
//! driver reports a stall on DIAG only when its motor is driven into the
//! end of the axis with stall detection on.

use onechip_app::config_files::ConfigFiles;
use onechip_app::pin_check::BOARD_RESERVED;
use onechip_app::setup::PrinterSetup;
use onechip_config::ConfigFile;
use onechip_host::console_printer::ConsolePrinter;
use onechip_host::{Options, SimError, Start};
use onechip_planner::tmc::config::TSTEP_MAX;
use onechip_tests::sd_folder;
use std::path::PathBuf;

fn corpus() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/klipper-configs")
}

/// A fresh SD folder named `name` holding `cfg` as printer.cfg.
fn sd(name: &str, cfg: &str) -> PathBuf {
    sd_folder::new(&format!("sensorless-{name}"), cfg, None)
}

/// Stock config `file`'s text with `edits` (`from`, `to`) made.
fn stock(file: &str, edits: &[(&str, &str)]) -> String {
    let mut text = std::fs::read_to_string(corpus().join(file)).expect("stock config");
    for (from, to) in edits {
        assert!(text.contains(from), "{file} has no {from:?}");
        text = text.replacen(from, to, 1);
    }
    text
}

/// The toolhead starts at X 120, Y 150, Z 40 (mm), inside the travel; the
/// config's pins are those of its own board.
fn options() -> Options {
    Options {
        start: Start::At([120.0, 150.0, 40.0]),
        board_pins: false,
        ..Options::default()
    }
}

/// Register `name`'s address on driver `stepper`.
fn addr(p: &mut ConsolePrinter, stepper: &str, name: &str) -> u8 {
    let d = p.tmc_drivers().driver(stepper).expect("driver");
    d.kind.register(name).expect("register").addr
}

/// The writes driver `stepper` received since `from` (an index into its
/// write log), and the log's length now.
fn writes_since(p: &mut ConsolePrinter, stepper: &str, from: usize) -> (Vec<(u8, u32)>, usize) {
    let d = p.tmc_drivers().driver(stepper).expect("driver");
    (d.written[from..].to_vec(), d.written.len())
}

/// A step interval at `speed` mm/s on a 40 mm / 3200 microstep rail, s.
fn interval(speed: f64) -> f64 {
    40.0 / 3200.0 / speed
}

#[test]
fn a_sovol_sv06_homes_x_and_y_on_the_stall_with_klippers_register_writes() {
    let dir = sd("sv06", &stock("printer-sovol-sv06-2022.cfg", &[]));
    let mut p = ConsolePrinter::new(&dir, &options()).expect("loads");
    // Registers written at start.
    p.send("M400");
    let (init, mut seen) = writes_since(&mut p, "stepper_x", 0);
    assert!(!init.is_empty());
    // As configured (stealthchop_threshold 0: stealthChop at every speed,
    // TPWMTHRS = TSTEP_MAX; no coolstep_threshold: TCOOLTHRS 0), the
    // driver reports no stall at the homing speed even when blocked.
    let x = p.tmc_drivers().driver("stepper_x").expect("x");
    let (gconf, tpwmthrs) = (x.register_named("GCONF"), x.register_named("TPWMTHRS"));
    assert_eq!(x.register_named("TCOOLTHRS"), 0);
    assert_eq!(tpwmthrs, TSTEP_MAX);
    assert_eq!(x.field("en_spreadcycle"), Some(0));
    assert_eq!(x.field("sgthrs"), Some(81));
    assert!(!x.stall_detect().get().reports(Some(interval(40.0))));

    let out = p.send("G28 X");
    assert!(out.ends_with("ok\n") && !out.contains("!!"), "{out}");
    // Klipper's writes: at the homing move's start TPWMTHRS 0 and GCONF
    // with en_spreadcycle clear (StallGuard4 needs stealthChop), TCOOLTHRS
    // 0xfffff (it was 0); at its end TPWMTHRS and GCONF as they were and
    // TCOOLTHRS 0.
    let (tpwm, gc, tcool) = (
        addr(&mut p, "stepper_x", "TPWMTHRS"),
        addr(&mut p, "stepper_x", "GCONF"),
        addr(&mut p, "stepper_x", "TCOOLTHRS"),
    );
    let (homing, now) = writes_since(&mut p, "stepper_x", seen);
    seen = now;
    assert_eq!(
        homing,
        [
            (tpwm, 0),
            (gc, gconf),
            (tcool, TSTEP_MAX),
            (tpwm, tpwmthrs),
            (gc, gconf),
            (tcool, 0),
        ]
    );
    // Y's driver was not touched.
    assert_eq!(
        writes_since(&mut p, "stepper_y", 0).0,
        init_of(&mut p, "stepper_y")
    );
    // The stall stopped X at its end: position_endstop 0, no retract.
    let triggers = p.triggers().to_vec();
    assert_eq!(triggers.len(), 1);
    assert_eq!(triggers[0].0, 0, "X");
    assert_eq!(
        p.stalls(),
        [0],
        "X's trigger was the driver's stall on DIAG"
    );
    let real = p.real_position().expect("physics");
    assert!(real[0].abs() < 0.05 && real[0] <= 0.0, "{real:?}");
    assert!((real[1] - 150.0).abs() < 1e-9, "{real:?}");
    // Registers back as configured: no stall reported blocked at rest.
    let out = p.send("M119");
    assert!(out.starts_with("x:open y:open"), "{out}");

    let out = p.send("G28 Y");
    assert!(out.ends_with("ok\n") && !out.contains("!!"), "{out}");
    assert_eq!(writes_since(&mut p, "stepper_x", seen).0, []);
    let triggers = p.triggers().to_vec();
    assert_eq!(triggers.len(), 2);
    assert_eq!(triggers[1].0, 1, "Y");
    assert_eq!(p.stalls(), [0, 1]);
    let out = p.send("M114");
    assert!(out.starts_with("X:0.000 Y:0.000 "), "{out}");
    let real = p.real_position().expect("physics");
    assert!(real[0].abs() < 0.05 && real[1].abs() < 0.05, "{real:?}");
    std::fs::remove_dir_all(&dir).ok();
}

/// The writes driver `stepper` received when the registers were written
/// at start (all of them, then GSTAT cleared).
fn init_of(p: &mut ConsolePrinter, stepper: &str) -> Vec<(u8, u32)> {
    let d = p.tmc_drivers().driver(stepper).expect("driver");
    d.written.clone()
}

#[test]
fn coolstep_threshold_kept_above_the_homing_speed_means_no_stall_as_in_klipper() {
    // A TCOOLTHRS the config sets (not 0) is kept for homing, as Klipper
    // keeps it: here one so low (1) that stall detection works at no
    // speed the rail can reach, so the homing move runs its full length.
    let dir = sd("coolstep", &stock("printer-sovol-sv06-2022.cfg", &[]));
    let mut p = ConsolePrinter::new(&dir, &options()).expect("loads");
    let out = p.send("SET_TMC_FIELD STEPPER=stepper_x FIELD=tcoolthrs VALUE=1");
    assert!(!out.contains("!!"), "{out}");
    let x = p.tmc_drivers().driver("stepper_x").expect("x");
    let (gconf, seen) = (x.register_named("GCONF"), x.written.len());
    let out = p.send("G28 X");
    assert!(
        out.contains("!! No trigger on x after full movement"),
        "{out}"
    );
    assert!(p.triggers().is_empty());
    // Set up for StallGuard4 all the same (stealthChop), TCOOLTHRS kept.
    let (tpwm, gc, tcool) = (
        addr(&mut p, "stepper_x", "TPWMTHRS"),
        addr(&mut p, "stepper_x", "GCONF"),
        addr(&mut p, "stepper_x", "TCOOLTHRS"),
    );
    let (homing, _) = writes_since(&mut p, "stepper_x", seen);
    assert_eq!(
        homing,
        [
            (tpwm, 0),
            (gc, gconf),
            (tpwm, TSTEP_MAX),
            (gc, gconf),
            (tcool, 1)
        ]
    );
    // The registers are put back after the failed move as after any.
    let x = p.tmc_drivers().driver("stepper_x").expect("x");
    assert_eq!(x.register_named("TCOOLTHRS"), 1);
    assert_eq!(x.register_named("TPWMTHRS"), TSTEP_MAX);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_driver_that_never_stalls_ends_with_no_trigger_after_full_movement() {
    // SGTHRS 0: StallGuard4 never reports a stall.
    let cfg = stock(
        "printer-sovol-sv06-2022.cfg",
        &[("driver_SGTHRS: 81", "driver_SGTHRS: 0")],
    );
    let dir = sd("never", &cfg);
    let mut p = ConsolePrinter::new(&dir, &options()).expect("loads");
    let out = p.send("G28 X");
    assert!(
        out.contains("!! No trigger on x after full movement"),
        "{out}"
    );
    assert!(p.triggers().is_empty());
    // The homing move ran its whole length into the frame: 1.5 x the
    // travel (220 mm) from where the firmware assumed X was (at
    // position_max).
    let real = p.real_position().expect("physics");
    assert!(real[0] < -100.0, "{real:?}");
    std::fs::remove_dir_all(&dir).ok();
}

/// The shipped Octopus Pro config with a TMC5160 on X over SPI (cs PC4,
/// hardware SPI), homing on its DIAG1 output wired to `diag` (the X
/// endstop input, PG6, pulled up), written as `endstop`.
fn octopus_5160(endstop: &str, diag: Option<&str>) -> String {
    let cfg = sd_folder::shipped_cfg();
    let x = cfg.find("[stepper_x]").expect("[stepper_x]");
    let line = cfg[x..].find("endstop_pin:").expect("endstop_pin") + x;
    let end = cfg[line..].find('\n').expect("line end") + line;
    let mut cfg = format!("{}endstop_pin: {endstop}{}", &cfg[..line], &cfg[end..]);
    cfg.push_str(
        "\n[tmc5160 stepper_x]\ncs_pin: PC4\nspi_bus: spi1\nrun_current: 0.800\n\
         stealthchop_threshold: 999999\ndriver_SGT: 1\n",
    );
    if let Some(diag) = diag {
        cfg.push_str(&format!("diag1_pin: {diag}\n"));
    }
    cfg
}

#[test]
fn a_tmc5160_homes_on_its_diag1_pin_with_klippers_register_writes() {
    let dir = sd(
        "5160",
        &octopus_5160("tmc5160_stepper_x:virtual_endstop", Some("^!PG6")),
    );
    let mut p = ConsolePrinter::new(&dir, &Options::default()).expect("loads");
    p.send("M400");
    let x = p.tmc_drivers().driver("stepper_x").expect("x");
    // stealthchop_threshold 999999: en_pwm_mode set (stealthChop, in which
    // StallGuard2 measures nothing), TCOOLTHRS and THIGH 0.
    let (gconf, thigh) = (x.register_named("GCONF"), x.register_named("THIGH"));
    assert_eq!(x.field("en_pwm_mode"), Some(1));
    assert_eq!(x.field("diag1_stall"), Some(0));
    assert_eq!(x.register_named("TCOOLTHRS"), 0);
    let seen = x.written.len();
    let out = p.send("G28 X");
    assert!(out.ends_with("ok\n") && !out.contains("!!"), "{out}");
    // Klipper's writes for StallGuard2: GCONF with en_pwm_mode (bit 2)
    // clear and diag1_stall (bit 8) set, TCOOLTHRS 0xfffff, THIGH 0; then
    // GCONF, TCOOLTHRS and THIGH as they were.
    let (gc, tcool, th) = (
        addr(&mut p, "stepper_x", "GCONF"),
        addr(&mut p, "stepper_x", "TCOOLTHRS"),
        addr(&mut p, "stepper_x", "THIGH"),
    );
    let homing_gconf = (gconf & !(1 << 2)) | 1 << 8;
    let (homing, _) = writes_since(&mut p, "stepper_x", seen);
    // The shipped config homes X with a second, slower move after a
    // retract: the same writes around each homing move.
    let one = [
        (gc, homing_gconf),
        (tcool, TSTEP_MAX),
        (th, 0),
        (gc, gconf),
        (tcool, 0),
        (th, thigh),
    ];
    assert_eq!(homing, [one, one].concat());
    assert_eq!(p.triggers().len(), 2);
    assert_eq!(p.stalls(), [0, 0]);
    let out = p.send("M114");
    assert!(out.starts_with("X:0.000 "), "{out}");
    let real = p.real_position().expect("physics");
    assert!(real[0].abs() < 0.05, "{real:?}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_virtual_endstop_the_driver_cannot_give_is_refused_as_klipper_words_it() {
    let refused = |name: &str, cfg: String| -> String {
        let dir = sd(name, &cfg);
        let result = ConsolePrinter::new(&dir, &Options::default());
        std::fs::remove_dir_all(&dir).ok();
        match result {
            Err(SimError::Config(message)) => message,
            Err(other) => panic!("{name}: {other}"),
            Ok(_) => panic!("{name}: loaded"),
        }
    };
    let stepper_x_line = |cfg: &str| {
        let x = cfg.find("[stepper_x]").expect("[stepper_x]");
        cfg[..x + cfg[x..].find("endstop_pin:").expect("endstop_pin")]
            .lines()
            .count()
            + 1
    };
    let cases = [
        (
            "nodiag",
            octopus_5160("tmc5160_stepper_x:virtual_endstop", None),
            "tmc virtual endstop requires diag pin config",
        ),
        (
            "nodriver",
            octopus_5160("tmc2209_stepper_x:virtual_endstop", Some("^PG6")),
            "Unknown pin chip name 'tmc2209_stepper_x'",
        ),
        (
            "inverted",
            octopus_5160("!tmc5160_stepper_x:virtual_endstop", Some("^PG6")),
            "Can not pullup/invert tmc virtual pin",
        ),
        (
            "otherpin",
            octopus_5160("tmc5160_stepper_x:diag", Some("^PG6")),
            "tmc virtual endstop only useful as endstop",
        ),
    ];
    for (name, cfg, klipper) in cases {
        let message = refused(name, cfg.clone());
        let line = stepper_x_line(&cfg);
        assert_eq!(
            message,
            format!("printer.cfg:{line}: option 'endstop_pin' in section 'stepper_x': {klipper}"),
            "{name}"
        );
    }
    // A TMC2208 has no StallGuard, so no virtual endstop: its chip is
    // unknown, as in Klipper.
    let cfg = stock(
        "printer-sovol-sv06-2022.cfg",
        &[
            (
                "tmc2209_stepper_x:virtual_endstop",
                "tmc2208_stepper_x:virtual_endstop",
            ),
            ("[tmc2209 stepper_x]", "[tmc2208 stepper_x]"),
            ("uart_address: 3\ndriver_SGTHRS: 81\ndiag_pin: PA5\n", ""),
        ],
    );
    let message = refused("tmc2208", cfg);
    assert_eq!(
        message,
        "printer.cfg:29: option 'endstop_pin' in section 'stepper_x': \
         Unknown pin chip name 'tmc2208_stepper_x'"
    );
    // The DIAG pin is checked as the section's diag_pin: here it is also
    // the fan's pin.
    let cfg = stock(
        "printer-sovol-sv06-2022.cfg",
        &[("diag_pin: PA5", "diag_pin: PA0")],
    );
    let message = refused("shared", cfg.clone());
    assert!(
        message.contains("[tmc2209 stepper_x] diag_pin"),
        "{message}\n{}",
        cfg.lines()
            .filter(|l| l.contains("PA0"))
            .collect::<Vec<_>>()
            .join("\n")
    );
}

/// The endstop input each rail's stepper is wired to, as a board wires
/// them from `cfg` (with the pins the Octopus Pro keeps for itself if
/// `board`).
fn endstop_inputs(cfg: &str, board: bool) -> Vec<Option<String>> {
    let mut files = ConfigFiles::new();
    files
        .push(ConfigFile {
            name: "printer.cfg",
            text: cfg,
        })
        .expect("one file");
    let mut scratch = Box::new(std::mem::MaybeUninit::uninit());
    let reserved = if board { BOARD_RESERVED } else { &[] };
    let setup = PrinterSetup::load(&files, reserved, &mut scratch).expect("loads");
    setup
        .steppers()
        .take(3)
        .map(|s| s.endstop_pin.map(str::to_string))
        .collect()
}

#[test]
fn the_board_reads_the_diag_pin_as_the_rails_endstop_input() {
    // The sv06: X and Y on their drivers' DIAG pins, Z on the probe.
    let cfg = stock("printer-sovol-sv06-2022.cfg", &[]);
    assert_eq!(
        endstop_inputs(&cfg, false),
        [Some("PA5".to_string()), Some("PA6".to_string()), None]
    );
    // The Octopus Pro with a TMC5160 on X: its DIAG1 pin as written
    // (pulled up, inverted), on this board's pins.
    let cfg = octopus_5160("tmc5160_stepper_x:virtual_endstop", Some("^!PG6"));
    let inputs = endstop_inputs(&cfg, true);
    assert_eq!(inputs[0].as_deref(), Some("^!PG6"));
}
