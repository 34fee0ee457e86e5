//! Fetching an MCU's data dictionary: the `identify` exchange.
//!
//! The host asks `identify offset=N count=40` repeatedly; the MCU answers
//! `identify_response offset=N data=…` with that slice of its
//! zlib-compressed dictionary, and an empty slice past the end. The
//! [`Fetcher`] inflates the chunks as they arrive straight into the caller's
//! buffer (no heap, no copy of the compressed data) with [`crate::inflate`],
//! checking the zlib checksum at the end.

use crate::inflate::{Inflater, Stop};
use core::mem::MaybeUninit;
use core::ptr::addr_of_mut;

/// Bytes requested per `identify`, as Klipper's host asks.
pub const CHUNK: u8 = 40;

/// Why fetching the dictionary failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IdentifyError {
    /// The answer is for another offset than the one asked (stale reply).
    WrongOffset {
        /// Offset asked.
        expected: u32,
        /// Offset answered.
        got: u32,
    },
    /// The dictionary inflates to more than the output buffer holds.
    TooLarge,
    /// The compressed data is corrupt (or its checksum is wrong).
    Corrupt,
    /// The MCU's data ended before the compressed stream did.
    Truncated,
}

impl core::fmt::Display for IdentifyError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::WrongOffset { expected, got } => {
                write!(f, "identify answer for offset {got}, expected {expected}")
            }
            Self::TooLarge => f.write_str("data dictionary larger than its buffer"),
            Self::Corrupt => f.write_str("data dictionary is not valid zlib data"),
            Self::Truncated => f.write_str("data dictionary ended early"),
        }
    }
}

/// Where a fetch stands after an answer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Progress {
    /// Ask again at [`Fetcher::offset`].
    More,
    /// The dictionary is complete: this many bytes of JSON in the buffer.
    Done(usize),
}

/// Host-side state of one dictionary fetch.
pub struct Fetcher<'b> {
    inflater: Inflater,
    out: &'b mut [u8],
    out_len: usize,
    offset: u32,
    stream_ended: bool,
}

impl<'b> Fetcher<'b> {
    /// Starts a fetch that inflates into `out`.
    pub fn new(out: &'b mut [u8]) -> Self {
        let mut slot = MaybeUninit::uninit();
        Self::init_in(&mut slot, out);
        // SAFETY: `init_in` initialised it.
        unsafe { slot.assume_init() }
    }

    /// [`Self::new`] built in place in `slot`: the inflate state is about
    /// 1.6 KB, which a microcontroller's stack should not carry twice.
    pub fn init_in<'s>(slot: &'s mut MaybeUninit<Self>, out: &'b mut [u8]) -> &'s mut Self {
        let p = slot.as_mut_ptr();
        // SAFETY: `p` is valid for writes; each field is written once, in
        // place, before the slot is taken as initialised.
        unsafe {
            addr_of_mut!((*p).inflater).write(Inflater::new());
            addr_of_mut!((*p).out).write(out);
            addr_of_mut!((*p).out_len).write(0);
            addr_of_mut!((*p).offset).write(0);
            addr_of_mut!((*p).stream_ended).write(false);
            slot.assume_init_mut()
        }
    }

    /// The same fetch from its start, into the same buffer.
    pub fn restart(&mut self) {
        self.inflater = Inflater::new();
        (self.out_len, self.offset, self.stream_ended) = (0, 0, false);
    }

    /// The offset to ask for next (`identify offset=… count=CHUNK`).
    pub fn offset(&self) -> u32 {
        self.offset
    }

    /// Takes one `identify_response`.
    pub fn on_response(&mut self, offset: u32, data: &[u8]) -> Result<Progress, IdentifyError> {
        if offset != self.offset {
            return Err(IdentifyError::WrongOffset {
                expected: self.offset,
                got: offset,
            });
        }
        if data.is_empty() {
            return if self.stream_ended {
                Ok(Progress::Done(self.out_len))
            } else {
                Err(IdentifyError::Truncated)
            };
        }
        if self.stream_ended {
            return Err(IdentifyError::Corrupt);
        }
        self.offset += data.len() as u32;
        match self.inflater.inflate(data, self.out, &mut self.out_len) {
            Ok(()) => {
                self.stream_ended = true;
                Ok(Progress::More)
            }
            Err(Stop::NeedsInput) => Ok(Progress::More),
            Err(Stop::OutputFull) => Err(IdentifyError::TooLarge),
            Err(Stop::Corrupt) => Err(IdentifyError::Corrupt),
        }
    }

