//! G-code lines: parsing without allocation, errors as values.
//!
//! One line at a time (lines come from a bounded assembler); results borrow
//! the line. Rules, as Klipper reads G-code, plus checksum validation:
//! - `;` starts a comment to the end of the line; `( … )` is a comment in
//!   traditional commands (as Marlin and RepRapFirmware allow);
//! - an optional `N<number>` line number comes first; `*<number>` at the end
//!   is a checksum (XOR of every byte before the `*`) and must match;
//! - a traditional command is a letter and a number (`G1`, `M104`, `G28.1`)
//!   followed by parameters, each a run of letters and the text up to the
//!   next letter (`X10 Y-2.5`, also `X10Y-2.5`); letters are case-insensitive;
//! - anything else is an extended command, `NAME KEY=VALUE …`, with values
//!   optionally quoted (`MSG="two words"`).

use core::fmt;
use onechip_config::decimal;

/// Why a line could not be parsed, or a parameter not read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GcodeError<'a> {
    /// The line's checksum does not match its contents.
    ChecksumMismatch {
        /// Checksum written on the line.
        sent: u8,
        /// Checksum of the line's bytes.
        computed: u8,
    },
    /// The text after `*` is not a number from 0 to 255.
    BadChecksum(&'a str),
    /// The text after `N` is not a line number.
    BadLineNumber(&'a str),
    /// An unclosed `(` comment.
    UnclosedComment,
    /// An extended command parameter without `=`, or an unclosed quote.
    Malformed(&'a str),
    /// A parameter's value is not a finite number.
    BadNumber {
        /// The parameter.
        key: &'a str,
        /// Its text.
        value: &'a str,
    },
    /// A required parameter is absent.
    Missing(&'a str),
}

impl fmt::Display for GcodeError<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::ChecksumMismatch { sent, computed } => {
                write!(
                    f,
                    "checksum mismatch: line says {sent}, contents give {computed}"
                )
            }
            Self::BadChecksum(text) => write!(f, "invalid checksum '{}'", Escaped(text)),
            Self::BadLineNumber(text) => write!(f, "invalid line number '{}'", Escaped(text)),
            Self::UnclosedComment => f.write_str("unclosed '(' comment"),
            Self::Malformed(word) => write!(f, "malformed parameter '{}'", Escaped(word)),
            Self::BadNumber { key, value } => {
                write!(f, "unable to parse {}={}", Escaped(key), Escaped(value))
            }
            Self::Missing(key) => write!(f, "missing {}", Escaped(key)),
        }
    }
}

/// Text of a G-code line as a message quotes it: tab, line feed and
/// carriage return as `\t`, `\n`, `\r`, other ASCII control characters
/// as `\x1b`, unprintable non-ASCII characters as `\u{85}`; printable
/// characters (ASCII or not, quotes and backslashes too) as they are.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Escaped<'a>(pub &'a str);

impl fmt::Display for Escaped<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        use fmt::Write;
        for c in self.0.chars() {
            match c {
                '\t' => f.write_str("\\t")?,
                '\n' => f.write_str("\\n")?,
                '\r' => f.write_str("\\r")?,
                ' '..='~' => f.write_char(c)?,
                '\0'..='\x7f' => write!(f, "\\x{:02x}", u32::from(c))?,
                _ if printable(c) => f.write_char(c)?,
                _ => write!(f, "{}", c.escape_unicode())?,
            }
        }
        Ok(())
    }
}

/// True if the non-ASCII `c` shows as itself where `str::escape_debug`
/// would leave it inside a text (combining marks included).
fn printable(c: char) -> bool {
    let mut pair = [b' '; 5];
    let len = 1 + c.len_utf8();
    c.encode_utf8(&mut pair[1..]);
    core::str::from_utf8(&pair[..len]).is_ok_and(|pair| pair.escape_debug().count() == 2)
}

/// A parsed line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Line<'a> {
    /// The `N` line number, if any.
    pub number: Option<u32>,
    /// The command.
    pub command: Command<'a>,
}

/// The command of a line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Command<'a> {
    /// Nothing but whitespace and comments.
    Empty,
    /// A letter-and-number command such as `G1`.
    Traditional(Traditional<'a>),
    /// A named command such as `SET_VELOCITY_LIMIT`.
    Extended(Extended<'a>),
}

/// A traditional command: `letter` `number[.sub]` and its parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Traditional<'a> {
    /// The command letter, uppercase (`G`, `M`, `T`).
    pub letter: u8,
    /// The command number (`1` in `G1`).
    pub number: u16,
    /// The subcode (`1` in `G28.1`), if any.
    pub sub: Option<u16>,
    /// The parameter text, comments and checksum removed.
    params: &'a str,
    /// True if `params` holds `( … )` comments still to skip.
    has_paren_comments: bool,
}

