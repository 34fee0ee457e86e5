//! Klipper data dictionaries: the table of commands, responses,
//! enumerations and constants an MCU describes itself with.
//!
//! The dictionary is JSON (zlib-compressed when an MCU sends it in answer to
//! `identify`). [`Dictionary::parse`] indexes it without copying: the
//! message formats, enumeration bodies and constants stay slices of the text.
//!
//! Message formats read `name param=%type …`; the types are `%u` (u32),
//! `%i` (i32), `%hu` (u16), `%hi` (i16), `%c` (u8), `%s` (string), `%.*s`
//! and `%*s` (byte buffers). A parameter uses an enumeration when its name
//! equals the enumeration's name or ends with `_` and that name (`step_pin`
//! uses `pin`); the first such enumeration in dictionary order wins.

use crate::json::{self, JsonError, Object, Str, Value};
use core::fmt;
use core::mem::MaybeUninit;
use core::ptr::addr_of_mut;

/// Most messages (commands, responses, built-ins) one dictionary may hold.
pub const MAX_MESSAGES: usize = 320;
/// Most enumerations one dictionary may hold.
pub const MAX_ENUMERATIONS: usize = 48;
/// Most parameters one message may have.
pub const MAX_PARAMS: usize = 16;

/// Messages every Klipper MCU understands before its dictionary is known.
const BUILT_IN: [(i32, Kind, &str); 2] = [
    (0, Kind::Response, "identify_response offset=%u data=%.*s"),
    (1, Kind::Command, "identify offset=%u count=%c"),
];

/// Ids that travel in one VLQ byte; looked up through a direct table.
const SHORT_IDS: core::ops::RangeInclusive<i32> = -32..=95;

/// Which way a message travels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// Host to MCU.
    Command,
    /// MCU to host.
    Response,
}

/// The wire type of one parameter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ParamType {
    /// `%u`: unsigned 32-bit.
    U32,
    /// `%i`: signed 32-bit.
    I32,
    /// `%hu`: unsigned 16-bit.
    U16,
    /// `%hi`: signed 16-bit.
    I16,
    /// `%c`: unsigned 8-bit.
    U8,
    /// `%s`: a string (length byte, then bytes).
    String,
    /// `%.*s`: a buffer from the MCU's program memory (same encoding).
    ProgmemBuffer,
    /// `%*s`: a byte buffer (same encoding).
    Buffer,
}

impl ParamType {
    /// The type named by a format specifier such as `%hu`.
    pub fn from_spec(spec: &str) -> Option<Self> {
        Some(match spec {
            "%u" => Self::U32,
            "%i" => Self::I32,
            "%hu" => Self::U16,
            "%hi" => Self::I16,
            "%c" => Self::U8,
            "%s" => Self::String,
            "%.*s" => Self::ProgmemBuffer,
            "%*s" => Self::Buffer,
            _ => return None,
        })
    }

    /// True for the length-prefixed byte types.
    pub fn is_bytes(self) -> bool {
        matches!(self, Self::String | Self::ProgmemBuffer | Self::Buffer)
    }

    /// True for the signed integer types.
    pub fn is_signed(self) -> bool {
        matches!(self, Self::I32 | Self::I16)
    }

    /// The values this integer type can carry.
    pub fn range(self) -> core::ops::RangeInclusive<i64> {
        match self {
            Self::U32 => 0..=i64::from(u32::MAX),
            Self::I32 => i64::from(i32::MIN)..=i64::from(i32::MAX),
            Self::U16 => 0..=i64::from(u16::MAX),
            Self::I16 => i64::from(i16::MIN)..=i64::from(i16::MAX),
            Self::U8 => 0..=i64::from(u8::MAX),
            Self::String | Self::ProgmemBuffer | Self::Buffer => 0..=0,
        }
    }
}

/// One message of the dictionary.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Message<'a> {
    /// The message id (its tag; sent as a VLQ).
    pub id: i32,
    /// Direction.
    pub kind: Kind,
    /// The format string, e.g. `queue_step oid=%c interval=%u count=%hu add=%hi`.
    pub format: &'a str,
}

impl<'a> Message<'a> {
    /// The message name (the format's first word).
    pub fn name(&self) -> &'a str {
        self.format
            .split_ascii_whitespace()
            .next()
            .unwrap_or_default()
    }

    /// The parameters, in wire order, as `(name, type)`. Formats are checked
    /// when the dictionary is parsed, so every item is well formed.
    pub fn params(&self) -> impl Iterator<Item = (&'a str, ParamType)> + 'a {
        self.format
            .split_ascii_whitespace()
            .skip(1)
            .filter_map(parse_param)
    }
}

