//! Decimal numbers in and out, without core's float parser and formatter
//! (about 30 KiB of tables and code the firmware cannot spare).
//!
//! - [`parse`] reads what Python's `float()` reads for printer.cfg values
//!   and G-code parameters: an optional sign, digits with an optional point,
//!   an optional exponent (`1.5e-3`), and `inf`/`infinity`/`nan`. It is
//!   correctly rounded (bit-identical to Python's `float()`) for at most 19
//!   significant digits and a decimal exponent within ±19 of them, which
//!   covers every number a slicer or a printer.cfg writes. Beyond that
//!   (more digits are cut to 19; larger exponents are scaled in steps of
//!   10¹⁹ with 64-bit intermediate precision) it is within one unit in the
//!   last place.
//! - [`Fixed`] prints C's `%.Nf` exactly: the binary value's exact decimal
//!   expansion, rounded half to even at N places (as Python's `%.3f` and
//!   Rust's `{:.3}` print it).
//! - [`Shortest`] prints the fewest decimals (at least one) that read back
//!   as the same value: Python's `repr` of a float for the numbers a
//!   printer's limits are (magnitudes 1e-4 to 1e9).

use core::fmt;

/// Most places [`Fixed`] prints.
pub const MAX_PLACES: u8 = 9;

/// `value` printed with `places` decimals (at most [`MAX_PLACES`]), as C's
/// `%.Nf`: `Fixed(0.0625, 3)` is `0.062`, `Fixed(-1.0, 1)` is `-1.0`.
/// Infinities print `inf`/`-inf`, NaN prints `NaN`.
#[derive(Debug, Clone, Copy)]
pub struct Fixed(pub f64, pub u8);

impl fmt::Display for Fixed {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let Fixed(value, places) = *self;
        let places = u32::from(places.min(MAX_PLACES));
        if value.is_nan() {
            return f.write_str("NaN");
        }
        if value.is_sign_negative() {
            f.write_str("-")?;
        }
        if value.is_infinite() {
            return f.write_str("inf");
        }
        // |value| = mantissa · 2^exponent, exactly.
        let bits = value.to_bits();
        let biased = ((bits >> 52) & 0x7ff) as i32;
        let fraction = bits & ((1 << 52) - 1);
        let (mantissa, exponent) = match biased {
            0 => (fraction, -1074),
            _ => (fraction | 1 << 52, biased - 1075),
        };
        let scale = 10u128.pow(places);
        let (whole, decimals) = if exponent >= 0 {
            (Whole::shifted(mantissa, exponent as u32), 0)
        } else {
            let shift = exponent.unsigned_abs();
            // mantissa < 2^53 and scale < 2^30: below 2^83, so a shift of
            // 84 or more leaves nothing and a remainder under one half.
            if shift > 83 {
                (Whole::shifted(0, 0), 0)
            } else {
                let int = if shift >= 64 { 0 } else { mantissa >> shift };
                let rest = u128::from(mantissa) & ((1u128 << shift) - 1);
                let scaled = rest * scale;
                let (mut digits, remainder) = (scaled >> shift, scaled & ((1u128 << shift) - 1));
                let half = 1u128 << (shift - 1);
                // A tie goes to the even last digit printed.
                let last = if places == 0 { u128::from(int) } else { digits };
                if remainder > half || (remainder == half && last & 1 == 1) {
                    digits += 1;
                }
                if digits == scale {
                    (Whole::shifted(int + 1, 0), 0)
                } else {
                    (Whole::shifted(int, 0), digits)
                }
            }
        };
        whole.write(f)?;
        if places > 0 {
            let mut text = [b'0'; MAX_PLACES as usize + 1];
            text[0] = b'.';
            write_digits(&mut text[1..=places as usize], decimals as u64);
            f.write_str(core::str::from_utf8(&text[..=places as usize]).map_err(|_| fmt::Error)?)?;
        }
        Ok(())
    }
}

/// Writes `value` right-aligned into `out` as decimal digits (the leading
/// positions left as they are).
fn write_digits(out: &mut [u8], mut value: u64) {
    for byte in out.iter_mut().rev() {
        *byte = b'0' + (value % 10) as u8;
        value /= 10;
    }
}

/// A whole number up to 2^1024, as 32-bit limbs (least significant first).
struct Whole {
    limbs: [u32; 34],
}

