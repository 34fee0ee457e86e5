//! Thermistors behind a pullup resistor, as Klipper reads them: the
//! built-in types (`sensor_type: EPCOS 100K B57560G104F`, ...) and custom
//! `[thermistor NAME]` sections.
//!
//! The thermistor and the pullup form a voltage divider to the ADC's
//! reference, so an ADC reading `adc` (fraction of full scale) means a
//! resistance `R = pullup · adc / (1 − adc)` (less `inline_resistor`).
//! Resistance and temperature follow the Steinhart-Hart equation
//! `1/T = c1 + c2 ln R + c3 (ln R)³` (T in kelvin), whose coefficients
//! come from three (°C, Ω) points of a data sheet, or from one point and a
//! beta (`c3 = 0`).

use crate::reader::{Read, Reader};
use crate::temperature_sensor::position;
use onechip_config::Bounds;

/// 0 °C in kelvin.
pub const ZERO_CELSIUS: f64 = 273.15;

/// How a thermistor's curve is given.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Curve {
    /// Three (°C, Ω) points, in rising temperature.
    Points([(f64, f64); 3]),
    /// One (°C, Ω) point and the beta, K.
    Beta((f64, f64), f64),
}

/// The thermistors Klipper knows by `sensor_type` name (Klipper's
/// `temperature_sensors.cfg`), in [`CURVES`]' order.
static NAMES: [&str; 9] = [
    "EPCOS 100K B57560G104F",
    "ATC Semitec 104GT-2",
    "ATC Semitec 104NT-4-R025H42G",
    "Generic 3950",
    "SliceEngineering 450",
    "TDK NTCG104LH104JT1",
    "Honeywell 100K 135-104LAG-J01",
    "NTC 100K beta 3950",
    "NTC 100K MGB18-104F39050L32",
];

/// The curves of [`NAMES`]: the points of their data sheets.
static CURVES: [Curve; 9] = [
    Curve::Points([(25.0, 100_000.0), (150.0, 1641.9), (250.0, 226.15)]),
    Curve::Points([(20.0, 126_800.0), (150.0, 1360.0), (300.0, 80.65)]),
    Curve::Points([(25.0, 100_000.0), (160.0, 1074.0), (300.0, 82.78)]),
    Curve::Points([(25.0, 100_000.0), (150.0, 1770.0), (250.0, 230.0)]),
    Curve::Points([(25.0, 500_000.0), (200.0, 3734.0), (400.0, 240.0)]),
    Curve::Points([(25.0, 100_000.0), (50.0, 31_230.0), (125.0, 2066.0)]),
    Curve::Beta((25.0, 100_000.0), 3974.0),
    Curve::Beta((25.0, 100_000.0), 3950.0),
    Curve::Beta((25.0, 100_000.0), 4100.0),
];

/// The curve of the built-in thermistor type `name`.
pub fn built_in(name: &str) -> Option<Curve> {
    position(&NAMES, name).and_then(|i| CURVES.get(i).copied())
}

/// A thermistor behind a pullup resistor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Thermistor {
    c1: f64,
    c2: f64,
    c3: f64,
    /// pullup_resistor, Ω.
    pullup: f64,
    /// inline_resistor, Ω.
    inline: f64,
}

impl Thermistor {
    /// The thermistor of `curve` behind `pullup` Ω, with `inline` Ω in
    /// series.
    pub fn new(curve: Curve, pullup: f64, inline: f64) -> Self {
        match curve {
            Curve::Points(points) => Self::from_points(points, pullup, inline),
            Curve::Beta(point, beta) => Self::from_beta(point, beta, pullup, inline),
        }
    }

    /// The built-in type `name` behind `pullup` and `inline` Ω.
    pub fn named(name: &str, pullup: f64, inline: f64) -> Option<Self> {
        built_in(name).map(|curve| Self::new(curve, pullup, inline))
    }

    /// Steinhart-Hart through three (°C, Ω) points; if they need a
    /// negative cubic term, the beta of the outer two instead (as
    /// Klipper).
    fn from_points(points: [(f64, f64); 3], pullup: f64, inline: f64) -> Self {
        let [(t1, r1), (t2, r2), (t3, r3)] = points;
        let inv = |t: f64| 1.0 / (t + ZERO_CELSIUS);
        let (l1, l2, l3) = (libm::log(r1), libm::log(r2), libm::log(r3));
        let (i12, i13) = (inv(t1) - inv(t2), inv(t1) - inv(t3));
        let (l12, l13) = (l1 - l2, l1 - l3);
        let (c12, c13) = (l1 * l1 * l1 - l2 * l2 * l2, l1 * l1 * l1 - l3 * l3 * l3);
        let c3 = (i12 - i13 * l12 / l13) / (c12 - c13 * l12 / l13);
        if c3 <= 0.0 {
            return Self::from_beta((t1, r1), l13 / i13, pullup, inline);
        }
        let c2 = (i12 - c3 * c12) / l12;
        Self {
            c1: inv(t1) - c2 * l1 - c3 * l1 * l1 * l1,
            c2,
            c3,
            pullup,
            inline,
        }
    }

