//! A small, allocation-free JSON reader for Klipper data dictionaries.
//!
//! Values borrow from the document: strings are raw slices (escapes left in
//! place, compared through [`Str::eq_str`]), objects and arrays are spans that
//! are walked on demand. Nesting deeper than [`MAX_DEPTH`] is an error, so
//! hostile input cannot exhaust the stack. Numbers that are not integers are
//! kept as text.

/// Deepest nesting of arrays and objects accepted.
pub const MAX_DEPTH: usize = 16;

/// A JSON syntax error at a byte offset of the document.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct JsonError {
    /// Offset of the offending byte, from the start of the parsed text.
    pub offset: usize,
    /// What was wrong there.
    pub reason: &'static str,
}

/// A JSON string, as written between its quotes (escapes not yet decoded).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Str<'a> {
    raw: &'a str,
}

impl<'a> Str<'a> {
    /// The text between the quotes, escapes included.
    pub fn raw(&self) -> &'a str {
        self.raw
    }

    /// The text, if it has no escape sequences (the common case in
    /// dictionaries); `None` otherwise.
    pub fn plain(&self) -> Option<&'a str> {
        (!self.raw.contains('\\')).then_some(self.raw)
    }

    /// True if the decoded string equals `s`.
    pub fn eq_str(&self, s: &str) -> bool {
        // Each decoded character against the front of the rest of `s`
        // (no decoding of `s` to characters).
        let mut rest = s;
        for c in self.chars() {
            match c.and_then(|c| rest.strip_prefix(c)) {
                Some(after) => rest = after,
                None => return false,
            }
        }
        rest.is_empty()
    }

    /// The decoded characters; `None` items stand for malformed escapes.
    pub fn chars(&self) -> impl Iterator<Item = Option<char>> + 'a {
        let mut rest = self.raw.chars();
        core::iter::from_fn(move || {
            let c = rest.next()?;
            if c != '\\' {
                return Some(Some(c));
            }
            Some(match rest.next() {
                Some('"') => Some('"'),
                Some('\\') => Some('\\'),
                Some('/') => Some('/'),
                Some('b') => Some('\u{8}'),
                Some('f') => Some('\u{c}'),
                Some('n') => Some('\n'),
                Some('r') => Some('\r'),
                Some('t') => Some('\t'),
                Some('u') => {
                    let hex: [Option<char>; 4] = core::array::from_fn(|_| rest.next());
                    let mut code = 0u32;
                    let mut ok = true;
                    for h in hex {
                        match h.and_then(|h| h.to_digit(16)) {
                            Some(d) => code = code * 16 + d,
                            None => ok = false,
                        }
                    }
                    if ok { char::from_u32(code) } else { None }
                }
                _ => None,
            })
        })
    }
}

/// A JSON value borrowed from the document.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Value<'a> {
    /// `null`.
    Null,
    /// `true` or `false`.
    Bool(bool),
    /// An integer that fits `i64`.
    Int(i64),
    /// Any other number, as written.
    Number(&'a str),
    /// A string.
    Str(Str<'a>),
    /// An object; walk it with [`Object::members`].
    Object(Object<'a>),
    /// An array; walk it with [`Array::items`].
    Array(Array<'a>),
}

/// An object's span in the document (from `{` to `}` inclusive).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Object<'a> {
    span: &'a str,
    depth: usize,
}

/// An array's span in the document (from `[` to `]` inclusive).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Array<'a> {
    span: &'a str,
    depth: usize,
}

/// Parses a complete document: one value, then only whitespace.
pub fn parse(text: &str) -> Result<Value<'_>, JsonError> {
    let mut p = Parser { text, pos: 0 };
    let value = p.value(0)?;
    p.skip_ws();
    if p.pos != text.len() {
        return Err(p.error("trailing characters after the document"));
    }
    Ok(value)
}

