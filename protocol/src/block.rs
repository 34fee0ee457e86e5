//! Message-block framing.
//!
//! A block is `len, seq, payload…, crc_hi, crc_lo, 0x7e`: `len` counts the
//! whole block (5..=64 bytes), `seq` is `0x10 | (sequence & 0x0f)`, and the
//! CRC16 ([`crate::crc::crc16`]) covers `len`, `seq` and the payload.

use crate::crc::crc16;

/// Smallest block: header and trailer with an empty payload (an ack).
pub const MIN_LEN: usize = 5;
/// Largest block, in bytes.
pub const MAX_LEN: usize = 64;
/// Bytes before the payload (`len`, `seq`).
pub const HEADER_LEN: usize = 2;
/// Bytes after the payload (`crc_hi`, `crc_lo`, sync).
pub const TRAILER_LEN: usize = 3;
/// Largest payload of one block, in bytes.
pub const MAX_PAYLOAD: usize = MAX_LEN - MIN_LEN;
/// The byte that ends every block.
pub const SYNC: u8 = 0x7e;
/// High bits that every sequence byte carries.
pub const SEQ_DEST: u8 = 0x10;
/// Bits of the sequence byte that hold the sequence number.
pub const SEQ_MASK: u8 = 0x0f;

/// A well-formed block found at the front of a buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Block<'a> {
    /// Sequence number, 0..=15.
    pub seq: u8,
    /// The encoded commands (or responses) the block carries.
    pub payload: &'a [u8],
}

impl Block<'_> {
    /// Total length of the block on the wire, in bytes.
    pub fn wire_len(&self) -> usize {
        self.payload.len() + MIN_LEN
    }
}

/// Why the front of a buffer is not (yet) a block.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BlockError {
    /// The buffer is shorter than the block it starts; read more bytes.
    Incomplete,
    /// The length byte is outside 5..=64.
    BadLength(u8),
    /// The sequence byte lacks the `0x10` destination bits.
    BadSequenceByte(u8),
    /// The CRC does not match the block's contents.
    BadCrc {
        /// CRC carried by the block.
        sent: u16,
        /// CRC computed over the received bytes.
        computed: u16,
    },
    /// The last byte is not the sync byte `0x7e`.
    MissingSync,
}

/// Reads the block at the front of `buf`.
pub fn parse(buf: &[u8]) -> Result<Block<'_>, BlockError> {
    let &len = buf.first().ok_or(BlockError::Incomplete)?;
    let n = usize::from(len);
    if !(MIN_LEN..=MAX_LEN).contains(&n) {
        return Err(BlockError::BadLength(len));
    }
    let frame = buf.get(..n).ok_or(BlockError::Incomplete)?;
    if frame[n - 1] != SYNC {
        return Err(BlockError::MissingSync);
    }
    let seq_byte = frame[1];
    if seq_byte & !SEQ_MASK != SEQ_DEST {
        return Err(BlockError::BadSequenceByte(seq_byte));
    }
    let sent = u16::from_be_bytes([frame[n - 3], frame[n - 2]]);
    let computed = crc16(&frame[..n - TRAILER_LEN]);
    if sent != computed {
        return Err(BlockError::BadCrc { sent, computed });
    }
    Ok(Block {
        seq: seq_byte & SEQ_MASK,
        payload: &frame[HEADER_LEN..n - TRAILER_LEN],
    })
}

/// Payload too large for one block.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PayloadTooLarge(pub usize);

/// Frames `payload` with sequence number `seq` (low 4 bits used) into `out`,
/// returning the block's length.
pub fn encode(seq: u8, payload: &[u8], out: &mut [u8; MAX_LEN]) -> Result<usize, PayloadTooLarge> {
    if payload.len() > MAX_PAYLOAD {
        return Err(PayloadTooLarge(payload.len()));
    }
    let n = payload.len() + MIN_LEN;
    out[0] = n as u8;
    out[1] = SEQ_DEST | (seq & SEQ_MASK);
    out[HEADER_LEN..HEADER_LEN + payload.len()].copy_from_slice(payload);
    let crc = crc16(&out[..n - TRAILER_LEN]);
    out[n - 3..n - 1].copy_from_slice(&crc.to_be_bytes());
    out[n - 1] = SYNC;
    Ok(n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn encode_then_parse_round_trips_every_payload_size() {
        let mut out = [0u8; MAX_LEN];
        for size in 0..=MAX_PAYLOAD {
            let payload: [u8; MAX_PAYLOAD] = core::array::from_fn(|i| (i * 7 + size) as u8);
            let n = encode(size as u8, &payload[..size], &mut out).expect("fits");
            let block = parse(&out[..n]).expect("valid block");
            assert_eq!(block.seq, (size as u8) & SEQ_MASK);
            assert_eq!(block.payload, &payload[..size]);
            assert_eq!(block.wire_len(), n);
        }
    }

    #[test]
    fn oversize_payload_is_refused() {
        let mut out = [0u8; MAX_LEN];
        assert_eq!(
            encode(0, &[0; MAX_PAYLOAD + 1], &mut out),
            Err(PayloadTooLarge(MAX_PAYLOAD + 1))
        );
    }

    #[test]
    fn every_single_bit_flip_is_detected() {
        let mut out = [0u8; MAX_LEN];
        let n = encode(3, b"\x01\x02\x03\x04\x05", &mut out).expect("fits");
        for byte in 0..n {
            for bit in 0..8 {
                let mut damaged = out;
                damaged[byte] ^= 1 << bit;
                assert!(
                    parse(&damaged[..n]).is_err(),
                    "flip {byte}:{bit} undetected"
                );
            }
        }
    }

    #[test]
    fn short_buffers_ask_for_more() {
        let mut out = [0u8; MAX_LEN];
        let n = encode(0, b"abc", &mut out).expect("fits");
        for cut in 0..n {
            assert_eq!(parse(&out[..cut]), Err(BlockError::Incomplete));
        }
    }
}
