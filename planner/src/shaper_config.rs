//! The `[input_shaper]` section: which shaper filters each axis, at what
//! frequency and damping, and each shaper's impulses as Klipper defines
//! them. Applying the filter is step generation's work; this reads and
//! checks the settings as Klipper does.

use crate::reader::{Read, Reader};
use onechip_config::Bounds;

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

/// Most impulses of any shaper.
pub const MAX_PULSES: usize = 5;

/// Residual vibration Klipper's extra-insensitive shapers tolerate (1/20).
const VIBRATION_TOLERANCE: f64 = 1.0 / 20.0;

/// A shaper as the filter step generation applies: position(t) =
/// Σ `a[i]` · unshaped_position(t + `t[i]`), with the amplitudes summing to
/// 1 and their weighted mean time 0 (so constant-speed motion is unchanged).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShaperPulses {
    /// Number of impulses in use.
    pub len: usize,
    /// Amplitudes (normalised).
    pub a: [f64; MAX_PULSES],
    /// Time offsets, s, ascending.
    pub t: [f64; MAX_PULSES],
}

impl ShaperPulses {
    /// How far the filter looks ahead of `t`, s (steps may come this much
    /// before a move that drives the axis).
    pub fn lead(&self) -> f64 {
        self.t[self.len - 1].max(0.0)
    }

    /// How far the filter looks behind `t`, s (steps may come this much
    /// after a move that drives the axis).
    pub fn lag(&self) -> f64 {
        (-self.t[0]).max(0.0)
    }
}

impl AxisShaper {
    /// The shaper's impulses (Klipper's definitions, after normalising,
    /// reversing in time and centring).
    pub fn pulses(&self) -> ShaperPulses {
        let (amps, times, n) = self.impulses();
        let sum: f64 = amps[..n].iter().sum();
        let mut p = ShaperPulses {
            len: n,
            a: [0.0; MAX_PULSES],
            t: [0.0; MAX_PULSES],
        };
        for i in 0..n {
            p.a[n - 1 - i] = amps[i] / sum;
            p.t[n - 1 - i] = -times[i];
        }
        let mean: f64 = (0..n).map(|i| p.a[i] * p.t[i]).sum();
        for t in &mut p.t[..n] {
            *t -= mean;
        }
        p
    }

    /// Impulse amplitudes and times (s, from 0) in the textbook orientation.
    fn impulses(&self) -> ([f64; MAX_PULSES], [f64; MAX_PULSES], usize) {
        let zeta = self.damping_ratio;
        let df = crate::math::sqrt(1.0 - zeta * zeta);
        // Damped period, s.
        let t_d = 1.0 / (self.freq * df);
        let k = libm::exp(-zeta * core::f64::consts::PI / df);
        let mut a = [0.0; MAX_PULSES];
        let mut t = [0.0; MAX_PULSES];
        let n = match self.kind {
            ShaperType::Zv => {
                a[..2].copy_from_slice(&[1.0, k]);
                t[..2].copy_from_slice(&[0.0, 0.5 * t_d]);
                2
            }
            ShaperType::Zvd => {
                a[..3].copy_from_slice(&[1.0, 2.0 * k, k * k]);
                t[..3].copy_from_slice(&[0.0, 0.5 * t_d, t_d]);
                3
            }
            ShaperType::Mzv => {
                // Three impulses over 3/4 of the damped period.
                let k = libm::exp(-0.75 * zeta * core::f64::consts::PI / df);
                let edge = 1.0 - core::f64::consts::FRAC_1_SQRT_2;
                let mid = core::f64::consts::SQRT_2 - 1.0;
                a[..3].copy_from_slice(&[edge, mid * k, edge * k * k]);
                t[..3].copy_from_slice(&[0.0, 0.375 * t_d, 0.75 * t_d]);
                3
            }
            ShaperType::Ei => {
                let (v, d) = (VIBRATION_TOLERANCE, zeta);
                let a1 = (0.24968 + 0.24961 * v)
                    + ((0.80008 + 1.23328 * v) + (0.49599 + 3.17316 * v) * d) * d;
                let a3 = (0.25149 + 0.21474 * v)
                    + ((-0.83249 + 1.41498 * v) + (0.85181 - 4.90094 * v) * d) * d;
                let t2 = 0.4999
                    + (((0.46159 + 8.57843 * v) * v)
                        + (((4.26169 - 108.644 * v) * v) + ((1.75601 + 336.989 * v) * v) * d) * d)
                        * d;
                a[..3].copy_from_slice(&[a1, 1.0 - a1 - a3, a3]);
                t[..3].copy_from_slice(&[0.0, t2 * t_d, t_d]);
                3
            }
            ShaperType::TwoHumpEi => expansion(&TWO_HUMP_EI, zeta, self.freq, &mut a, &mut t),
            ShaperType::ThreeHumpEi => expansion(&THREE_HUMP_EI, zeta, self.freq, &mut a, &mut t),
        };
        (a, t, n)
    }
}

/// Multi-hump EI shapers: per impulse, time (in periods of the shaper
/// frequency) and amplitude as cubic polynomials of the damping ratio.
type Expansion<const N: usize> = [([f64; 4], [f64; 4]); N];

