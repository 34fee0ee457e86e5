//! The firmware's answers to lines arriving on the console (USB CDC).
//!
//! Hosts such as OctoPrint, Pronterface and Cura send one line and wait for
//! `ok` before the next, so every line, good or bad, gets exactly one `ok`,
//! preceded by any reply text; errors are reported on a line starting with
//! `!!` as Klipper does. M115 is answered here; every other command goes to
//! the runner the board supplies (the printer).

use crate::line::LineEvent;
use core::fmt::{Display, Write};

/// An error message from a runner, owned (the error it describes may borrow
/// the line) and bounded; longer messages are cut.
pub type ErrorText = heapless::String<96>;

/// Formats `e` as an [`ErrorText`], cutting what does not fit.
pub fn error_text(e: &impl Display) -> ErrorText {
    cut_text(e)
}

/// Formats `e` into a string of at most `N` bytes, cutting what does not
/// fit (at a character boundary).
pub fn cut_text<const N: usize>(e: &impl Display) -> heapless::String<N> {
    struct Cut<const N: usize>(heapless::String<N>);
    impl<const N: usize> Write for Cut<N> {
        fn write_str(&mut self, s: &str) -> core::fmt::Result {
            for c in s.chars() {
                if self.0.push(c).is_err() {
                    break;
                }
            }
            Ok(())
        }
    }
    let mut cut = Cut(heapless::String::new());
    let _ = write!(cut, "{e}");
    cut.0
}

/// Answers one console event: M115 directly, other lines through `run`
/// (which may write replies to `out`); always ends with `ok\n`.
pub fn answer<W: Write>(
    event: &LineEvent<'_>,
    out: &mut W,
    run: impl FnOnce(&str, &mut W) -> Result<(), ErrorText>,
) -> core::fmt::Result {
    match event {
        LineEvent::Complete(line) if command_word(line).eq_ignore_ascii_case(b"M115") => writeln!(
            out,
            "FIRMWARE_NAME:{} FIRMWARE_VERSION:{}",
            crate::FIRMWARE_NAME,
            crate::FIRMWARE_VERSION
        )?,
        LineEvent::Complete(line) => match core::str::from_utf8(line) {
            Ok(text) => {
                if let Err(e) = run(text, out) {
                    writeln!(out, "!! {e}")?;
                }
            }
            Err(_) => writeln!(out, "!! line is not valid UTF-8, ignored")?,
        },
        LineEvent::TooLong { len } => writeln!(out, "!! line too long ({len} bytes), ignored")?,
    }
    out.write_str("ok\n")
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
    use std::string::String;
    use std::vec::Vec;

    /// Answers `event` with a runner that records the lines it is given and
    /// fails on lines containing "bad".
    fn reply(event: LineEvent<'_>) -> (String, Vec<String>) {
        let mut s = String::new();
        let mut seen = Vec::new();
        answer(&event, &mut s, |text, out: &mut String| {
            seen.push(text.into());
            if text.contains("bad") {
                return Err(error_text(&"unable to parse"));
            }
            out.push_str("// ran\n");
            Ok(())
        })
        .expect("String never fails");
        (s, seen)
    }

    #[test]
    fn m115_identifies_the_firmware_without_running_anything() {
        let (r, seen) = reply(LineEvent::Complete(b"M115"));
        assert!(
            r.starts_with("FIRMWARE_NAME:onechip FIRMWARE_VERSION:"),
            "{r}"
        );
        assert!(r.ends_with("\nok\n"), "{r}");
        assert!(seen.is_empty());
        assert_eq!(reply(LineEvent::Complete(b"N12 m115 *34")).0, r);
    }

    #[test]
    fn other_lines_run_and_get_exactly_one_ok() {
        assert_eq!(
            reply(LineEvent::Complete(b"G1 X10")),
            ("// ran\nok\n".into(), std::vec!["G1 X10".into()])
        );
    }

    #[test]
    fn long_error_texts_are_cut_not_lost() {
        let long = "x".repeat(500);
        assert_eq!(error_text(&long).len(), 96);
    }

    #[test]
    fn failures_are_reported_and_still_acknowledged() {
        assert_eq!(
            reply(LineEvent::Complete(b"G1 Xbad")).0,
            "!! unable to parse\nok\n"
        );
        assert_eq!(
            reply(LineEvent::Complete(b"G1 \xff")).0,
            "!! line is not valid UTF-8, ignored\nok\n"
        );
        assert_eq!(
            reply(LineEvent::TooLong { len: 300 }).0,
            "!! line too long (300 bytes), ignored\nok\n"
        );
    }
}