fn parse_param(part: &str) -> Option<(&str, ParamType)> {
    let (name, spec) = part.split_once('=')?;
    Some((name, ParamType::from_spec(spec)?))
}

/// A named set of symbolic values (pins, bus names, …).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Enumeration<'a> {
    /// Its name, e.g. `pin`.
    pub name: &'a str,
    entries: Object<'a>,
}

/// One enumeration entry: a single value, or a run of `count` values named
/// by a root and consecutive numbers (`"PA0": [0, 16]` is PA0..PA15 = 0..15).
enum Entry<'a> {
    Single(Str<'a>, i64),
    Range {
        root: &'a str,
        first_number: i64,
        first_value: i64,
        count: i64,
    },
}

impl<'a> Entry<'a> {
    /// The member `key: value` of an enumeration's body as an entry: a
    /// number, or an array of exactly two numbers under a name without
    /// escapes; None for anything else.
    fn new(key: Str<'a>, value: Value<'a>) -> Option<Self> {
        match value {
            Value::Int(v) => Some(Entry::Single(key, v)),
            Value::Array(pair) => {
                let mut items = pair.items();
                let (Some(Ok(Value::Int(first_value))), Some(Ok(Value::Int(count))), None) =
                    (items.next(), items.next(), items.next())
                else {
                    return None;
                };
                let name = key.plain()?;
                let root = name.trim_end_matches(|c: char| c.is_ascii_digit());
                let first_number = name
                    .get(root.len()..)
                    .and_then(|digits| digits.parse().ok())
                    .unwrap_or(0);
                Some(Entry::Range {
                    root,
                    first_number,
                    first_value,
                    count,
                })
            }
            _ => None,
        }
    }
}

impl<'a> Enumeration<'a> {
    fn entries(&self) -> impl Iterator<Item = Entry<'a>> + 'a {
        // Entries were validated by Dictionary::parse.
        self.entries
            .members()
            .filter_map(Result::ok)
            .filter_map(|(key, value)| Entry::new(key, value))
    }

    /// The value of the symbol `name`.
    pub fn value_of(&self, name: &str) -> Option<i64> {
        self.entries().find_map(|entry| match entry {
            Entry::Single(key, v) => key.eq_str(name).then_some(v),
            Entry::Range {
                root,
                first_number,
                first_value,
                count,
            } => {
                let number: i64 = name.strip_prefix(root)?.parse().ok()?;
                let canonical = name.len() - root.len() == decimal_len(number);
                (canonical && (first_number..first_number + count).contains(&number))
                    .then_some(first_value + number - first_number)
            }
        })
    }

    /// The symbol of a single entry for `value` (the last one defined, if
    /// several share it), escapes included, as [`Self::write_name`]
    /// writes it; None if no single entry has it.
    pub fn name_of(&self, value: i64) -> Option<&'a str> {
        let singles = self.entries().filter_map(|entry| match entry {
            Entry::Single(key, v) if v == value => Some(key.raw()),
            _ => None,
        });
        singles.last()
    }

    /// Writes the symbol for `value` (the last one defined, if several
    /// share it), or `?value` if none has it.
    pub fn write_name(&self, value: i64, out: &mut impl fmt::Write) -> fmt::Result {
        let mut found = None;
        for entry in self.entries() {
            match entry {
                Entry::Single(key, v) if v == value => found = Some((key.raw(), None)),
                Entry::Range {
                    root,
                    first_number,
                    first_value,
                    count,
                } if (first_value..first_value + count).contains(&value) => {
                    found = Some((root, Some(first_number + value - first_value)));
                }
                _ => {}
            }
        }
        match found {
            Some((name, None)) => out.write_str(name),
            Some((root, Some(number))) => write!(out, "{root}{number}"),
            None => write!(out, "?{value}"),
        }
    }
}

fn decimal_len(n: i64) -> usize {
    let mut len = if n <= 0 { 1 } else { 0 };
    let mut rest = n.unsigned_abs();
    while rest > 0 {
        len += 1;
        rest /= 10;
    }
    len
}

