//! Assembly of text lines from a byte stream (USB CDC packets, file blocks).
//!
//! Lines end at `\n` or `\r` (so CRLF, LF and lone CR all work); empty lines
//! are skipped. The buffer is fixed: a line longer than `N` bytes is reported
//! once as [`LineEvent::TooLong`] and the rest of it, up to its end, is dropped —
//! the following lines are unaffected.

/// One event produced by [`LineAssembler::push`].
#[derive(Debug, PartialEq, Eq)]
pub enum LineEvent<'a> {
    /// A complete line without its terminator.
    Complete(&'a [u8]),
    /// A line exceeded the buffer; `len` is how many bytes it had when it
    /// ended (its content is lost).
    TooLong {
        /// Length of the dropped line, in bytes.
        len: usize,
    },
}

/// Bounded line assembler holding at most `N` bytes of one pending line.
#[derive(Debug)]
pub struct LineAssembler<const N: usize> {
    buf: [u8; N],
    len: usize,
    /// Bytes of the current line beyond `N`, while it is being dropped.
    overflow: usize,
}

impl<const N: usize> Default for LineAssembler<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> LineAssembler<N> {
    /// An empty assembler.
    pub const fn new() -> Self {
        Self {
            buf: [0; N],
            len: 0,
            overflow: 0,
        }
    }

    /// True when no byte of a line is pending.
    pub fn is_empty(&self) -> bool {
        self.len == 0 && self.overflow == 0
    }

    /// Feeds one byte; returns an event when it ends a line.
    pub fn push(&mut self, byte: u8) -> Option<LineEvent<'_>> {
        if byte == b'\n' || byte == b'\r' {
            let (len, overflow) = (self.len, self.overflow);
            self.len = 0;
            self.overflow = 0;
            return match (len, overflow) {
                (0, 0) => None,
                (len, 0) => Some(LineEvent::Complete(&self.buf[..len])),
                (len, extra) => Some(LineEvent::TooLong { len: len + extra }),
            };
        }
        if self.len < N && self.overflow == 0 {
            self.buf[self.len] = byte;
            self.len += 1;
        } else {
            self.overflow += 1;
        }
        None
    }
}

/// The first word of a G-code line, after an optional `N<number>` line number.
pub fn command_word(line: &[u8]) -> &[u8] {
    let mut words = line
        .split(|b| b.is_ascii_whitespace())
        .filter(|w| !w.is_empty());
    let first = words.next().unwrap_or_default();
    if first.first().is_some_and(|b| b.eq_ignore_ascii_case(&b'N')) {
        words.next().unwrap_or_default()
    } else {
        first
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec::Vec;

    fn lines<const N: usize>(input: &[u8]) -> Vec<Result<Vec<u8>, usize>> {
        let mut asm = LineAssembler::<N>::new();
        let mut out = Vec::new();
        for &b in input {
            match asm.push(b) {
                Some(LineEvent::Complete(l)) => out.push(Ok(l.to_vec())),
                Some(LineEvent::TooLong { len }) => out.push(Err(len)),
                None => {}
            }
        }
        out
    }

    #[test]
    fn splits_on_any_line_ending_and_skips_blank_lines() {
        let got = lines::<16>(b"G28\r\nG1 X1\n\n\rM400\r");
        assert_eq!(
            got,
            [
                Ok(b"G28".to_vec()),
                Ok(b"G1 X1".to_vec()),
                Ok(b"M400".to_vec())
            ]
        );
    }

    #[test]
    fn an_overlong_line_is_reported_once_and_loses_no_neighbour() {
        let got = lines::<4>(b"G1\nG1 X10 Y10\nM84\n");
        assert_eq!(got, [Ok(b"G1".to_vec()), Err(10), Ok(b"M84".to_vec())]);
    }

    #[test]
    fn a_line_of_exactly_capacity_fits() {
        assert_eq!(lines::<4>(b"M114\n"), [Ok(b"M114".to_vec())]);
    }

    #[test]
    fn an_unterminated_tail_stays_pending() {
        assert!(lines::<8>(b"G1 X").is_empty());
    }
}
