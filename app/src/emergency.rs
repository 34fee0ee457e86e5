//! The emergency parser: spots `M112` in the console's byte stream as the
//! bytes arrive, before the line waits its turn behind a full line buffer
//! or a running command, so the printer stops at once (Marlin's
//! `EMERGENCY_PARSER`). The board runs it in its USB receive path, the
//! simulator in its serial reader.
//!
//! `M112` counts when it is the command of a line: at the line's start,
//! after an optional line number `N<n>`, and followed by the line's end, a
//! space, `*` (a checksum) or `;` (a comment). The line itself still goes
//! on to the console as usual.

/// Where in the current line the parser is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    /// At the start of a line, or in spaces before the command.
    Start,
    /// In a line number's digits.
    Number,
    /// After the line number, in spaces.
    AfterNumber,
    /// `M112` matched this many bytes.
    Command(u8),
    /// `M112` matched whole: the next byte decides.
    Matched,
    /// Not M112: nothing more until the line ends.
    Rest,
}

/// The command the parser looks for.
const M112: &[u8] = b"M112";

/// Byte-at-a-time M112 detector.
#[derive(Debug, Clone)]
pub struct EmergencyParser {
    state: State,
}

impl Default for EmergencyParser {
    fn default() -> Self {
        Self::new()
    }
}

impl EmergencyParser {
    /// At the start of a line.
    pub const fn new() -> Self {
        Self {
            state: State::Start,
        }
    }

    /// Feeds one byte; true when it completes an `M112` command.
    pub fn push(&mut self, byte: u8) -> bool {
        let end = byte == b'\n' || byte == b'\r';
        let upper = byte.to_ascii_uppercase();
        let (next, found) = match self.state {
            _ if end => (State::Start, self.state == State::Matched),
            State::Start if byte == b' ' || byte == b'\t' => (State::Start, false),
            State::Start if upper == b'N' => (State::Number, false),
            State::Number if byte.is_ascii_digit() => (State::Number, false),
            State::Number | State::AfterNumber if byte == b' ' || byte == b'\t' => {
                (State::AfterNumber, false)
            }
            State::Start | State::AfterNumber if upper == M112[0] => (State::Command(1), false),
            State::Command(n) if M112.get(usize::from(n)) == Some(&upper) => {
                let n = n + 1;
                if usize::from(n) == M112.len() {
                    (State::Matched, false)
                } else {
                    (State::Command(n), false)
                }
            }
            State::Matched if matches!(byte, b' ' | b'\t' | b'*' | b';') => (State::Rest, true),
            _ => (State::Rest, false),
        };
        self.state = next;
        found
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// How many M112 commands the parser finds in `bytes`.
    fn count(bytes: &[u8]) -> usize {
        let mut p = EmergencyParser::new();
        bytes.iter().filter(|&&b| p.push(b)).count()
    }

    #[test]
    fn finds_m112_however_hosts_send_it() {
        assert_eq!(count(b"M112\n"), 1);
        assert_eq!(count(b"m112\r\n"), 1);
        assert_eq!(count(b"N123 M112*31\n"), 1);
        assert_eq!(count(b"  M112 ; stop\n"), 1);
        assert_eq!(count(b"G1 X1\nM112\nG1 X2\nM112\n"), 2);
    }

    #[test]
    fn finds_it_at_once_not_at_the_end_of_the_line() {
        let mut p = EmergencyParser::new();
        let found: usize = b"N7 M112*".iter().position(|&b| p.push(b)).expect("found");
        assert_eq!(found, 7, "on the byte after M112");
    }

    #[test]
    fn ignores_other_commands_and_m112_elsewhere_in_a_line() {
        for line in [
            &b"M1120\n"[..],
            b"M11\n",
            b"G1 M112\n",
            b"M117 M112\n",
            b"NM112\n",
            b"N1M112\n",
            b"RESPOND MSG=M112\n",
        ] {
            assert_eq!(count(line), 0, "{line:?}");
        }
    }
}
