//! Reading a section's options with one error slot for the whole reading.
//!
//! A [`ConfigError`] is 48 bytes: every `?` passing one on copies it, some
//! 40 bytes of flash each, hundreds of times over the section readers. A
//! [`Reader`] reads as [`Section`] does but keeps the error in its
//! [`Errors`] and returns [`Failed`], which has nothing to copy;
//! [`Errors::run`] gives the error back at the end.

use core::cell::Cell;
use core::ops::Deref;
use onechip_config::{Bounds, ConfigError, ConfigErrorKind, Section};

/// A read failed; its error is in the reading's [`Errors`].
#[derive(Debug)]
pub struct Failed(());

/// What a [`Reader`] returns.
pub type Read<T> = Result<T, Failed>;

/// The error of a reading, kept until it ends.
#[derive(Default)]
pub struct Errors<'c>(Cell<Option<ConfigError<'c>>>);

impl<'c> Errors<'c> {
    /// Runs `read` with an error slot; the error it failed with, if any.
    pub fn run<T>(read: impl FnOnce(&Errors<'c>) -> Read<T>) -> Result<T, ConfigError<'c>> {
        let errors = Errors::default();
        read(&errors).map_err(|_| errors.take())
    }

    /// Notes `error` as the reading's; the failure to return.
    #[inline(never)]
    pub fn fail(&self, error: ConfigError<'c>) -> Failed {
        self.0.set(Some(error));
        Failed(())
    }

    /// Passes on `result`'s error as a [`Failed`] (for readers that return
    /// [`ConfigError`]s).
    pub fn check<T>(&self, result: Result<T, ConfigError<'c>>) -> Read<T> {
        result.map_err(|e| self.fail(e))
    }

    /// The error noted last.
    #[inline(never)]
    fn take(&self) -> ConfigError<'c> {
        // A `Failed` is only made by `fail`, which noted its error.
        self.0.take().unwrap_or(ConfigError {
            file: "printer.cfg",
            line: 0,
            kind: ConfigErrorKind::Syntax,
        })
    }
}

/// A section read into an [`Errors`]: [`Section`]'s methods, those that
/// fail returning [`Failed`].
#[derive(Clone, Copy)]
pub struct Reader<'r, 'c, 'a> {
    section: Section<'c, 'a>,
    errors: &'r Errors<'c>,
}

impl<'c, 'a> Deref for Reader<'_, 'c, 'a> {
    type Target = Section<'c, 'a>;

    fn deref(&self) -> &Section<'c, 'a> {
        &self.section
    }
}

impl<'r, 'c, 'a> Reader<'r, 'c, 'a> {
    /// Reads `section`, failing into `errors`.
    pub fn new(section: Section<'c, 'a>, errors: &'r Errors<'c>) -> Self {
        Self { section, errors }
    }

    /// The reading's errors (for readers of other sections).
    pub fn errors(&self) -> &'r Errors<'c> {
        self.errors
    }

    /// Fails with [`Section::error_for`].
    pub fn error_for(&self, option: &'c str, reason: &'static str) -> Failed {
        self.errors.fail(self.section.error_for(option, reason))
    }

    /// [`Section::get`].
    #[inline(never)]
    pub fn get(&self, option: &'c str) -> Read<&'a str> {
        self.errors.check(self.section.get(option))
    }

    /// [`Section::get_float`].
    #[inline(never)]
    pub fn get_float(&self, option: &'c str, default: Option<f64>, bounds: Bounds) -> Read<f64> {
        self.errors
            .check(self.section.get_float(option, default, bounds))
    }

    /// [`Section::get_float`] with a default (taken apart from the
    /// default's `Option`, which each call would otherwise build).
    #[inline(never)]
    pub fn float(&self, option: &'c str, default: f64, bounds: Bounds) -> Read<f64> {
        self.get_float(option, Some(default), bounds)
    }

    /// [`Section::get_float`] of an option that must be present.
    #[inline(never)]
    pub fn required_float(&self, option: &'c str, bounds: Bounds) -> Read<f64> {
        self.get_float(option, None, bounds)
    }

    /// [`Section::get_float_opt`].
    #[inline(never)]
    pub fn get_float_opt(&self, option: &'c str, bounds: Bounds) -> Read<Option<f64>> {
        self.errors
            .check(self.section.get_float_opt(option, bounds))
    }

    /// [`Section::get_int`].
    #[inline(never)]
    pub fn get_int(&self, option: &'c str, default: Option<i64>, minval: Option<i64>) -> Read<i64> {
        self.errors
            .check(self.section.get_int(option, default, minval))
    }

    /// [`Section::get_bool`].
    #[inline(never)]
    pub fn get_bool(&self, option: &'c str, default: bool) -> Read<bool> {
        self.errors.check(self.section.get_bool(option, default))
    }

    /// [`Section::get_choice`].
    #[inline(never)]
    pub fn get_choice(
        &self,
        option: &'c str,
        choices: &[&str],
        default: Option<&'a str>,
    ) -> Read<&'a str> {
        self.errors
            .check(self.section.get_choice(option, choices, default))
    }
}
