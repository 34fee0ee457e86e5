//! The envelope Marlin-family hosts put around console lines: a line
//! number `N<n>` and a `*<checksum>` (the XOR of every byte before the
//! `*`), so that a line corrupted or lost on the wire is sent again.
//!
//! A numbered line is run only if its checksum is right and its number
//! follows the last one run. Otherwise it is not run, and the host is asked
//! to send again from the line after the last one run (`Resend: N`). A
//! line numbered at or below the last one run (a resend of a line that
//! already ran) is acknowledged without running it again. `M110 N<n>`
//! sets the last line number. Lines without a number run as they come,
//! unless they carry a checksum (as Marlin: such a line is the tail of a
//! numbered line split by a corrupted byte).

use core::fmt;

/// Why a line was refused, with Marlin's wording (hosts recognise these
/// as requests to resend, not as printer faults).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// The checksum does not match the line.
    ChecksumMismatch,
    /// A numbered line without a checksum.
    NoChecksum,
    /// A checksum on a line without a number: most likely the tail of a
    /// numbered line whose middle byte was corrupted into a line end.
    NoLineNumber,
    /// The line number skips one or more lines.
    NotNext,
    /// The line overflowed the line buffer, so neither its number nor its
    /// checksum could be read.
    TooLong {
        /// Its length, bytes.
        len: usize,
    },
}

/// What to do with one line.
#[derive(Debug, PartialEq, Eq)]
pub enum Checked<'a> {
    /// Run it: the line without its number and checksum.
    Run(&'a [u8]),
    /// A line that already ran: acknowledge it, do not run it.
    Repeat,
    /// Refuse it: report `refusal`, then ask for line `resend` again.
    Resend {
        /// Why.
        refusal: Refusal,
        /// The last line number run.
        last: i64,
        /// The line to send again (the one after `last`).
        resend: i64,
    },
}

/// The line numbering state of one console.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct LineNumbers {
    /// The number of the last numbered line run (`M110 N-1` makes the
    /// next one 0, as Printrun does).
    last: i64,
    /// A numbered line has arrived since start: the host keeps a history
    /// of its lines and can resend.
    numbered: bool,
}

impl LineNumbers {
    /// No line run yet (the host starts at line 1, or sends `M110`).
    pub const fn new() -> Self {
        Self {
            last: 0,
            numbered: false,
        }
    }

    /// The number of the last numbered line run.
    pub fn last(&self) -> i64 {
        self.last
    }

    /// Checks one complete line (without its terminator).
    pub fn check<'a>(&mut self, line: &'a [u8]) -> Checked<'a> {
        let (body, checksum) = split_checksum(line);
        let (number, command) = split_number(trim(body));
        let computed = body.iter().fold(0u8, |acc, b| acc ^ b);
        let checksum_ok = match checksum {
            Some(Ok(sent)) => sent == computed,
            Some(Err(())) => false,
            None => true,
        };
        let Some(number) = number else {
            if checksum.is_some() {
                return self.refuse(Refusal::NoLineNumber);
            }
            if is_m110(command)
                && let Some(n) = m110_number(command)
            {
                self.last = n;
            }
            return Checked::Run(command);
        };
        self.numbered = true;
        if checksum.is_none() {
            return self.refuse(Refusal::NoChecksum);
        }
        if !checksum_ok {
            return self.refuse(Refusal::ChecksumMismatch);
        }
        if is_m110(command) {
            // M110 sets the numbering: to its N parameter, or else to the
            // number of the line that carries it.
            self.last = m110_number(command).unwrap_or(number);
            return Checked::Run(command);
        }
        if number <= self.last {
            return Checked::Repeat;
        }
        if number != self.last + 1 {
            return self.refuse(Refusal::NotNext);
        }
        self.last = number;
        Checked::Run(command)
    }

    /// A line too long for the buffer: refused (with a resend if the host
    /// numbers its lines).
    pub fn too_long(&mut self, len: usize) -> Checked<'static> {
        self.refuse(Refusal::TooLong { len })
    }

    /// Refuses the line, asking for the one after the last run.
    fn refuse(&self, refusal: Refusal) -> Checked<'static> {
        Checked::Resend {
            refusal,
            last: self.last,
            resend: self.last + 1,
        }
    }

    /// True once a numbered line has arrived: a refused line is worth a
    /// `Resend:` request.
    pub fn host_numbers_lines(&self) -> bool {
        self.numbered
    }
}

