//! Messages to and from bytes, with a [`Dictionary`].
//!
//! A message on the wire is its id, then each parameter in format order:
//! integers as VLQs ([`crate::vlq`]), byte types as a length byte and the
//! bytes. The text form is Klipper's (`parsedump.py`, and the `mcu-commands`
//! logs): `name param=value …`, enumeration values by symbol, buffers as
//! Python bytes literals when printed and as hex digits when parsed.
//!
//! The hot path for step commands is [`Encoder`]: resolved once by name, it
//! encodes integer arguments without looking anything up.

use crate::dictionary::{Dictionary, MAX_PARAMS, Message, ParamType};
use crate::vlq;
use core::fmt;

/// An argument for [`Encoder::encode`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Arg<'v> {
    /// An integer parameter (or an enumeration's numeric value).
    Int(i64),
    /// A string or buffer parameter.
    Bytes(&'v [u8]),
}

/// Why a message could not be encoded. `'x` borrows the input text or the
/// dictionary.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EncodeError<'x> {
    /// The dictionary has no message of that name.
    UnknownMessage(&'x str),
    /// The message has no parameter of that name.
    UnknownParam(&'x str),
    /// A parameter of the message was not given.
    MissingParam(&'x str),
    /// A parameter was given twice.
    DuplicateParam(&'x str),
    /// Wrong number of arguments for [`Encoder::encode`].
    ArgCount {
        /// Parameters the message has.
        expected: usize,
        /// Arguments given.
        given: usize,
    },
    /// An argument of the wrong kind (bytes for an integer or the reverse),
    /// or text that is neither a number nor a symbol of the enumeration.
    BadValue(&'x str),
    /// An integer outside its parameter's type.
    OutOfRange {
        /// The parameter.
        param: &'x str,
        /// The value given.
        value: i64,
    },
    /// A buffer longer than 255 bytes.
    BufferTooLong(&'x str),
    /// The output buffer is full.
    NoSpace,
}

impl fmt::Display for EncodeError<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::UnknownMessage(name) => write!(f, "unknown command '{name}'"),
            Self::UnknownParam(name) => write!(f, "unknown parameter '{name}'"),
            Self::MissingParam(name) => write!(f, "missing parameter '{name}'"),
            Self::DuplicateParam(name) => write!(f, "parameter '{name}' given twice"),
            Self::ArgCount { expected, given } => {
                write!(f, "{given} arguments for {expected} parameters")
            }
            Self::BadValue(text) => write!(f, "bad value '{text}'"),
            Self::OutOfRange { param, value } => write!(f, "{param}={value} is out of range"),
            Self::BufferTooLong(name) => write!(f, "buffer '{name}' is longer than 255 bytes"),
            Self::NoSpace => f.write_str("message does not fit the output buffer"),
        }
    }
}

/// Why bytes could not be decoded into a message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DecodeError {
    /// The bytes end inside the message.
    Truncated,
    /// No message of the dictionary has this id.
    UnknownId(i64),
}

impl fmt::Display for DecodeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Truncated => f.write_str("message truncated"),
            Self::UnknownId(id) => write!(f, "unknown message id {id}"),
        }
    }
}

/// Appends encoded values to a byte slice.
struct Writer<'o> {
    out: &'o mut [u8],
    len: usize,
}

impl Writer<'_> {
    #[inline]
    fn int(&mut self, value: i64) -> Result<(), EncodeError<'static>> {
        // Encode in place when five bytes of room remain (no copy), else
        // through a scratch buffer.
        if let Some(room) = self.out.get_mut(self.len..self.len + vlq::MAX_LEN) {
            let room: &mut [u8; vlq::MAX_LEN] =
                room.try_into().map_err(|_| EncodeError::NoSpace)?;
            self.len += vlq::encode(value, room);
            return Ok(());
        }
        let mut buf = [0u8; vlq::MAX_LEN];
        let n = vlq::encode(value, &mut buf);
        self.bytes(&buf[..n])
    }

    fn bytes(&mut self, bytes: &[u8]) -> Result<(), EncodeError<'static>> {
        let dest = self
            .out
            .get_mut(self.len..self.len + bytes.len())
            .ok_or(EncodeError::NoSpace)?;
        dest.copy_from_slice(bytes);
        self.len += bytes.len();
        Ok(())
    }
}