const TWO_HUMP_EI: Expansion<4> = [
    ([0.0, 0.0, 0.0, 0.0], [0.16054, 0.76699, 2.26560, -1.22750]),
    (
        [0.49890, 0.16270, -0.54262, 6.16180],
        [0.33911, 0.45081, -2.58080, 1.73650],
    ),
    (
        [0.99748, 0.18382, -1.58270, 8.17120],
        [0.34089, -0.61533, -0.68765, 0.42261],
    ),
    (
        [1.49920, -0.09297, -0.28338, 1.85710],
        [0.15997, -0.60246, 1.00280, -0.93145],
    ),
];

const THREE_HUMP_EI: Expansion<5> = [
    ([0.0, 0.0, 0.0, 0.0], [0.11275, 0.76632, 3.29160, -1.44380]),
    (
        [0.49974, 0.23834, 0.44559, 12.4720],
        [0.23698, 0.61164, -2.57850, 4.85220],
    ),
    (
        [0.99849, 0.29808, -2.36460, 23.3990],
        [0.30008, -0.19062, -2.14560, 0.13744],
    ),
    (
        [1.49870, 0.10306, -2.01390, 17.0320],
        [0.23775, -0.73297, 0.46885, -2.08650],
    ),
    (
        [1.99960, -0.28231, 0.61536, 5.40450],
        [0.11244, -0.45439, 0.96382, -1.46000],
    ),
];

/// Evaluates an [`Expansion`] at damping `zeta` for frequency `freq` (Hz)
/// into `a` and `t` (s); returns the number of impulses.
fn expansion<const N: usize>(
    table: &Expansion<N>,
    zeta: f64,
    freq: f64,
    a: &mut [f64; MAX_PULSES],
    t: &mut [f64; MAX_PULSES],
) -> usize {
    let poly = |c: &[f64; 4]| c[0] + zeta * (c[1] + zeta * (c[2] + zeta * c[3]));
    for (i, (tc, ac)) in table.iter().enumerate() {
        t[i] = poly(tc) / freq;
        a[i] = poly(ac);
    }
    N
}

/// Reads `[input_shaper]`.
// Out of line: see `Machine::from_config_in`.
#[inline(never)]
pub(crate) fn read(section: &Reader<'_, '_, '_>) -> Read<InputShaperConfig> {
    let names: [&str; 6] = ShaperType::NAMES.map(|(n, _)| n);
    let default_type = section.get_choice("shaper_type", &names, Some("mzv"))?;
    let mut axes = [None; 2];
    for (slot, (type_key, freq_key, damping_key)) in axes.iter_mut().zip([
        ("shaper_type_x", "shaper_freq_x", "damping_ratio_x"),
        ("shaper_type_y", "shaper_freq_y", "damping_ratio_y"),
    ]) {
        let name = section.get_choice(type_key, &names, Some(default_type))?;
        let freq = section.float(freq_key, 0.0, Bounds::NON_NEGATIVE)?;
        let damping_ratio = section.float(damping_key, 0.1, Bounds::UNIT)?;
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
    use crate::reader::Errors;
    use onechip_config::{Config, ConfigError};

    /// `config`'s `[input_shaper]`.
    fn input_shaper<'c>(config: &'c Config<'_>) -> Result<InputShaperConfig, ConfigError<'c>> {
        let section = config.require("input_shaper").expect("present");
        Errors::run(|errors| read(&Reader::new(section, errors)))
    }

    #[test]
    fn reads_types_frequencies_and_default_damping() {
        let text = "[input_shaper]\nshaper_type_x: mzv\nshaper_freq_x: 40\nshaper_type_y: ei\nshaper_freq_y: 35\n";
        let config = Config::parse("p.cfg", text).expect("valid");
        let shaper = input_shaper(&config).expect("valid");
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
            let result = input_shaper(&config);
            assert_eq!(result.is_ok(), ok, "{text}");
            if let Ok(s) = result {
                assert_eq!(s, InputShaperConfig::default());
            }
        }
    }

    #[test]
    fn pulses_are_normalised_centred_and_cancel_their_frequency() {
        for kind in ShaperType::NAMES.map(|(_, t)| t) {
            let shaper = AxisShaper {
                kind,
                freq: 40.0,
                damping_ratio: 0.1,
            };
            let p = shaper.pulses();
            let (a, t) = (&p.a[..p.len], &p.t[..p.len]);
            let sum: f64 = a.iter().sum();
            let mean: f64 = a.iter().zip(t).map(|(a, t)| a * t).sum();
            assert!((sum - 1.0).abs() < 1e-12, "{kind:?} sum {sum}");
            assert!(mean.abs() < 1e-12, "{kind:?} mean {mean}");
            assert!(t.windows(2).all(|w| w[0] < w[1]), "{kind:?} {t:?}");
            // Residual vibration of a damped 40 Hz oscillator after the
            // impulses (the earliest offset is the last impulse in
            // textbook time): every shaper leaves at most ~5 %.
            let df = crate::math::sqrt(1.0 - 0.01);
            let w = 2.0 * core::f64::consts::PI * 40.0 * df;
            let (mut c, mut s) = (0.0, 0.0);
            for (a, t) in a.iter().zip(t) {
                let decay = libm::exp(-0.1 * 2.0 * core::f64::consts::PI * 40.0 * (t - p.t[0]));
                c += a * decay * libm::cos(w * t);
                s += a * decay * libm::sin(w * t);
            }
            let residual = crate::math::sqrt(c * c + s * s);
            assert!(residual < 0.051, "{kind:?} residual {residual}");
        }
    }
}
