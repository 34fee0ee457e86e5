//! A small resumable zlib inflater (RFC 1950 around RFC 1951) for data
//! dictionaries: stored, fixed- and dynamic-Huffman blocks, the zlib header
//! and its Adler-32 checksum.
//!
//! The compressed stream may arrive in pieces of any size: every step takes
//! all the bits it needs (a header, a literal, a whole length/distance pair)
//! or none, pulling input bytes only as it needs them, so a piece that ends
//! mid-step leaves its last bits in [`Inflater`] until the next piece. The
//! output is one non-wrapping buffer, which back-references read from (the
//! whole dictionary is kept: no 32 KiB window of its own). Huffman codes are
//! decoded bit by bit from the canonical code counts (as zlib's `puff`):
//! slow, but a dictionary is 10–15 KB, decoded once per connection.
//!
//! No heap, no panics: bad data is [`Stop::Corrupt`], never an overrun.

/// Why [`Inflater::inflate`] stopped before the end of the stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stop {
    /// The input ran out mid-stream: call again with the next piece.
    NeedsInput,
    /// The data is not a valid zlib stream (or its checksum is wrong, or
    /// bytes follow its end).
    Corrupt,
    /// The output buffer is full before the stream's end.
    OutputFull,
}

/// Where the stream stands: the step that comes next.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    /// The two-byte zlib header.
    Header,
    /// A block's 3-bit header (last-block flag and type).
    Block,
    /// A stored block's byte-aligned LEN and NLEN.
    StoredLength,
    /// A stored block's bytes, this many still to copy.
    Stored(u16),
    /// A dynamic block's code counts (HLIT, HDIST, HCLEN).
    Counts,
    /// A dynamic block's code-length code lengths, this many read.
    CodeLengthLengths(u16),
    /// A dynamic block's literal/length and distance code lengths, this
    /// many read.
    Lengths(u16),
    /// A block's literals and length/distance pairs.
    Codes,
    /// The Adler-32 checksum after the last block.
    Trailer,
    /// The stream has ended (and its checksum matched).
    Done,
}

/// Longest Huffman code, bits.
const MAX_BITS: usize = 15;
/// Literal/length symbols (286 and 287 appear only in the fixed code).
const LITERAL_SYMBOLS: usize = 288;
/// Literal/length plus distance code lengths in a dynamic block, at most.
const MAX_LENGTHS: usize = 286 + 30;
/// The order code-length code lengths come in (RFC 1951 3.2.7).
const CODE_LENGTH_ORDER: [u8; 19] = [
    16, 17, 18, 0, 8, 7, 9, 6, 10, 5, 11, 4, 12, 3, 13, 2, 14, 1, 15,
];
/// Match length of length symbols 257.., bytes.
const LENGTH_BASE: [u16; 29] = [
    3, 4, 5, 6, 7, 8, 9, 10, 11, 13, 15, 17, 19, 23, 27, 31, 35, 43, 51, 59, 67, 83, 99, 115, 131,
    163, 195, 227, 258,
];
/// Extra bits after length symbols 257...
const LENGTH_EXTRA: [u8; 29] = [
    0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3, 4, 4, 4, 4, 5, 5, 5, 5, 0,
];
/// Distance of distance symbols 0.., bytes back.
const DISTANCE_BASE: [u16; 30] = [
    1, 2, 3, 4, 5, 7, 9, 13, 17, 25, 33, 49, 65, 97, 129, 193, 257, 385, 513, 769, 1025, 1537,
    2049, 3073, 4097, 6145, 8193, 12289, 16385, 24577,
];
/// Extra bits after distance symbols 0...
const DISTANCE_EXTRA: [u8; 30] = [
    0, 0, 0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5, 6, 6, 7, 7, 8, 8, 9, 9, 10, 10, 11, 11, 12, 12, 13,
    13,
];

/// The input bits taken but not yet used, least significant first.
#[derive(Debug, Clone, Copy)]
struct Bits {
    /// The bits, the next one in bit 0.
    buffer: u64,
    /// How many bits `buffer` holds (at most 55: a step needs 48 at most).
    count: u32,
}

