//! TMC drivers: register values for Klipper's stock configs equal what
//! Klipper computes (each expected value derived below from Klipper's
//! formulas and defaults, `klippy/extras/tmc*.py`), the simulated drivers
//! hold what the firmware wrote over the shared UART/SPI datagrams, a
//! driver reset mid-run is seen and repaired, and the G-code commands
//! answer as Klipper does. A survey prints how many of the stock configs'
//! TMC sections load.

use onechip_config::Config;
use onechip_host::Options;
use onechip_host::console_printer::ConsolePrinter;
use onechip_planner::machine::Machine;
use onechip_planner::tmc::config::{Bus, TmcDriver};
use onechip_tests::sd_folder;
use std::path::PathBuf;

fn corpus() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/klipper-configs")
}

/// The TMC driver of `stepper` in stock config `file`, read with the
/// whole machine (as the firmware loads it).
fn driver(file: &'static str, stepper: &str) -> TmcDriver<'static> {
    let text = std::fs::read_to_string(corpus().join(file)).expect("stock config");
    let text: &'static str = Box::leak(text.into_boxed_str());
    let config: &'static Config<'static> =
        Box::leak(Box::new(Config::parse(file, text).expect("parses")));
    let machine = Machine::from_config(config).unwrap_or_else(|e| panic!("{file}: {e}"));
    machine
        .tmc
        .iter()
        .find(|d| d.stepper == stepper)
        .cloned()
        .unwrap_or_else(|| panic!("{file}: no driver for {stepper}"))
}

/// Klipper's current bits for the TMC2130/2208/2209 (`_calc_current_bits`):
/// int(32 * (R + 0.020) * I * √2 / vref + .5) - 1, within 0..=31.
fn cs_2130(r: f64, current: f64, vref: f64) -> u32 {
    ((32.0 * (r + 0.020) * current * 2f64.sqrt() / vref + 0.5) as i64 - 1).clamp(0, 31) as u32
}

/// Register `name` of `d`.
fn reg(d: &TmcDriver<'_>, name: &str) -> u32 {
    d.regs.value_of(name)
}

#[test]
fn tmc2209_registers_equal_klippers() {
    // [stepper_x]: microsteps 16, rotation_distance 40 (200 full steps).
    // [tmc2209 stepper_x]: uart_pin PC11, tx_pin PC10, uart_address 0,
    // run_current 0.580, stealthchop_threshold 999999.
    let d = driver("generic-bigtreetech-skr-mini-e3-v2.0.cfg", "stepper_x");
    assert!(matches!(
        d.bus,
        Bus::Uart {
            uart_pin: "PC11",
            tx_pin: Some("PC10"),
            address: 0,
            ..
        }
    ));
    // Current: hold_current defaults to 2.0 A and is capped at run: 0.58 A.
    // vsense (0.18 V) first: 32 * 0.13 * 0.58 * √2 / 0.18 = 18.96 ->
    // int(19.46) - 1 = 18; not 31, so vsense stays.
    let cs = cs_2130(0.110, 0.580, 0.18);
    assert_eq!(cs, 18);
    // IHOLD_IRUN: ihold 18, irun 18 << 8, iholddelay 8 << 16.
    assert_eq!(reg(&d, "IHOLD_IRUN"), cs | cs << 8 | 8 << 16);
    assert_eq!(reg(&d, "IHOLD_IRUN"), 0x0008_1212);
    // CHOPCONF: toff 3, hstrt 5 << 4, hend 0, tbl 2 << 15, vsense 1 << 17,
    // mres = 8 - log2(16) = 4 << 24, intpol 1 << 28.
    assert_eq!(
        reg(&d, "CHOPCONF"),
        3 | 5 << 4 | 2 << 15 | 1 << 17 | 4 << 24 | 1 << 28
    );
    assert_eq!(reg(&d, "CHOPCONF"), 0x1403_0053);
    // GCONF: pdn_disable 1 << 6, mstep_reg_select 1 << 7, multistep_filt
    // 1 << 8; stealthchop_threshold set, so en_spreadcycle (bit 2) = 0.
    assert_eq!(reg(&d, "GCONF"), 0x1c0);
    // TPWMTHRS: int(12 MHz * (40 / 3200 / 2^4) / 999999 + .5) = int(0.509) = 0.
    let step_dist_256 = 40.0 / (200.0 * 16.0) / 16.0;
    assert_eq!(
        reg(&d, "TPWMTHRS"),
        (12e6 * step_dist_256 / 999_999.0 + 0.5) as u32
    );
    assert_eq!(reg(&d, "TPWMTHRS"), 0);
    // PWMCONF: pwm_ofs 36, pwm_grad 14 << 8, pwm_freq 1 << 16, autoscale
    // 1 << 18, autograd 1 << 19, pwm_reg 8 << 24, pwm_lim 12 << 28.
    assert_eq!(
        reg(&d, "PWMCONF"),
        36 | 14 << 8 | 1 << 16 | 1 << 18 | 1 << 19 | 8 << 24 | 12 << 28
    );
    // SLAVECONF: senddelay 2 << 8; TPOWERDOWN 20; TCOOLTHRS, COOLCONF and
    // SGTHRS 0.
    assert_eq!(reg(&d, "SLAVECONF"), 0x200);
    assert_eq!(reg(&d, "TPOWERDOWN"), 20);
    for zero in ["TCOOLTHRS", "COOLCONF", "SGTHRS"] {
        assert_eq!(reg(&d, zero), 0, "{zero}");
    }
    // Klipper writes them in the order its fields were first set.
    let order: Vec<&str> = d
        .regs
        .iter()
        .filter_map(|(a, _)| d.kind.register_at(a).map(|r| r.name))
        .collect();
    assert_eq!(
        order,
        [
            "GCONF",
            "SLAVECONF",
            "CHOPCONF",
            "IHOLD_IRUN",
            "TPWMTHRS",
            "TCOOLTHRS",
            "COOLCONF",
            "PWMCONF",
            "TPOWERDOWN",
            "SGTHRS"
        ]
    );
    // The drivers on the same UART have their own addresses.
    let e = driver("generic-bigtreetech-skr-mini-e3-v2.0.cfg", "extruder");
    assert!(matches!(e.bus, Bus::Uart { address: 3, .. }));
}

#[test]
fn tmc2208_registers_equal_klippers() {
    // [stepper_x]: microsteps 16, rotation 40; [tmc2208 stepper_x]:
    // uart_pin P0.5, tx_pin P0.4, run_current 0.600,
    // stealthchop_threshold 999999.
    let d = driver("generic-th3d-ezboard-lite-v1.2.cfg", "stepper_x");
    assert!(matches!(
        d.bus,
        Bus::Uart {
            uart_pin: "P0.5",
            tx_pin: Some("P0.4"),
            address: 0,
            ..
        }
    ));
    // 32 * 0.13 * 0.6 * √2 / 0.18 = 19.61 -> int(20.11) - 1 = 19, vsense.
    let cs = cs_2130(0.110, 0.6, 0.18);
    assert_eq!(cs, 19);
    assert_eq!(reg(&d, "IHOLD_IRUN"), cs | cs << 8 | 8 << 16);
    assert_eq!(reg(&d, "IHOLD_IRUN"), 0x0008_1313);
    // CHOPCONF and GCONF as the TMC2209's (same defaults, vsense set).
    assert_eq!(reg(&d, "CHOPCONF"), 0x1403_0053);
    assert_eq!(reg(&d, "GCONF"), 0x1c0);
    // No SLAVECONF (senddelay is the TMC2209's), no coolStep registers.
    assert!(d.kind.register("TCOOLTHRS").is_none());
    assert_eq!(reg(&d, "SLAVECONF"), 0);
}

#[test]
fn tmc2130_registers_equal_klippers() {
    // [stepper_x]: microsteps 16, rotation 40; [tmc2130 stepper_x]:
    // cs_pin PG0, run_current .5, sense_resistor 0.220, diag1_pin !PK2.
    let d = driver("generic-einsy-rambo.cfg", "stepper_x");
    assert_eq!(d.diag, Some(("!PK2", Some("diag1_stall"))));
    // 32 * 0.24 * 0.5 * √2 / 0.18 = 30.17 -> int(30.67) - 1 = 29, vsense.
    let cs = cs_2130(0.220, 0.5, 0.18);
    assert_eq!(cs, 29);
    assert_eq!(reg(&d, "IHOLD_IRUN"), cs | cs << 8 | 8 << 16);
    // CHOPCONF: toff 4, hstrt 0, hend 7 << 7, tbl 1 << 15, vsense 1 << 17,
    // mres 4 << 24, intpol 1 << 28.
    assert_eq!(
        reg(&d, "CHOPCONF"),
        4 | 7 << 7 | 1 << 15 | 1 << 17 | 4 << 24 | 1 << 28
    );
    assert_eq!(reg(&d, "CHOPCONF"), 0x1402_8384);
    // No stealthchop_threshold: en_pwm_mode 0, TPWMTHRS 0xfffff; no
    // coolstep/high velocity thresholds: 0.
    assert_eq!(reg(&d, "GCONF"), 0);
    assert_eq!(reg(&d, "TPWMTHRS"), 0xfffff);
    assert_eq!((reg(&d, "TCOOLTHRS"), reg(&d, "THIGH")), (0, 0));
    // PWMCONF: pwm_ampl 128, pwm_grad 4 << 8, pwm_freq 1 << 16, autoscale
    // 1 << 18.
    assert_eq!(reg(&d, "PWMCONF"), 128 | 4 << 8 | 1 << 16 | 1 << 18);
    // The default wave table: MSLUTSEL w0 2, w1..w3 1, x1 128, x2 x3 255;
    // MSLUTSTART start_sin90 247.
    assert_eq!(
        reg(&d, "MSLUTSEL"),
        2 | 1 << 2 | 1 << 4 | 1 << 6 | 128 << 8 | 255 << 16 | 255 << 24
    );
    assert_eq!(reg(&d, "MSLUTSTART"), 247 << 16);
    assert_eq!(reg(&d, "MSLUT0"), 0xAAAA_B554);
}

#[test]
fn tmc5160_registers_equal_klippers() {
    // [stepper_x]: microsteps 32, rotation 40; [tmc5160 stepper_x]:
    // interpolate False, sense_resistor 0.075, run_current 0.8,
    // stealthchop_threshold 0.
    let d = driver("generic-ldo-leviathan-v1.2.cfg", "stepper_x");
    let sqrt2 = 2f64.sqrt();
    // GLOBALSCALER: int(0.8 * 256 * √2 * 0.075 / 0.325 + .5) = int(67.34)
    // = 67 (at least 32, below 256).
    let gs = (0.8 * 256.0 * sqrt2 * 0.075 / 0.325 + 0.5) as u32;
    assert_eq!(gs, 67);
    assert_eq!(reg(&d, "GLOBALSCALER"), gs);
    // IRUN: int(0.8 * 256 * 32 * √2 * 0.075 / (67 * 0.325) - 1 + .5)
    // = int(31.42) = 31; hold (10 A default, capped at run) the same.
    let cs = (0.8 * 256.0 * 32.0 * sqrt2 * 0.075 / (f64::from(gs) * 0.325) - 1.0 + 0.5) as u32;
    assert_eq!(cs, 31);
    assert_eq!(reg(&d, "IHOLD_IRUN"), cs | cs << 8 | 6 << 16);
    // CHOPCONF: toff 3, hstrt 5 << 4, hend 2 << 7, tbl 2 << 15, tpfd
    // 4 << 20, mres 8 - log2(32) = 3 << 24, intpol off.
    assert_eq!(
        reg(&d, "CHOPCONF"),
        3 | 5 << 4 | 2 << 7 | 2 << 15 | 4 << 20 | 3 << 24
    );
    // stealthchop_threshold 0 is set: en_pwm_mode (bit 2) with
    // multistep_filt (bit 3); TPWMTHRS for 0 mm/s is 0xfffff.
    assert_eq!(reg(&d, "GCONF"), 1 << 2 | 1 << 3);
    assert_eq!(reg(&d, "TPWMTHRS"), 0xfffff);
    // PWMCONF: pwm_ofs 30, autoscale, autograd, pwm_reg 4 << 24, pwm_lim
    // 12 << 28; DRV_CONF bbmclks 4 << 8; TPOWERDOWN 10.
    assert_eq!(
        reg(&d, "PWMCONF"),
        30 | 1 << 18 | 1 << 19 | 4 << 24 | 12 << 28
    );
    assert_eq!(reg(&d, "DRV_CONF"), 4 << 8);
    assert_eq!(reg(&d, "TPOWERDOWN"), 10);
    // A daisy chain (Duet 3 6HC): positions 1.. of 6 on one chip select.
    let y = driver("generic-duet3-6hc.cfg", "stepper_y");
    assert!(matches!(
        y.bus,
        Bus::Spi {
            cs_pin: "PD17",
            chain_position: 2,
            chain_length: 6,
            ..
        }
    ));
}

#[test]
fn tmc2660_registers_equal_klippers() {
    // [stepper_x]: microsteps 16; [tmc2660 stepper_x]: run_current 1.000,
    // sense_resistor 0.051.
    let d = driver("generic-duet2.cfg", "stepper_x");
    // CS: vsense (0.165 V) first: int(32 * 0.051 * 1.0 * √2 / 0.165 + .5)
    // - 1 = int(14.49) - 1 = 13.
    let cs = ((32.0 * 0.051 * 2f64.sqrt() / 0.165 + 0.5) as u32) - 1;
    assert_eq!(cs, 13);
    assert_eq!(reg(&d, "SGCSCONF"), cs);
    // DRVCONF: vsense 1 << 6, ts2g 3 << 8 (sdoff and rdsel 0).
    assert_eq!(reg(&d, "DRVCONF"), 1 << 6 | 3 << 8);
    // DRVCTRL: mres 4, intpol 1 << 9; CHOPCONF: toff 4, hstrt 3 << 4, hend
    // 3 << 7, tbl 2 << 15.
    assert_eq!(reg(&d, "DRVCTRL"), 4 | 1 << 9);
    assert_eq!(reg(&d, "CHOPCONF"), 4 | 3 << 4 | 3 << 7 | 2 << 15);
}

#[test]
fn tmc2240_registers_equal_klippers() {
    // No stock config has a TMC2240: the Einsy's X driver swapped for one
    // (rref 12 kΩ by default), run_current 1.0, stealthchop_threshold 50;
    // [stepper_x]: microsteps 16, rotation 40.
    let text = std::fs::read_to_string(corpus().join("generic-einsy-rambo.cfg")).expect("cfg");
    let text = text.replace(
        "[tmc2130 stepper_x]\ncs_pin: PG0\nrun_current: .5\nsense_resistor: 0.220\ndiag1_pin: !PK2\n",
        "[tmc2240 stepper_x]\ncs_pin: PG0\nrun_current: 1.0\nstealthchop_threshold: 50\ndiag0_pin: !PK2\n",
    );
    let config = Config::parse("printer.cfg", &text).expect("parses");
    let machine = Machine::from_config(&config).expect("loads");
    let d = machine
        .tmc
        .iter()
        .find(|d| d.stepper == "stepper_x")
        .expect("x");
    assert_eq!(d.diag, Some(("!PK2", Some("diag0_stall"))));
    let sqrt2 = 2f64.sqrt();
    // Full scale per current_range: KIFS / rref / √2 = 11750, 24000, 36000
    // (A·Ω) / 12000 / √2 = 0.692, 1.414, 2.121 A: 1.0 A needs range 1.
    let ifs = 24000.0 / 12000.0 / sqrt2;
    assert_eq!(reg(d, "DRV_CONF"), 1);
    // GLOBALSCALER: int(1.0 * 256 / 1.414 + .5) = int(181.52) = 181.
    let gs = (256.0 / ifs + 0.5) as u32;
    assert_eq!(gs, 181);
    assert_eq!(reg(d, "GLOBALSCALER"), gs);
    // IRUN: int(1.0 * 256 * 32 / (181 * 1.414) - 1 + .5) = int(31.50) = 31;
    // hold (default: the range-3 full scale, capped at run) the same;
    // iholddelay 6, irundelay 4.
    let cs = (256.0 * 32.0 / (f64::from(gs) * ifs) - 1.0 + 0.5) as u32;
    assert_eq!(cs, 31);
    assert_eq!(reg(d, "IHOLD_IRUN"), cs | cs << 8 | 6 << 16 | 4 << 24);
    // CHOPCONF: toff 3, hstrt 5 << 4, hend 2 << 7, tbl 2 << 15, tpfd
    // 4 << 20, mres 4 << 24, intpol 1 << 28.
    assert_eq!(
        reg(d, "CHOPCONF"),
        3 | 5 << 4 | 2 << 7 | 2 << 15 | 4 << 20 | 4 << 24 | 1 << 28
    );
    // en_pwm_mode and multistep_filt; TPWMTHRS at the 12.5 MHz clock:
    // int(12.5e6 * (40 / 3200 / 16) / 50 + .5) = int(195.81) = 195.
    assert_eq!(reg(d, "GCONF"), 1 << 2 | 1 << 3);
    let tpwmthrs = (12.5e6 * (40.0 / (200.0 * 16.0) / 16.0) / 50.0 + 0.5) as u32;
    assert_eq!(tpwmthrs, 195);
    assert_eq!(reg(d, "TPWMTHRS"), tpwmthrs);
    // PWMCONF: pwm_ofs 29, autoscale, autograd, pwm_reg 4, pwm_lim 12;
    // SG4_THRS: sg4_angle_offset; TPOWERDOWN 10.
    assert_eq!(
        reg(d, "PWMCONF"),
        29 | 1 << 18 | 1 << 19 | 4 << 24 | 12 << 28
    );
    assert_eq!(reg(d, "SG4_THRS"), 1 << 9);
    assert_eq!(reg(d, "TPOWERDOWN"), 10);
}

#[test]
fn invalid_driver_fields_name_file_line_and_option() {
    let base = std::fs::read_to_string(corpus().join("generic-einsy-rambo.cfg")).expect("cfg");
    for (option, value) in [
        ("driver_TOFF", "16"),
        ("driver_SGT", "-65"),
        ("hold_current", "2.5"),
        ("driver_IHOLDDELAY", "16"),
        ("driver_PWM_AUTOSCALE", "maybe"),
    ] {
        let text = base.replace(
            "[tmc2130 stepper_x]\n",
            &format!("[tmc2130 stepper_x]\n{option}: {value}\n"),
        );
        let config = Config::parse("printer.cfg", &text).expect("parses");
        let error = Machine::from_config(&config).expect_err(option).to_string();
        let line = text
            .lines()
            .position(|l| l.starts_with(option))
            .map(|i| i + 1)
            .expect("line");
        assert!(
            error.starts_with(&format!("printer.cfg:{line}: option '{option}'")),
            "{error}"
        );
        assert!(error.contains("tmc2130 stepper_x"), "{error}");
    }
}

/// An SD folder: the shipped Octopus Pro config with TMC2209 drivers on
/// its X, Y, Z and extruder sockets (the board's UART pins).
/// One folder per test (`test`): the tests of this file run as threads of
/// one process, and one making its folder would remove another's.
fn sd_with_drivers(test: &str) -> PathBuf {
    let drivers: String = [
        ("stepper_x", "PC4"),
        ("stepper_y", "PD11"),
        ("stepper_z", "PC6"),
        ("extruder", "PC7"),
    ]
    .iter()
    .map(|(stepper, pin)| {
        format!(
            "\n[tmc2209 {stepper}]\nuart_pin: {pin}\nrun_current: 0.800\nstealthchop_threshold: 999999\n"
        )
    })
    .collect();
    shipped_plus(&format!("drivers-{test}"), &drivers)
}

/// The registers the session wrote equal those the simulated driver of
/// `stepper` holds.
fn in_sync(p: &mut ConsolePrinter, stepper: &str) -> bool {
    let written: Vec<(u8, u32)> = p.tmc().registers(stepper).expect("driver").iter().collect();
    let sim = p.tmc_drivers().driver(stepper).expect("simulated");
    written
        .iter()
        .all(|&(addr, value)| sim.register(addr) == value)
}

#[test]
fn registers_are_written_at_start_and_again_after_a_driver_reset() {
    let dir = sd_with_drivers("reset");
    let mut p = ConsolePrinter::new(&dir, &Options::default()).expect("loads");
    // Power-on: the simulated drivers hold zeros until the firmware writes.
    assert_eq!(
        p.tmc_drivers()
            .driver("stepper_x")
            .map(|d| d.register_named("CHOPCONF")),
        Some(0)
    );
    let out = p.send("G28");
    assert!(out.contains("ok"), "{out}");
    for stepper in ["stepper_x", "stepper_y", "stepper_z", "extruder"] {
        assert!(in_sync(&mut p, stepper), "{stepper}");
    }
    // Written over the UART: IHOLD_IRUN as configured (0.8 A: 25).
    let x = p.tmc_drivers().driver("stepper_x").expect("x");
    assert_eq!(x.field("irun"), Some(25));
    assert_eq!(x.field("reset"), Some(0), "GSTAT cleared at start");
    // Mid-run the Y driver loses power: registers 0, GSTAT reset set.
    p.send("G1 X50 Y50 F3000");
    let y = p.tmc_drivers().driver("stepper_y").expect("y");
    y.power_cycle();
    assert!(!in_sync(&mut p, "stepper_y"));
    // Within the next check period the firmware sees it and writes again.
    let out = p.run_for(1.5);
    assert!(
        out.contains("// TMC 'stepper_y' was reset (power loss?): registers written again"),
        "{out}"
    );
    assert!(in_sync(&mut p, "stepper_y"));
    let y = p.tmc_drivers().driver("stepper_y").expect("y");
    assert_eq!(y.field("reset"), Some(0));
    // The others were left alone (only checked).
    let out = p.run_for(1.5);
    assert!(!out.contains("was reset"), "{out}");
}

#[test]
fn a_driver_error_is_reported_as_klipper_words_it_and_shuts_the_printer_down() {
    let dir = sd_with_drivers("error");
    let mut p = ConsolePrinter::new(&dir, &Options::default()).expect("loads");
    p.send("G28");
    let out = p.run_for(1.5);
    assert!(!out.contains("reports error"), "{out}");
    // The Z driver overheats: DRV_STATUS' ot flag (TMC2209: bit 1).
    let z = p.tmc_drivers().driver("stepper_z").expect("z");
    let drv_status = z.kind.register_any("DRV_STATUS").expect("DRV_STATUS").addr;
    z.inject(drv_status, 1 << 1);
    let out = p.run_for(1.5);
    assert!(
        out.contains("!! TMC 'stepper_z' reports error: DRV_STATUS: 00000002 ot=1(OvertempError!)"),
        "{out}"
    );
    // As in Klipper, the printer shuts down: nothing moves or heats.
    let refused = p.send("G1 X10");
    assert!(
        refused.contains("TMC driver error (see the message above)"),
        "{refused}"
    );
    assert!(p.heaters_on().iter().all(|on| !on));
}

#[test]
fn tmc_gcode_commands_answer_as_klipper() {
    let dir = sd_with_drivers("gcode");
    let mut p = ConsolePrinter::new(&dir, &Options::default()).expect("loads");
    // 0.8 A on 0.110 Ω: IRUN 25 with vsense, which gives back
    // 26 * 0.18 / (32 * 0.13 * √2) = 0.7955 A: "0.80A".
    let out = p.send("SET_TMC_CURRENT STEPPER=stepper_x");
    assert!(
        out.contains("// Run Current: 0.80A Hold Current: 0.80A"),
        "{out}"
    );
    // 1.2 A needs the coarse scale (vsense off): IRUN int(22.56) - 1 =
    // 21, which gives 22 * 0.32 / (32 * 0.13 * √2) = 1.1966 A; hold 0.5 A
    // on that scale: int(9.69) - 1 = 8 -> 0.4894 A.
    let out = p.send("SET_TMC_CURRENT STEPPER=stepper_x CURRENT=1.2 HOLDCURRENT=0.5");
    assert!(
        out.contains("// Run Current: 1.20A Hold Current: 0.49A"),
        "{out}"
    );
    let x = p.tmc_drivers().driver("stepper_x").expect("x");
    assert_eq!(
        (x.field("irun"), x.field("ihold"), x.field("vsense")),
        (Some(21), Some(8), Some(0))
    );
    let out = p.send("SET_TMC_CURRENT STEPPER=stepper_x CURRENT=2.5");
    assert!(out.contains("CURRENT must have maximum of 2.0"), "{out}");
    let out = p.send("SET_TMC_CURRENT STEPPER=stepper_q CURRENT=1");
    assert!(
        out.contains("The value 'stepper_q' is not valid for STEPPER"),
        "{out}"
    );
    // SET_TMC_FIELD by value and by velocity (TSTEP at 50 mm/s: 12 MHz *
    // 40/3200/16 mm / 50 mm/s = 187.5 -> 188).
    p.send("SET_TMC_FIELD STEPPER=stepper_y FIELD=sgthrs VALUE=77");
    p.send("SET_TMC_FIELD STEPPER=stepper_y FIELD=tcoolthrs VELOCITY=50");
    let tstep_50 = (12e6 * (40.0 / (200.0 * 16.0) / 16.0) / 50.0 + 0.5) as i64;
    assert_eq!(tstep_50, 188);
    let y = p.tmc_drivers().driver("stepper_y").expect("y");
    assert_eq!(
        (y.field("sgthrs"), y.field("tcoolthrs")),
        (Some(77), Some(tstep_50))
    );
    let out = p.send("SET_TMC_FIELD STEPPER=stepper_y FIELD=nonsense VALUE=1");
    assert!(out.contains("Unknown field name 'nonsense'"), "{out}");
    let out = p.send("SET_TMC_FIELD STEPPER=stepper_y FIELD=toff");
    assert!(out.contains("Specify either VALUE or VELOCITY"), "{out}");
    // DUMP_TMC: write-only registers from memory, the others read back.
    let out = p.send("DUMP_TMC STEPPER=stepper_y");
    assert!(
        out.contains("// ========== Write-only registers =========="),
        "{out}"
    );
    assert!(out.contains("// SGTHRS:     0000004d sgthrs=77"), "{out}");
    assert!(
        out.contains("// ========== Queried registers =========="),
        "{out}"
    );
    assert!(
        out.contains(
            "// CHOPCONF:   14030053 toff=3 hstrt=5 tbl=2 vsense=1 mres=4(16usteps) intpol=1"
        ),
        "{out}"
    );
    let out = p.send("DUMP_TMC STEPPER=stepper_y REGISTER=ihold_irun");
    assert!(
        out.contains("// IHOLD_IRUN: 00081919 ihold=25 irun=25 iholddelay=8"),
        "{out}"
    );
    // INIT_TMC writes everything again.
    let y = p.tmc_drivers().driver("stepper_y").expect("y");
    y.power_cycle();
    p.send("INIT_TMC STEPPER=stepper_y");
    assert!(in_sync(&mut p, "stepper_y"));
}

/// How many TMC sections of the stock configs load (printed), and every
/// refusal names file, line and option.
#[test]
fn stock_tmc_sections_load_or_say_why() {
    let mut files: Vec<_> = std::fs::read_dir(corpus())
        .expect("corpus")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "cfg"))
        .collect();
    files.sort();
    let (mut sections, mut loaded, mut refused) = (0, 0, Vec::new());
    for file in &files {
        let text = std::fs::read_to_string(file).expect("text");
        let name = file.file_name().and_then(|n| n.to_str()).unwrap_or("?");
        let Ok(config) = Config::parse(name, &text) else {
            continue;
        };
        let count = config
            .section_names()
            .filter(|s| onechip_planner::tmc::DriverKind::of_section(s).is_some())
            .count();
        if count == 0 {
            continue;
        }
        sections += count;
        let mut drivers = Default::default();
        match onechip_planner::tmc::config::read_all(
            &config,
            onechip_planner::machine::step_distance,
            &mut drivers,
        ) {
            Ok(()) => loaded += drivers.len(),
            Err(e) => refused.push(format!("{name}: {e}")),
        }
    }
    println!("TMC sections in the stock configs: {sections}, loaded: {loaded}");
    for r in &refused {
        println!("  refused: {r}");
    }
    assert!(sections > 100);
    assert!(
        refused
            .iter()
            .all(|r| r.contains("option '") || r.contains("section '")),
        "{refused:?}"
    );
}