/// Why a dictionary was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DictError<'a> {
    /// The text is not valid JSON.
    Json(JsonError),
    /// The document or a member has the wrong JSON type.
    WrongType(&'static str),
    /// A required member is absent.
    Missing(&'static str),
    /// More entries than this build holds.
    TooMany(&'static str),
    /// A message format this implementation cannot use.
    BadFormat(&'a str),
    /// A message id outside the 32-bit range, or used twice.
    BadId(i64),
}

impl From<JsonError> for DictError<'_> {
    fn from(e: JsonError) -> Self {
        Self::Json(e)
    }
}

impl fmt::Display for DictError<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Json(e) => write!(f, "dictionary JSON: {} at byte {}", e.reason, e.offset),
            Self::WrongType(what) => write!(f, "dictionary: {what} has the wrong type"),
            Self::Missing(what) => write!(f, "dictionary: no {what}"),
            Self::TooMany(what) => write!(f, "dictionary: too many {what}"),
            Self::BadFormat(format) => write!(f, "dictionary: unusable message format '{format}'"),
            Self::BadId(id) => write!(f, "dictionary: bad or duplicate message id {id}"),
        }
    }
}

/// An indexed data dictionary, borrowing its JSON text.
#[derive(Debug, Clone)]
pub struct Dictionary<'a> {
    messages: heapless::Vec<Message<'a>, MAX_MESSAGES>,
    /// `index + 1` of the message with each short id (`id + 32`); 0 if none.
    short_ids: [u16; 128],
    enumerations: heapless::Vec<Enumeration<'a>, MAX_ENUMERATIONS>,
    config: Option<Object<'a>>,
    version: Option<Str<'a>>,
    build_versions: Option<Str<'a>>,
}

impl<'a> Dictionary<'a> {
    /// Parses and indexes a dictionary's JSON text.
    pub fn parse(text: &'a str) -> Result<Self, DictError<'a>> {
        let mut slot = MaybeUninit::uninit();
        Self::parse_in(&mut slot, text)?;
        // SAFETY: `parse_in` initialised it.
        Ok(unsafe { slot.assume_init() })
    }

    /// [`Self::parse`] into `slot` (a dictionary is about 10 KB, which a
    /// microcontroller's stack should not carry): on an error the slot
    /// holds an empty or partial dictionary, which owns nothing.
    pub fn parse_in<'s>(
        slot: &'s mut MaybeUninit<Self>,
        text: &'a str,
    ) -> Result<&'s mut Self, DictError<'a>> {
        let p = slot.as_mut_ptr();
        // SAFETY: `p` is valid for writes; each field is written once, in
        // place, before the slot is taken as initialised.
        let dict = unsafe {
            addr_of_mut!((*p).messages).write(heapless::Vec::new());
            addr_of_mut!((*p).short_ids).write([0; 128]);
            addr_of_mut!((*p).enumerations).write(heapless::Vec::new());
            addr_of_mut!((*p).config).write(None);
            addr_of_mut!((*p).version).write(None);
            addr_of_mut!((*p).build_versions).write(None);
            slot.assume_init_mut()
        };
        let Value::Object(root) = json::parse(text)? else {
            return Err(DictError::WrongType("the document"));
        };
        let mut saw_commands = false;
        for member in root.members() {
            let (key, value) = member?;
            match (key.raw(), value) {
                ("commands", Value::Object(o)) => {
                    dict.add_messages(o, Kind::Command)?;
                    saw_commands = true;
                }
                ("responses", Value::Object(o)) => dict.add_messages(o, Kind::Response)?,
                ("enumerations", Value::Object(o)) => dict.add_enumerations(o)?,
                ("config", Value::Object(o)) => dict.config = Some(o),
                ("version", Value::Str(s)) => dict.version = Some(s),
                ("build_versions", Value::Str(s)) => dict.build_versions = Some(s),
                ("commands" | "responses" | "enumerations" | "config", _) => {
                    return Err(DictError::WrongType(
                        "a message, enumeration or config table",
                    ));
                }
                _ => {}
            }
        }
        if !saw_commands {
            return Err(DictError::Missing("commands"));
        }
        for (id, kind, format) in BUILT_IN {
            if dict.by_id(id).is_none() {
                dict.add(Message { id, kind, format })?;
            }
        }
        Ok(dict)
    }