impl Bits {
    /// The `n` bits (`n` ≤ 32) starting `at` bits ahead, without using
    /// them; pulls input bytes until it holds them.
    fn peek(&mut self, input: &mut &[u8], at: u32, n: u32) -> Result<u32, Stop> {
        while self.count < at + n {
            let (&byte, rest) = input.split_first().ok_or(Stop::NeedsInput)?;
            *input = rest;
            self.buffer |= u64::from(byte) << self.count;
            self.count += 8;
        }
        Ok(((self.buffer >> at) & ((1 << n) - 1)) as u32)
    }

    /// Uses the next `n` bits (held: peeked before).
    fn consume(&mut self, n: u32) {
        self.buffer >>= n;
        self.count -= n;
    }

    /// Drops the bits up to the next byte boundary.
    fn align(&mut self) {
        self.consume(self.count % 8);
    }
}

/// A canonical Huffman code: how many codes of each length, and the
/// symbols in code order.
#[derive(Debug, Clone, Copy)]
struct Huffman {
    /// Codes of each length 0..=15 bits (`count[0]`: unused symbols).
    count: [u16; MAX_BITS + 1],
    /// Symbols ordered by code (the first `count[1..].sum()` are used).
    symbol: [u16; LITERAL_SYMBOLS],
}

impl Huffman {
    const EMPTY: Self = Self {
        count: [0; MAX_BITS + 1],
        symbol: [0; LITERAL_SYMBOLS],
    };

    /// Builds the code of symbols with these code `lengths` (0: unused; at
    /// most [`LITERAL_SYMBOLS`]). Over-subscribed lengths are corrupt, and
    /// so is an incomplete code unless `single_allowed` and it has at most
    /// one code (of 1 bit), as zlib allows for literal and distance codes.
    fn build(&mut self, lengths: &[u8], single_allowed: bool) -> Result<(), Stop> {
        self.count = [0; MAX_BITS + 1];
        for &length in lengths {
            *self
                .count
                .get_mut(usize::from(length))
                .ok_or(Stop::Corrupt)? += 1;
        }
        let mut left: i32 = 1;
        let mut offsets = [0u16; MAX_BITS + 1];
        for bits in 1..=MAX_BITS {
            left = (left << 1) - i32::from(self.count[bits]);
            if left < 0 {
                return Err(Stop::Corrupt);
            }
            if bits < MAX_BITS {
                offsets[bits + 1] = offsets[bits] + self.count[bits];
            }
        }
        let unused = usize::from(self.count[0]) + usize::from(self.count[1]);
        if left > 0 && !(single_allowed && unused == lengths.len()) {
            return Err(Stop::Corrupt);
        }
        for (symbol, &length) in (0u16..).zip(lengths) {
            if length != 0 {
                let offset = &mut offsets[usize::from(length)];
                *self
                    .symbol
                    .get_mut(usize::from(*offset))
                    .ok_or(Stop::Corrupt)? = symbol;
                *offset += 1;
            }
        }
        Ok(())
    }

    /// The symbol whose code starts `at` bits ahead, and its code's length
    /// in bits (codes are sent most significant bit first).
    fn decode(&self, bits: &mut Bits, input: &mut &[u8], at: u32) -> Result<(u16, u32), Stop> {
        let (mut code, mut first, mut index) = (0u32, 0u32, 0u32);
        for length in 1..=MAX_BITS as u32 {
            code |= bits.peek(input, at + length - 1, 1)?;
            let count = u32::from(self.count[length as usize]);
            if code < first + count {
                let symbol = self.symbol.get((index + code - first) as usize);
                return Ok((*symbol.ok_or(Stop::Corrupt)?, length));
            }
            index += count;
            first = (first + count) << 1;
            code <<= 1;
        }
        Err(Stop::Corrupt)
    }
}

/// The state of one zlib stream's inflation (about 1.6 KB).
#[derive(Debug, Clone)]
pub struct Inflater {
    state: State,
    bits: Bits,
    /// The block being inflated is the stream's last.
    last_block: bool,
    /// Literal/length code lengths of a dynamic block (HLIT).
    literal_codes: u16,
    /// Distance code lengths of a dynamic block (HDIST).
    distance_codes: u16,
    /// Code-length code lengths of a dynamic block (HCLEN).
    code_length_codes: u16,
    /// Code lengths read so far of a dynamic block's codes.
    lengths: [u8; MAX_LENGTHS],
    /// The block's literal/length code.
    literal: Huffman,
    /// The block's distance code (while its code lengths are read: the
    /// code-length code).
    distance: Huffman,
}

