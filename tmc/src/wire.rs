//! The drivers' datagrams, as bytes: built by the firmware's side, decoded
//! by a driver (the simulator's), so both ends share one definition.
//!
//! - Single-wire UART (TMC2208, TMC2209): a read request is 4 bytes
//!   `sync, address, register, crc`; a write 8 bytes `sync, address,
//!   register | 0x80, data (4 bytes, most significant first), crc`; the
//!   driver answers a read with 8 bytes `0x05, 0xff, register, data, crc`.
//!   Requests carry sync byte 0xf5 (the 0x5 sync nibble, reserved bits
//!   set), as Klipper sends. The CRC is CRC-8 with polynomial 0x07, bits
//!   taken least significant first.
//! - SPI (TMC2130, TMC2240, TMC5160): 40-bit datagrams, `register (| 0x80
//!   to write), data (4 bytes)`; each answer comes with the next
//!   datagram: a status byte and the register the previous datagram
//!   read (or the data it wrote). Drivers in a daisy chain share a chip
//!   select: one transfer carries a datagram for each, the one for chain
//!   position `p` of `n` after `(n - p)` empty ones.
//! - SPI (TMC2660): 20-bit datagrams in 3 bytes, `register bits << 16 |
//!   data`; the answer is 20 bits left-aligned in 24.

/// The sync byte of requests to a driver.
pub const UART_SYNC: u8 = 0xf5;
/// The sync byte of a driver's answer.
pub const UART_REPLY_SYNC: u8 = 0x05;
/// The address byte of a driver's answer (to the master).
pub const UART_REPLY_ADDR: u8 = 0xff;
/// Bytes of a UART write request or answer.
pub const UART_LONG: usize = 8;
/// Bytes of a UART read request.
pub const UART_SHORT: usize = 4;
/// Bytes of one SPI datagram (TMC2130/2240/5160).
pub const SPI_DATAGRAM: usize = 5;
/// Bytes of one TMC2660 datagram.
pub const SPI_2660: usize = 3;

/// CRC-8 of a UART datagram (polynomial 0x07, least significant bit of
/// each byte first, initial value 0).
pub fn crc8(data: &[u8]) -> u8 {
    let mut crc = 0u8;
    for &byte in data {
        let mut b = byte;
        for _ in 0..8 {
            let feedback = (crc >> 7) ^ (b & 1);
            crc <<= 1;
            if feedback != 0 {
                crc ^= 0x07;
            }
            b >>= 1;
        }
    }
    crc
}

/// A register read request to the driver at `address`.
pub fn uart_read(address: u8, reg: u8) -> [u8; UART_SHORT] {
    let mut d = [UART_SYNC, address, reg, 0];
    d[3] = crc8(&d[..3]);
    d
}

/// An 8-byte datagram `sync, address, reg, value, crc`.
fn uart_long(sync: u8, address: u8, reg: u8, value: u32) -> [u8; UART_LONG] {
    let v = value.to_be_bytes();
    let mut d = [sync, address, reg, v[0], v[1], v[2], v[3], 0];
    d[7] = crc8(&d[..7]);
    d
}

/// A register write request to the driver at `address`.
pub fn uart_write(address: u8, reg: u8, value: u32) -> [u8; UART_LONG] {
    uart_long(UART_SYNC, address, reg | 0x80, value)
}

/// A driver's answer to a read of `reg`.
pub fn uart_reply(reg: u8, value: u32) -> [u8; UART_LONG] {
    uart_long(UART_REPLY_SYNC, UART_REPLY_ADDR, reg, value)
}

/// The value in a driver's answer to a read of `reg`, if the answer is
/// whole and its CRC right.
pub fn uart_decode_reply(reg: u8, reply: &[u8]) -> Option<u32> {
    let d: [u8; UART_LONG] = reply.try_into().ok()?;
    let value = u32::from_be_bytes([d[3], d[4], d[5], d[6]]);
    (uart_reply(reg, value) == d).then_some(value)
}

/// A request as a driver decodes it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct UartRequest {
    /// The driver addressed (0..=3).
    pub address: u8,
    /// The register (without the write bit).
    pub reg: u8,
    /// The value written; `None` for a read.
    pub write: Option<u32>,
}

/// Decodes a request (read or write); `None` if its sync nibble, length
/// or CRC is wrong (a driver ignores it).
pub fn uart_decode_request(bytes: &[u8]) -> Option<UartRequest> {
    let (&crc, body) = bytes.split_last()?;
    if body.first()? & 0x0f != UART_REPLY_SYNC || crc8(body) != crc {
        return None;
    }
    let (address, reg) = (*body.get(1)?, *body.get(2)?);
    match bytes.len() {
        UART_SHORT if reg & 0x80 == 0 => Some(UartRequest {
            address,
            reg,
            write: None,
        }),
        UART_LONG if reg & 0x80 != 0 => Some(UartRequest {
            address,
            reg: reg & 0x7f,
            write: Some(u32::from_be_bytes([body[3], body[4], body[5], body[6]])),
        }),
        _ => None,
    }
}

/// A 40-bit SPI datagram: a read of `reg`, or a write of `value`.
pub fn spi_datagram(reg: u8, write: Option<u32>) -> [u8; SPI_DATAGRAM] {
    let (r, v) = match write {
        Some(value) => (reg | 0x80, value),
        None => (reg & 0x7f, 0),
    };
    let b = v.to_be_bytes();
    [r, b[0], b[1], b[2], b[3]]
}

