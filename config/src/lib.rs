//! Reading Klipper's `printer.cfg` format without allocation.
//!
//! The text stays in the caller's buffer; [`Config::parse`] indexes its
//! sections and option lines. Format, as Klipper reads it: `[section name]`
//! headers; `option: value` or `option = value` lines (names are
//! case-insensitive); whole-line comments starting with `#` or `;`, inline
//! comments after whitespace; indented lines continue the previous value; a
//! repeated section adds to (and overrides) the earlier one; the
//! `#*# <---- SAVE_CONFIG ---->` block at the end is read like the rest.
//!
//! Every option that the firmware reads is marked used; [`Config::check_unused`]
//! then reports the first option nobody read, as Klipper does ("Option 'x' is
//! not valid in section 'y'").
//!
//! Below `onechip-planner`, which builds the machine from these sections:
//! nothing here knows about motion.
#![cfg_attr(not(feature = "std"), no_std)]

pub mod decimal;

use core::cell::Cell;
use core::fmt;

/// Most sections (counting repeats) one config may have.
pub const MAX_SECTIONS: usize = 96;
/// Most option lines one config may have.
pub const MAX_OPTIONS: usize = 1024;
/// Most files (printer.cfg and its includes) one config may read.
pub const MAX_FILES: usize = 16;
/// Deepest nesting of `[include]`.
pub const MAX_INCLUDE_DEPTH: usize = 4;

/// One file of a config: its name (as `[include]` patterns see it) and text.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConfigFile<'a> {
    /// File name, relative to the folder of printer.cfg.
    pub name: &'a str,
    /// Its contents.
    pub text: &'a str,
}

/// True if `name` matches `pattern`, where `*` matches any run of
/// characters and `?` any one character.
pub fn glob_match(pattern: &str, name: &str) -> bool {
    let (p, n) = (pattern.as_bytes(), name.as_bytes());
    let (mut pi, mut ni) = (0, 0);
    let mut star: Option<(usize, usize)> = None;
    while ni < n.len() {
        match p.get(pi) {
            Some(b'*') => {
                star = Some((pi, ni));
                pi += 1;
            }
            Some(&c) if c == b'?' || c == n[ni] => {
                pi += 1;
                ni += 1;
            }
            _ => match star {
                Some((sp, sn)) => {
                    pi = sp + 1;
                    ni = sn + 1;
                    star = Some((sp, sn + 1));
                }
                None => return false,
            },
        }
    }
    p[pi..].iter().all(|&c| c == b'*')
}

/// Why the config was refused; every error names where.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConfigError<'a> {
    /// The file's name (for messages).
    pub file: &'a str,
    /// 1-based line number (0: not tied to a line).
    pub line: usize,
    /// What is wrong.
    pub kind: ConfigErrorKind<'a>,
}