impl<'a> Object<'a> {
    /// The members, in document order.
    pub fn members(&self) -> impl Iterator<Item = Result<(Str<'a>, Value<'a>), JsonError>> + 'a {
        elements(self.span, self.depth, Parser::next_member)
    }

    /// The value of the first member named `key`, if any.
    pub fn get(&self, key: &str) -> Result<Option<Value<'a>>, JsonError> {
        for member in self.members() {
            let (name, value) = member?;
            if name.eq_str(key) {
                return Ok(Some(value));
            }
        }
        Ok(None)
    }
}

impl<'a> Array<'a> {
    /// The items, in document order.
    pub fn items(&self) -> impl Iterator<Item = Result<Value<'a>, JsonError>> + 'a {
        elements(self.span, self.depth, Parser::next_item)
    }
}

/// Walks the elements of a container span with `next` (members or items),
/// ending after the closer or the first error.
fn elements<'a, T: 'a>(
    span: &'a str,
    depth: usize,
    next: fn(&mut Parser<'a>, usize, &mut bool) -> Result<Option<T>, JsonError>,
) -> impl Iterator<Item = Result<T, JsonError>> + 'a {
    let mut p = Parser { text: span, pos: 1 };
    let mut first = true;
    let mut done = false;
    core::iter::from_fn(move || {
        if done {
            return None;
        }
        let item = next(&mut p, depth, &mut first);
        done = !matches!(item, Ok(Some(_)));
        item.transpose()
    })
}

struct Parser<'a> {
    text: &'a str,
    pos: usize,
}

impl<'a> Parser<'a> {
    fn error(&self, reason: &'static str) -> JsonError {
        JsonError {
            offset: self.pos,
            reason,
        }
    }

    fn peek(&self) -> Option<u8> {
        self.text.as_bytes().get(self.pos).copied()
    }

    fn skip_ws(&mut self) {
        while matches!(self.peek(), Some(b' ' | b'\t' | b'\n' | b'\r')) {
            self.pos += 1;
        }
    }

    fn expect(&mut self, byte: u8, reason: &'static str) -> Result<(), JsonError> {
        self.skip_ws();
        if self.peek() == Some(byte) {
            self.pos += 1;
            Ok(())
        } else {
            Err(self.error(reason))
        }
    }

    /// Next object member, after `{` or a previous member.
    fn next_member(
        &mut self,
        depth: usize,
        first: &mut bool,
    ) -> Result<Option<(Str<'a>, Value<'a>)>, JsonError> {
        if !self.next_element(b'}', first)? {
            return Ok(None);
        }
        self.skip_ws();
        if self.peek() != Some(b'"') {
            return Err(self.error("expected a member name"));
        }
        let key = self.string()?;
        self.expect(b':', "expected ':' after a member name")?;
        Ok(Some((key, self.value(depth + 1)?)))
    }