    fn add_messages(&mut self, table: Object<'a>, kind: Kind) -> Result<(), DictError<'a>> {
        for member in table.members() {
            let (format, id) = member?;
            let Value::Int(id) = id else {
                return Err(DictError::WrongType("a message id"));
            };
            let format = format.plain().ok_or(DictError::BadFormat(format.raw()))?;
            let id = i32::try_from(id).map_err(|_| DictError::BadId(id))?;
            self.add(Message { id, kind, format })?;
        }
        Ok(())
    }

    fn add(&mut self, message: Message<'a>) -> Result<(), DictError<'a>> {
        let format = message.format;
        let mut parts = format.split_ascii_whitespace();
        let name_ok = parts.next().is_some_and(|n| !n.contains('='));
        let mut count = 0;
        for part in parts {
            parse_param(part).ok_or(DictError::BadFormat(format))?;
            count += 1;
        }
        if !name_ok || count > MAX_PARAMS {
            return Err(DictError::BadFormat(format));
        }
        if self.by_id(message.id).is_some() {
            return Err(DictError::BadId(i64::from(message.id)));
        }
        let index = self.messages.len();
        self.messages
            .push(message)
            .map_err(|_| DictError::TooMany("messages"))?;
        if SHORT_IDS.contains(&message.id) {
            self.short_ids[(message.id + 32) as usize] = index as u16 + 1;
        }
        Ok(())
    }

    fn add_enumerations(&mut self, table: Object<'a>) -> Result<(), DictError<'a>> {
        for member in table.members() {
            let (name, body) = member?;
            let Value::Object(entries) = body else {
                return Err(DictError::WrongType("an enumeration"));
            };
            for entry in entries.members() {
                let (key, value) = entry?;
                if Entry::new(key, value).is_none() {
                    let range = matches!(value, Value::Array(_)) && key.plain().is_some();
                    return Err(DictError::WrongType(if range {
                        "an enumeration range"
                    } else {
                        "an enumeration entry"
                    }));
                }
            }
            let name = name
                .plain()
                .ok_or(DictError::WrongType("an enumeration name"))?;
            self.enumerations
                .push(Enumeration { name, entries })
                .map_err(|_| DictError::TooMany("enumerations"))?;
        }
        Ok(())
    }

    /// Every message, built-ins included.
    pub fn messages(&self) -> &[Message<'a>] {
        &self.messages
    }

    /// The message with id `id`.
    pub fn by_id(&self, id: i32) -> Option<&Message<'a>> {
        if SHORT_IDS.contains(&id) {
            let slot = self.short_ids[(id + 32) as usize];
            return slot.checked_sub(1).map(|i| &self.messages[usize::from(i)]);
        }
        self.messages.iter().find(|m| m.id == id)
    }

    /// The message named `name` (commands and responses share one namespace).
    pub fn by_name(&self, name: &str) -> Option<&Message<'a>> {
        self.messages.iter().find(|m| m.name() == name)
    }

    /// The enumeration a parameter named `param` uses, if any.
    pub fn enumeration_for(&self, param: &str) -> Option<&Enumeration<'a>> {
        self.enumerations.iter().find(|e| {
            param == e.name
                || param
                    .strip_suffix(e.name)
                    .is_some_and(|head| head.ends_with('_'))
        })
    }

