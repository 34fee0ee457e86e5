//! Motor current (A rms) to a driver's current bits, with Klipper's
//! formulas and rounding (`int(x + .5)`), operation for operation so the
//! doubles round alike.
//!
//! - TMC2130, TMC2208, TMC2209: a 5-bit current scale (IRUN/IHOLD) of a
//!   full scale set by the sense resistor (plus 20 mΩ of internal
//!   resistance) and the sense voltage: 0.32 V, or 0.18 V with `vsense`.
//! - TMC2660: the same with 0.310 V / 0.165 V and no added resistance; one
//!   current (CS).
//! - TMC5160: GLOBALSCALER (32..255, 0 meaning 256) scales a 0.325 V full
//!   scale, then the 5-bit IRUN/IHOLD.
//! - TMC2240: the full scale is set by the reference resistor (`rref`) and
//!   `current_range`; then GLOBALSCALER and IRUN/IHOLD.

/// √2, correctly rounded: the bits of Python's `math.sqrt(2)` (Klipper's
/// formulas take the square root of 2 each time).
const SQRT_2: f64 = core::f64::consts::SQRT_2;

/// How a driver turns current into bits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CurrentScale {
    /// TMC2130/2208/2209 (`offset` 0.020 Ω, 0.32/0.18 V) and TMC2660
    /// (`offset` 0, 0.310/0.165 V).
    Vsense {
        /// The sense resistor plus `offset`, Ω.
        resistance: f64,
        /// Full-scale sense voltage without vsense, V.
        vref_high: f64,
        /// Full-scale sense voltage with vsense, V.
        vref_low: f64,
    },
    /// TMC5160: sense resistor, Ω.
    GlobalScaler {
        /// The sense resistor, Ω.
        sense_resistor: f64,
    },
    /// TMC2240: reference resistor, Ω, and the current range chosen
    /// for the configured run current (kept when the current changes, as
    /// Klipper keeps it).
    Rref {
        /// `rref`, Ω (12 kΩ to 60 kΩ).
        rref: f64,
        /// current_range (0..=3).
        range: u8,
    },
}

/// The TMC5160's full-scale sense voltage, V.
const VREF_5160: f64 = 0.325;
/// The TMC2240's full-scale constants (KIFS) per current_range, A·Ω.
const KIFS: [f64; 4] = [11750.0, 24000.0, 36000.0, 36000.0];

/// Register bits for a pair of currents.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CurrentBits {
    /// IRUN (CS on the TMC2660).
    pub irun: u8,
    /// IHOLD (unused on the TMC2660).
    pub ihold: u8,
    /// vsense (Vsense drivers).
    pub vsense: bool,
    /// GLOBALSCALER (0 meaning 256; TMC5160, TMC2240).
    pub globalscaler: u16,
    /// current_range (TMC2240).
    pub current_range: u8,
}

/// `int(x + .5) - 1` clamped to 0..=31 (Klipper's TMC2130 and TMC2660
/// rounding): `x` is the current over one step of the scale.
fn cs_bits(x: f64) -> u8 {
    ((x + 0.5) as i64 - 1).clamp(0, 31) as u8
}

/// `int(x - 1. + .5)` clamped to 0..=31 (Klipper's TMC5160 and TMC2240
/// rounding, which differs from [`cs_bits`] in the last bit of a few
/// doubles).
fn cs_bits_late(x: f64) -> u8 {
    ((x - 1.0 + 0.5) as i64).clamp(0, 31) as u8
}

impl CurrentScale {
    /// Vsense drivers: the bits for `current` A.
    fn vsense_bits(resistance: f64, vref: f64, current: f64) -> u8 {
        cs_bits(32.0 * resistance * current * SQRT_2 / vref)
    }

    /// Vsense drivers: the current of `cs` bits, A.
    fn vsense_current(resistance: f64, vref: f64, cs: u8) -> f64 {
        f64::from(cs + 1) * vref / (32.0 * resistance * SQRT_2)
    }

    /// TMC2240: the full scale of `range`, A rms.
    pub fn ifs_rms(rref: f64, range: u8) -> f64 {
        KIFS[usize::from(range.min(3))] / rref / SQRT_2
    }

    /// TMC2240: the smallest current_range whose full scale takes `run`
    /// A (3 if none does).
    pub fn range_for(rref: f64, run: f64) -> u8 {
        (0..4u8)
            .find(|&r| run <= Self::ifs_rms(rref, r))
            .unwrap_or(3)
    }