/// What is wrong with a config.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConfigErrorKind<'a> {
    /// A line that is neither a section, an option nor a comment.
    Syntax,
    /// An option before the first section.
    OptionOutsideSection,
    /// More sections or options than this build holds.
    TooLarge,
    /// A required section is absent.
    MissingSection(&'a str),
    /// A required option is absent.
    MissingOption {
        /// The section.
        section: &'a str,
        /// The option.
        option: &'a str,
    },
    /// An option's value is not valid.
    BadValue {
        /// The section.
        section: &'a str,
        /// The option.
        option: &'a str,
        /// Why.
        reason: &'static str,
    },
    /// A pin option refused as Klipper refuses it, in its words
    /// (`Unknown pin chip name 'tmc2209_stepper_x'`: `message` then the
    /// quoted `name`, if any).
    BadPin {
        /// The section.
        section: &'a str,
        /// The option.
        option: &'a str,
        /// Klipper's message.
        message: &'static str,
        /// The name it quotes, if any.
        name: Option<&'a str>,
    },
    /// An option nobody reads (a typo, or a feature not supported).
    UnknownOption {
        /// The section.
        section: &'a str,
        /// The option.
        option: &'a str,
    },
    /// A section this firmware does not support.
    UnsupportedSection(&'a str),
    /// An `[include]` names a file that does not exist.
    MissingInclude,
    /// `[include]` nested deeper than [`MAX_INCLUDE_DEPTH`].
    IncludeTooDeep,
}

impl fmt::Display for ConfigError<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.line > 0 {
            write!(f, "{}:{}: ", self.file, self.line)?;
        } else {
            write!(f, "{}: ", self.file)?;
        }
        match self.kind {
            ConfigErrorKind::Syntax => f.write_str("not a section, an option or a comment"),
            ConfigErrorKind::OptionOutsideSection => {
                f.write_str("option before the first [section]")
            }
            ConfigErrorKind::TooLarge => f.write_str("too many sections or options"),
            ConfigErrorKind::MissingSection(s) => write!(f, "section '{s}' is required"),
            ConfigErrorKind::MissingOption { section, option } => {
                write!(
                    f,
                    "option '{option}' in section '{section}' must be specified"
                )
            }
            ConfigErrorKind::BadValue {
                section,
                option,
                reason,
            } => {
                write!(f, "option '{option}' in section '{section}' {reason}")
            }
            ConfigErrorKind::BadPin {
                section,
                option,
                message,
                name,
            } => {
                write!(f, "option '{option}' in section '{section}': {message}")?;
                match name {
                    Some(name) => write!(f, " '{name}'"),
                    None => Ok(()),
                }
            }
            ConfigErrorKind::UnknownOption { section, option } => {
                write!(f, "option '{option}' is not valid in section '{section}'")
            }
            ConfigErrorKind::UnsupportedSection(s) => {
                write!(f, "section '{s}' is not supported by onechip yet")
            }
            ConfigErrorKind::MissingInclude => f.write_str("include file does not exist"),
            ConfigErrorKind::IncludeTooDeep => f.write_str("includes nested too deeply"),
        }
    }
}

/// A section header: the section's name and where it is.
#[derive(Debug, Clone, Copy)]
struct Header<'a> {
    name: &'a str,
    /// Index of its file in `Config::files`.
    file: usize,
    /// 1-based line number.
    line: usize,
}

/// One option line: where it is and its text.
#[derive(Debug, Clone, Copy)]
struct OptionLine<'a> {
    section: usize,
    /// Index of its file in `Config::files`.
    file: usize,
    line: usize,
    name: &'a str,
    /// The value, continuation lines included.
    value: &'a str,
}

/// An indexed config file.
#[derive(Debug)]
pub struct Config<'a> {
    /// File names, the main file first, in the order they were read.
    files: heapless::Vec<&'a str, MAX_FILES>,
    /// Section headers, in file order (repeats included).
    sections: heapless::Vec<Header<'a>, MAX_SECTIONS>,
    options: heapless::Vec<OptionLine<'a>, MAX_OPTIONS>,
    used: [Cell<u32>; MAX_OPTIONS / 32],
}

