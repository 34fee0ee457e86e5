//! Klipper's variable-length quantity (VLQ) integer encoding.
//!
//! Every command argument travels as an integer in 1 to 5 bytes. Each byte
//! carries 7 bits, most significant group first; bit 7 set means "more bytes
//! follow". The first byte's bits 5..6 both set marks a negative number, so
//! small negative values stay short (-32..=95 fit in one byte).
//!
//! Values span `-2^31 ..= 2^32 - 1`: signed parameters are encoded from their
//! negative value, unsigned ones from their non-negative value, and the two
//! encodings of one 32-bit pattern can differ (`0x8765_4321` as unsigned
//! starts `0x88`, as `i32` it starts `0xf8`). Klipper's MCUs
//! accept both; the host sends the one matching the parameter's type.
//!
//! Klipper's host also passes absolute clocks as 64-bit values: they are
//! encoded from the full value (a leading byte carries bits 28..34) and the
//! MCU keeps the low 32 bits. [`encode`] does the same for any `i64`, so our
//! bytes equal klippy's.
/// The longest encoding of one value, in bytes.
pub const MAX_LEN: usize = 5;

/// Error decoding a VLQ: the input ended in the middle of a value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Truncated;

/// Encodes `value` into `out`, returning the number of bytes used. Values
/// outside `-2^31 ..= 2^32 - 1` keep only the bits a 5-byte VLQ carries, as
/// in Klipper's host (callers check their parameters' ranges). Not
/// inlined: its callers are many and it is not short.
#[inline(never)]
pub fn encode(value: i64, out: &mut [u8; MAX_LEN]) -> usize {
    if (-0x0400_0000..0x0c00_0000).contains(&value) {
        // Fits 4 bytes: 32-bit arithmetic, which the Cortex-M does natively.
        let v = value as i32;
        let n = if (-0x20..0x60).contains(&v) {
            1
        } else if (-0x1000..0x3000).contains(&v) {
            2
        } else if (-0x0008_0000..0x0018_0000).contains(&v) {
            3
        } else {
            4
        };
        for (i, byte) in out.iter_mut().enumerate().take(n) {
            let group = ((v >> (7 * (n - 1 - i))) & 0x7f) as u8;
            *byte = if i + 1 < n { 0x80 | group } else { group };
        }
        n
    } else {
        for (i, byte) in out.iter_mut().enumerate() {
            let group = ((value >> (7 * (MAX_LEN - 1 - i))) & 0x7f) as u8;
            *byte = if i + 1 < MAX_LEN { 0x80 | group } else { group };
        }
        MAX_LEN
    }
}

/// Decodes one value from the front of `input`; returns it with the number of
/// bytes it took. The result is as sent (possibly negative for an unsigned
/// parameter sent by a C peer); [`as_u32`] and [`as_i32`] give the parameter.
pub fn decode(input: &[u8]) -> Result<(i64, usize), Truncated> {
    let mut bytes = input.iter().take(MAX_LEN);
    let &first = bytes.next().ok_or(Truncated)?;
    let mut value = i64::from(first & 0x7f);
    if first & 0x60 == 0x60 {
        value |= -0x20;
    }
    let mut used = 1;
    let mut byte = first;
    while byte & 0x80 != 0 {
        byte = *bytes.next().ok_or(Truncated)?;
        value = (value << 7) | i64::from(byte & 0x7f);
        used += 1;
    }
    Ok((value, used))
}

/// The 32-bit unsigned parameter a decoded value carries.
pub fn as_u32(value: i64) -> u32 {
    value as u32
}

/// The 32-bit signed parameter a decoded value carries.
pub fn as_i32(value: i64) -> i32 {
    value as i32
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(v: i64) -> usize {
        let mut buf = [0u8; MAX_LEN];
        let n = encode(v, &mut buf);
        assert_eq!(decode(&buf[..n]), Ok((v, n)), "value {v}");
        n
    }

    #[test]
    fn lengths_follow_the_sign_aware_thresholds() {
        assert_eq!(round_trip(0), 1);
        assert_eq!(round_trip(95), 1);
        assert_eq!(round_trip(96), 2);
        assert_eq!(round_trip(-32), 1);
        assert_eq!(round_trip(-33), 2);
        assert_eq!(round_trip(0x2fff), 2);
        assert_eq!(round_trip(0x3000), 3);
        assert_eq!(round_trip(i64::from(i32::MAX)), 5);
        assert_eq!(round_trip(i64::from(i32::MIN)), 5);
        assert_eq!(round_trip(i64::from(u32::MAX)), 5);
        assert_eq!(round_trip(-1), 1);
    }

    #[test]
    fn round_trips_across_the_whole_range() {
        // A deterministic walk over magnitudes and signs (xorshift).
        let mut x: u32 = 0x1234_5678;
        for _ in 0..100_000 {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            let shift = x % 32;
            round_trip(i64::from((x as i32) >> shift));
            round_trip(i64::from(x >> shift));
        }
    }

    #[test]
    fn unsigned_and_signed_encodings_of_one_pattern_differ_only_in_sign_handling() {
        let clock: u32 = 0x8765_4321;
        let mut unsigned = [0u8; MAX_LEN];
        let mut signed = [0u8; MAX_LEN];
        let n = encode(i64::from(clock), &mut unsigned);
        let m = encode(i64::from(clock as i32), &mut signed);
        assert_eq!((n, m), (5, 5));
        assert_eq!((unsigned[0], signed[0]), (0x88, 0xf8));
        assert_eq!(unsigned[1..], signed[1..]);
        for bytes in [&unsigned, &signed] {
            let (v, _) = decode(bytes).expect("complete");
            assert_eq!(as_u32(v), clock);
        }
    }

    #[test]
    fn a_64_bit_clock_keeps_bits_28_to_34_in_its_first_byte() {
        // klippy sent this clock (43.8 s at 180 MHz) in the golden homing case.
        let clock: i64 = 7_888_379_999;
        let mut buf = [0u8; MAX_LEN];
        assert_eq!(encode(clock, &mut buf), 5);
        assert_eq!(buf[0], 0x80 | ((clock >> 28) & 0x7f) as u8);
        let (v, _) = decode(&buf).expect("complete");
        assert_eq!((v, as_u32(v)), (clock, clock as u32));
    }

    #[test]
    fn truncated_input_is_an_error_not_a_panic() {
        assert_eq!(decode(&[]), Err(Truncated));
        assert_eq!(decode(&[0x81]), Err(Truncated));
        assert_eq!(decode(&[0x81, 0x80, 0x80]), Err(Truncated));
        // More than five continuation bytes is not a value either.
        assert_eq!(decode(&[0x81; 8]), Err(Truncated));
    }
}
