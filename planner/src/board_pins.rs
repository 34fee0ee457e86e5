//! Klipper's `[board_pins]` and `[board_pins NAME]`: pin aliases
//! (`aliases: EXP1_1=PE8, EXP1_2=PE7, EXP1_9=<GND>`) that any pin option
//! may use instead of the MCU's pin name; a value written `<NAME>` marks
//! the alias as reserved (using it is an error). `mcu:` lists the chips
//! the aliases apply to (default `mcu`).
//!
//! The aliases are not copied into a table: each section's `aliases` text
//! is kept and searched when a pin is resolved, so a board with many
//! aliases costs nothing more.

use crate::output_pin::{list_items, unique_sections};
use crate::reader::{Errors, Read, Reader};
use core::fmt;
use onechip_config::Config;

/// Most `[board_pins]` sections.
pub const MAX_SECTIONS: usize = 4;
/// An alias naming an alias is followed at most this deep.
const MAX_DEPTH: usize = 4;

/// One `[board_pins]` section.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct AliasSection<'a> {
    /// The chips (`mcu`, or a secondary's name), comma-separated.
    chips: &'a str,
    /// The `aliases` text: `NAME=PIN` pairs, comma-separated.
    aliases: &'a str,
}

/// Every `[board_pins]` section of a config.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct BoardPins<'a> {
    sections: heapless::Vec<AliasSection<'a>, MAX_SECTIONS>,
}

/// A pin as an option writes it, with any alias resolved: modifiers
/// (`!`, `^`, `~`), chip and the pin's name on that chip.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ResolvedPin<'a> {
    /// The modifiers as written (`!^`), possibly empty.
    pub modifiers: &'a str,
    /// The chip, if written `chip:pin`.
    pub chip: Option<&'a str>,
    /// The pin's name on its chip (`PE8`).
    pub name: &'a str,
}

impl fmt::Display for ResolvedPin<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.modifiers)?;
        if let Some(chip) = self.chip {
            write!(f, "{chip}:")?;
        }
        f.write_str(self.name)
    }
}

/// A pin that cannot be used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReservedPin<'a> {
    /// The alias used.
    pub name: &'a str,
    /// What it is reserved for (`<GND>`).
    pub by: &'a str,
}

impl fmt::Display for ReservedPin<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "pin {} is reserved for {}", self.name, self.by)
    }
}

/// The `NAME=VALUE` pairs of an `aliases` text (over several lines,
/// comments left out); `None` for an entry without `=`.
fn pairs(aliases: &str) -> impl Iterator<Item = Option<(&str, &str)>> {
    list_items(aliases).map(|pair| {
        pair.split_once('=')
            .map(|(name, value)| (name.trim(), value.trim()))
    })
}

/// True if `value` is a pin name an alias may map to: no modifiers, chip
/// or spaces (Klipper's check).
fn valid_target(value: &str) -> bool {
    !value.is_empty()
        && !value
            .chars()
            .any(|c| matches!(c, '^' | '~' | '!' | ':') || c.is_whitespace())
}

/// True if `section` is a `[board_pins]` section.
pub fn is_section(section: &str) -> bool {
    section == "board_pins" || section.starts_with("board_pins ")
}