/// The shipped printer.cfg with `extra` sections, in its own SD folder.
fn shipped_plus(name: &str, extra: &str) -> PathBuf {
    sd_folder::new(
        &format!("tmc-{name}"),
        &(sd_folder::shipped_cfg() + extra),
        None,
    )
}

#[test]
fn a_drivers_uart_or_chip_select_pin_is_checked_as_klipper_checks_pins() {
    let options = Options::default();
    // Four drivers on one UART pin, told apart by address (as the SKR
    // Mini E3's): allowed.
    let shared: String = (["stepper_x", "stepper_y", "stepper_z", "extruder"]
        .iter()
        .enumerate())
    .map(|(a, s)| format!("\n[tmc2209 {s}]\nuart_pin: PC4\nuart_address: {a}\nrun_current: 0.8\n"))
    .collect();
    let dir = shipped_plus("shared-uart", &shared);
    assert!(
        ConsolePrinter::new(&dir, &options).is_ok(),
        "a shared UART refused"
    );
    // A fan on a driver's UART pin: refused, naming both.
    let clash = "\n[tmc2209 stepper_x]\nuart_pin: PC4\nrun_current: 0.8\n\
                 [fan_generic aux]\npin: PC4\n";
    let dir = shipped_plus("uart-clash", clash);
    let message = match ConsolePrinter::new(&dir, &options) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("a fan on a TMC UART pin"),
    };
    assert!(
        message.contains(
            "pin PC4 used by both [tmc2209 stepper_x] uart_pin and [fan_generic aux] pin"
        ),
        "{message}"
    );
    // A driver's chip select on the board's USB pin: refused.
    let usb = "\n[tmc2130 stepper_x]\ncs_pin: PA12\nspi_bus: spi1\nrun_current: 0.8\n";
    let dir = shipped_plus("cs-usb", usb);
    let message = match ConsolePrinter::new(&dir, &options) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("a chip select on USB D+"),
    };
    assert!(
        message.contains("PA12") && message.contains("USB D+"),
        "{message}"
    );
}