/// One parameter of a traditional command: a key (a run of letters) and its
/// value text, trimmed (empty for a bare flag such as the `X` of `G28 X`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Param<'a> {
    /// The key as written (compare case-insensitively).
    pub key: &'a str,
    /// The value text.
    pub value: &'a str,
}

/// Reads a value as a finite number.
fn number<'a>(key: &'a str, value: &'a str) -> Result<f64, GcodeError<'a>> {
    decimal::parse(value)
        .filter(|v| v.is_finite())
        .ok_or(GcodeError::BadNumber { key, value })
}

impl<'a> Traditional<'a> {
    /// True if this is `letter` `number` with no subcode (`is(b'G', 1)`).
    pub fn is(&self, letter: u8, number: u16) -> bool {
        self.letter == letter && self.number == number && self.sub.is_none()
    }

    /// The raw parameter text (M117 messages, file names).
    pub fn raw_params(&self) -> &'a str {
        self.params.trim()
    }

    /// The parameters, in line order.
    pub fn params(&self) -> impl Iterator<Item = Param<'a>> + 'a {
        let text = self.params;
        let skip_parens = self.has_paren_comments;
        let bytes = text.as_bytes();
        let mut at = 0;
        core::iter::from_fn(move || {
            loop {
                while at < bytes.len() && !is_key_byte(bytes[at]) {
                    if skip_parens && bytes[at] == b'(' {
                        at += bytes[at..]
                            .iter()
                            .position(|&b| b == b')')
                            .map_or(bytes.len() - at, |p| p + 1);
                    } else {
                        at += 1;
                    }
                }
                if at >= bytes.len() {
                    return None;
                }
                let key_start = at;
                while at < bytes.len() && is_key_byte(bytes[at]) {
                    at += 1;
                }
                let value_start = at;
                while at < bytes.len()
                    && !is_key_byte(bytes[at])
                    && !(skip_parens && bytes[at] == b'(')
                {
                    at += 1;
                }
                let key = &text[key_start..value_start];
                let value = text[value_start..at].trim();
                if !key.is_empty() {
                    return Some(Param { key, value });
                }
            }
        })
    }

    /// The last parameter named `key` (case-insensitive), as Klipper keeps
    /// the last of repeated keys.
    pub fn param(&self, key: &str) -> Option<Param<'a>> {
        self.params()
            .filter(|p| p.key.eq_ignore_ascii_case(key))
            .last()
    }

    /// The number given for `key`, if the key is present.
    pub fn float(&self, key: &str) -> Result<Option<f64>, GcodeError<'a>> {
        self.param(key).map(|p| number(p.key, p.value)).transpose()
    }

    /// The numbers given for each of `keys` (case-insensitive, the last of
    /// repeated keys), read in one pass over the parameters.
    pub fn floats<const K: usize>(
        &self,
        keys: [&str; K],
    ) -> Result<[Option<f64>; K], GcodeError<'a>> {
        let mut found: [Option<Param<'a>>; K] = [None; K];
        for p in self.params() {
            if let Some(slot) = keys.iter().position(|k| p.key.eq_ignore_ascii_case(k)) {
                found[slot] = Some(p);
            }
        }
        let mut out = [None; K];
        for (slot, p) in out.iter_mut().zip(found) {
            *slot = p.map(|p| number(p.key, p.value)).transpose()?;
        }
        Ok(out)
    }
}

fn is_key_byte(b: u8) -> bool {
    b.is_ascii_alphabetic() || b == b'_'
}

/// An extended command: a name and `KEY=VALUE` parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Extended<'a> {
    /// The command name as written (compare case-insensitively).
    pub name: &'a str,
    params: &'a str,
}

impl<'a> Extended<'a> {
    /// The parameters in line order, keys as written and values unquoted;
    /// a word without `=` or an unclosed quote is an error.
    pub fn params(&self) -> impl Iterator<Item = Result<(&'a str, &'a str), GcodeError<'a>>> + 'a {
        let text = self.params;
        let mut rest = text;
        let mut failed = false;
        core::iter::from_fn(move || {
            if failed {
                return None;
            }
            rest = rest.trim_start();
            if rest.is_empty() || rest.starts_with(['#', ';']) {
                return None;
            }
            let item = split_word(rest).map(|(key, value, tail)| {
                rest = tail;
                (key, value)
            });
            failed = item.is_err();
            Some(item)
        })
    }