impl<'a> Config<'a> {
    /// Indexes `text`, naming it `file` in errors.
    pub fn parse(file: &'a str, text: &'a str) -> Result<Self, ConfigError<'a>> {
        Self::parse_files(&[ConfigFile { name: file, text }])
    }

    /// Indexes `files[0]` (the printer.cfg), splicing in the files its
    /// `[include pattern]` sections name at the point they are named.
    /// `files` must hold every file a pattern can match (the loader reads
    /// them); patterns use `*` and `?` and match file names as given.
    pub fn parse_files(files: &[ConfigFile<'a>]) -> Result<Self, ConfigError<'a>> {
        let mut slot = core::mem::MaybeUninit::uninit();
        Self::parse_files_in(&mut slot, files)?;
        // SAFETY: `parse_files_in` initialised it (it returned Ok).
        Ok(unsafe { slot.assume_init() })
    }

    /// [`Self::parse_files`] built in place in `slot` (a config is tens of
    /// KB, too large to pass through a microcontroller's stack); returns it.
    /// On an error `slot` is left initialised but holds a partial config.
    pub fn parse_files_in<'s>(
        slot: &'s mut core::mem::MaybeUninit<Self>,
        files: &[ConfigFile<'a>],
    ) -> Result<&'s mut Self, ConfigError<'a>> {
        // Written into the slot: the empty vectors' storage is
        // uninitialised, so only their lengths and `used` are stored.
        let config = slot.write(Self {
            files: heapless::Vec::new(),
            sections: heapless::Vec::new(),
            options: heapless::Vec::new(),
            used: Default::default(),
        });
        let main = files.first().ok_or(ConfigError {
            file: "printer.cfg",
            line: 0,
            kind: ConfigErrorKind::Syntax,
        })?;
        config.read_file(files, main, 0)?;
        Ok(config)
    }

    fn read_file(
        &mut self,
        files: &[ConfigFile<'a>],
        file: &ConfigFile<'a>,
        depth: usize,
    ) -> Result<(), ConfigError<'a>> {
        let (name, text) = (file.name, file.text);
        let err = |line, kind| ConfigError {
            file: name,
            line,
            kind,
        };
        let file_index = self.files.len();
        self.files
            .push(name)
            .map_err(|_| err(0, ConfigErrorKind::TooLarge))?;
        let mut offset = 0;
        for (index, raw) in text.split_inclusive('\n').enumerate() {
            let line = index + 1;
            let start = offset;
            offset += raw.len();
            // SAVE_CONFIG lines are read like the rest, prefix removed.
            let content = raw.strip_prefix("#*#").map_or(raw, str::trim_start);
            let trimmed = strip_inline_comment(content).trim();
            if trimmed.is_empty() {
                continue;
            }
            if content.starts_with([' ', '\t']) {
                // A continuation of the previous option's value (same file).
                let last = self
                    .options
                    .last_mut()
                    .filter(|o| o.file == file_index)
                    .ok_or(err(line, ConfigErrorKind::Syntax))?;
                let value_start = last.value.as_ptr() as usize - text.as_ptr() as usize;
                let end = start + raw.trim_end().len();
                // Within the text, on character boundaries: never empty.
                last.value = text
                    .get(value_start.min(end)..end)
                    .unwrap_or_default()
                    .trim();
                continue;
            }
            if let Some(header) = trimmed.strip_prefix('[') {
                let section = header
                    .strip_suffix(']')
                    .ok_or(err(line, ConfigErrorKind::Syntax))?
                    .trim();
                if let Some(pattern) = section.strip_prefix("include ") {
                    self.include(files, pattern.trim(), depth)?;
                    continue;
                }
                self.sections
                    .push(Header {
                        name: section,
                        file: file_index,
                        line,
                    })
                    .map_err(|_| err(line, ConfigErrorKind::TooLarge))?;
                continue;
            }
            let (option, value) = trimmed
                .split_once([':', '='])
                .ok_or(err(line, ConfigErrorKind::Syntax))?;
            let option = option.trim();
            if option.is_empty() {
                return Err(err(line, ConfigErrorKind::Syntax));
            }
            let section = self
                .sections
                .iter()
                .rposition(|h| h.file == file_index)
                .ok_or(err(line, ConfigErrorKind::OptionOutsideSection))?;
            let value = value.trim();
            self.options
                .push(OptionLine {
                    section,
                    file: file_index,
                    line,
                    name: option,
                    value,
                })
                .map_err(|_| err(line, ConfigErrorKind::TooLarge))?;
        }
        Ok(())
    }

    /// Reads every file matching `pattern`, in name order; an error inside
    /// an included file names that file.
    fn include(
        &mut self,
        files: &[ConfigFile<'a>],
        pattern: &str,
        depth: usize,
    ) -> Result<(), ConfigError<'a>> {
        let including = self.files.last().copied().unwrap_or("printer.cfg");
        let err = |kind| ConfigError {
            file: including,
            line: 0,
            kind,
        };
        if depth >= MAX_INCLUDE_DEPTH {
            return Err(err(ConfigErrorKind::IncludeTooDeep));
        }
        let mut last: Option<&str> = None;
        let mut found = false;
        // Files in name order, each once, without sorting into a buffer.
        while let Some(next) = files
            .iter()
            .filter(|f| glob_match(pattern, f.name) && last.is_none_or(|l| f.name > l))
            .min_by(|a, b| a.name.cmp(b.name))
        {
            found = true;
            last = Some(next.name);
            self.read_file(files, next, depth + 1)?;
        }
        if !found && !pattern.contains(['*', '?']) {
            return Err(err(ConfigErrorKind::MissingInclude));
        }
        Ok(())
    }

    /// The name of the main file (printer.cfg).
    pub fn file(&self) -> &'a str {
        self.files.first().copied().unwrap_or("printer.cfg")
    }

    /// The name of the file an option line comes from.
    fn file_of(&self, option: &OptionLine<'a>) -> &'a str {
        self.files
            .get(option.file)
            .copied()
            .unwrap_or("printer.cfg")
    }

    /// Names of all sections, in file order (repeats included).
    pub fn section_names(&self) -> impl Iterator<Item = &'a str> + '_ {
        self.sections.iter().map(|h| h.name)
    }

    /// True if a section of this name exists.
    pub fn has_section(&self, name: &str) -> bool {
        self.sections.iter().any(|h| h.name == name)
    }

    /// Access to the section `name` (all its repeats, later lines winning).
    pub fn section<'c>(&'c self, name: &'c str) -> Option<Section<'c, 'a>> {
        self.has_section(name)
            .then_some(Section { config: self, name })
    }

    /// The section `name`, or an error saying it is required.
    pub fn require<'c>(&'c self, name: &'c str) -> Result<Section<'c, 'a>, ConfigError<'c>> {
        self.section(name).ok_or(ConfigError {
            file: self.file(),
            line: 0,
            kind: ConfigErrorKind::MissingSection(name),
        })
    }

    /// Marks every option of section `name` as used (sections whose options
    /// belong to features handled elsewhere).
    pub fn accept_section(&self, name: &str) {
        for (i, option) in self.options.iter().enumerate() {
            if self.section_of(option) == name {
                self.mark_used(i);
            }
        }
    }

    /// The name of the section an option line is in.
    fn section_of(&self, option: &OptionLine<'a>) -> &'a str {
        // Every line's section was pushed before it: never "".
        self.sections.get(option.section).map_or("", |h| h.name)
    }

    fn mark_used(&self, index: usize) {
        if let Some(cell) = self.used.get(index / 32) {
            cell.set(cell.get() | 1 << (index % 32));
        }
    }

    fn is_used(&self, index: usize) -> bool {
        self.used
            .get(index / 32)
            .is_some_and(|cell| cell.get() & (1 << (index % 32)) != 0)
    }

    /// The first option nobody read, as an error.
    pub fn check_unused(&self) -> Result<(), ConfigError<'a>> {
        match self
            .options
            .iter()
            .enumerate()
            .find(|(i, _)| !self.is_used(*i))
        {
            None => Ok(()),
            Some((_, option)) => Err(ConfigError {
                file: self.file_of(option),
                line: option.line,
                kind: ConfigErrorKind::UnknownOption {
                    section: self.section_of(option),
                    option: option.name,
                },
            }),
        }
    }
}

