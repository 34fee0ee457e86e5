//! Klipper's variable-length quantity (VLQ) integer encoding.
//!
//! Every command argument travels as a 32-bit integer in 1 to 5 bytes. Each
//! byte carries 7 bits, most significant group first; bit 7 set means "more
//! bytes follow". The first byte's bits 5..6 both set marks a negative number,
//! so small negative values stay short (-32..=95 fit in one byte).

/// The longest encoding of one 32-bit value, in bytes.
pub const MAX_LEN: usize = 5;

/// Error decoding a VLQ: the input ended in the middle of a value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Truncated;

/// Encodes `value` (signed or unsigned 32-bit, as Klipper does: the bit
/// pattern is what travels) into `out`, returning the number of bytes used.
pub fn encode(value: i32, out: &mut [u8; MAX_LEN]) -> usize {
    let v = value;
    let mut n = 0;
    // Each threshold is the first value that no longer fits in one fewer
    // group of 7 bits, given the sign convention of the first byte.
    let groups: [(i32, i32, u32); 4] = [
        (0x0c00_0000, -0x0400_0000, 28),
        (0x0018_0000, -0x0008_0000, 21),
        (0x3000, -0x1000, 14),
        (0x60, -0x20, 7),
    ];
    for (pos_limit, neg_limit, shift) in groups {
        if v >= pos_limit || v < neg_limit {
            out[n] = 0x80 | ((v >> shift) & 0x7f) as u8;
            n += 1;
        }
    }
    out[n] = (v & 0x7f) as u8;
    n + 1
}

/// Decodes one value from the front of `input`; returns it with the number of
/// bytes it took. The value is the 32-bit pattern: callers reinterpret it as
/// `u32` for unsigned parameters.
pub fn decode(input: &[u8]) -> Result<(i32, usize), Truncated> {
    let mut bytes = input.iter();
    let &first = bytes.next().ok_or(Truncated)?;
    let mut value = i32::from(first & 0x7f);
    if first & 0x60 == 0x60 {
        value |= -0x20;
    }
    let mut used = 1;
    let mut byte = first;
    while byte & 0x80 != 0 {
        byte = *bytes.next().ok_or(Truncated)?;
        value = (value << 7) | i32::from(byte & 0x7f);
        used += 1;
    }
    Ok((value, used))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(v: i32) -> usize {
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
        assert_eq!(round_trip(i32::MAX), 5);
        assert_eq!(round_trip(i32::MIN), 5);
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
            round_trip((x as i32) >> shift);
        }
    }

    #[test]
    fn unsigned_values_travel_as_their_bit_pattern() {
        // A uint32 clock above i32::MAX is sent as its two's-complement pattern.
        let clock: u32 = 0xfedc_ba98;
        let mut buf = [0u8; MAX_LEN];
        let n = encode(clock as i32, &mut buf);
        let (v, _) = decode(&buf[..n]).expect("complete value");
        assert_eq!(v as u32, clock);
    }

    #[test]
    fn truncated_input_is_an_error_not_a_panic() {
        assert_eq!(decode(&[]), Err(Truncated));
        assert_eq!(decode(&[0x81]), Err(Truncated));
        assert_eq!(decode(&[0x81, 0x80, 0x80]), Err(Truncated));
    }
}