    /// The enumeration named `name`.
    pub fn enumeration(&self, name: &str) -> Option<&Enumeration<'a>> {
        self.enumerations.iter().find(|e| e.name == name)
    }

    /// An integer constant from the `config` table, e.g. `CLOCK_FREQ`.
    /// Klipper writes some numeric constants as strings; those parse too.
    pub fn constant_int(&self, name: &str) -> Option<i64> {
        match self.config?.get(name).ok()?? {
            Value::Int(v) => Some(v),
            Value::Str(s) => s.plain()?.trim().parse().ok(),
            _ => None,
        }
    }

    /// A string constant from the `config` table, e.g. `MCU`.
    pub fn constant_str(&self, name: &str) -> Option<&'a str> {
        match self.config?.get(name).ok()?? {
            Value::Str(s) => s.plain(),
            _ => None,
        }
    }

    /// The firmware version string.
    pub fn version(&self) -> Option<&'a str> {
        self.version.and_then(|s| s.plain())
    }

    /// The compiler and binutils versions the firmware was built with.
    pub fn build_versions(&self) -> Option<&'a str> {
        self.build_versions.and_then(|s| s.plain())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DICT: &str = r#"{
        "commands": {"queue_step oid=%c interval=%u count=%hu add=%hi": 20,
                     "config_stepper oid=%c step_pin=%u dir_pin=%u": -5,
                     "big oid=%c": 300},
        "responses": {"clock clock=%u": -2},
        "enumerations": {"pin": {"PA0": [0, 16], "PB3": [19, 2], "ADC_TEMPERATURE": 254},
                         "spi_bus": {"spi1": 1, "spi1a": 1}},
        "config": {"CLOCK_FREQ": 180000000, "MCU": "stm32f446xx", "STATS_SUMSQ_BASE": "256"},
        "version": "v1"
    }"#;

    fn dict() -> Dictionary<'static> {
        Dictionary::parse(DICT).expect("valid dictionary")
    }

    #[test]
    fn indexes_messages_by_id_and_name() {
        let d = dict();
        assert_eq!(d.by_id(20).map(Message::name), Some("queue_step"));
        assert_eq!(d.by_id(-5).map(Message::name), Some("config_stepper"));
        assert_eq!(d.by_id(300).map(Message::name), Some("big"));
        assert_eq!(d.by_id(1).map(Message::name), Some("identify"));
        assert_eq!(d.by_name("clock").map(|m| m.kind), Some(Kind::Response));
        let params: heapless::Vec<_, 4> = d.by_id(20).expect("present").params().collect();
        assert_eq!(
            params,
            [
                ("oid", ParamType::U8),
                ("interval", ParamType::U32),
                ("count", ParamType::U16),
                ("add", ParamType::I16)
            ]
        );
    }

    #[test]
    fn enumerations_expand_ranges_and_match_suffixes() {
        let d = dict();
        let pin = d.enumeration_for("step_pin").expect("pin enumeration");
        assert_eq!(pin.name, "pin");
        assert!(d.enumeration_for("oid").is_none());
        assert!(d.enumeration_for("spin").is_none());
        assert_eq!(pin.value_of("PA15"), Some(15));
        assert_eq!(pin.value_of("PA16"), None);
        assert_eq!(pin.value_of("PA01"), None);
        assert_eq!(pin.value_of("PB4"), Some(20));
        assert_eq!(pin.value_of("ADC_TEMPERATURE"), Some(254));
        let mut s = heapless::String::<16>::new();
        pin.write_name(20, &mut s).expect("fits");
        assert_eq!(s, "PB4");
        s.clear();
        pin.write_name(99, &mut s).expect("fits");
        assert_eq!(s, "?99");
        s.clear();
        d.enumeration("spi_bus")
            .expect("present")
            .write_name(1, &mut s)
            .expect("fits");
        assert_eq!(s, "spi1a");
    }

    #[test]
    fn constants_and_version() {
        let d = dict();
        assert_eq!(d.constant_int("CLOCK_FREQ"), Some(180_000_000));
        assert_eq!(d.constant_int("STATS_SUMSQ_BASE"), Some(256));
        assert_eq!(d.constant_str("MCU"), Some("stm32f446xx"));
        assert_eq!(d.constant_int("MISSING"), None);
        assert_eq!(d.version(), Some("v1"));
    }

    #[test]
    fn malformed_dictionaries_are_errors() {
        let cases: &[(&str, DictError<'static>)] = &[
            ("[]", DictError::WrongType("the document")),
            ("{}", DictError::Missing("commands")),
            (
                r#"{"commands": {"a x=%q": 1}}"#,
                DictError::BadFormat("a x=%q"),
            ),
            (r#"{"commands": {"a": 1, "b": 1}}"#, DictError::BadId(1)),
            (
                r#"{"commands": {"a": 4294967296}}"#,
                DictError::BadId(4_294_967_296),
            ),
            (
                r#"{"commands": {"a": "1"}}"#,
                DictError::WrongType("a message id"),
            ),
            (
                r#"{"commands": {}, "enumerations": {"e": {"x": [1]}}}"#,
                DictError::WrongType("an enumeration range"),
            ),
            (
                r#"{"commands": {}, "enumerations": {"e": {"x": [1, 2, 3]}}}"#,
                DictError::WrongType("an enumeration range"),
            ),
            (
                r#"{"commands": {}, "enumerations": {"e": {"x": [1, "2"]}}}"#,
                DictError::WrongType("an enumeration range"),
            ),
            (
                r#"{"commands": {}, "enumerations": {"e": {"x\u0030": [1, 2]}}}"#,
                DictError::WrongType("an enumeration entry"),
            ),
            (
                r#"{"commands": {}, "enumerations": {"e": {"x": "1"}}}"#,
                DictError::WrongType("an enumeration entry"),
            ),
        ];
        for (text, expected) in cases {
            assert_eq!(
                Dictionary::parse(text).expect_err(text),
                *expected,
                "{text}"
            );
        }
    }
}