/// Removes a `#` or `;` comment that starts a line or follows whitespace.
fn strip_inline_comment(line: &str) -> &str {
    let bytes = line.as_bytes();
    for (i, &b) in bytes.iter().enumerate() {
        if (b == b'#' || b == b';') && (i == 0 || bytes[i - 1].is_ascii_whitespace()) {
            return &line[..i];
        }
    }
    line
}

/// Bounds for a number option, as Klipper's `getfloat` takes them.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Bounds {
    /// Smallest allowed value.
    pub minval: Option<f64>,
    /// Largest allowed value.
    pub maxval: Option<f64>,
    /// The value must be greater than this.
    pub above: Option<f64>,
    /// The value must be less than this.
    pub below: Option<f64>,
}

impl Bounds {
    /// No bounds.
    pub const NONE: Self = Self {
        minval: None,
        maxval: None,
        above: None,
        below: None,
    };
    /// Strictly positive.
    pub const POSITIVE: Self = Self {
        minval: None,
        maxval: None,
        above: Some(0.0),
        below: None,
    };
    /// Zero or more.
    pub const NON_NEGATIVE: Self = Self {
        minval: Some(0.0),
        maxval: None,
        above: None,
        below: None,
    };
    /// `[0, 1]`.
    pub const UNIT: Self = Self {
        minval: Some(0.0),
        maxval: Some(1.0),
        above: None,
        below: None,
    };
    /// `(0, 1]`.
    pub const UNIT_ABOVE_ZERO: Self = Self {
        minval: None,
        maxval: Some(1.0),
        above: Some(0.0),
        below: None,
    };
    /// `[0, 1)`.
    pub const UNIT_BELOW_ONE: Self = Self {
        minval: Some(0.0),
        maxval: None,
        above: None,
        below: Some(1.0),
    };
}