    /// Beta equation through one (°C, Ω) point.
    fn from_beta((t1, r1): (f64, f64), beta: f64, pullup: f64, inline: f64) -> Self {
        let c2 = 1.0 / beta;
        Self {
            c1: 1.0 / (t1 + ZERO_CELSIUS) - c2 * libm::log(r1),
            c2,
            c3: 0.0,
            pullup,
            inline,
        }
    }

    /// True if the curve's coefficients are numbers (three points with two
    /// temperatures or resistances alike give none).
    pub fn is_valid(&self) -> bool {
        self.c1.is_finite() && self.c2.is_finite() && self.c3.is_finite()
    }

    /// Temperature at ADC reading `adc` (fraction of full scale), °C.
    pub fn temperature(&self, adc: f64) -> f64 {
        let adc = crate::math::clamp(adc, 0.00001, 0.99999);
        let r = self.pullup * adc / (1.0 - adc);
        let ln_r = libm::log(r - self.inline);
        1.0 / (self.c1 + self.c2 * ln_r + self.c3 * ln_r * ln_r * ln_r) - ZERO_CELSIUS
    }

    /// ADC reading (fraction of full scale) at temperature `t`, °C.
    pub fn adc(&self, t: f64) -> f64 {
        if t <= -ZERO_CELSIUS {
            return 1.0;
        }
        let inv_t = 1.0 / (t + ZERO_CELSIUS);
        let ln_r = if self.c3 != 0.0 {
            // The cubic c3 x^3 + c2 x + (c1 - 1/T) = 0, by Cardano.
            let y = (self.c1 - inv_t) / (2.0 * self.c3);
            let x = crate::math::sqrt(libm::pow(self.c2 / (3.0 * self.c3), 3.0) + y * y);
            libm::cbrt(x - y) - libm::cbrt(x + y)
        } else {
            (inv_t - self.c1) / self.c2
        };
        let r = libm::exp(ln_r) + self.inline;
        r / (self.pullup + r)
    }
}

/// The options of a heater section that a thermistor reads, with
/// Klipper's defaults: `pullup_resistor` and `inline_resistor`, Ω. Klipper
/// also reads `adc_ref`, `pullup_ref` and `vo_ref` (Recore's amplified
/// input); a `vo_ref` above 0 selects that circuit, which onechip does not
/// support.
pub(crate) fn read_resistors(section: &Reader<'_, '_, '_>) -> Read<(f64, f64)> {
    let pullup = section.float("pullup_resistor", 4700.0, Bounds::POSITIVE)?;
    let inline = section.float("inline_resistor", 0.0, Bounds::NON_NEGATIVE)?;
    section.float("adc_ref", 3.3, Bounds::NONE)?;
    section.float("pullup_ref", 3.2, Bounds::NONE)?;
    if section.float("vo_ref", 0.0, Bounds::NONE)? > 0.0 {
        return Err(section.error_for(
            "vo_ref",
            "selects Recore's amplified input, which onechip does not support yet",
        ));
    }
    Ok((pullup, inline))
}

/// Reads the point `temperature` (°C), `resistance` (Ω) of a
/// `[thermistor NAME]` section, with Klipper's bounds (kept out of line:
/// unrolled, the three points' reading would take three times the flash).
#[inline(never)]
fn read_point<'c>(
    section: &Reader<'_, 'c, '_>,
    temperature: &'c str,
    resistance: &'c str,
) -> Read<(f64, f64)> {
    let celsius = Bounds {
        minval: Some(-ZERO_CELSIUS),
        ..Bounds::NONE
    };
    Ok((
        section.required_float(temperature, celsius)?,
        section.required_float(resistance, Bounds::NON_NEGATIVE)?,
    ))
}

