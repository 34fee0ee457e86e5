//! The heater's MCU configuration from each golden printer.cfg is what
//! klippy sent (`mcu-commands.txt`): the heater pin's software PWM cycle and
//! max_duration, and the thermistor's sampling and ADC range, which comes
//! from the thermistor's curve at min_temp and max_temp.

use onechip_app::heaters::McuSetup;
use onechip_config::Config;
use onechip_planner::machine::Machine;
use onechip_sched::outputs::OutputKind;
use onechip_tests::{golden_adc_max, summary_value};
use std::collections::HashMap;

/// The `key=value` fields of the first line of `commands` starting with
/// `name` and having all of `with`.
fn command(commands: &str, name: &str, with: &[(&str, &str)]) -> HashMap<String, String> {
    commands
        .lines()
        .filter_map(|l| l.strip_prefix(name).filter(|r| r.starts_with(' ')))
        .map(|rest| {
            rest.split_whitespace()
                .filter_map(|kv| kv.split_once('='))
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect::<HashMap<_, _>>()
        })
        .find(|fields| {
            with.iter()
                .all(|(k, v)| fields.get(*k).map(String::as_str) == Some(*v))
        })
        .unwrap_or_else(|| panic!("no {name} with {with:?}"))
}

fn number(fields: &HashMap<String, String>, key: &str) -> u64 {
    fields[key].parse().expect("number")
}

#[test]
fn heater_and_thermistor_configuration_matches_klippy() {
    // One extrusion case for each of the six golden configs.
    let cases = [
        "cart_extrude",
        "corexy_extrude",
        "delta_extrude",
        "shaper_extrude",
        "avr_cart_extrude",
        "h723_cart_extrude",
    ];
    for case in cases {
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
        let commands = onechip_golden::read_string(format!("{case}/mcu-commands.txt"));

        let (pin, heater) = setup.outputs[0];
        let out = command(&commands, "config_digital_out", &[("pin", pin)]);
        let oid = out["oid"].as_str();
        let cycle = command(&commands, "set_digital_out_pwm_cycle", &[("oid", oid)]);
        assert_eq!(
            heater.kind,
            OutputKind::Digital {
                cycle_ticks: number(&cycle, "cycle_ticks") as u32
            },
            "{case}"
        );
        assert_eq!(
            u64::from(heater.max_duration),
            number(&out, "max_duration"),
            "{case}"
        );
        assert_eq!(
            u64::from(heater.default),
            number(&out, "default_value"),
            "{case}"
        );

        let (sensor, query) = setup.inputs[0];
        let query = *query.adc().expect("a thermistor's ADC query");
        let adc = command(&commands, "config_analog_in", &[("pin", sensor)]);
        let q = command(
            &commands,
            "query_analog_in",
            &[("oid", adc["oid"].as_str())],
        );
        let ours = [
            u64::from(query.sample_ticks),
            u64::from(query.sample_count),
            u64::from(query.rest_ticks),
            u64::from(query.min),
            u64::from(query.max),
            u64::from(query.range_check_count),
        ];
        let klippy = [
            "sample_ticks",
            "sample_count",
            "rest_ticks",
            "min_value",
            "max_value",
            "range_check_count",
        ]
        .map(|k| number(&q, k));
        assert_eq!(ours, klippy, "{case}");
    }
}