/// One section of a config.
#[derive(Debug, Clone, Copy)]
pub struct Section<'c, 'a> {
    config: &'c Config<'a>,
    name: &'c str,
}

impl<'c, 'a> Section<'c, 'a> {
    /// The section's name.
    pub fn name(&self) -> &'c str {
        self.name
    }

    /// The section's name as written in the file.
    pub fn name_in_file(&self) -> &'a str {
        self.header().map_or("", |h| h.name)
    }

    /// The section's first header.
    fn header(&self) -> Option<&Header<'a>> {
        self.config.sections.iter().find(|h| h.name == self.name)
    }

    /// Where `option` is defined (its last definition), or else where the
    /// section starts: file name and 1-based line.
    pub fn locate(&self, option: &str) -> (&'a str, usize) {
        match self.find(option) {
            Some((_, o)) => (self.config.file_of(o), o.line),
            None => self.start(),
        }
    }

    /// Where the section starts: its first header's file and line.
    #[inline(never)]
    fn start(&self) -> (&'a str, usize) {
        self.header().map_or((self.config.file(), 0), |h| {
            let file = self.config.files.get(h.file).copied();
            (file.unwrap_or(self.config.file()), h.line)
        })
    }

    /// An error about `option` (at its line, if present).
    pub fn error_for(&self, option: &'c str, reason: &'static str) -> ConfigError<'c> {
        let at = self.find(option).map(|(_, l)| l);
        self.error(
            at,
            ConfigErrorKind::BadValue {
                section: self.name,
                option,
                reason,
            },
        )
    }

    /// A pin `option` refused with Klipper's `message` (quoting `name`, if
    /// any), at the option's line.
    pub fn pin_error(
        &self,
        option: &'c str,
        message: &'static str,
        name: Option<&'c str>,
    ) -> ConfigError<'c> {
        let at = self.find(option).map(|(_, l)| l);
        self.error(
            at,
            ConfigErrorKind::BadPin {
                section: self.name,
                option,
                message,
                name,
            },
        )
    }

    /// Marks every definition of `option` in this section as read (later
    /// definitions override earlier ones, which are not errors).
    fn mark_read(&self, option: &str, last: usize) {
        for (i, o) in self.config.options.iter().enumerate().take(last + 1) {
            if self.config.section_of(o) == self.name && o.name.eq_ignore_ascii_case(option) {
                self.config.mark_used(i);
            }
        }
    }

    fn find(&self, option: &str) -> Option<(usize, &'c OptionLine<'a>)> {
        self.config.options.iter().enumerate().rev().find(|(_, o)| {
            self.config.section_of(o) == self.name && o.name.eq_ignore_ascii_case(option)
        })
    }

    /// An error at option line `at` (in its file), or at the section's
    /// header when there is no such line (an option that must be added).
    #[inline(never)]
    fn error(&self, at: Option<&OptionLine<'a>>, kind: ConfigErrorKind<'c>) -> ConfigError<'c> {
        let (file, line) = match at {
            Some(o) => (self.config.file_of(o), o.line),
            None => self.start(),
        };
        ConfigError { file, line, kind }
    }

    /// The definition of `option` (marked read); else `default`; else an
    /// error saying the option is required.
    fn lookup<T>(
        &self,
        option: &'c str,
        default: Option<T>,
    ) -> Result<Result<&'c OptionLine<'a>, T>, ConfigError<'c>> {
        match self.find(option) {
            Some((index, line)) => {
                self.mark_read(option, index);
                Ok(Ok(line))
            }
            None => default.map(Err).ok_or(self.error(
                None,
                ConfigErrorKind::MissingOption {
                    section: self.name,
                    option,
                },
            )),
        }
    }

    /// A bad-value error at `line`.
    fn bad_value(
        &self,
        line: &OptionLine<'a>,
        option: &'c str,
        reason: &'static str,
    ) -> ConfigError<'c> {
        self.error(
            Some(line),
            ConfigErrorKind::BadValue {
                section: self.name,
                option,
                reason,
            },
        )
    }

    /// `option`'s name as the file writes it (its last definition), if
    /// present; for errors about options whose names are built at run
    /// time (`driver_SGTHRS`).
    pub fn option_name(&self, option: &str) -> Option<&'a str> {
        self.find(option).map(|(_, line)| line.name)
    }

    /// The text of `option`, if present (marks it used).
    pub fn get_opt(&self, option: &str) -> Option<&'a str> {
        let (index, line) = self.find(option)?;
        self.mark_read(option, index);
        Some(line.value)
    }

    /// The text of `option`, which must be present.
    pub fn get(&self, option: &'c str) -> Result<&'a str, ConfigError<'c>> {
        self.lookup(option, None::<&str>)
            .map(|found| found.map_or_else(|default| default, |line| line.value))
    }

    /// A number option; `default` when absent (None: required).
    pub fn get_float(
        &self,
        option: &'c str,
        default: Option<f64>,
        bounds: Bounds,
    ) -> Result<f64, ConfigError<'c>> {
        let line = match self.lookup(option, default)? {
            Ok(line) => line,
            Err(default) => return Ok(default),
        };
        let bad = |reason| self.bad_value(line, option, reason);
        let value: f64 = decimal::parse(line.value)
            .filter(|v: &f64| v.is_finite())
            .ok_or(bad("is not a number"))?;
        if bounds.minval.is_some_and(|m| value < m) {
            return Err(bad("is below its minimum"));
        }
        if bounds.maxval.is_some_and(|m| value > m) {
            return Err(bad("is above its maximum"));
        }
        if bounds.above.is_some_and(|m| value <= m) {
            return Err(bad("must be above its lower limit"));
        }
        if bounds.below.is_some_and(|m| value >= m) {
            return Err(bad("must be below its upper limit"));
        }
        Ok(value)
    }

    /// An optional number option.
    pub fn get_float_opt(
        &self,
        option: &'c str,
        bounds: Bounds,
    ) -> Result<Option<f64>, ConfigError<'c>> {
        if self.find(option).is_none() {
            return Ok(None);
        }
        self.get_float(option, None, bounds).map(Some)
    }

    /// An integer option; `default` when absent (None: required).
    pub fn get_int(
        &self,
        option: &'c str,
        default: Option<i64>,
        minval: Option<i64>,
    ) -> Result<i64, ConfigError<'c>> {
        let line = match self.lookup(option, default)? {
            Ok(line) => line,
            Err(default) => return Ok(default),
        };
        let bad = |reason| self.bad_value(line, option, reason);
        let value = parse_int(line.value).ok_or_else(|| bad("is not an integer"))?;
        if minval.is_some_and(|m| value < m) {
            return Err(bad("is below its minimum"));
        }
        Ok(value)
    }

    /// A boolean option (`True`/`False`, `yes`/`no`, `on`/`off`, `1`/`0`).
    pub fn get_bool(&self, option: &'c str, default: bool) -> Result<bool, ConfigError<'c>> {
        let line = match self.lookup(option, Some(default))? {
            Ok(line) => line,
            Err(default) => return Ok(default),
        };
        line.value.to_ascii_lowercase_bytes().ok_or(self.bad_value(
            line,
            option,
            "is not a boolean",
        ))
    }

    /// One of `choices` (exact match).
    pub fn get_choice(
        &self,
        option: &'c str,
        choices: &[&str],
        default: Option<&'a str>,
    ) -> Result<&'a str, ConfigError<'c>> {
        let line = match self.lookup(option, default)? {
            Ok(line) => line,
            Err(default) => return Ok(default),
        };
        if choices.contains(&line.value) {
            Ok(line.value)
        } else {
            Err(self.bad_value(line, option, "is not one of the choices"))
        }
    }

    /// Marks `options` as read by code outside the motion pipeline (heaters,
    /// pins) so they are not reported as unknown.
    pub fn accept(&self, options: &[&str]) {
        for option in options {
            let _ = self.get_opt(option);
        }
    }
}

