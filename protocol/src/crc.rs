//! The CRC16 that protects every Klipper message block.
//!
//! It is CRC-16/MCRF4XX (CCITT polynomial 0x1021, reflected, initial value
//! 0xffff, no final xor). It is computed over the block's length byte,
//! sequence byte and payload, and sent big-endian before the sync byte.

/// CRC16 of `data`.
pub fn crc16(data: &[u8]) -> u16 {
    data.iter().fold(0xffff_u16, |crc, &byte| {
        // Byte-wise reflected CCITT step (no table: 8 bit operations a byte).
        let mut d = byte ^ (crc as u8);
        d ^= d << 4;
        let d = u16::from(d);
        ((d << 8) | (crc >> 8)) ^ (d >> 4) ^ (d << 3)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_the_published_check_value() {
        // CRC-16/MCRF4XX check value for the ASCII string "123456789".
        assert_eq!(crc16(b"123456789"), 0x6f91);
    }

    #[test]
    fn empty_input_is_the_initial_value() {
        assert_eq!(crc16(&[]), 0xffff);
    }
}