    /// The value of `key` (case-insensitive; the last one if repeated).
    pub fn get(&self, key: &str) -> Result<Option<&'a str>, GcodeError<'a>> {
        let mut found = None;
        for param in self.params() {
            let (k, v) = param?;
            if k.eq_ignore_ascii_case(key) {
                found = Some(v);
            }
        }
        Ok(found)
    }

    /// The number given for `key`, if present.
    pub fn float(&self, key: &'a str) -> Result<Option<f64>, GcodeError<'a>> {
        self.get(key)?.map(|v| number(key, v)).transpose()
    }
}

/// Splits `KEY=VALUE` (value possibly quoted) off the front of `text`.
fn split_word(text: &str) -> Result<(&str, &str, &str), GcodeError<'_>> {
    let end = text.find(char::is_whitespace).unwrap_or(text.len());
    let (key, after_eq) = text
        .split_once('=')
        .filter(|(k, _)| k.len() < end)
        .ok_or(GcodeError::Malformed(&text[..end]))?;
    if key.is_empty() {
        return Err(GcodeError::Malformed(&text[..end]));
    }
    match after_eq.chars().next() {
        Some(q @ ('"' | '\'')) => {
            let body = &after_eq[1..];
            let close = body.find(q).ok_or(GcodeError::Malformed(text))?;
            Ok((key, &body[..close], &body[close + 1..]))
        }
        _ => {
            let len = after_eq.find(char::is_whitespace).unwrap_or(after_eq.len());
            Ok((key, &after_eq[..len], &after_eq[len..]))
        }
    }
}

/// Parses one line (without its line terminator).
pub fn parse(line: &str) -> Result<Line<'_>, GcodeError<'_>> {
    let body = verify_checksum(line)?;
    let body = body.split(';').next().unwrap_or_default().trim();
    let (number, mut body) = split_line_number(body)?;
    while body.starts_with('(') {
        body = skip_paren_comment(body)?.trim_start();
    }
    let bytes = body.as_bytes();
    let command = match bytes {
        [] => Command::Empty,
        [letter, digit, ..] if letter.is_ascii_alphabetic() && digit.is_ascii_digit() => {
            match traditional(body) {
                Some(t) => Command::Traditional(t?),
                None => extended(body)?,
            }
        }
        _ => extended(body)?,
    };
    Ok(Line { number, command })
}

fn skip_paren_comment(text: &str) -> Result<&str, GcodeError<'_>> {
    let close = text.find(')').ok_or(GcodeError::UnclosedComment)?;
    Ok(&text[close + 1..])
}

/// Checks and removes a trailing `*checksum`.
fn verify_checksum(line: &str) -> Result<&str, GcodeError<'_>> {
    let Some(star) = line.rfind('*') else {
        return Ok(line);
    };
    let text = line[star + 1..].trim();
    // Only `*` and digits at the end is a checksum (not a `*` in a comment
    // or a quoted value).
    if text.is_empty() || !text.bytes().all(|b| b.is_ascii_digit()) || line[..star].contains(';') {
        return Ok(line);
    }
    let sent: u8 = text.parse().map_err(|_| GcodeError::BadChecksum(text))?;
    let computed = line.as_bytes()[..star].iter().fold(0u8, |acc, b| acc ^ b);
    if sent != computed {
        return Err(GcodeError::ChecksumMismatch { sent, computed });
    }
    Ok(&line[..star])
}

fn split_line_number(body: &str) -> Result<(Option<u32>, &str), GcodeError<'_>> {
    let bytes = body.as_bytes();
    if !matches!(bytes, [b'N' | b'n', d, ..] if d.is_ascii_digit()) {
        return Ok((None, body));
    }
    let end = bytes[1..]
        .iter()
        .position(|b| !b.is_ascii_digit())
        .map_or(bytes.len(), |p| p + 1);
    let digits = &body[1..end];
    let number = digits
        .parse()
        .map_err(|_| GcodeError::BadLineNumber(digits))?;
    Ok((Some(number), body[end..].trim_start()))
}