impl Whole {
    /// `mantissa · 2^shift` (mantissa < 2^64, shift ≤ 971).
    fn shifted(mantissa: u64, shift: u32) -> Self {
        let mut limbs = [0u32; 34];
        let (word, bit) = ((shift / 32) as usize, shift % 32);
        let wide = u128::from(mantissa) << bit;
        for (i, limb) in limbs.iter_mut().skip(word).take(3).enumerate() {
            *limb = (wide >> (32 * i)) as u32;
        }
        Self { limbs }
    }

    /// Divides by 10⁹ in place; the remainder.
    fn div_billion(&mut self) -> u32 {
        let mut remainder = 0u64;
        for limb in self.limbs.iter_mut().rev() {
            let current = (remainder << 32) | u64::from(*limb);
            *limb = (current / 1_000_000_000) as u32;
            remainder = current % 1_000_000_000;
        }
        remainder as u32
    }

    fn is_zero(&self) -> bool {
        self.limbs.iter().all(|&l| l == 0)
    }

    /// Prints the number in decimal, without leading zeros.
    fn write(mut self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // 2^1024 has 309 digits: at most 35 groups of nine.
        let mut groups = [0u32; 35];
        let mut count = 0;
        loop {
            groups[count] = self.div_billion();
            count += 1;
            if self.is_zero() || count == groups.len() {
                break;
            }
        }
        let mut text = [0u8; 9];
        for (i, &group) in groups[..count].iter().rev().enumerate() {
            write_digits(&mut text, u64::from(group));
            let digits = if i == 0 {
                let skip = text.iter().take(8).take_while(|&&b| b == b'0').count();
                &text[skip..]
            } else {
                &text[..]
            };
            f.write_str(core::str::from_utf8(digits).map_err(|_| fmt::Error)?)?;
        }
        Ok(())
    }
}

/// Exact powers of ten in f64.
const POW10: [f64; 23] = [
    1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16,
    1e17, 1e18, 1e19, 1e20, 1e21, 1e22,
];

/// Most significant digits kept.
const MAX_DIGITS: u32 = 19;

/// `value` printed with the fewest decimals, at least one and at most
/// [`MAX_PLACES`], that [`parse`] reads back as `value` (Python's `repr`
/// of a float within the magnitudes it prints without an exponent:
/// `Shortest(0.1)` is `0.1`, `Shortest(2.0)` is `2.0`).
#[derive(Debug, Clone, Copy)]
pub struct Shortest(pub f64);

impl fmt::Display for Shortest {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut text: heapless::String<64> = heapless::String::new();
        for places in 1..MAX_PLACES {
            text.clear();
            if fmt::write(&mut text, format_args!("{}", Fixed(self.0, places))).is_ok()
                && parse(&text) == Some(self.0)
            {
                return f.write_str(&text);
            }
        }
        write!(f, "{}", Fixed(self.0, MAX_PLACES))
    }
}

/// Reads `text` as Python's `float()` does (without surrounding spaces or
/// `_` separators); None if it is not a number. See the module comment for
/// how exact it is.
pub fn parse(text: &str) -> Option<f64> {
    let (negative, body) = match text.as_bytes() {
        [b'-', rest @ ..] => (true, rest),
        [b'+', rest @ ..] => (false, rest),
        rest => (false, rest),
    };
    let magnitude = special(body).or_else(|| finite(body))?;
    Some(if negative { -magnitude } else { magnitude })
}

/// `inf`, `infinity` or `nan`, in any case.
fn special(body: &[u8]) -> Option<f64> {
    let is = |word: &[u8]| body.eq_ignore_ascii_case(word);
    if is(b"inf") || is(b"infinity") {
        Some(f64::INFINITY)
    } else if is(b"nan") {
        Some(f64::NAN)
    } else {
        None
    }
}

/// Digits, point and exponent, no sign.
fn finite(body: &[u8]) -> Option<f64> {
    let (mut digits, mut kept, mut exponent) = (0u64, 0u32, 0i64);
    let (mut any, mut after_point) = (false, false);
    let mut at = 0;
    while let Some(&b) = body.get(at) {
        match b {
            b'0'..=b'9' => {
                any = true;
                if kept < MAX_DIGITS {
                    if digits != 0 || b != b'0' {
                        kept += 1;
                    }
                    digits = digits * 10 + u64::from(b - b'0');
                    exponent -= i64::from(after_point);
                } else {
                    // Cut: a digit before the point still scales by ten.
                    exponent += i64::from(!after_point);
                }
            }
            b'.' if !after_point => after_point = true,
            b'e' | b'E' => break,
            _ => return None,
        }
        at += 1;
    }
    if !any {
        return None;
    }
    if at < body.len() {
        exponent += exponent_part(&body[at + 1..])?;
    }
    Some(scale(digits, exponent))
}