impl<'a> BoardPins<'a> {
    /// Reads every `[board_pins]` section of `config`: every entry must be
    /// `NAME=PIN` (a plain pin name, or `<NAME>`), and no alias may map to
    /// two pins on one chip.
    #[inline(never)]
    pub(crate) fn read<'c>(config: &'c Config<'a>, errors: &Errors<'c>) -> Read<Self> {
        let mut pins = Self::default();
        for name in unique_sections(config).filter(|n| is_section(n)) {
            let Some(section) = config.section(name) else {
                continue;
            };
            let section = Reader::new(section, errors);
            let chip = name.strip_prefix("board_pins").map_or("", str::trim);
            let chips =
                section
                    .get_opt("mcu")
                    .unwrap_or(if chip.is_empty() { "mcu" } else { chip });
            let aliases = section.get("aliases")?;
            pins.sections
                .push(AliasSection { chips, aliases })
                .map_err(|_| {
                    section.error_for("aliases", "is in one [board_pins] too many (at most 4)")
                })?;
            pins.check(&section, chips, aliases)?;
        }
        Ok(pins)
    }

    /// The entries of `aliases` (of the section just added, for `chips`)
    /// parse, and each alias' first mapping on each chip is this one.
    fn check(&self, section: &Reader<'_, '_, 'a>, chips: &str, aliases: &'a str) -> Read<()> {
        for pair in pairs(aliases) {
            let Some((name, value)) = pair else {
                return Err(section.error_for("aliases", "has an entry that is not NAME=PIN"));
            };
            let reserved = value.starts_with('<') && value.ends_with('>');
            if name.is_empty() || !(reserved || valid_target(value)) {
                return Err(section.error_for("aliases", "has an invalid pin alias"));
            }
            if list_items(chips).any(|chip| self.lookup(chip, name) != Some(value)) {
                return Err(section.error_for("aliases", "maps one alias to two pins"));
            }
        }
        Ok(())
    }

    /// The alias `name` has on `chip`, if any: its value as written.
    fn lookup(&self, chip: &str, name: &str) -> Option<&'a str> {
        self.sections
            .iter()
            .filter(|s| list_items(s.chips).any(|c| c == chip))
            .find_map(|s| pairs(s.aliases).flatten().find(|(n, _)| *n == name))
            .map(|(_, v)| v)
    }

    /// `pin` as an option writes it (`!EXP1_1`, `mcu:PE8`), with its alias
    /// resolved; an alias reserved with `<NAME>` is an error.
    pub fn resolve(&self, pin: &'a str) -> Result<ResolvedPin<'a>, ReservedPin<'a>> {
        let text = pin.trim();
        let bare =
            text.trim_start_matches(|c: char| matches!(c, '!' | '^' | '~') || c.is_whitespace());
        let modifiers = text[..text.len() - bare.len()].trim_end();
        let (chip, mut name) = match bare.split_once(':') {
            Some((chip, name)) => (Some(chip.trim()), name.trim()),
            None => (None, bare),
        };
        let on = chip.unwrap_or("mcu");
        for _ in 0..MAX_DEPTH {
            match self.lookup(on, name) {
                Some(value) if value.starts_with('<') => {
                    return Err(ReservedPin { name, by: value });
                }
                Some(value) if value != name => name = value,
                _ => break,
            }
        }
        Ok(ResolvedPin {
            modifiers,
            chip,
            name,
        })
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use onechip_config::ConfigError;

    /// `config`'s `[board_pins]`.
    fn read<'c, 'a>(config: &'c Config<'a>) -> Result<BoardPins<'a>, ConfigError<'c>> {
        Errors::run(|errors| BoardPins::read(config, errors))
    }

    const BOARD: &str = "[board_pins]\naliases:\n    # EXP1\n    EXP1_1=PE8, EXP1_2=PE7, # a comment\n    EXP1_9=<GND>, BEEPER=EXP1_1,\n\
        [board_pins second]\nmcu: extra\naliases: EXP1_1=PA1\n";

    #[test]
    fn aliases_resolve_with_modifiers_and_chips() {
        let config = Config::parse("printer.cfg", BOARD).expect("parses");
        let pins = read(&config).expect("reads");
        let text = |p: &'static str| {
            let mut s = heapless::String::<32>::new();
            core::fmt::write(&mut s, format_args!("{}", pins.resolve(p).expect("usable")))
                .expect("fits");
            s
        };
        assert_eq!(text("EXP1_1"), "PE8");
        assert_eq!(text("!^ EXP1_2"), "!^PE7");
        assert_eq!(text("BEEPER"), "PE8");
        assert_eq!(text("extra:EXP1_1"), "extra:PA1");
        assert_eq!(text("mcu:EXP1_1"), "mcu:PE8");
        assert_eq!(text("PF13"), "PF13");
        let reserved = pins.resolve("EXP1_9").expect_err("reserved");
        assert_eq!(
            std::format!("{reserved}"),
            "pin EXP1_9 is reserved for <GND>"
        );
    }

    #[test]
    fn a_bad_alias_names_its_file_and_line() {
        let bad = "[board_pins]\naliases: EXP1_1=PE8, EXP1_2\n";
        let config = Config::parse("printer.cfg", bad).expect("parses");
        let e = read(&config).expect_err("refused");
        assert_eq!(
            std::format!("{e}"),
            "printer.cfg:2: option 'aliases' in section 'board_pins' has an entry that is not NAME=PIN"
        );
        let twice = "[board_pins]\naliases: A=PE8, A=PE7\n";
        let config = Config::parse("printer.cfg", twice).expect("parses");
        assert!(read(&config).is_err());
        let across = "[board_pins]\naliases: A=PE8\n[board_pins b]\nmcu: mcu\naliases: A=PE7\n";
        let config = Config::parse("printer.cfg", across).expect("parses");
        let e = read(&config).expect_err("refused");
        assert_eq!(e.line, 5, "{e}");
        let other_chip = "[board_pins]\naliases: A=PE8\n[board_pins b]\naliases: A=PE7\n";
        let config = Config::parse("printer.cfg", other_chip).expect("parses");
        assert!(read(&config).is_ok());
        let modifier = "[board_pins]\naliases: A=!PE8\n";
        let config = Config::parse("printer.cfg", modifier).expect("parses");
        assert!(read(&config).is_err());
    }
}
