//! The `[input_shaper]` section: which shaper filters each axis, at what
//! frequency and damping. Applying the filters is step generation's work
//! (issue #4); this reads and checks the settings as Klipper does.

use crate::config::{Bounds, ConfigError, Section};

/// The input shapers Klipper defines.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ShaperType {
    /// Zero vibration.
    Zv,
    /// Modified zero vibration.
    Mzv,
    /// Zero vibration and derivative.
    Zvd,
    /// Extra insensitive.
    Ei,
    /// Two-hump extra insensitive.
    TwoHumpEi,
    /// Three-hump extra insensitive.
    ThreeHumpEi,
}

impl ShaperType {
    const NAMES: [(&'static str, Self); 6] = [
        ("zv", Self::Zv),
        ("mzv", Self::Mzv),
        ("zvd", Self::Zvd),
        ("ei", Self::Ei),
        ("2hump_ei", Self::TwoHumpEi),
        ("3hump_ei", Self::ThreeHumpEi),
    ];

    /// The name used in printer.cfg.
    pub fn name(self) -> &'static str {
        Self::NAMES
            .iter()
            .find(|(_, t)| *t == self)
            .map_or("", |(n, _)| n)
    }
}

/// One axis' shaper.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisShaper {
    /// The filter.
    pub kind: ShaperType,
    /// Resonance frequency it targets, Hz.
    pub freq: f64,
    /// Damping ratio (0..1).
    pub damping_ratio: f64,
}

/// Shapers for X and Y (None: that axis is not shaped).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct InputShaperConfig {
    /// X axis.
    pub x: Option<AxisShaper>,
    /// Y axis.
    pub y: Option<AxisShaper>,
}

/// Reads `[input_shaper]`.
pub fn read<'c>(section: &Section<'c, '_>) -> Result<InputShaperConfig, ConfigError<'c>> {
    let names: [&str; 6] = ShaperType::NAMES.map(|(n, _)| n);
    let default_type = section.get_choice("shaper_type", &names, Some("mzv"))?;
    let mut axes = [None; 2];
    for (slot, (type_key, freq_key, damping_key)) in axes.iter_mut().zip([
        ("shaper_type_x", "shaper_freq_x", "damping_ratio_x"),
        ("shaper_type_y", "shaper_freq_y", "damping_ratio_y"),
    ]) {
        let name = section.get_choice(type_key, &names, Some(default_type))?;
        let freq = section.get_float(freq_key, Some(0.0), Bounds::NON_NEGATIVE)?;
        let damping_ratio = section.get_float(
            damping_key,
            Some(0.1),
            Bounds {
                minval: Some(0.0),
                maxval: Some(1.0),
                ..Bounds::NONE
            },
        )?;
        let kind = ShaperType::NAMES
            .iter()
            .find(|(n, _)| *n == name)
            .map_or(ShaperType::Mzv, |(_, t)| *t);
        *slot = (freq > 0.0).then_some(AxisShaper {
            kind,
            freq,
            damping_ratio,
        });
    }
    Ok(InputShaperConfig {
        x: axes[0],
        y: axes[1],
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;

    #[test]
    fn reads_types_frequencies_and_default_damping() {
        let text = "[input_shaper]\nshaper_type_x: mzv\nshaper_freq_x: 40\nshaper_type_y: ei\nshaper_freq_y: 35\n";
        let config = Config::parse("p.cfg", text).expect("valid");
        let shaper = read(&config.require("input_shaper").expect("present")).expect("valid");
        assert_eq!(
            shaper.x,
            Some(AxisShaper {
                kind: ShaperType::Mzv,
                freq: 40.0,
                damping_ratio: 0.1
            })
        );
        assert_eq!(
            shaper.y.map(|s| (s.kind.name(), s.freq)),
            Some(("ei", 35.0))
        );
        assert!(config.check_unused().is_ok());
    }

    #[test]
    fn bad_settings_are_errors_and_zero_frequency_means_off() {
        for (text, ok) in [
            ("[input_shaper]\nshaper_type: wobble\n", false),
            ("[input_shaper]\nshaper_freq_x: -1\n", false),
            ("[input_shaper]\ndamping_ratio_y: 2\n", false),
            ("[input_shaper]\nshaper_freq_x: 0\n", true),
        ] {
            let config = Config::parse("p.cfg", text).expect("syntax");
            let result = read(&config.require("input_shaper").expect("present"));
            assert_eq!(result.is_ok(), ok, "{text}");
            if let Ok(s) = result {
                assert_eq!(s, InputShaperConfig::default());
            }
        }
    }
}