/// The digits after `e`: an optional sign and at least one digit
/// (saturated far beyond any finite f64).
fn exponent_part(text: &[u8]) -> Option<i64> {
    let (negative, digits) = match text {
        [b'-', rest @ ..] => (true, rest),
        [b'+', rest @ ..] => (false, rest),
        rest => (false, rest),
    };
    if digits.is_empty() {
        return None;
    }
    let mut value = 0i64;
    for &b in digits {
        if !b.is_ascii_digit() {
            return None;
        }
        value = (value * 10 + i64::from(b - b'0')).min(100_000);
    }
    Some(if negative { -value } else { value })
}

/// `digits · 10^exponent`, rounded to the nearest f64.
fn scale(digits: u64, exponent: i64) -> f64 {
    if digits == 0 {
        return 0.0;
    }
    // Clinger's fast path: both factors exact, one correctly rounded op.
    if digits < 1 << 53 && exponent.unsigned_abs() < POW10.len() as u64 {
        let power = POW10[exponent.unsigned_abs() as usize];
        return if exponent < 0 {
            digits as f64 / power
        } else {
            digits as f64 * power
        };
    }
    if exponent > 400 {
        return f64::INFINITY;
    }
    if exponent < -400 {
        return 0.0;
    }
    // mantissa · 2^binary, with the bits shifted out kept as a sticky
    // bit 0 (well below the 53 bits the final rounding keeps).
    let (mut mantissa, mut binary) = (u128::from(digits), 0i32);
    let mut exponent = exponent as i32;
    while exponent > 0 {
        let step = exponent.min(MAX_DIGITS as i32);
        let over = (128 - mantissa.leading_zeros()).saturating_sub(64);
        if over > 0 {
            let lost = mantissa & ((1 << over) - 1) != 0;
            mantissa = (mantissa >> over) | u128::from(lost);
            binary += over as i32;
        }
        mantissa *= 10u128.pow(step as u32);
        exponent -= step;
    }
    while exponent < 0 {
        let step = (-exponent).min(MAX_DIGITS as i32);
        let room = mantissa.leading_zeros();
        mantissa <<= room;
        binary -= room as i32;
        let power = 10u128.pow(step as u32);
        mantissa = (mantissa / power) | u128::from(mantissa % power != 0);
        exponent += step;
    }
    times_power_of_two(mantissa as f64, binary)
}