/// True for parameters that carry an absolute MCU clock (`clock`,
/// `report_clock`, …). The host keeps clocks in 64 bits and, as Klipper's
/// host does, sends them whole; the MCU keeps the low 32 bits.
pub fn is_absolute_clock(param: &str) -> bool {
    param == "clock" || param.ends_with("_clock")
}

/// The values a parameter accepts.
fn value_range(param: &str, ty: ParamType) -> core::ops::RangeInclusive<i64> {
    int_range(ty, is_absolute_clock(param))
}

/// The values an integer parameter of type `ty` accepts; `clock`: it
/// carries an absolute clock.
fn int_range(ty: ParamType, clock: bool) -> core::ops::RangeInclusive<i64> {
    if ty == ParamType::U32 && clock {
        0..=i64::MAX
    } else {
        ty.range()
    }
}

fn check_range(param: &str, ty: ParamType, value: i64) -> Result<(), EncodeError<'_>> {
    if value_range(param, ty).contains(&value) {
        Ok(())
    } else {
        Err(EncodeError::OutOfRange { param, value })
    }
}

/// A command resolved once for repeated encoding (no name or enum lookups).
#[derive(Debug, Clone, Copy)]
pub struct Encoder<'d> {
    message: &'d Message<'d>,
    types: [ParamType; MAX_PARAMS],
    /// Bit `i` set: parameter `i` carries an absolute clock (see
    /// [`is_absolute_clock`]).
    clocks: u16,
    count: u8,
    /// The message id, already encoded.
    id: [u8; vlq::MAX_LEN],
    id_len: u8,
}

impl<'d> Encoder<'d> {
    /// Resolves the message `name` of `dict`.
    pub fn new(dict: &'d Dictionary<'d>, name: &'d str) -> Result<Self, EncodeError<'d>> {
        let message = dict
            .by_name(name)
            .ok_or(EncodeError::UnknownMessage(name))?;
        let mut types = [ParamType::U8; MAX_PARAMS];
        let mut clocks = 0;
        let mut count = 0;
        for ((param, ty), slot) in message.params().zip(&mut types) {
            *slot = ty;
            if is_absolute_clock(param) {
                clocks |= 1 << count;
            }
            count += 1;
        }
        let mut id = [0u8; vlq::MAX_LEN];
        let id_len = vlq::encode(i64::from(message.id), &mut id) as u8;
        Ok(Self {
            message,
            types,
            clocks,
            count,
            id,
            id_len,
        })
    }

    /// The message id.
    pub fn id(&self) -> i32 {
        self.message.id
    }

    /// Encodes the message with `args` in format order into `out`; returns
    /// the number of bytes written.
    pub fn encode(&self, args: &[Arg<'_>], out: &mut [u8]) -> Result<usize, EncodeError<'d>> {
        self.check_count(args.len())?;
        let mut w = Writer { out, len: 0 };
        w.int(i64::from(self.message.id))?;
        for ((name, ty), arg) in self.message.params().zip(args) {
            match (*arg, ty.is_bytes()) {
                (Arg::Int(value), false) => {
                    check_range(name, ty, value)?;
                    w.int(value)?;
                }
                (Arg::Bytes(bytes), true) => {
                    let len =
                        u8::try_from(bytes.len()).map_err(|_| EncodeError::BufferTooLong(name))?;
                    w.bytes(&[len])?;
                    w.bytes(bytes)?;
                }
                _ => return Err(EncodeError::BadValue(name)),
            }
        }
        Ok(w.len)
    }

    /// Encodes integer arguments only (the step-command hot path).
    pub fn encode_ints(&self, args: &[i64], out: &mut [u8]) -> Result<usize, EncodeError<'d>> {
        self.check_count(args.len())?;
        for (i, (&value, &ty)) in args.iter().zip(&self.types).enumerate() {
            if ty.is_bytes() || !int_range(ty, self.clocks & (1 << i) != 0).contains(&value) {
                return Err(self.int_error(i, value));
            }
        }
        if out.len() < (args.len() + 1) * vlq::MAX_LEN {
            // Little room left: the checked path.
            let mut w = Writer { out, len: 0 };
            w.bytes(&self.id[..usize::from(self.id_len)])?;
            for &value in args {
                w.int(value)?;
            }
            return Ok(w.len);
        }
        // Room for the longest encoding of every value: write in place.
        *out.first_chunk_mut::<{ vlq::MAX_LEN }>()
            .ok_or(EncodeError::NoSpace)? = self.id;
        let mut len = usize::from(self.id_len);
        for &value in args {
            let room = out
                .get_mut(len..)
                .and_then(<[u8]>::first_chunk_mut::<{ vlq::MAX_LEN }>)
                .ok_or(EncodeError::NoSpace)?;
            len += vlq::encode(value, room);
        }
        Ok(len)
    }

    /// An error unless `given` arguments are one per parameter.
    fn check_count(&self, given: usize) -> Result<(), EncodeError<'d>> {
        let expected = usize::from(self.count);
        if given == expected {
            Ok(())
        } else {
            Err(EncodeError::ArgCount { expected, given })
        }
    }

    /// The error for a bad integer argument `i` (off the hot path).
    #[cold]
    fn int_error(&self, i: usize, value: i64) -> EncodeError<'d> {
        let name = self.message.params().nth(i).map_or("?", |(n, _)| n);
        if self.types.get(i).is_some_and(|ty| ty.is_bytes()) {
            EncodeError::BadValue(name)
        } else {
            EncodeError::OutOfRange { param: name, value }
        }
    }
}

