//! How long a stepper's step pulse lasts: Klipper's `step_pulse_duration`
//! rule (klippy/stepper.py and the TMC drivers' `setup_default_pulse_duration`).
//!
//! A `[stepper_…]` or `[extruder]` section may set `step_pulse_duration`
//! (0 to 0.001 s). Without it, the pulse is 100 ns for a stepper whose
//! driver has a `[tmcXXXX <stepper>]` section (such a driver is always in
//! UART or SPI mode: the section requires `uart_pin` or `cs_pin`), and
//! 2 µs for every other stepper (step/dir drivers, TMC drivers in
//! standalone mode). The same duration is the least time between a step
//! pulse and a direction change.

use onechip_planner::tmc::DriverKind;

/// The pulse without a `[tmcXXXX]` section: 2 µs.
pub const DEFAULT: f64 = 0.000_002;
/// The pulse of a TMC driver in UART or SPI mode: 100 ns.
pub const TMC_DEFAULT: f64 = 0.000_000_100;
/// The longest `step_pulse_duration` printer.cfg may set, s (the shortest
/// is 0; [`Machine::from_config`](onechip_planner::machine::Machine::from_config)
/// refuses longer).
pub const MAX: f64 = onechip_planner::machine::MAX_STEP_PULSE_DURATION;

/// The step pulse of a stepper, s: `config_value` (its
/// `step_pulse_duration`) if set, else [`TMC_DEFAULT`] if a TMC driver in
/// UART/SPI mode drives it (`has_tmc_uart_or_spi`, see
/// [`has_tmc_driver`]), else [`DEFAULT`].
pub fn step_pulse_duration(config_value: Option<f64>, has_tmc_uart_or_spi: bool) -> f64 {
    match config_value {
        Some(seconds) => seconds,
        None if has_tmc_uart_or_spi => TMC_DEFAULT,
        None => DEFAULT,
    }
}

/// True if one of `sections` (printer.cfg's section names) is a TMC
/// driver's section for the stepper named `stepper` (`tmc2209 stepper_x`
/// for `stepper_x`).
pub fn has_tmc_driver<'a>(sections: impl IntoIterator<Item = &'a str>, stepper: &str) -> bool {
    sections
        .into_iter()
        .any(|section| DriverKind::of_section(section).is_some_and(|(_, name)| name == stepper))
}

/// `seconds` in ticks of a `freq` Hz clock, rounded up (a pulse is never
/// shorter than configured; a few parts per million of float error are
/// not rounded up).
pub fn pulse_ticks(seconds: f64, freq: f64) -> u32 {
    let ticks = seconds * freq;
    // Saturates: negative and NaN give 0, huge values u32::MAX.
    let whole = ticks as u32;
    if ticks - f64::from(whole) > 1e-6 {
        whole.saturating_add(1)
    } else {
        whole
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn without_the_option_a_plain_stepper_gets_two_microseconds() {
        assert_eq!(step_pulse_duration(None, false), 0.000_002);
    }

    #[test]
    fn without_the_option_a_tmc_stepper_gets_one_hundred_nanoseconds() {
        assert_eq!(step_pulse_duration(None, true), 0.000_000_1);
    }

    #[test]
    fn the_option_wins_over_both_defaults() {
        assert_eq!(step_pulse_duration(Some(0.000_005), false), 0.000_005);
        assert_eq!(step_pulse_duration(Some(0.000_005), true), 0.000_005);
        // 0 is a valid setting, not "unset".
        assert_eq!(step_pulse_duration(Some(0.0), false), 0.0);
    }

    #[test]
    fn a_tmc_section_is_found_for_its_stepper_only() {
        let sections = [
            "printer",
            "stepper_x",
            "tmc2209 stepper_x",
            "tmc5160 extruder",
        ];
        assert!(has_tmc_driver(sections, "stepper_x"));
        assert!(has_tmc_driver(sections, "extruder"));
        assert!(!has_tmc_driver(sections, "stepper_y"));
        // Another stepper whose name starts the same.
        assert!(!has_tmc_driver(["tmc2209 stepper_z1"], "stepper_z"));
        // Not a TMC driver section, or one without a stepper.
        assert!(!has_tmc_driver(["tmcfoo stepper_x"], "stepper_x"));
        assert!(!has_tmc_driver(["tmc2209"], "stepper_x"));
        assert!(!has_tmc_driver(["tmc2209 stepper_x extra"], "stepper_x"));
        // An extruder stepper's driver.
        let e1 = "extruder_stepper e1";
        assert!(has_tmc_driver(["tmc2209 extruder_stepper e1"], e1));
        assert!(!has_tmc_driver(["tmc2209 e1"], e1));
    }

    #[test]
    fn every_klipper_tmc_driver_counts() {
        let drivers = [
            "tmc2130", "tmc2208", "tmc2209", "tmc2240", "tmc2660", "tmc5160",
        ];
        for driver in drivers {
            let section = [driver, " stepper_y"].concat();
            assert!(has_tmc_driver([section.as_str()], "stepper_y"), "{driver}");
        }
    }

    #[test]
    fn ticks_round_up_but_not_float_noise() {
        // 520 MHz core: 2 µs = 1040 cycles, 100 ns = 52 (1e-7 * 5.2e8 is
        // not exactly 52 in binary).
        assert_eq!(pulse_ticks(DEFAULT, 520e6), 1040);
        assert_eq!(pulse_ticks(TMC_DEFAULT, 520e6), 52);
        // 260 MHz timer: 501 ns = 130.26 ticks, rounded up.
        assert_eq!(pulse_ticks(0.000_000_501, 260e6), 131);
        assert_eq!(pulse_ticks(0.0, 520e6), 0);
        assert_eq!(pulse_ticks(MAX, 520e6), 520_000);
        assert_eq!(pulse_ticks(-1.0, 520e6), 0);
        assert_eq!(pulse_ticks(f64::NAN, 520e6), 0);
    }
}
