//! End-to-end tests of the host build live in `tests/`; the golden data
//! they read comes from `onechip-golden`, re-exported here.

pub mod noisy_link;
pub mod peers;
pub mod qemu;
pub mod sd_folder;

pub use onechip_golden::{golden_dir, summary_value};

/// The ADC's full scale (`ADC_MAX`) of the MCU golden case `case` ran on,
/// from its dictionary.
///
/// # Panics
///
/// If the dictionary has no `ADC_MAX` constant of 16 bits.
pub fn golden_adc_max(case: &str) -> u16 {
    u16::try_from(golden_constant(case, "ADC_MAX")).expect("ADC_MAX")
}

/// The integer constant `name` of the MCU golden case `case` ran on, from
/// its dictionary.
///
/// # Panics
///
/// If the dictionary has no such constant.
pub fn golden_constant(case: &str, name: &str) -> u32 {
    let dict = onechip_golden::dict(onechip_golden::dict_for(case));
    dict.split(&format!("\"{name}\":"))
        .nth(1)
        .and_then(|r| r.split(|c: char| !c.is_ascii_digit()).next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{name} in {case}'s dictionary"))
}

/// Checks a run that heated the hot end to 200 °C with M109 and reported
/// M105 (`name` in the messages): no error or shutdown; M109 waited until
/// the firmware measured 200 °C, the simulated hot end really is there
/// (within a reading or so), and M105 says so.
///
/// # Panics
///
/// If any of that does not hold.
pub fn assert_held_200(s: &onechip_host::Summary, name: &str) {
    assert_eq!(
        (s.errors.len(), s.shutdown.as_ref()),
        (0, None),
        "{name}: {s}"
    );
    let hot_end = &s.heaters[0];
    assert!(s.heat_wait > 10.0, "{name}: {}", s.heat_wait);
    assert!(
        (hot_end.temperature - 200.0).abs() < 3.0,
        "{name}: measured {hot_end:?}"
    );
    assert!(
        (195.0..210.0).contains(&hot_end.peak),
        "{name}: really reached {hot_end:?}"
    );
    let (_, report) = s.temperatures.last().expect("M105");
    assert!(
        report.starts_with("T:19") || report.starts_with("T:20"),
        "{name}: {report}"
    );
}