#[test]
fn set_tmc_current_takes_effect_once_the_queued_moves_have_run() {
    let dir = sd_with_drivers("current");
    let mut p = ConsolePrinter::new(&dir, &Options::default()).expect("loads");
    assert!(p.send("G28").contains("ok"));
    // A 10 s move queued, then a new run current for X (0.5 A: irun 15).
    let irun = |p: &mut ConsolePrinter| {
        p.tmc_drivers()
            .driver("stepper_x")
            .and_then(|d| d.field("irun"))
    };
    assert_eq!(irun(&mut p), Some(25));
    let start = p.now();
    let out = p.send("G1 X100 F600\nSET_TMC_CURRENT STEPPER=stepper_x CURRENT=0.5");
    assert!(out.ends_with("ok\n") && !out.contains("!!"), "{out}");
    // The write waited for the move (100 mm at 10 mm/s from the endstop
    // at X 0), as Klipper's does: the reply came after it (the shipped
    // printer's clock: 260 MHz).
    let waited = (p.now() - start) as f64 / 260e6;
    assert!(waited > 9.0, "SET_TMC_CURRENT answered after {waited} s");
    assert_eq!(irun(&mut p), Some(15));
    assert!(in_sync(&mut p, "stepper_x"));
}

#[test]
fn a_tmc2660_runs_at_its_idle_current_percent_while_the_printer_is_ready() {
    // Klipper's CS for 1.0 A over 0.051 Ω: with VSENSE 0 (0.310 V)
    // int(32 × 1.0 × 0.051 × √2 / 0.310 − 1 + .5) = 6 < 16, so VSENSE 1
    // (0.165 V): int(13.49) = 13. At 50 %, 0.5 A: int(6.49) = 6.
    let section = "\n[tmc2660 stepper_x]\ncs_pin: PC4\nspi_bus: spi1\nrun_current: 1.0\n\
                   sense_resistor: 0.051\nidle_current_percent: 50\n";
    let dir = shipped_plus("idle-current", section);
    let mut p = ConsolePrinter::new(&dir, &Options::default()).expect("loads");
    let cs = |p: &mut ConsolePrinter| {
        p.tmc_drivers()
            .driver("stepper_x")
            .and_then(|d| d.field("cs"))
    };
    assert!(p.send("G28").ends_with("ok\n"));
    assert_eq!(cs(&mut p), Some(13), "printing: the run current");
    // Ready 0.5 s after the last move finished: half the current.
    p.run_for(2.0);
    assert_eq!(cs(&mut p), Some(6), "ready: idle_current_percent of it");
    // A move: printing again, at the run current.
    assert!(p.send("G1 X20 F3000").ends_with("ok\n"));
    assert_eq!(cs(&mut p), Some(13));
    // SET_TMC_CURRENT changes the run current the idle share is taken of.
    p.run_for(2.0);
    let out = p.send("SET_TMC_CURRENT STEPPER=stepper_x CURRENT=1.2");
    assert!(out.contains("// Run Current: 1.20A"), "{out}");
    // 1.2 A: int(32 × 1.2 × 0.051 × √2 / 0.165 − .5) = 16; ready, 0.6 A:
    // int(7.89) = 7.
    p.send("G1 X30");
    assert_eq!(cs(&mut p), Some(16));
    p.run_for(2.0);
    assert_eq!(cs(&mut p), Some(7), "ready: 0.6 A");
}