impl<'a> Dictionary<'a> {
    /// Encodes a message written as text, `name param=value …` (any order of
    /// parameters; integers in decimal or `0x` hex; enumeration symbols;
    /// buffers as hex digits), into `out`; returns the bytes written.
    pub fn encode_text<'x>(
        &'x self,
        line: &'x str,
        out: &mut [u8],
    ) -> Result<usize, EncodeError<'x>> {
        let mut words = line.split_ascii_whitespace();
        let name = words.next().ok_or(EncodeError::UnknownMessage(line))?;
        let message = self
            .by_name(name)
            .ok_or(EncodeError::UnknownMessage(name))?;
        // One pass over the arguments, in order: each must name a
        // parameter, and none may follow a `name=value` of the same name.
        let mut values: [Option<&str>; MAX_PARAMS] = [None; MAX_PARAMS];
        for word in words {
            let (key, value) = match word.split_once('=') {
                Some((key, value)) => (key, Some(value)),
                None => (word, None),
            };
            let slot = message
                .params()
                .position(|(p, _)| p == key)
                .and_then(|i| values.get_mut(i))
                .ok_or(EncodeError::UnknownParam(key))?;
            if slot.is_some() {
                return Err(EncodeError::DuplicateParam(key));
            }
            if value.is_some() {
                *slot = value;
            }
        }
        let mut w = Writer { out, len: 0 };
        w.int(i64::from(message.id))?;
        for ((param, ty), text) in message.params().zip(values) {
            let text = text.ok_or(EncodeError::MissingParam(param))?;
            if ty.is_bytes() {
                write_hex_buffer(&mut w, param, text)?;
                continue;
            }
            let value = match self.enumeration_for(param) {
                Some(e) => e.value_of(text).ok_or(EncodeError::BadValue(text))?,
                None => parse_int(text).ok_or(EncodeError::BadValue(text))?,
            };
            check_range(param, ty, value)?;
            w.int(value)?;
        }
        Ok(w.len)
    }

    /// Decodes the message at the front of `payload`; returns it with the
    /// number of bytes it took.
    pub fn decode<'d, 'p>(
        &'d self,
        payload: &'p [u8],
    ) -> Result<(Decoded<'d, 'a, 'p>, usize), DecodeError> {
        let (id, mut at) = vlq::decode(payload).map_err(|_| DecodeError::Truncated)?;
        let message = i32::try_from(id)
            .ok()
            .and_then(|id| self.by_id(id))
            .ok_or(DecodeError::UnknownId(id))?;
        let mut fields = heapless::Vec::new();
        for (_, ty) in message.params() {
            let rest = payload.get(at..).ok_or(DecodeError::Truncated)?;
            let field = if ty.is_bytes() {
                let (&len, data) = rest.split_first().ok_or(DecodeError::Truncated)?;
                let bytes = data.get(..usize::from(len)).ok_or(DecodeError::Truncated)?;
                at += 1 + bytes.len();
                Field::Bytes(bytes)
            } else {
                let (raw, n) = vlq::decode(rest).map_err(|_| DecodeError::Truncated)?;
                at += n;
                Field::Int(if ty.is_signed() {
                    raw
                } else {
                    i64::from(vlq::as_u32(raw))
                })
            };
            // Formats hold at most MAX_PARAMS parameters (checked at parse).
            let _ = fields.push(field);
        }
        Ok((
            Decoded {
                dict: self,
                message,
                fields,
            },
            at,
        ))
    }
}