/// `G1 …`, `M104 …`, `G28.1 …`; None if the first word is an extended
/// name that merely starts with a letter and a digit (`G1_FOO`).
fn traditional(body: &str) -> Option<Result<Traditional<'_>, GcodeError<'_>>> {
    let bytes = body.as_bytes();
    let digits_end = |from: usize| {
        bytes[from..]
            .iter()
            .position(|b| !b.is_ascii_digit())
            .map_or(bytes.len(), |p| p + from)
    };
    let mut end = digits_end(1);
    let has_sub = bytes.get(end) == Some(&b'.');
    let sub_end = if has_sub { digits_end(end + 1) } else { end };
    if bytes.get(sub_end).is_some_and(|&b| b == b'_' || b == b'.') {
        return None;
    }
    let word = &body[..sub_end];
    let parse_u16 = |text: &str| text.parse::<u16>().map_err(|_| GcodeError::Malformed(word));
    let number = match parse_u16(&body[1..end]) {
        Ok(n) => n,
        Err(e) => return Some(Err(e)),
    };
    let mut sub = None;
    if has_sub {
        match parse_u16(&body[end + 1..sub_end]) {
            Ok(n) => sub = Some(n),
            Err(e) => return Some(Err(e)),
        }
        end = sub_end;
    }
    let params = &body[end..];
    Some(Ok(Traditional {
        letter: bytes[0].to_ascii_uppercase(),
        number,
        sub,
        params,
        has_paren_comments: params.contains('('),
    }))
}