/// `value · 2^binary`, exact while the result is a normal number.
fn times_power_of_two(mut value: f64, mut binary: i32) -> f64 {
    let power = |e: i32| f64::from_bits(((e + 1023) as u64) << 52);
    while binary > 1000 {
        value *= power(1000);
        binary -= 1000;
    }
    while binary < -1000 {
        value *= power(-1000);
        binary += 1000;
    }
    value * power(binary)
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;

    #[test]
    fn shortest_prints_as_pythons_repr() {
        use std::string::ToString;
        for (value, repr) in [
            (0.0, "0.0"),
            (2.0, "2.0"),
            (0.1, "0.1"),
            (-1.5, "-1.5"),
            (0.0001, "0.0001"),
            (1.0 / 3.0, "0.333333333"),
            (2.1e9, "2100000000.0"),
        ] {
            assert_eq!(Shortest(value).to_string(), repr);
        }
    }
    use std::format;
    use std::string::String;

    /// xorshift64*: a repeatable stream of test inputs.
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
        }
    }

    #[test]
    fn fixed_matches_exact_formatting_on_random_doubles() {
        let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
        for _ in 0..40_000 {
            let bits = rng.next();
            let value = f64::from_bits(bits);
            // Every exponent, and values of the sizes printers show.
            let small = (bits % 2_000_000) as f64 / 1024.0 - 976.5;
            for v in [value, small, small / 7.0] {
                for places in 0..=MAX_PLACES {
                    let p = usize::from(places);
                    let expected = format!("{v:.p$}");
                    assert_eq!(format!("{}", Fixed(v, places)), expected, "{v:e} .{places}");
                }
            }
        }
    }

    #[test]
    fn fixed_rounds_ties_to_even_and_keeps_the_sign() {
        let cases = [
            (0.0625, 3, "0.062"),
            (0.1875, 3, "0.188"),
            (2.5, 0, "2"),
            (3.5, 0, "4"),
            (0.9999996, 6, "1.000000"),
            (-0.0001, 3, "-0.000"),
            (-0.0, 1, "-0.0"),
            (123.456, 3, "123.456"),
            (1e22, 1, "10000000000000000000000.0"),
            (
                f64::MAX,
                0,
                "179769313486231570814527423731704356798070567525844996598917476803157260780028538760589558632766878171540458953514382464234321326889464182768467546703537516986049910576551282076245490090389328944075868508455133942304583236903222948165808559332123348274797826204144723168738177180919299881250404026184124858368",
            ),
            (5e-324, 9, "0.000000000"),
            (f64::NEG_INFINITY, 3, "-inf"),
            (f64::NAN, 3, "NaN"),
        ];
        for (value, places, text) in cases {
            assert_eq!(format!("{}", Fixed(value, places)), text);
        }
    }

    /// A decimal string of `digits` significant digits with the point at a
    /// random place and an optional exponent.
    fn random_decimal(rng: &mut Rng, digits: u32, max_exp: i64) -> String {
        let mut text = String::new();
        if rng.next() & 1 == 0 {
            text.push('-');
        }
        let point = (rng.next() % u64::from(digits + 1)) as u32;
        for i in 0..digits {
            if i == point {
                text.push('.');
            }
            let d = (rng.next() % 10) as u8;
            text.push(char::from(b'0' + if i == 0 && d == 0 { 1 } else { d }));
        }
        if max_exp > 0 && rng.next() & 1 == 0 {
            let e = (rng.next() % (2 * max_exp as u64 + 1)) as i64 - max_exp;
            text.push_str(&format!("e{e}"));
        }
        text
    }

    #[test]
    fn parse_is_correctly_rounded_up_to_19_digits() {
        let mut rng = Rng(0x1234_5678_9abc_def1);
        for _ in 0..300_000 {
            let digits = 1 + (rng.next() % 19) as u32;
            let text = random_decimal(&mut rng, digits, 19 - i64::from(digits).min(19) / 2);
            let expected: f64 = text.parse().expect("a decimal");
            let (mantissa, exponent) = significant_and_exponent(&text);
            if mantissa.len() > 19 || exponent.abs() > 19 {
                continue;
            }
            assert_eq!(
                parse(&text).map(f64::to_bits),
                Some(expected.to_bits()),
                "{text}"
            );
        }
    }

    /// The significant digits and the decimal exponent of their last one.
    fn significant_and_exponent(text: &str) -> (String, i64) {
        let (body, exp) = text.split_once('e').unwrap_or((text, "0"));
        let exp: i64 = exp.parse().expect("an exponent");
        let after = body.split_once('.').map_or(0, |(_, b)| b.len() as i64);
        let digits: String = body.chars().filter(char::is_ascii_digit).collect();
        let significant = digits.trim_start_matches('0');
        (significant.into(), exp - after)
    }

    #[test]
    fn parse_is_within_one_ulp_beyond() {
        let mut rng = Rng(0x0bad_cafe_f00d_d00d);
        for _ in 0..100_000 {
            let digits = 1 + (rng.next() % 30) as u32;
            let text = random_decimal(&mut rng, digits, 290);
            let expected: f64 = text.parse().expect("a decimal");
            let got = parse(&text).expect("a decimal");
            let ulps = (got.to_bits() as i64 - expected.to_bits() as i64).abs();
            assert!(ulps <= 1, "{text}: {got:e} vs {expected:e}");
        }
    }

    #[test]
    fn parse_reads_what_python_float_reads() {
        let cases = [
            ("0", 0.0),
            ("-0", -0.0),
            ("1.", 1.0),
            (".5", 0.5),
            ("+2.5e3", 2500.0),
            ("1E-2", 0.01),
            ("007.10", 7.1),
            ("1e400", f64::INFINITY),
            ("1e-400", 0.0),
            ("-Infinity", f64::NEG_INFINITY),
            ("0.1", 0.1),
            ("123456789012345678901234567890", 1.2345678901234568e29),
        ];
        for (text, value) in cases {
            assert_eq!(
                parse(text).map(f64::to_bits),
                Some(value.to_bits()),
                "{text}"
            );
        }
        assert!(parse("nan").is_some_and(f64::is_nan));
        for bad in [
            "", "-", ".", "e5", "1e", "1e+", "1.2.3", "1,5", " 1", "0x10", "1_0", "--1",
        ] {
            assert_eq!(parse(bad), None, "{bad:?}");
        }
    }
}