/// Parses an integer as Klipper's text form allows: decimal or `0x` hex,
/// optionally negative.
fn parse_int(text: &str) -> Option<i64> {
    let (negative, digits) = match text.strip_prefix('-') {
        Some(rest) => (true, rest),
        None => (false, text),
    };
    let magnitude = match digits
        .strip_prefix("0x")
        .or_else(|| digits.strip_prefix("0X"))
    {
        Some(hex) => i64::from_str_radix(hex, 16).ok()?,
        None if digits.bytes().all(|b| b.is_ascii_digit()) => digits.parse().ok()?,
        None => return None,
    };
    Some(if negative { -magnitude } else { magnitude })
}

/// Writes a buffer given as hex digits (two per byte) with its length byte.
fn write_hex_buffer<'x>(
    w: &mut Writer<'_>,
    param: &'x str,
    hex: &'x str,
) -> Result<(), EncodeError<'x>> {
    if !hex.len().is_multiple_of(2) || !hex.bytes().all(|b| b.is_ascii_hexdigit()) {
        return Err(EncodeError::BadValue(hex));
    }
    let len = u8::try_from(hex.len() / 2).map_err(|_| EncodeError::BufferTooLong(param))?;
    w.bytes(&[len])?;
    let digit = |b: u8| (b as char).to_digit(16).unwrap_or(0) as u8;
    for &[high, low] in hex.as_bytes().as_chunks::<2>().0 {
        w.bytes(&[digit(high) << 4 | digit(low)])?;
    }
    Ok(())
}

/// One decoded parameter value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Field<'p> {
    /// An integer (unsigned types as their 32-bit value).
    Int(i64),
    /// A string or buffer.
    Bytes(&'p [u8]),
}

/// A decoded message; `Display` writes Klipper's text form.
#[derive(Debug, Clone)]
pub struct Decoded<'d, 'a, 'p> {
    dict: &'d Dictionary<'a>,
    /// The message's dictionary entry.
    pub message: &'d Message<'a>,
    /// Its parameter values, in format order.
    pub fields: heapless::Vec<Field<'p>, MAX_PARAMS>,
}

impl Decoded<'_, '_, '_> {
    /// The value of the integer parameter `name`.
    pub fn int(&self, name: &str) -> Option<i64> {
        self.message
            .params()
            .zip(&self.fields)
            .find_map(|((n, _), f)| match f {
                Field::Int(v) if n == name => Some(*v),
                _ => None,
            })
    }
}

impl fmt::Display for Decoded<'_, '_, '_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.message.name())?;
        for ((name, _), field) in self.message.params().zip(&self.fields) {
            write!(f, " {name}=")?;
            match (*field, self.dict.enumeration_for(name)) {
                (Field::Int(v), Some(e)) => e.write_name(v, f)?,
                (Field::Int(v), None) => write!(f, "{v}")?,
                (Field::Bytes(b), _) => write_bytes_literal(b, f)?,
            }
        }
        Ok(())
    }
}