/// Where chain position `position` (1-based, of `length`) sits in a
/// chained transfer: its byte offset.
pub fn chain_offset(position: u8, length: u8) -> usize {
    usize::from(length.saturating_sub(position)) * SPI_DATAGRAM
}

/// Places `datagram` for chain position `position` of `length` in `out`
/// (`length` datagrams long), the other positions' datagrams empty;
/// returns the bytes used.
pub fn spi_chain(datagram: [u8; SPI_DATAGRAM], position: u8, length: u8, out: &mut [u8]) -> usize {
    let len = usize::from(length.max(1)) * SPI_DATAGRAM;
    let Some(buf) = out.get_mut(..len) else {
        return 0;
    };
    buf.fill(0);
    let at = chain_offset(position, length);
    if let Some(slot) = buf.get_mut(at..at + SPI_DATAGRAM) {
        slot.copy_from_slice(&datagram);
    }
    len
}

/// The data (without the status byte) of chain position `position`'s
/// answer in a chained transfer's received bytes.
pub fn spi_chain_answer(received: &[u8], position: u8, length: u8) -> Option<u32> {
    let at = chain_offset(position, length);
    let d = received.get(at..at + SPI_DATAGRAM)?;
    Some(u32::from_be_bytes([d[1], d[2], d[3], d[4]]))
}

/// A TMC2660 datagram writing `value` (bits 0..=16) to the register with
/// address bits `reg` (0x0, 0x8, 0xa, 0xc, 0xe).
pub fn spi_2660(reg: u8, value: u32) -> [u8; SPI_2660] {
    let v = value.to_be_bytes();
    [((value >> 16) as u8 | reg), v[2], v[3]]
}

/// The register address bits and value of a TMC2660 datagram.
pub fn spi_2660_decode(d: [u8; SPI_2660]) -> (u8, u32) {
    let word = u32::from_be_bytes([0, d[0], d[1], d[2]]) & 0xf_ffff;
    let reg = if word >> 19 == 0 {
        0
    } else {
        (word >> 16) as u8 & 0x0e
    };
    let mask = if reg == 0 { 0x3_ffff } else { 0x1_ffff };
    (reg, word & mask)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc8_matches_the_data_sheet_algorithm() {
        // A read of IFCNT (0x02) at address 0: Klipper's frame
        // f5 00 02 + crc; the CRC checked bit by bit from its definition.
        let mut crc = 0u8;
        for byte in [0xf5u8, 0x00, 0x02] {
            for bit in 0..8 {
                let msb = crc & 0x80 != 0;
                crc <<= 1;
                if msb != (byte >> bit & 1 != 0) {
                    crc ^= 0x07;
                }
            }
        }
        assert_eq!(uart_read(0, 0x02)[3], crc);
        assert_ne!(crc8(&[0x05, 0xff, 0x02]), crc8(&[0x05, 0xff, 0x03]));
    }

    #[test]
    fn uart_requests_and_replies_round_trip() {
        let w = uart_write(3, 0x10, 0x0008_1f10);
        assert_eq!(&w[..7], &[0xf5, 3, 0x90, 0x00, 0x08, 0x1f, 0x10]);
        assert_eq!(
            uart_decode_request(&w),
            Some(UartRequest {
                address: 3,
                reg: 0x10,
                write: Some(0x0008_1f10)
            })
        );
        let r = uart_read(1, 0x6f);
        assert_eq!(uart_decode_request(&r).map(|q| q.write), Some(None));
        let mut bad = w;
        bad[4] ^= 1;
        assert_eq!(uart_decode_request(&bad), None);
        let reply = uart_reply(0x6f, 0xc01f_0000);
        assert_eq!(uart_decode_reply(0x6f, &reply), Some(0xc01f_0000));
        assert_eq!(uart_decode_reply(0x6c, &reply), None);
        assert_eq!(uart_decode_reply(0x6f, &reply[..7]), None);
    }

    #[test]
    fn spi_chain_positions_count_from_the_end() {
        let d = spi_datagram(0x6c, Some(0x1234_5678));
        assert_eq!(d, [0xec, 0x12, 0x34, 0x56, 0x78]);
        let mut buf = [0xaa; 30];
        // Position 1 of 3 goes last, position 3 first.
        assert_eq!(spi_chain(d, 1, 3, &mut buf), 15);
        assert_eq!(&buf[10..15], &d);
        assert!(buf[..10].iter().all(|&b| b == 0));
        assert_eq!(spi_chain_answer(&buf, 1, 3), Some(0x1234_5678));
        spi_chain(d, 3, 3, &mut buf);
        assert_eq!(&buf[..5], &d);
    }

    #[test]
    fn tmc2660_datagrams_carry_the_register_in_the_top_bits() {
        // DRVCONF (0xe) with tst (bit 16) set.
        let d = spi_2660(0xe, 0x1_0300);
        assert_eq!(d, [0x0f, 0x03, 0x00]);
        assert_eq!(spi_2660_decode(d), (0xe, 0x1_0300));
        // DRVCTRL: bit 19 clear, 18 data bits.
        assert_eq!(spi_2660_decode(spi_2660(0, 0x204)), (0, 0x204));
    }
}
