//! The card this machine has: printer.cfg only, built into the image
//! (`include_str!` of the file `build.rs` chose), read-only.

use onechip_app::card::{Card, Entry};
use onechip_app::config_files::Files;

/// printer.cfg's text.
pub const PRINTER_CFG: &str = include_str!(concat!(env!("OUT_DIR"), "/printer.cfg"));

/// The file's name on the card.
const NAME: &str = "printer.cfg";

/// A read-only card holding printer.cfg.
pub struct BuiltIn;

/// Why a card operation failed.
#[derive(Debug)]
pub enum CardError {
    /// No such file.
    NotFound,
    /// The buffer is too small for the file.
    TooLarge,
    /// The card cannot be written.
    ReadOnly,
}

impl core::fmt::Display for CardError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::NotFound => "file not found",
            Self::TooLarge => "file too large",
            Self::ReadOnly => "the built-in card is read-only",
        })
    }
}

impl Files for BuiltIn {
    type Error = CardError;

    fn each_file(&mut self, f: &mut dyn FnMut(&str)) -> Result<(), Self::Error> {
        f(NAME);
        Ok(())
    }

    fn read(&mut self, path: &str, buf: &mut [u8]) -> Result<usize, Self::Error> {
        if path != NAME {
            return Err(CardError::NotFound);
        }
        let dest = buf
            .get_mut(..PRINTER_CFG.len())
            .ok_or(CardError::TooLarge)?;
        dest.copy_from_slice(PRINTER_CFG.as_bytes());
        Ok(PRINTER_CFG.len())
    }
}

impl Card for BuiltIn {
    fn each_entry(&mut self, f: &mut dyn FnMut(&Entry<'_>)) -> Result<(), Self::Error> {
        f(&Entry {
            path: NAME,
            size: PRINTER_CFG.len() as u32,
            long_name: NAME,
        });
        Ok(())
    }

    fn read_at(&mut self, path: &str, offset: u32, buf: &mut [u8]) -> Result<usize, Self::Error> {
        if path != NAME {
            return Err(CardError::NotFound);
        }
        let rest = PRINTER_CFG
            .as_bytes()
            .get(offset as usize..)
            .unwrap_or_default();
        let n = rest.len().min(buf.len());
        buf[..n].copy_from_slice(&rest[..n]);
        Ok(n)
    }

    fn create(&mut self, _path: &str) -> Result<(), Self::Error> {
        Err(CardError::ReadOnly)
    }

    fn append(&mut self, _path: &str, _data: &[u8]) -> Result<(), Self::Error> {
        Err(CardError::ReadOnly)
    }

    fn delete(&mut self, _path: &str) -> Result<bool, Self::Error> {
        Err(CardError::ReadOnly)
    }
}
