//! End-to-end tests of the host build live in `tests/`; the golden data
//! they read comes from `onechip-golden`, re-exported here.

pub mod noisy_link;
pub mod peers;

pub use onechip_golden::{golden_dir, summary_value};

/// The ADC's full scale (`ADC_MAX`) of the MCU golden case `case` ran on,
/// from its dictionary.
///
/// # Panics
///
/// If the dictionary has no `ADC_MAX` constant.
pub fn golden_adc_max(case: &str) -> u16 {
    let dict = onechip_golden::dict(onechip_golden::dict_for(case));
    dict.split("\"ADC_MAX\":")
        .nth(1)
        .and_then(|r| r.split(|c: char| !c.is_ascii_digit()).next())
        .and_then(|n| n.parse().ok())
        .expect("ADC_MAX")
}