/// Writes bytes as a Python bytes literal (`b'..'`), as Klipper's logs do.
fn write_bytes_literal(bytes: &[u8], f: &mut impl fmt::Write) -> fmt::Result {
    let quote = if bytes.contains(&b'\'') && !bytes.contains(&b'"') {
        '"'
    } else {
        '\''
    };
    write!(f, "b{quote}")?;
    for &b in bytes {
        match b {
            b'\\' => f.write_str("\\\\")?,
            b'\t' => f.write_str("\\t")?,
            b'\n' => f.write_str("\\n")?,
            b'\r' => f.write_str("\\r")?,
            _ if char::from(b) == quote => write!(f, "\\{quote}")?,
            0x20..=0x7e => f.write_char(char::from(b))?,
            _ => write!(f, "\\x{b:02x}")?,
        }
    }
    f.write_char(quote)
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::string::ToString;

    const DICT: &str = r#"{"commands": {
        "queue_step oid=%c interval=%u count=%hu add=%hi": 20,
        "config_stepper oid=%c step_pin=%u dir_pin=%u invert_step=%c": 21,
        "spi_send oid=%c data=%*s": 22,
        "set_clock clock=%u offset=%i": 23},
        "responses": {},
        "enumerations": {"pin": {"PA0": [0, 16], "PG0": [96, 16]}}}"#;

    fn dict() -> Dictionary<'static> {
        Dictionary::parse(DICT).expect("valid")
    }

    fn text_round_trip(line: &str) {
        let d = dict();
        let mut buf = [0u8; 64];
        let n = d.encode_text(line, &mut buf).expect(line);
        let (decoded, used) = d.decode(&buf[..n]).expect("decodes");
        assert_eq!(used, n);
        assert_eq!(decoded.to_string(), line);
    }

    #[test]
    fn text_round_trips() {
        text_round_trip("queue_step oid=2 interval=45367423 count=1 add=0");
        text_round_trip("queue_step oid=2 interval=4294967295 count=65535 add=-32768");
        text_round_trip("config_stepper oid=2 step_pin=PG13 dir_pin=PA0 invert_step=0");
        text_round_trip("set_clock clock=2147483648 offset=-2147483648");
    }

    #[test]
    fn absolute_clocks_may_carry_64_bit_values_and_decode_to_their_low_32_bits() {
        let d = dict();
        let mut buf = [0u8; 64];
        let n = d
            .encode_text("set_clock clock=7888379999 offset=0", &mut buf)
            .expect("64-bit clock");
        let (decoded, _) = d.decode(&buf[..n]).expect("decodes");
        assert_eq!(
            decoded.int("clock"),
            Some(i64::from(7_888_379_999_u64 as u32))
        );
        let enc = Encoder::new(&d, "set_clock").expect("known");
        let mut fast = [0u8; 64];
        let m = enc
            .encode_ints(&[7_888_379_999, 0], &mut fast)
            .expect("64-bit clock");
        assert_eq!(&fast[..m], &buf[..n]);
    }

    #[test]
    fn hex_buffers_parameters_in_any_order_and_hex_ints() {
        let d = dict();
        let mut buf = [0u8; 64];
        let n = d
            .encode_text("spi_send data=0102ff oid=0x10", &mut buf)
            .expect("valid");
        assert_eq!(&buf[..n], &[22, 16, 3, 1, 2, 0xff]);
        let m = d
            .encode_text("spi_send oid=1 data=01415c27", &mut buf)
            .expect("valid");
        let (decoded, _) = d.decode(&buf[..m]).expect("decodes");
        assert_eq!(decoded.to_string(), "spi_send oid=1 data=b\"\\x01A\\\\'\"");
    }

    #[test]
    fn encoder_matches_text_encoding() {
        let d = dict();
        let enc = Encoder::new(&d, "queue_step").expect("known");
        let (mut a, mut b) = ([0u8; 32], [0u8; 32]);
        let n = enc
            .encode_ints(&[2, 3_000_000_000, 7, -5], &mut a)
            .expect("valid");
        let m = d
            .encode_text(
                "queue_step oid=2 interval=3000000000 count=7 add=-5",
                &mut b,
            )
            .expect("valid");
        assert_eq!(&a[..n], &b[..m]);
        let k = enc
            .encode(
                &[
                    Arg::Int(2),
                    Arg::Int(3_000_000_000),
                    Arg::Int(7),
                    Arg::Int(-5),
                ],
                &mut b,
            )
            .expect("ok");
        assert_eq!(&a[..n], &b[..k]);
    }

    #[test]
    fn encode_ints_checks_each_argument_against_its_parameter() {
        let d = dict();
        let mut buf = [0u8; 64];
        let step = Encoder::new(&d, "queue_step").expect("known");
        assert_eq!(
            step.encode_ints(&[1, 2, 65_536, 0], &mut buf),
            Err(EncodeError::OutOfRange {
                param: "count",
                value: 65_536
            })
        );
        assert_eq!(
            step.encode_ints(&[1, 2, 3], &mut buf),
            Err(EncodeError::ArgCount {
                expected: 4,
                given: 3
            })
        );
        let clock = Encoder::new(&d, "set_clock").expect("known");
        assert_eq!(
            clock.encode_ints(&[1 << 40, 1 << 31], &mut buf),
            Err(EncodeError::OutOfRange {
                param: "offset",
                value: 1 << 31
            })
        );
        assert_eq!(
            clock.encode_ints(&[-1, 0], &mut buf),
            Err(EncodeError::OutOfRange {
                param: "clock",
                value: -1
            })
        );
        let spi = Encoder::new(&d, "spi_send").expect("known");
        assert_eq!(
            spi.encode_ints(&[1, 0], &mut buf),
            Err(EncodeError::BadValue("data"))
        );
    }

    #[test]
    fn bad_input_is_an_error_naming_the_problem() {
        let d = dict();
        let mut buf = [0u8; 64];
        let cases: &[(&str, EncodeError<'_>)] = &[
            ("nope oid=1", EncodeError::UnknownMessage("nope")),
            (
                "queue_step oid=1 interval=1 count=1",
                EncodeError::MissingParam("add"),
            ),
            (
                "queue_step oid=1 interval=1 count=1 add=0 x=1",
                EncodeError::UnknownParam("x"),
            ),
            (
                "queue_step oid=1 oid=1 interval=1 count=1 add=0",
                EncodeError::DuplicateParam("oid"),
            ),
            (
                "queue_step oid=1 interval=1 count=65536 add=0",
                EncodeError::OutOfRange {
                    param: "count",
                    value: 65536,
                },
            ),
            (
                "queue_step oid=1 interval=-1 count=1 add=0",
                EncodeError::OutOfRange {
                    param: "interval",
                    value: -1,
                },
            ),
            (
                "queue_step oid=1 interval=4294967296 count=1 add=0",
                EncodeError::OutOfRange {
                    param: "interval",
                    value: 4_294_967_296,
                },
            ),
            (
                "set_clock clock=-1 offset=0",
                EncodeError::OutOfRange {
                    param: "clock",
                    value: -1,
                },
            ),
            (
                "queue_step oid=1 interval=1 count=1 add=1.5",
                EncodeError::BadValue("1.5"),
            ),
            (
                "config_stepper oid=1 step_pin=PZ9 dir_pin=PA0 invert_step=0",
                EncodeError::BadValue("PZ9"),
            ),
            ("spi_send oid=1 data=abc", EncodeError::BadValue("abc")),
            // A bare parameter name after its `name=value` repeats it; one
            // before it is ignored.
            (
                "queue_step oid=1 interval=1 count=1 add=0 oid",
                EncodeError::DuplicateParam("oid"),
            ),
            (
                "queue_step oid oid=1 count=1",
                EncodeError::MissingParam("interval"),
            ),
            // The first unknown or repeated parameter is the one named.
            ("queue_step x=1 oid=1 oid=2", EncodeError::UnknownParam("x")),
            (
                "queue_step oid=1 oid=2 x=1",
                EncodeError::DuplicateParam("oid"),
            ),
        ];
        for (line, expected) in cases {
            assert_eq!(d.encode_text(line, &mut buf), Err(*expected), "{line}");
        }
        assert_eq!(
            d.encode_text("queue_step oid=1 interval=1 count=1 add=0", &mut buf[..3]),
            Err(EncodeError::NoSpace)
        );
    }

    #[test]
    fn truncated_and_unknown_bytes_are_errors() {
        let d = dict();
        let mut buf = [0u8; 64];
        let n = d
            .encode_text("queue_step oid=2 interval=45367423 count=1 add=0", &mut buf)
            .expect("valid");
        for cut in 0..n {
            assert_eq!(
                d.decode(&buf[..cut]).map(|(_, n)| n),
                Err(DecodeError::Truncated),
                "cut {cut}"
            );
        }
        assert_eq!(
            d.decode(&[90]).map(|(_, n)| n),
            Err(DecodeError::UnknownId(90))
        );
    }
}