impl fmt::Display for Refusal {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::ChecksumMismatch => f.write_str("checksum mismatch"),
            Self::NoChecksum => f.write_str("No Checksum with line number"),
            Self::NoLineNumber => f.write_str("No Line Number with checksum"),
            Self::NotNext => f.write_str("Line Number is not Last Line Number+1"),
            Self::TooLong { len } => {
                write!(f, "Line too long ({len} bytes), checksum not verified")
            }
        }
    }
}

/// Writes a refusal as Marlin does: `Error:<why>, Last Line: <n>`, then
/// `Resend: <n+1>` if the host numbers its lines (the caller adds `ok`).
pub fn write_refusal(
    out: &mut impl fmt::Write,
    refusal: Refusal,
    last: i64,
    resend: Option<i64>,
) -> fmt::Result {
    writeln!(out, "Error:{refusal}, Last Line: {last}")?;
    match resend {
        Some(n) => writeln!(out, "Resend: {n}"),
        None => Ok(()),
    }
}

/// The line before a trailing `*<digits>`, and the checksum: None without
/// a `*`, Err if what follows the last `*` is not a number below 256.
fn split_checksum(line: &[u8]) -> (&[u8], Option<Result<u8, ()>>) {
    let Some(star) = line.iter().rposition(|&b| b == b'*') else {
        return (line, None);
    };
    let digits = trim(&line[star + 1..]);
    let value = (!digits.is_empty() && digits.len() <= 3 && digits.iter().all(u8::is_ascii_digit))
        .then(|| {
            digits
                .iter()
                .fold(0u16, |v, d| v * 10 + u16::from(d - b'0'))
        })
        .and_then(|v| u8::try_from(v).ok())
        .ok_or(());
    (&line[..star], Some(value))
}

/// `N<digits>` (or `N-<digits>`) at the start, and the rest (trimmed).
fn split_number(body: &[u8]) -> (Option<i64>, &[u8]) {
    let [b'N' | b'n', rest @ ..] = body else {
        return (None, body);
    };
    let (negative, rest) = match rest {
        [b'-', rest @ ..] => (true, rest),
        _ => (false, rest),
    };
    let digits = rest.iter().take_while(|b| b.is_ascii_digit()).count();
    if digits == 0 || digits > 18 {
        // No number, or one too large for any host's history.
        return (None, body);
    }
    let number = rest[..digits]
        .iter()
        .fold(0i64, |v, d| v * 10 + i64::from(d - b'0'));
    let number = if negative { -number } else { number };
    (Some(number), trim(&rest[digits..]))
}

fn trim(bytes: &[u8]) -> &[u8] {
    bytes.trim_ascii()
}

/// `M110` as the command word.
fn is_m110(command: &[u8]) -> bool {
    let word = command
        .split(u8::is_ascii_whitespace)
        .next()
        .unwrap_or_default();
    word.eq_ignore_ascii_case(b"M110")
}