/// Reads a `[thermistor NAME]` section: `temperature1`, `resistance1` and
/// `beta`, or three `temperatureN`/`resistanceN` points (any order), with
/// Klipper's bounds.
#[inline(never)]
pub(crate) fn read_section(section: &Reader<'_, '_, '_>) -> Read<Curve> {
    const NAMES: [(&str, &str); 3] = [
        ("temperature1", "resistance1"),
        ("temperature2", "resistance2"),
        ("temperature3", "resistance3"),
    ];
    let mut points = [(0.0, 0.0); 3];
    let count = if section.get_opt("beta").is_some() {
        1
    } else {
        3
    };
    for ((t, r), point) in NAMES.iter().zip(&mut points).take(count) {
        *point = read_point(section, t, r)?;
    }
    let curve = match section.get_float_opt("beta", Bounds::POSITIVE)? {
        Some(beta) => Curve::Beta(points[0], beta),
        None => {
            // Klipper sorts the points by temperature (then resistance:
            // two at one temperature define no curve anyway).
            for i in 1..3 {
                let mut j = i;
                while j > 0 && points[j - 1].0 > points[j].0 {
                    points.swap(j - 1, j);
                    j -= 1;
                }
            }
            Curve::Points(points)
        }
    };
    if !Thermistor::new(curve, 4700.0, 0.0).is_valid() {
        return Err(section.error_for(
            "temperature1",
            "and the other points define no curve (a resistance of 0, or two points alike)",
        ));
    }
    Ok(curve)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The ADC reading of `ohm` behind a 4.7 kΩ pullup (the divider
    /// formula Klipper's `calc_adc` ends with).
    fn adc(ohm: f64) -> f64 {
        ohm / (ohm + 4700.0)
    }

    #[test]
    fn every_built_in_thermistor_passes_through_its_data_sheet_points() {
        for (name, curve) in NAMES.iter().zip(CURVES) {
            let t = Thermistor::named(name, 4700.0, 0.0).expect("built in");
            let points = match curve {
                Curve::Points(p) => p,
                Curve::Beta(p, _) => [p; 3],
            };
            for (celsius, ohm) in points {
                let reading = adc(ohm);
                assert!((t.temperature(reading) - celsius).abs() < 1e-9, "{name}");
                assert!((t.adc(celsius) - reading).abs() < 1e-12, "{name}");
            }
            // The two conversions invert each other.
            for celsius in [0.0, 20.0, 60.0, 110.0, 200.0, 280.0] {
                let back = t.temperature(t.adc(celsius));
                assert!((back - celsius).abs() < 1e-6, "{name} {celsius}");
            }
        }
        assert_eq!(Thermistor::named("PT1000", 4700.0, 0.0), None);
    }

    #[test]
    fn temperatures_between_the_points_are_klippers() {
        // Expected values from Klipper's formulas: R = 4700 adc / (1 - adc),
        // then Steinhart-Hart with the coefficients solved from the three
        // points (Gaussian elimination, in Python), or
        // 1/T = 1/T1 + ln(R/R1)/beta.
        let cases = [
            ("EPCOS 100K B57560G104F", 0.5, 110.14689109907766),
            ("EPCOS 100K B57560G104F", 0.05, 244.54075207050084),
            ("ATC Semitec 104GT-2", 0.1, 191.65772039633237),
            ("Generic 3950", 0.2, 167.31040823904584),
            ("SliceEngineering 450", 0.02, 506.2381462575538),
            ("NTC 100K beta 3950", 0.5, 114.45613240847592),
            ("Honeywell 100K 135-104LAG-J01", 0.3, 148.5412828755729),
        ];
        for (name, reading, celsius) in cases {
            let t = Thermistor::named(name, 4700.0, 0.0).expect("built in");
            let got = t.temperature(reading);
            assert!((got - celsius).abs() < 1e-6, "{name} at {reading}: {got}");
        }
    }

    #[test]
    fn an_inline_resistor_is_taken_off_the_measured_resistance() {
        let t = Thermistor::named("Generic 3950", 4700.0, 100.0).expect("built in");
        // 1770 Ω of thermistor (150 °C) plus 100 Ω in line.
        assert!((t.temperature(adc(1870.0)) - 150.0).abs() < 1e-9);
        assert!((t.adc(150.0) - adc(1870.0)).abs() < 1e-12);
    }

    #[test]
    fn three_points_needing_a_negative_cubic_term_fall_back_to_their_beta() {
        // printer-robo3d-r2's NTCS0603E3104FXT: its points need c3 < 0, so
        // Klipper uses the beta of the outer two points instead.
        let points = [(25.0, 100_000.0), (50.0, 29_536.0), (125.0, 1908.0)];
        let t = Thermistor::new(Curve::Points(points), 4700.0, 0.0);
        let beta = libm::log(100_000.0 / 1908.0) / (1.0 / 298.15 - 1.0 / 398.15);
        let b = Thermistor::new(Curve::Beta((25.0, 100_000.0), beta), 4700.0, 0.0);
        assert_eq!(t.c3, 0.0);
        assert!((t.temperature(0.3) - b.temperature(0.3)).abs() < 1e-9);
        assert!((t.temperature(1908.0 / 6608.0) - 125.0).abs() < 1e-9);
    }
}
