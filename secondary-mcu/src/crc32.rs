//! The CRC-32 of zlib (IEEE 802.3, reflected, polynomial `0xEDB88320`),
//! which klippy sends in `finalize_config crc=…` over its config commands.

/// Continues a CRC-32 over `bytes`; start with 0.
pub fn update(crc: u32, bytes: &[u8]) -> u32 {
    let mut crc = !crc;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            let mask = (crc & 1).wrapping_neg();
            crc = (crc >> 1) ^ (0xEDB8_8320 & mask);
        }
    }
    !crc
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_zlibs_check_value_and_continues_across_pieces() {
        // The standard check value of CRC-32 over "123456789".
        assert_eq!(update(0, b"123456789"), 0xCBF4_3926);
        assert_eq!(update(update(0, b"1234"), b"56789"), 0xCBF4_3926);
        assert_eq!(update(0, b""), 0);
    }
}