    /// The dictionary text inflated so far.
    pub fn output(&self) -> &[u8] {
        self.out.get(..self.out_len).unwrap_or_default()
    }

    /// Ends the fetch, handing back the dictionary text inflated so far
    /// (the fetcher keeps no buffer after).
    pub fn take_output(&mut self) -> &'b [u8] {
        let out: &'b mut [u8] = core::mem::take(&mut self.out);
        let out: &'b [u8] = out;
        out.get(..core::mem::take(&mut self.out_len))
            .unwrap_or_default()
    }
}

/// The MCU side: serves a compressed dictionary in `identify` chunks.
#[derive(Debug, Clone, Copy)]
pub struct Server {
    compressed: &'static [u8],
}

impl Server {
    /// Serves `compressed` (zlib data).
    pub const fn new(compressed: &'static [u8]) -> Self {
        Self { compressed }
    }

    /// The slice answering `identify offset count` (empty past the end).
    pub fn chunk(&self, offset: u32, count: u8) -> &'static [u8] {
        let start = (offset as usize).min(self.compressed.len());
        let end = (start + usize::from(count)).min(self.compressed.len());
        &self.compressed[start..end]
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec;

    fn fetch(server: &Server, out: &mut [u8]) -> Result<usize, IdentifyError> {
        let mut fetcher = Fetcher::new(out);
        loop {
            let offset = fetcher.offset();
            if let Progress::Done(n) = fetcher.on_response(offset, server.chunk(offset, CHUNK))? {
                return Ok(n);
            }
        }
    }

    #[test]
    fn the_built_in_dictionary_round_trips_through_identify() {
        let server = Server::new(crate::mcu::DICTIONARY_ZLIB);
        let mut out = vec![0u8; 8192];
        let n = fetch(&server, &mut out).expect("fetches");
        assert_eq!(&out[..n], crate::mcu::DICTIONARY_JSON.as_bytes());
    }

    #[test]
    fn a_small_buffer_is_an_error_not_an_overrun() {
        let server = Server::new(crate::mcu::DICTIONARY_ZLIB);
        let mut out = [0u8; 64];
        assert_eq!(fetch(&server, &mut out), Err(IdentifyError::TooLarge));
    }

    #[test]
    fn damaged_or_short_data_is_detected() {
        let mut damaged = crate::mcu::DICTIONARY_ZLIB.to_vec();
        let last = damaged.len() - 1;
        damaged[last] ^= 1; // breaks the Adler-32 checksum
        let server = Server::new(damaged.leak());
        let mut out = vec![0u8; 8192];
        assert_eq!(fetch(&server, &mut out), Err(IdentifyError::Corrupt));

        let short = &crate::mcu::DICTIONARY_ZLIB[..crate::mcu::DICTIONARY_ZLIB.len() - 10];
        assert_eq!(
            fetch(&Server::new(short), &mut out),
            Err(IdentifyError::Truncated)
        );
    }

    #[test]
    fn a_stale_answer_is_refused() {
        let mut out = vec![0u8; 8192];
        let mut fetcher = Fetcher::new(&mut out);
        assert_eq!(
            fetcher.on_response(40, b"x"),
            Err(IdentifyError::WrongOffset {
                expected: 0,
                got: 40
            })
        );
    }

    #[test]
    fn a_fetch_restarted_midway_starts_over_and_hands_over_the_whole_text() {
        let server = Server::new(crate::mcu::DICTIONARY_ZLIB);
        let mut out = vec![0u8; 8192];
        let mut fetcher = Fetcher::new(&mut out);
        // Half of it, then the link goes: the fetch starts over.
        for _ in 0..3 {
            let offset = fetcher.offset();
            fetcher
                .on_response(offset, server.chunk(offset, CHUNK))
                .expect("more");
        }
        fetcher.restart();
        assert_eq!((fetcher.offset(), fetcher.output().len()), (0, 0));
        let n = loop {
            let offset = fetcher.offset();
            match fetcher.on_response(offset, server.chunk(offset, CHUNK)) {
                Ok(Progress::Done(n)) => break n,
                Ok(Progress::More) => {}
                Err(e) => panic!("{e:?}"),
            }
        };
        let text = fetcher.take_output();
        assert_eq!(text.len(), n);
        assert_eq!(text, crate::mcu::DICTIONARY_JSON.as_bytes());
        assert!(fetcher.take_output().is_empty(), "handed over once");
    }
}