    /// Bits for `run` A and `hold` A (hold is capped at run).
    pub fn bits(&self, run: f64, hold: f64) -> CurrentBits {
        let hold = hold.min(run);
        let mut out = CurrentBits {
            irun: 0,
            ihold: 0,
            vsense: false,
            globalscaler: 0,
            current_range: match *self {
                Self::Rref { range, .. } => range,
                _ => 0,
            },
        };
        match *self {
            Self::Vsense {
                resistance,
                vref_high,
                vref_low,
            } => {
                // vsense (the finer scale) unless run current needs the
                // coarse one and is nearer to what it gives.
                let mut vsense = true;
                let mut irun = Self::vsense_bits(resistance, vref_low, run);
                if irun == 31 {
                    let cur = Self::vsense_current(resistance, vref_low, irun);
                    if cur < run {
                        let irun2 = Self::vsense_bits(resistance, vref_high, run);
                        let cur2 = Self::vsense_current(resistance, vref_high, irun2);
                        if (run - cur2).abs() < (run - cur).abs() {
                            vsense = false;
                            irun = irun2;
                        }
                    }
                }
                let vref = if vsense { vref_low } else { vref_high };
                out.vsense = vsense;
                out.irun = irun;
                out.ihold = Self::vsense_bits(resistance, vref, hold);
            }
            Self::GlobalScaler { sense_resistor } => {
                let gs = scaler(run * 256.0 * SQRT_2 * sense_resistor / VREF_5160);
                let scale = f64::from(if gs == 0 { 256 } else { gs }) * VREF_5160;
                let bits =
                    |c: f64| cs_bits_late(c * 256.0 * 32.0 * SQRT_2 * sense_resistor / scale);
                out.globalscaler = gs;
                out.irun = bits(run);
                out.ihold = bits(hold);
            }
            Self::Rref { rref, range } => {
                let ifs = Self::ifs_rms(rref, range);
                let gs = scaler(run * 256.0 / ifs);
                let scale = f64::from(if gs == 0 { 256 } else { gs }) * ifs;
                let bits = |c: f64| cs_bits_late(c * 256.0 * 32.0 / scale);
                out.current_range = range;
                out.globalscaler = gs;
                out.irun = bits(run);
                out.ihold = bits(hold);
            }
        }
        out
    }

    /// The current `cs` bits give with `vsense` / `globalscaler` /
    /// `current_range` as in `bits`, A rms.
    pub fn current(&self, cs: u8, bits: &CurrentBits) -> f64 {
        let gs = f64::from(if bits.globalscaler == 0 {
            256
        } else {
            bits.globalscaler
        });
        match *self {
            Self::Vsense {
                resistance,
                vref_high,
                vref_low,
            } => {
                let vref = if bits.vsense { vref_low } else { vref_high };
                Self::vsense_current(resistance, vref, cs)
            }
            Self::GlobalScaler { sense_resistor } => {
                gs * f64::from(cs + 1) * VREF_5160 / (256.0 * 32.0 * SQRT_2 * sense_resistor)
            }
            Self::Rref { rref, range } => {
                gs * f64::from(cs + 1) * Self::ifs_rms(rref, range) / (256.0 * 32.0)
            }
        }
    }
}

/// GLOBALSCALER from its unrounded value: rounded, at least 32, and 0
/// (meaning 256) from 256 up.
fn scaler(x: f64) -> u16 {
    let gs = ((x + 0.5) as i64).max(32);
    if gs >= 256 { 0 } else { gs as u16 }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TMC2209: CurrentScale = CurrentScale::Vsense {
        resistance: 0.110 + 0.020,
        vref_high: 0.32,
        vref_low: 0.18,
    };

    #[test]
    fn sqrt_2_is_the_correctly_rounded_root() {
        assert_eq!(SQRT_2.to_bits(), 2f64.sqrt().to_bits());
    }

    #[test]
    fn vsense_scale_rounds_as_klipper() {
        // 0.8 A on 0.110 Ω: 32 * 0.13 * 0.8 * 1.41421356 / 0.18 = 26.15
        // → int(26.65) - 1 = 25, with vsense.
        let b = TMC2209.bits(0.8, 0.8);
        assert_eq!((b.irun, b.ihold, b.vsense), (25, 25, true));
        // 1.2 A: 39.2 on the fine scale (> 31): coarse, 22.06 → 21.
        let b = TMC2209.bits(1.2, 0.6);
        assert_eq!((b.irun, b.vsense), (21, false));
        // 0.6 A on the coarse scale: 11.03 → int(11.53) - 1 = 10.
        assert_eq!(b.ihold, 10);
        // The current given back: (21 + 1) * 0.32 / (32 * 0.13 * √2).
        let back = TMC2209.current(21, &b);
        assert!((back - 22.0 * 0.32 / (32.0 * 0.13 * 2f64.sqrt())).abs() < 1e-12);
    }

    #[test]
    fn globalscaler_caps_and_wraps() {
        let tmc5160 = CurrentScale::GlobalScaler {
            sense_resistor: 0.075,
        };
        // 1 A: 256 * √2 * 0.075 / 0.325 = 83.55 → 84; bits
        // 1 * 8192 * √2 * 0.075 / (84 * 0.325) - 1 + .5 = 31.33 → 31.
        let b = tmc5160.bits(1.0, 1.0);
        assert_eq!((b.globalscaler, b.irun), (84, 31));
        // Tiny currents keep the scaler at 32.
        assert_eq!(tmc5160.bits(0.1, 0.1).globalscaler, 32);
        // Large ones wrap to 0 (256).
        assert_eq!(tmc5160.bits(4.0, 4.0).globalscaler, 0);
    }

    #[test]
    fn rref_picks_the_smallest_range_that_fits() {
        // Range 0 full scale: 11750 / 12000 / √2 = 0.692 A.
        assert_eq!(CurrentScale::range_for(12000.0, 0.6), 0);
        // Range 1: 24000 / 12000 / √2 = 1.414 A.
        assert_eq!(CurrentScale::range_for(12000.0, 1.0), 1);
        assert_eq!(CurrentScale::range_for(12000.0, 1.6), 2);
        assert_eq!(CurrentScale::range_for(12000.0, 9.0), 3);
        // 1 A in range 1: globalscaler int(256 / 1.41421 + .5) = 181;
        // irun int(8192 / (181 * 1.41421) - 1 + .5) = int(31.50) = 31.
        let tmc2240 = CurrentScale::Rref {
            rref: 12000.0,
            range: 1,
        };
        let b = tmc2240.bits(1.0, 0.5);
        assert_eq!((b.globalscaler, b.irun, b.ihold), (181, 31, 15));
    }
}
