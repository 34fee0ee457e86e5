//! The config phase a Klipper MCU gets from us is klippy's, command for
//! command: on every golden case, the commands `mcu_config` writes for the
//! case's printer.cfg equal klippy's (`mcu-commands.txt` up to
//! `finalize_config`), and so does their CRC.

use onechip_app::heaters::McuSetup;
use onechip_app::mcu_config::{ConfigTarget, MAIN, write_config};
use onechip_app::step_pulse;
use onechip_config::Config;
use onechip_planner::machine::Machine;
use onechip_secondary_mcu::connection::config_crc;
use onechip_tests::{golden_adc_max, golden_constant, summary_value};

#[test]
fn config_commands_and_crc_equal_klippys_on_every_golden_case() {
    let cases = onechip_golden::cases();
    assert!(cases.len() >= 15, "golden cases: {cases:?}");
    for case in &cases {
        let text = onechip_golden::config(onechip_golden::config_for(case));
        let config = Config::parse("printer.cfg", &text).expect("config");
        let machine = Machine::from_config(&config).expect("machine");
        let adc_max = golden_adc_max(case);
        let freq = summary_value(case, "clock_freq");
        let setup = McuSetup::new(
            &machine,
            freq,
            adc_max,
            onechip_host::thermal_plant::mcu_sensor(),
            0,
        );
        let pulse = |i: usize| {
            let duration =
                step_pulse::step_pulse_duration(machine.steppers[i].step_pulse_duration, false);
            step_pulse::pulse_ticks(duration, freq)
        };
        let mut ours = Vec::new();
        let main = ConfigTarget {
            mcu: MAIN,
            pwm_max: golden_constant(case, "PWM_MAX"),
            spi_bus: "spi",
        };
        let oids = write_config(&machine, &setup, main, &pulse, &mut |l| {
            ours.push(l.to_string())
        });
        let log = onechip_golden::read_string(format!("{case}/mcu-commands.txt"));
        let klippys: Vec<&str> = log
            .lines()
            .take_while(|l| !l.starts_with("finalize_config"))
            .collect();
        assert_eq!(ours, klippys, "{case}");
        let crc = log
            .lines()
            .find_map(|l| l.strip_prefix("finalize_config crc="))
            .expect("finalize_config");
        assert_eq!(
            config_crc(ours.iter().map(String::as_str)).to_string(),
            crc,
            "{case}"
        );
        assert_eq!(usize::from(oids.count), 16, "{case}");
    }
}