/// `text` as `i64::from_str` reads it (an optional sign, then decimal
/// digits, within i64), without core's generic parser (a few hundred
/// bytes of flash).
fn parse_int(text: &str) -> Option<i64> {
    let (negative, digits) = match text.as_bytes() {
        [b'-', rest @ ..] => (true, rest),
        [b'+', rest @ ..] => (false, rest),
        rest => (false, rest),
    };
    if digits.is_empty() {
        return None;
    }
    digits.iter().try_fold(0i64, |value, &b| {
        let digit = i64::from(b.wrapping_sub(b'0'));
        if digit > 9 {
            return None;
        }
        let value = value.checked_mul(10)?;
        // Negative numbers accumulate downwards: i64::MIN has no positive.
        if negative {
            value.checked_sub(digit)
        } else {
            value.checked_add(digit)
        }
    })
}

/// Boolean spellings Python's configparser accepts.
trait BoolText {
    fn to_ascii_lowercase_bytes(&self) -> Option<bool>;
}

impl BoolText for str {
    fn to_ascii_lowercase_bytes(&self) -> Option<bool> {
        const TRUE: [&str; 4] = ["1", "yes", "true", "on"];
        const FALSE: [&str; 4] = ["0", "no", "false", "off"];
        if TRUE.iter().any(|t| self.eq_ignore_ascii_case(t)) {
            Some(true)
        } else if FALSE.iter().any(|t| self.eq_ignore_ascii_case(t)) {
            Some(false)
        } else {
            None
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::string::ToString;

    const CFG: &str = "# comment\n[printer]\nkinematics: cartesian\nmax_velocity = 300 ; inline\nmax_accel: 3000#not a comment\n\n[stepper_x]\nstep_pin: PF13\ngcode:\n  G28\n  G1 X10\n[printer]\nmax_velocity: 250\n#*# [extruder]\n#*# pressure_advance = 0.05\n";

    #[test]
    fn sections_options_comments_and_overrides() {
        let c = Config::parse("printer.cfg", CFG).expect("valid");
        let printer = c.require("printer").expect("present");
        assert_eq!(printer.get("kinematics"), Ok("cartesian"));
        assert_eq!(
            printer.get_float("max_velocity", None, Bounds::POSITIVE),
            Ok(250.0)
        );
        let bad = printer
            .get_float("max_accel", None, Bounds::POSITIVE)
            .expect_err("not a number");
        assert_eq!(bad.line, 5);
        assert_eq!(
            printer.get_float("square_corner_velocity", Some(5.0), Bounds::NON_NEGATIVE),
            Ok(5.0)
        );
        let x = c.section("stepper_x").expect("present");
        assert_eq!(x.get("gcode"), Ok("G28\n  G1 X10"));
        let saved = c.section("extruder").expect("SAVE_CONFIG block");
        assert_eq!(
            saved.get_float("pressure_advance", None, Bounds::NON_NEGATIVE),
            Ok(0.05)
        );
    }

    #[test]
    fn includes_are_spliced_in_at_their_place_and_errors_name_their_file() {
        let files = [
            ConfigFile {
                name: "printer.cfg",
                text: "[include macros/*.cfg]\n[printer]\nmax_velocity: 300\n[include late.cfg]\n",
            },
            ConfigFile {
                name: "macros/b.cfg",
                text: "[printer]\nmax_accel: 2000\n",
            },
            ConfigFile {
                name: "macros/a.cfg",
                text: "[printer]\nmax_accel: 1000\nmax_velocity: 100\n",
            },
            ConfigFile {
                name: "late.cfg",
                text: "[printer]\nsquare_corner_velocity: x\n",
            },
            ConfigFile {
                name: "unrelated.cfg",
                text: "[printer]\nmax_accel: 1\n",
            },
        ];
        let c = Config::parse_files(&files).expect("valid");
        let p = c.require("printer").expect("present");
        // a.cfg then b.cfg (name order), then printer.cfg's own line.
        assert_eq!(p.get_float("max_accel", None, Bounds::POSITIVE), Ok(2000.0));
        assert_eq!(
            p.get_float("max_velocity", None, Bounds::POSITIVE),
            Ok(300.0)
        );
        let e = p
            .get_float("square_corner_velocity", None, Bounds::NONE)
            .expect_err("bad");
        assert_eq!((e.file, e.line), ("late.cfg", 2));
        let missing = [ConfigFile {
            name: "printer.cfg",
            text: "[include nope.cfg]\n",
        }];
        assert_eq!(
            Config::parse_files(&missing)
                .map(|_| ())
                .expect_err("missing")
                .kind,
            ConfigErrorKind::MissingInclude
        );
        let none_matching = [ConfigFile {
            name: "printer.cfg",
            text: "[include *.nothing]\n[printer]\n",
        }];
        assert!(Config::parse_files(&none_matching).is_ok());
        let looping = [ConfigFile {
            name: "printer.cfg",
            text: "[include printer.cfg]\n",
        }];
        assert_eq!(
            Config::parse_files(&looping)
                .map(|_| ())
                .expect_err("loop")
                .kind,
            ConfigErrorKind::IncludeTooDeep
        );
    }

    #[test]
    fn integers_read_as_rusts_parser_reads_them() {
        for text in [
            "0",
            "-0",
            "+7",
            "250000",
            "-12",
            "007",
            "9223372036854775807",
            "9223372036854775808",
            "-9223372036854775808",
            "-9223372036854775809",
            "",
            "-",
            "+",
            "+-1",
            "1.0",
            "1e3",
            " 1",
            "1_000",
            "0x10",
            "١",
        ] {
            assert_eq!(parse_int(text), text.parse::<i64>().ok(), "{text:?}");
        }
    }

    #[test]
    fn glob_patterns() {
        assert!(glob_match("*.cfg", "a.cfg"));
        assert!(glob_match("macros/*.cfg", "macros/x.cfg"));
        assert!(glob_match("m?cros/*", "macros/x.cfg"));
        assert!(!glob_match("*.cfg", "a.cfgx"));
        assert!(glob_match("a*b*c", "aXXbYYc"));
        assert!(!glob_match("a*b*c", "aXXbYY"));
    }

    #[test]
    fn an_overridden_option_is_not_reported_unknown() {
        let c = Config::parse(
            "p.cfg",
            "[printer]\nmax_velocity: 1\n[printer]\nmax_velocity: 2\n",
        )
        .expect("valid");
        let p = c.require("printer").expect("present");
        assert_eq!(p.get_float("max_velocity", None, Bounds::POSITIVE), Ok(2.0));
        assert!(c.check_unused().is_ok());
    }

    #[test]
    fn unused_options_are_reported_with_their_line() {
        let c = Config::parse(
            "printer.cfg",
            "[printer]\nkinematics: cartesian\nmax_velocty: 300\n",
        )
        .expect("valid");
        let _ = c.require("printer").and_then(|p| p.get("kinematics"));
        let err = c.check_unused().expect_err("typo");
        assert_eq!(err.line, 3);
        assert_eq!(
            err.to_string(),
            "printer.cfg:3: option 'max_velocty' is not valid in section 'printer'"
        );
    }

    #[test]
    fn errors_name_file_line_and_option() {
        assert_eq!(
            Config::parse("p.cfg", "[printer\n")
                .map(|_| ())
                .expect_err("syntax")
                .line,
            1
        );
        assert_eq!(
            Config::parse("p.cfg", "max_velocity: 3\n")
                .map(|_| ())
                .expect_err("outside")
                .kind,
            ConfigErrorKind::OptionOutsideSection
        );
        assert_eq!(
            Config::parse("p.cfg", "[a]\njunk\n")
                .map(|_| ())
                .expect_err("syntax")
                .line,
            2
        );
        let c = Config::parse("p.cfg", "[printer]\nmax_accel: -1\nflag: maybe\n").expect("valid");
        let p = c.require("printer").expect("present");
        let e = p
            .get_float("max_accel", None, Bounds::POSITIVE)
            .expect_err("negative");
        assert_eq!(
            e.to_string(),
            "p.cfg:2: option 'max_accel' in section 'printer' must be above its lower limit"
        );
        assert!(p.get_bool("flag", false).is_err());
        assert_eq!(
            p.get_float("max_velocity", None, Bounds::POSITIVE)
                .expect_err("missing")
                .to_string(),
            "p.cfg:1: option 'max_velocity' in section 'printer' must be specified"
        );
        // A missing option is reported at the section's header, in the
        // file that opened the section.
        let files = [
            ConfigFile {
                name: "printer.cfg",
                text: "[include x.cfg]
",
            },
            ConfigFile {
                name: "x.cfg",
                text: "\n[stepper_z]\nstep_pin: PA0\n",
            },
        ];
        let c = Config::parse_files(&files).expect("valid");
        let z = c.require("stepper_z").expect("present");
        let e = z.get("dir_pin").expect_err("missing");
        assert_eq!((e.file, e.line), ("x.cfg", 2));
        assert_eq!(z.locate("step_pin"), ("x.cfg", 3));
        assert!(c.require("stepper_x").is_err());
    }
}