    /// Next array item, after `[` or a previous item.
    fn next_item(
        &mut self,
        depth: usize,
        first: &mut bool,
    ) -> Result<Option<Value<'a>>, JsonError> {
        if !self.next_element(b']', first)? {
            return Ok(None);
        }
        Ok(Some(self.value(depth + 1)?))
    }

    /// Consumes the separator before the next element; false at the closer.
    fn next_element(&mut self, close: u8, first: &mut bool) -> Result<bool, JsonError> {
        self.skip_ws();
        if self.peek() == Some(close) {
            self.pos += 1;
            return Ok(false);
        }
        if !*first {
            self.expect(b',', "expected ',' between elements")?;
        }
        *first = false;
        Ok(true)
    }

    fn value(&mut self, depth: usize) -> Result<Value<'a>, JsonError> {
        if depth >= MAX_DEPTH {
            return Err(self.error("nesting too deep"));
        }
        self.skip_ws();
        let start = self.pos;
        match self.peek() {
            Some(b'{') => {
                self.pos += 1;
                let mut first = true;
                while self.next_member(depth, &mut first)?.is_some() {}
                Ok(Value::Object(Object {
                    span: &self.text[start..self.pos],
                    depth,
                }))
            }
            Some(b'[') => {
                self.pos += 1;
                let mut first = true;
                while self.next_item(depth, &mut first)?.is_some() {}
                Ok(Value::Array(Array {
                    span: &self.text[start..self.pos],
                    depth,
                }))
            }
            Some(b'"') => Ok(Value::Str(self.string()?)),
            Some(b't') => self.literal("true", Value::Bool(true)),
            Some(b'f') => self.literal("false", Value::Bool(false)),
            Some(b'n') => self.literal("null", Value::Null),
            Some(b'-' | b'0'..=b'9') => self.number(),
            Some(_) => Err(self.error("expected a value")),
            None => Err(self.error("unexpected end of document")),
        }
    }

    fn literal(&mut self, word: &'static str, value: Value<'a>) -> Result<Value<'a>, JsonError> {
        let rest = self.text.as_bytes().get(self.pos..).unwrap_or_default();
        if rest.starts_with(word.as_bytes()) {
            self.pos += word.len();
            Ok(value)
        } else {
            Err(self.error("unknown literal"))
        }
    }

    fn number(&mut self) -> Result<Value<'a>, JsonError> {
        let start = self.pos;
        while matches!(
            self.peek(),
            Some(b'-' | b'+' | b'.' | b'e' | b'E' | b'0'..=b'9')
        ) {
            self.pos += 1;
        }
        let text = &self.text[start..self.pos];
        if let Ok(int) = text.parse::<i64>() {
            return Ok(Value::Int(int));
        }
        if is_json_number(text.as_bytes()) {
            Ok(Value::Number(text))
        } else {
            Err(JsonError {
                offset: start,
                reason: "malformed number",
            })
        }
    }

    /// A string starting at the current `"`.
    fn string(&mut self) -> Result<Str<'a>, JsonError> {
        self.pos += 1;
        let start = self.pos;
        loop {
            match self.peek() {
                Some(b'"') => break,
                Some(b'\\') => self.pos += 2,
                Some(0..0x20) => return Err(self.error("control character in a string")),
                Some(_) => self.pos += 1,
                None => return Err(self.error("unterminated string")),
            }
        }
        let raw = self.text.get(start..self.pos).ok_or(JsonError {
            offset: start,
            reason: "unterminated string",
        })?;
        self.pos += 1;
        Ok(Str { raw })
    }
}