impl Default for Inflater {
    fn default() -> Self {
        Self::new()
    }
}

impl Inflater {
    /// Ready for a stream's first byte.
    pub const fn new() -> Self {
        Self {
            state: State::Header,
            bits: Bits {
                buffer: 0,
                count: 0,
            },
            last_block: false,
            literal_codes: 0,
            distance_codes: 0,
            code_length_codes: 0,
            lengths: [0; MAX_LENGTHS],
            literal: Huffman::EMPTY,
            distance: Huffman::EMPTY,
        }
    }

    /// Inflates the next piece of the stream into `out` after its first
    /// `*out_len` bytes (the stream's output so far), advancing `out_len`.
    /// `Ok` once the stream has ended exactly at the piece's end, its
    /// checksum checked; [`Stop::NeedsInput`] when the piece ran out first.
    pub fn inflate(
        &mut self,
        input: &[u8],
        out: &mut [u8],
        out_len: &mut usize,
    ) -> Result<(), Stop> {
        let mut input = input;
        while self.state != State::Done {
            self.step(&mut input, out, out_len)?;
        }
        if input.is_empty() {
            Ok(())
        } else {
            Err(Stop::Corrupt)
        }
    }

    /// Takes the next step (all the bits it needs, or none).
    fn step(&mut self, input: &mut &[u8], out: &mut [u8], out_len: &mut usize) -> Result<(), Stop> {
        let bits = &mut self.bits;
        self.state = match self.state {
            State::Header => {
                let header = bits.peek(input, 0, 16)?;
                let (method, flags) = (header & 0xff, header >> 8);
                let checked = ((method << 8) | flags) % 31 == 0;
                // Deflate, a window of at most 32 KiB, no preset dictionary.
                if method & 0x0f != 8 || method >> 4 > 7 || !checked || flags & 0x20 != 0 {
                    return Err(Stop::Corrupt);
                }
                bits.consume(16);
                State::Block
            }
            State::Block => {
                let header = bits.peek(input, 0, 3)?;
                bits.consume(3);
                self.last_block = header & 1 != 0;
                match header >> 1 {
                    0 => State::StoredLength,
                    1 => {
                        self.fixed_codes()?;
                        State::Codes
                    }
                    2 => State::Counts,
                    _ => return Err(Stop::Corrupt),
                }
            }
            State::StoredLength => {
                bits.align();
                let lengths = bits.peek(input, 0, 32)?;
                let length = lengths as u16;
                if length != !(lengths >> 16) as u16 {
                    return Err(Stop::Corrupt);
                }
                bits.consume(32);
                State::Stored(length)
            }
            State::Stored(0) => self.end_of_block(),
            State::Stored(left) => {
                let byte = bits.peek(input, 0, 8)?;
                put(out, out_len, byte as u8)?;
                bits.consume(8);
                State::Stored(left - 1)
            }
            State::Counts => {
                let counts = bits.peek(input, 0, 14)?;
                self.literal_codes = (counts & 0x1f) as u16 + 257;
                self.distance_codes = ((counts >> 5) & 0x1f) as u16 + 1;
                self.code_length_codes = (counts >> 10) as u16 + 4;
                if self.literal_codes > 286 || self.distance_codes > 30 {
                    return Err(Stop::Corrupt);
                }
                bits.consume(14);
                State::CodeLengthLengths(0)
            }
            State::CodeLengthLengths(read) => self.code_length_length(input, read)?,
            State::Lengths(read) => self.code_lengths(input, read)?,
            State::Codes => self.code(input, out, out_len)?,
            State::Trailer => {
                bits.align();
                let checksum = bits.peek(input, 0, 32)?.swap_bytes();
                let text = out.get(..*out_len).ok_or(Stop::Corrupt)?;
                if checksum != adler32(text) {
                    return Err(Stop::Corrupt);
                }
                bits.consume(32);
                State::Done
            }
            State::Done => State::Done,
        };
        Ok(())
    }