/// M110's `N` parameter.
fn m110_number(command: &[u8]) -> Option<i64> {
    command
        .split(u8::is_ascii_whitespace)
        .skip(1)
        .find_map(|word| match split_number(word) {
            (Some(n), []) => Some(n),
            _ => None,
        })
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::format;
    use std::string::String;

    /// `line` with its Marlin checksum appended.
    fn sum(line: &str) -> String {
        let c = line.bytes().fold(0u8, |a, b| a ^ b);
        format!("{line}*{c}")
    }

    fn resend(refusal: Refusal, last: i64) -> Checked<'static> {
        Checked::Resend {
            refusal,
            last,
            resend: last + 1,
        }
    }

    #[test]
    fn numbered_lines_run_in_order_without_their_envelope() {
        let mut n = LineNumbers::new();
        assert_eq!(
            n.check(sum("N1 G1 X10").as_bytes()),
            Checked::Run(b"G1 X10")
        );
        assert_eq!(n.check(sum("N2 M105").as_bytes()), Checked::Run(b"M105"));
        assert_eq!(n.last(), 2);
        assert!(n.host_numbers_lines());
    }

    #[test]
    fn m110_sets_the_numbering() {
        let mut n = LineNumbers::new();
        assert_eq!(
            n.check(sum("N0 M110 N0").as_bytes()),
            Checked::Run(b"M110 N0")
        );
        assert_eq!(n.last(), 0);
        assert_eq!(n.check(sum("N7 M110").as_bytes()), Checked::Run(b"M110"));
        assert_eq!(n.last(), 7);
        assert_eq!(n.check(sum("N8 G28").as_bytes()), Checked::Run(b"G28"));
        // Printrun starts from M110 N-1: its next line is N0.
        assert_eq!(
            n.check(sum("N-1 M110 N-1").as_bytes()),
            Checked::Run(b"M110 N-1")
        );
        assert_eq!(n.check(sum("N0 G28").as_bytes()), Checked::Run(b"G28"));
        assert_eq!(n.check(sum("N1 G28").as_bytes()), Checked::Run(b"G28"));
        // Unnumbered M110 N: also sets it.
        assert_eq!(n.check(b"M110 N41"), Checked::Run(b"M110 N41"));
        assert_eq!(n.check(sum("N42 G28").as_bytes()), Checked::Run(b"G28"));
    }

    #[test]
    fn corrupt_missing_or_skipped_lines_ask_for_the_next_line_again() {
        let mut n = LineNumbers::new();
        assert_eq!(n.check(sum("N1 G1 X1").as_bytes()), Checked::Run(b"G1 X1"));
        let mut bad = sum("N2 G1 X2").into_bytes();
        bad[5] = b'3';
        assert_eq!(n.check(&bad), resend(Refusal::ChecksumMismatch, 1));
        assert_eq!(n.check(b"N2 G1 X2"), resend(Refusal::NoChecksum, 1));
        assert_eq!(
            n.check(sum("N3 G1 X3").as_bytes()),
            resend(Refusal::NotNext, 1)
        );
        assert_eq!(n.check(b"N2 G1 X2*x"), resend(Refusal::ChecksumMismatch, 1));
        assert_eq!(
            n.check(b"N2 G1 X2*999"),
            resend(Refusal::ChecksumMismatch, 1)
        );
        assert_eq!(n.last(), 1, "nothing refused counts");
        assert_eq!(n.check(sum("N2 G1 X2").as_bytes()), Checked::Run(b"G1 X2"));
        assert_eq!(n.too_long(300), resend(Refusal::TooLong { len: 300 }, 2));
    }

    #[test]
    fn a_resent_line_that_already_ran_is_only_acknowledged() {
        let mut n = LineNumbers::new();
        for i in 1..=3 {
            let line = sum(&format!("N{i} G1 X{i}"));
            assert!(matches!(n.check(line.as_bytes()), Checked::Run(_)));
        }
        assert_eq!(n.check(sum("N2 G1 X2").as_bytes()), Checked::Repeat);
        assert_eq!(n.check(sum("N3 G1 X3").as_bytes()), Checked::Repeat);
        assert_eq!(n.check(sum("N4 G1 X4").as_bytes()), Checked::Run(b"G1 X4"));
    }

    #[test]
    fn unnumbered_lines_run_unless_they_carry_a_checksum() {
        let mut n = LineNumbers::new();
        assert_eq!(n.check(b"G28"), Checked::Run(b"G28"));
        assert_eq!(
            n.check(sum("G28").as_bytes()),
            resend(Refusal::NoLineNumber, 0)
        );
        assert_eq!(n.check(b"G28*1"), resend(Refusal::NoLineNumber, 0));
        assert!(!n.host_numbers_lines());
        // Not a line number: N without digits, or too many of them.
        assert_eq!(n.check(b"NOZZLE_WIPE"), Checked::Run(b"NOZZLE_WIPE"));
        assert_eq!(
            n.check(b"N9999999999999999999 G1"),
            Checked::Run(b"N9999999999999999999 G1")
        );
    }

    #[test]
    fn refusals_read_as_marlin_writes_them() {
        let mut s = String::new();
        write_refusal(&mut s, Refusal::ChecksumMismatch, 5, Some(6)).expect("String");
        assert_eq!(s, "Error:checksum mismatch, Last Line: 5\nResend: 6\n");
        let mut s = String::new();
        write_refusal(&mut s, Refusal::NotNext, 5, None).expect("String");
        assert_eq!(
            s,
            "Error:Line Number is not Last Line Number+1, Last Line: 5\n"
        );
    }
}
