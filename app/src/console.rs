//! The firmware's answers to lines arriving on the console (USB CDC).
//!
//! Hosts such as OctoPrint, Pronterface and Cura send one line and wait for
//! `ok` before the next, so every line, good or bad, gets exactly one `ok`,
//! preceded by any reply text; errors are reported on a line starting with
//! `!!` as Klipper does. Until the planner lands (issue #3), commands other
//! than M115 are acknowledged without effect.

use crate::line::Line;
use core::fmt::Write;

/// Answers one console event, writing the reply (always ending in `ok\n`)
/// into `out`.
pub fn answer(event: &Line<'_>, out: &mut impl Write) -> core::fmt::Result {
    match event {
        Line::Complete(line) => {
            if command_word(line).eq_ignore_ascii_case(b"M115") {
                writeln!(
                    out,
                    "FIRMWARE_NAME:{} FIRMWARE_VERSION:{}",
                    crate::FIRMWARE_NAME,
                    crate::FIRMWARE_VERSION
                )?;
            }
        }
        Line::TooLong { len } => writeln!(out, "!! line too long ({len} bytes), ignored")?,
    }
    out.write_str("ok\n")
}

/// The first word of a G-code line, after an optional `N<number>` line number.
fn command_word(line: &[u8]) -> &[u8] {
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

    fn reply(event: Line<'_>) -> String {
        let mut s = String::new();
        answer(&event, &mut s).expect("String never fails");
        s
    }

    #[test]
    fn m115_identifies_the_firmware_then_acknowledges() {
        let r = reply(Line::Complete(b"M115"));
        assert!(
            r.starts_with("FIRMWARE_NAME:onechip FIRMWARE_VERSION:"),
            "{r}"
        );
        assert!(r.ends_with("\nok\n"), "{r}");
        assert_eq!(reply(Line::Complete(b"N12 m115 *34")), r);
    }

    #[test]
    fn other_lines_get_exactly_one_ok() {
        assert_eq!(reply(Line::Complete(b"G1 X10")), "ok\n");
    }

    #[test]
    fn overlong_lines_get_an_error_and_still_one_ok() {
        assert_eq!(
            reply(Line::TooLong { len: 300 }),
            "!! line too long (300 bytes), ignored\nok\n"
        );
    }
}