    /// The state after a block: the next block's header, or the trailer.
    fn end_of_block(&self) -> State {
        if self.last_block {
            State::Trailer
        } else {
            State::Block
        }
    }

    /// Builds the fixed literal/length and distance codes (RFC 1951 3.2.6).
    fn fixed_codes(&mut self) -> Result<(), Stop> {
        let mut lengths = [0u8; LITERAL_SYMBOLS];
        for (symbol, length) in lengths.iter_mut().enumerate() {
            *length = match symbol {
                0..144 => 8,
                144..256 => 9,
                256..280 => 7,
                _ => 8,
            };
        }
        self.literal.build(&lengths, false)?;
        self.distance.build(&[5; 32], false)
    }

    /// Reads the code-length code's length number `read` (3 bits each, the
    /// ones not sent are 0); after the last, builds the code-length code.
    fn code_length_length(&mut self, input: &mut &[u8], read: u16) -> Result<State, Stop> {
        let Some(&symbol) = CODE_LENGTH_ORDER.get(usize::from(read)) else {
            self.distance.build(&self.lengths[..19], false)?;
            return Ok(State::Lengths(0));
        };
        let length = if read < self.code_length_codes {
            let length = self.bits.peek(input, 0, 3)?;
            self.bits.consume(3);
            length as u8
        } else {
            0
        };
        self.lengths[usize::from(symbol)] = length;
        Ok(State::CodeLengthLengths(read + 1))
    }

    /// Reads the next literal/length or distance code length (or a run of
    /// them) after `read` of them; after the last, builds both codes.
    fn code_lengths(&mut self, input: &mut &[u8], read: u16) -> Result<State, Stop> {
        let (literals, total) = (
            usize::from(self.literal_codes),
            usize::from(self.literal_codes + self.distance_codes),
        );
        let read = usize::from(read);
        if read >= total {
            if self.lengths[256] == 0 {
                return Err(Stop::Corrupt); // no end-of-block code
            }
            let literal = self.lengths.get(..literals).ok_or(Stop::Corrupt)?;
            self.literal.build(literal, true)?;
            let distance = self.lengths.get(literals..total).ok_or(Stop::Corrupt)?;
            self.distance.build(distance, true)?;
            return Ok(State::Codes);
        }
        let (symbol, code_bits) = self.distance.decode(&mut self.bits, input, 0)?;
        let (value, extra, base) = match symbol {
            0..16 => (symbol as u8, 0, 1),
            16 => {
                let previous = read.checked_sub(1).and_then(|i| self.lengths.get(i));
                (*previous.ok_or(Stop::Corrupt)?, 2, 3)
            }
            17 => (0, 3, 3),
            _ => (0, 7, 11),
        };
        let repeat = base + self.bits.peek(input, code_bits, extra)? as usize;
        if read + repeat > total {
            return Err(Stop::Corrupt);
        }
        let run = self.lengths.get_mut(read..read + repeat);
        run.ok_or(Stop::Corrupt)?.fill(value);
        self.bits.consume(code_bits + extra);
        Ok(State::Lengths((read + repeat) as u16))
    }

    /// Inflates the next literal, length/distance pair or end of block.
    fn code(
        &mut self,
        input: &mut &[u8],
        out: &mut [u8],
        out_len: &mut usize,
    ) -> Result<State, Stop> {
        let bits = &mut self.bits;
        let (symbol, mut used) = self.literal.decode(bits, input, 0)?;
        let Some(length_symbol) = symbol.checked_sub(257) else {
            if symbol == 256 {
                bits.consume(used);
                return Ok(self.end_of_block());
            }
            put(out, out_len, symbol as u8)?;
            bits.consume(used);
            return Ok(State::Codes);
        };
        let length = read_extra(
            bits,
            input,
            &mut used,
            &LENGTH_BASE,
            &LENGTH_EXTRA,
            length_symbol,
        )?;
        let (distance_symbol, distance_bits) = self.distance.decode(bits, input, used)?;
        used += distance_bits;
        let distance = read_extra(
            bits,
            input,
            &mut used,
            &DISTANCE_BASE,
            &DISTANCE_EXTRA,
            distance_symbol,
        )?;
        let start = out_len.checked_sub(distance).ok_or(Stop::Corrupt)?;
        for from in start..start + length {
            let byte = *out.get(from).ok_or(Stop::Corrupt)?;
            put(out, out_len, byte)?;
        }
        bits.consume(used);
        Ok(State::Codes)
    }
}