/// True if `text` is a whole JSON number,
/// `-?(0|[1-9][0-9]*)(.[0-9]+)?([eE][+-]?[0-9]+)?` (checked by hand: the
/// float parser would link 16 KB of tables and code only to validate).
fn is_json_number(text: &[u8]) -> bool {
    /// The rest of `text` after one or more leading digits; None if there
    /// is no digit.
    fn digits(text: &[u8]) -> Option<&[u8]> {
        let n = text.iter().take_while(|b| b.is_ascii_digit()).count();
        text.get(n..).filter(|_| n > 0)
    }
    let text = text.strip_prefix(b"-").unwrap_or(text);
    let rest = match text {
        [b'0', rest @ ..] => Some(rest),
        _ => digits(text),
    };
    let rest = match rest {
        Some([b'.', fraction @ ..]) => digits(fraction),
        rest => rest,
    };
    let rest = match rest {
        Some([b'e' | b'E', exponent @ ..]) => {
            let exponent = match exponent {
                [b'+' | b'-', digits @ ..] => digits,
                _ => exponent,
            };
            digits(exponent)
        }
        rest => rest,
    };
    rest == Some(&[])
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec::Vec;

    #[test]
    fn walks_nested_documents_in_order() {
        let doc = r#" {"a": 1, "b": [2, -3, {"c": "d\"e"}], "f": 1.5e3, "g": null, "h": true} "#;
        let Ok(Value::Object(obj)) = parse(doc) else {
            panic!("object expected")
        };
        let names: Vec<&str> = obj.members().map(|m| m.expect("valid").0.raw()).collect();
        assert_eq!(names, ["a", "b", "f", "g", "h"]);
        assert_eq!(obj.get("a"), Ok(Some(Value::Int(1))));
        assert_eq!(obj.get("f"), Ok(Some(Value::Number("1.5e3"))));
        let Ok(Some(Value::Array(items))) = obj.get("b") else {
            panic!("array expected")
        };
        let items: Vec<Value<'_>> = items.items().map(|i| i.expect("valid")).collect();
        assert_eq!(items[..2], [Value::Int(2), Value::Int(-3)]);
        let Value::Object(inner) = items[2] else {
            panic!("object expected")
        };
        let Ok(Some(Value::Str(s))) = inner.get("c") else {
            panic!("string expected")
        };
        assert!(s.eq_str("d\"e"));
        assert_eq!(s.plain(), None);
    }

    #[test]
    fn eq_str_compares_whole_decoded_strings() {
        let s = |raw| Str { raw };
        assert!(s("").eq_str(""));
        assert!(s("ab").eq_str("ab"));
        assert!(!s("ab").eq_str("abc"));
        assert!(!s("abc").eq_str("ab"));
        assert!(!s("").eq_str("a"));
        assert!(s(r"a\tb\u00e9").eq_str("a\tbé"));
        assert!(!s(r"a\u00e").eq_str("a"));
        assert!(!s(r"\q").eq_str("q"));
        assert!(!s("é").eq_str("e"));
    }

    #[test]
    fn unicode_escapes_decode() {
        let Ok(Value::Str(s)) = parse(r#""\u00e9t\u00E9""#) else {
            panic!("string expected")
        };
        assert!(s.eq_str("été"));
    }

    #[test]
    fn malformed_documents_are_errors_with_offsets() {
        let cases: &[(&str, usize)] = &[
            ("{\"a\" 1}", 5),
            ("[1, 2", 5),
            ("[1 2]", 3),
            ("\"abc", 4),
            ("{\"a\": tru}", 6),
            ("[1] x", 4),
            ("", 0),
            ("-", 0),
        ];
        for &(doc, offset) in cases {
            let err = parse(doc).expect_err(doc);
            assert_eq!(err.offset, offset, "{doc}: {err:?}");
        }
    }

    #[test]
    fn numbers_follow_the_json_grammar() {
        for text in [
            "0",
            "-0",
            "12",
            "1.5",
            "-0.25",
            "1e5",
            "1E+5",
            "1e-05",
            "-12.5e3",
            "0.0",
            "99999999999999999999",
            "-1.0E-0",
        ] {
            assert!(is_json_number(text.as_bytes()), "{text}");
            assert!(parse(text).is_ok(), "{text}");
        }
        for text in [
            "", "-", "+1", "01", "-01", "00.5", "1.", ".5", "-.5", "1.e3", "1e", "1e+", "1E-",
            "1e5.5", "1.5.5", "1-2", "1e+-5", "--1", "1ee5", "0x10",
        ] {
            assert!(!is_json_number(text.as_bytes()), "{text}");
        }
        // The reader takes every byte that may be part of a number, then
        // refuses the whole run if it is not one.
        for text in ["1.", "1.e3", "1-2", "1e", "-.5", "00.5"] {
            assert_eq!(
                parse(text),
                Err(JsonError {
                    offset: 0,
                    reason: "malformed number"
                }),
                "{text}"
            );
        }
        assert_eq!(parse("[1.5e3]").map(|_| ()), Ok(()));
        assert_eq!(parse("-1e-2"), Ok(Value::Number("-1e-2")));
    }

    #[test]
    fn deep_nesting_is_refused_not_a_stack_overflow() {
        let doc: std::string::String = "[".repeat(10_000) + &"]".repeat(10_000);
        assert_eq!(
            parse(&doc).expect_err("too deep").reason,
            "nesting too deep"
        );
    }
}