fn extended(body: &str) -> Result<Command<'_>, GcodeError<'_>> {
    let end = body.find(char::is_whitespace).unwrap_or(body.len());
    let name = &body[..end];
    if !name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_') {
        return Err(GcodeError::Malformed(name));
    }
    let params = body[end..].split('#').next().unwrap_or_default();
    Ok(Command::Extended(Extended { name, params }))
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec::Vec;

    fn trad(line: &str) -> Traditional<'_> {
        match parse(line) {
            Ok(Line {
                command: Command::Traditional(t),
                ..
            }) => t,
            other => panic!("{line}: {other:?}"),
        }
    }

    fn ext(line: &str) -> Extended<'_> {
        match parse(line) {
            Ok(Line {
                command: Command::Extended(e),
                ..
            }) => e,
            other => panic!("{line}: {other:?}"),
        }
    }

    #[test]
    fn traditional_commands_and_parameters() {
        let g = trad("G1 X10 Y-2.5 E0.1 F3000 ; move");
        assert!(g.is(b'G', 1));
        assert_eq!(g.float("X"), Ok(Some(10.0)));
        assert_eq!(g.float("y"), Ok(Some(-2.5)));
        assert_eq!(g.float("F"), Ok(Some(3000.0)));
        assert_eq!(g.float("Z"), Ok(None));
        let packed = trad("g1x10y20");
        assert_eq!(
            (packed.float("X"), packed.float("Y")),
            (Ok(Some(10.0)), Ok(Some(20.0)))
        );
        let home = trad("G28 X Y");
        let keys: Vec<&str> = home.params().map(|p| p.key).collect();
        assert_eq!(keys, ["X", "Y"]);
        assert_eq!(home.param("X").map(|p| p.value), Some(""));
        assert_eq!(trad("G1 X1 X2").float("X"), Ok(Some(2.0)));
        let sub = trad("G28.1");
        assert_eq!((sub.number, sub.sub), (28, Some(1)));
    }

    #[test]
    fn numbers_read_as_klipper_reads_them() {
        assert_eq!(number("X", "-0.5"), Ok(-0.5));
        assert_eq!(
            number("X", "1.2345678901234567"),
            Ok(1.234_567_890_123_456_7)
        );
        assert_eq!(number("E", "1e-3"), Ok(0.001));
        assert!(number("X", "inf").is_err());
        assert!(number("X", "1..2").is_err());
        let g = trad("G1 X1 Y2 Z3 X4");
        assert_eq!(g.floats(["X", "y", "E"]), Ok([Some(4.0), Some(2.0), None]));
    }

    #[test]
    fn comments_line_numbers_and_checksums() {
        assert_eq!(
            parse("  ; only a comment").map(|l| l.command),
            Ok(Command::Empty)
        );
        assert_eq!(
            parse("(only a comment)").map(|l| l.command),
            Ok(Command::Empty)
        );
        let g = trad("G1 (fast) X5 (and more) Y6");
        assert_eq!((g.float("X"), g.float("Y")), (Ok(Some(5.0)), Ok(Some(6.0))));
        let with_number = parse("N42 G1 X1").expect("valid");
        assert_eq!(with_number.number, Some(42));
        // "N3 T0*57": 57 is the XOR of the bytes before '*'.
        assert_eq!(parse("N3 T0*57").map(|l| l.number), Ok(Some(3)));
        assert_eq!(
            parse("N3 T0*58"),
            Err(GcodeError::ChecksumMismatch {
                sent: 58,
                computed: 57
            })
        );
        assert_eq!(parse("N3 T0*300"), Err(GcodeError::BadChecksum("300")));
        assert_eq!(trad("G1 X1 (unclosed").float("X"), Ok(Some(1.0)));
        assert_eq!(parse("(unclosed"), Err(GcodeError::UnclosedComment));
        assert_eq!(
            parse("(a) (b) G1 X2").map(|l| matches!(l.command, Command::Traditional(_))),
            Ok(true)
        );
        // A `*` that is not followed by digits is not a checksum.
        assert_eq!(ext("RESPOND MSG=\"a*b\"").get("MSG"), Ok(Some("a*b")));
    }

    #[test]
    fn extended_commands() {
        let e = ext("SET_VELOCITY_LIMIT VELOCITY=300 ACCEL=3000 # comment");
        assert_eq!(e.name, "SET_VELOCITY_LIMIT");
        assert_eq!(e.float("VELOCITY"), Ok(Some(300.0)));
        assert_eq!(e.float("accel"), Ok(Some(3000.0)));
        assert_eq!(e.get("SQUARE_CORNER_VELOCITY"), Ok(None));
        let quoted = ext("RESPOND MSG=\"hello world\" PREFIX='x'");
        assert_eq!(quoted.get("MSG"), Ok(Some("hello world")));
        assert_eq!(quoted.get("PREFIX"), Ok(Some("x")));
        assert_eq!(ext("G1_FOO X=1").name, "G1_FOO");
        assert_eq!(
            ext("SET_KINEMATIC_POSITION X=100 Y=100 Z=10").float("Z"),
            Ok(Some(10.0))
        );
    }

    #[test]
    fn error_messages_escape_unprintable_text() {
        use std::string::ToString;
        // The line's error, or the first parameter's.
        let message = |line: &str| {
            let error = match parse(line).map(|l| l.command) {
                Err(e) => Some(e),
                Ok(Command::Traditional(t)) => t.float("X").err(),
                Ok(Command::Extended(e)) => e.get("A").err(),
                Ok(Command::Empty) => None,
            };
            error.map(|e| e.to_string())
        };
        assert_eq!(
            message("FOO\x1b[2J BAR=1").as_deref(),
            Some("malformed parameter 'FOO\\x1b[2J'")
        );
        assert_eq!(
            message("G1 X1\x07").as_deref(),
            Some("unable to parse X=1\\x07")
        );
        assert_eq!(
            message("SET_X A=\"\x7f\u{85}é").as_deref(),
            Some("malformed parameter 'A=\"\\x7f\\u{85}é'")
        );
        // Printable text, ASCII or not, is left alone; so are combining
        // marks after a letter.
        let text = "a\tb\r\n\\'\"~ é e\u{301} 日本 \u{200b}\u{0}";
        assert_eq!(
            Escaped(text).to_string(),
            "a\\tb\\r\\n\\'\"~ é e\u{301} 日本 \\u{200b}\\x00"
        );
    }

    #[test]
    fn bad_input_is_an_error_not_a_panic() {
        // Letters run together form one key, as in Klipper: `Xabc` is `XABC`.
        assert_eq!(trad("G1 Xabc").float("X"), Ok(None));
        assert_eq!(
            trad("G1 X1.2.3").float("X"),
            Err(GcodeError::BadNumber {
                key: "X",
                value: "1.2.3"
            })
        );
        assert_eq!(
            trad("G1 X").float("X"),
            Err(GcodeError::BadNumber {
                key: "X",
                value: ""
            })
        );
        assert_eq!(
            trad("G1 X-").float("X"),
            Err(GcodeError::BadNumber {
                key: "X",
                value: "-"
            })
        );
        let e = ext("SET_VELOCITY_LIMIT VELOCITY=nan ACCEL=inf");
        assert_eq!(
            e.float("VELOCITY"),
            Err(GcodeError::BadNumber {
                key: "VELOCITY",
                value: "nan"
            })
        );
        assert_eq!(
            e.float("ACCEL"),
            Err(GcodeError::BadNumber {
                key: "ACCEL",
                value: "inf"
            })
        );
        assert_eq!(ext("FOO BAR").get("X"), Err(GcodeError::Malformed("BAR")));
        assert_eq!(
            ext("FOO A=\"open").get("A"),
            Err(GcodeError::Malformed("A=\"open"))
        );
        assert_eq!(
            parse("N99999999999 G1"),
            Err(GcodeError::BadLineNumber("99999999999"))
        );
        assert_eq!(parse("G99999 X1"), Err(GcodeError::Malformed("G99999")));
        assert_eq!(parse("G1.99999"), Err(GcodeError::Malformed("G1.99999")));
        assert!(parse("FOO-BAR").is_err());
        for text in [
            "", "*", "N", "G", "(", ")", "G1 (", "A=B", "=", "\"", "N1*", "G1.", "G1.x", "é", "Gé1",
        ] {
            let _ = parse(text);
        }
    }
}