/// The base value of `symbol` plus its extra bits, read `used` bits ahead
/// (`used` then counts them).
fn read_extra(
    bits: &mut Bits,
    input: &mut &[u8],
    used: &mut u32,
    base: &[u16],
    extra: &[u8],
    symbol: u16,
) -> Result<usize, Stop> {
    let index = usize::from(symbol);
    let (Some(&base), Some(&extra)) = (base.get(index), extra.get(index)) else {
        return Err(Stop::Corrupt);
    };
    let value = bits.peek(input, *used, u32::from(extra))?;
    *used += u32::from(extra);
    Ok(usize::from(base) + value as usize)
}

/// Appends `byte` to the output.
fn put(out: &mut [u8], out_len: &mut usize, byte: u8) -> Result<(), Stop> {
    *out.get_mut(*out_len).ok_or(Stop::OutputFull)? = byte;
    *out_len += 1;
    Ok(())
}

/// The Adler-32 checksum of `data` (RFC 1950).
fn adler32(data: &[u8]) -> u32 {
    const MOD: u32 = 65521;
    let (mut a, mut b) = (1u32, 0u32);
    for &byte in data {
        a = (a + u32::from(byte)) % MOD;
        b = (b + a) % MOD;
    }
    (b << 16) | a
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use miniz_oxide::deflate::core::{
        CompressionStrategy as Strategy, CompressorOxide, TDEFLFlush, TDEFLStatus, compress,
        create_comp_flags_from_zip_params,
    };
    use std::string::String;
    use std::vec;
    use std::vec::Vec;

    /// Klipper data dictionaries of real MCUs, and all of them in one text
    /// (twice: long enough for several blocks).
    fn dictionaries() -> Vec<Vec<u8>> {
        let peers = onechip_golden::golden_dir().join("../peers");
        let mut texts: Vec<Vec<u8>> = ["atmega2560", "lpc176x", "stm32f446", "stm32h723"]
            .iter()
            .map(|name| onechip_golden::dict(name).into_bytes())
            .collect();
        for peer in ["avr", "linux"] {
            let path = peers.join(peer).join("klipper.dict");
            texts.push(std::fs::read(&path).unwrap_or_else(|e| panic!("{path:?}: {e}")));
        }
        texts.push(texts.concat().repeat(2));
        texts
    }

    /// `text` zlib-compressed at `level` (0: stored blocks) with `strategy`.
    fn zlib(text: &[u8], level: u8, strategy: Strategy) -> Vec<u8> {
        let flags = create_comp_flags_from_zip_params(level.into(), 1, strategy.into());
        let mut compressor = CompressorOxide::new(flags);
        let mut out = vec![0; text.len() + text.len() / 8 + 64];
        let (status, read, written) = compress(&mut compressor, text, &mut out, TDEFLFlush::Finish);
        assert_eq!((status, read), (TDEFLStatus::Done, text.len()));
        out.truncate(written);
        out
    }

    /// Inflates `stream` fed in pieces of `piece` bytes into a buffer of
    /// `capacity` bytes: the text, or why it stopped (at the first piece
    /// that does not need more input).
    fn inflate(stream: &[u8], piece: usize, capacity: usize) -> Result<Vec<u8>, Stop> {
        let mut inflater = Inflater::new();
        let mut out = vec![0; capacity];
        let mut len = 0;
        let mut result = Err(Stop::NeedsInput);
        for chunk in stream.chunks(piece) {
            result = inflater.inflate(chunk, &mut out, &mut len);
            if result != Err(Stop::NeedsInput) {
                break;
            }
        }
        result.map(|()| out[..len].to_vec())
    }

    #[test]
    fn dictionaries_round_trip_in_every_block_kind_and_piece_size() {
        for text in dictionaries() {
            for (level, strategy) in [
                (0, Strategy::Default),
                (1, Strategy::Fixed),
                (6, Strategy::Default),
                (9, Strategy::Default),
                (9, Strategy::RLE),
            ] {
                let stream = zlib(&text, level, strategy);
                for piece in [1, 3, 40, stream.len()] {
                    let inflated = inflate(&stream, piece, text.len());
                    assert!(
                        inflated.as_deref() == Ok(&text[..]),
                        "level {level} piece {piece}"
                    );
                }
            }
        }
    }

    #[test]
    fn a_stream_from_zlib_itself_inflates() {
        // Python's zlib.compress(TEXT, 9): a fixed-Huffman block.
        const TEXT: &str =
            "identify_response offset=%u data=%.*s identify offset=%u count=%c identify_response";
        const STREAM: [u8; 61] = [
            0x78, 0xda, 0xcb, 0x4c, 0x49, 0xcd, 0x2b, 0xc9, 0x4c, 0xab, 0x8c, 0x2f, 0x4a, 0x2d,
            0x2e, 0xc8, 0xcf, 0x2b, 0x4e, 0x55, 0xc8, 0x4f, 0x4b, 0x2b, 0x4e, 0x2d, 0xb1, 0x55,
            0x2d, 0x55, 0x48, 0x49, 0x2c, 0x49, 0xb4, 0x55, 0xd5, 0xd3, 0x2a, 0x56, 0xc8, 0x84,
            0xaa, 0x42, 0x92, 0x4c, 0xce, 0x2f, 0xcd, 0x03, 0x32, 0x92, 0xe1, 0x72, 0x70, 0x13,
            0x00, 0x10, 0xa1, 0x1e, 0xe2,
        ];
        let text = inflate(&STREAM, 5, 100).expect("inflates");
        assert_eq!(String::from_utf8(text).expect("text"), TEXT);
    }

    #[test]
    fn a_short_buffer_or_trailing_bytes_are_errors() {
        let text = onechip_golden::dict("stm32h723").into_bytes();
        let mut stream = zlib(&text, 9, Strategy::Default);
        assert_eq!(inflate(&stream, 40, text.len() - 1), Err(Stop::OutputFull));
        stream.push(0);
        assert_eq!(inflate(&stream, 40, text.len()), Err(Stop::Corrupt));
    }

    /// Runs `check` on the golden dictionary `name` and each of its zlib
    /// streams of `kinds` (level, strategy).
    fn each_stream(name: &str, kinds: [(u8, Strategy); 2], check: impl Fn(&[u8], &[u8])) {
        let text = onechip_golden::dict(name).into_bytes();
        for (level, strategy) in kinds {
            check(&text, &zlib(&text, level, strategy));
        }
    }

    #[test]
    fn every_truncation_needs_input() {
        let kinds = [(0, Strategy::Default), (9, Strategy::Default)];
        each_stream("atmega2560", kinds, |text, stream| {
            for end in 0..stream.len() {
                let result = inflate(&stream[..end], 40, text.len());
                assert_eq!(result, Err(Stop::NeedsInput), "{end} bytes");
            }
        });
    }

    #[test]
    fn damaged_streams_are_errors_not_panics() {
        let kinds = [(1, Strategy::Fixed), (9, Strategy::Default)];
        each_stream("lpc176x", kinds, |text, stream| {
            let flips = (0..stream.len()).flat_map(|at| [(at, 0x01), (at, 0x40)]);
            for (at, flip) in flips {
                let mut damaged = stream.to_vec();
                damaged[at] ^= flip;
                // Any error will do (a longer text fills the buffer, a lost
                // last-block flag needs more input), or the text itself: the
                // padding before the checksum carries nothing.
                if let Ok(inflated) = inflate(&damaged, 40, text.len()) {
                    assert_eq!(inflated, text, "byte {at} ^ {flip:#x}");
                }
            }
        });
    }

    #[test]
    fn random_bytes_after_a_header_are_errors_not_panics() {
        let mut seed = 0x2545_f491_4f6c_dd1d_u64;
        let mut out = [0; 4096];
        for _ in 0..2000 {
            let mut stream = vec![0x78, 0x9c];
            for _ in 0..64 {
                seed ^= seed << 13;
                seed ^= seed >> 7;
                seed ^= seed << 17;
                stream.push(seed as u8);
            }
            let mut len = 0;
            let result = Inflater::new().inflate(&stream, &mut out, &mut len);
            assert!(result.is_err(), "{stream:x?}");
        }
    }
}
