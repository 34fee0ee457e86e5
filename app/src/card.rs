//! The SD card as printing needs it: a listing with sizes and long names,
//! reads at an offset, and writes (uploads with M28, deletes with M30).
//! The board implements it on its card ([`crate::sdcard::SdFiles`]), the
//! host build on a folder playing the card.

use crate::config_files::Files;

/// One file on the card.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Entry<'a> {
    /// The path that opens it, relative to the root, `/`-separated (on a
    /// FAT card: lower-case 8.3 names).
    pub path: &'a str,
    /// Its size, bytes.
    pub size: u32,
    /// Its long name (the path's last part where it has none).
    pub long_name: &'a str,
}

/// A card's files, readable and writable.
pub trait Card: Files {
    /// Calls `f` with every file in the root folder and the folders in it.
    fn each_entry(&mut self, f: &mut dyn FnMut(&Entry<'_>)) -> Result<(), Self::Error>;
    /// Reads from file `path` at byte `offset` into `buf`; returns how
    /// many bytes were read (0 at the end of the file).
    fn read_at(&mut self, path: &str, offset: u32, buf: &mut [u8]) -> Result<usize, Self::Error>;
    /// Creates file `path`, empty (an existing one is truncated).
    fn create(&mut self, path: &str) -> Result<(), Self::Error>;
    /// Appends `data` to file `path`.
    fn append(&mut self, path: &str, data: &[u8]) -> Result<(), Self::Error>;
    /// Deletes file `path`; false if there was none.
    fn delete(&mut self, path: &str) -> Result<bool, Self::Error>;
}

/// Why a card operation failed, where the card may be missing.
#[derive(Debug)]
pub enum MaybeCardError<E> {
    /// No card was found at start-up.
    NoCard,
    /// The card failed.
    Card(E),
}

impl<E: core::fmt::Display> core::fmt::Display for MaybeCardError<E> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::NoCard => f.write_str("no SD card"),
            Self::Card(e) => e.fmt(f),
        }
    }
}

/// A card that may be missing (the board without one still answers its
/// console, and lists nothing).
impl<C: Card> Files for Option<C> {
    type Error = MaybeCardError<C::Error>;

    fn each_file(&mut self, f: &mut dyn FnMut(&str)) -> Result<(), Self::Error> {
        present(self)?.each_file(f).map_err(MaybeCardError::Card)
    }

    fn read(&mut self, path: &str, buf: &mut [u8]) -> Result<usize, Self::Error> {
        present(self)?.read(path, buf).map_err(MaybeCardError::Card)
    }
}

impl<C: Card> Card for Option<C> {
    fn each_entry(&mut self, f: &mut dyn FnMut(&Entry<'_>)) -> Result<(), Self::Error> {
        present(self)?.each_entry(f).map_err(MaybeCardError::Card)
    }

    fn read_at(&mut self, path: &str, offset: u32, buf: &mut [u8]) -> Result<usize, Self::Error> {
        present(self)?
            .read_at(path, offset, buf)
            .map_err(MaybeCardError::Card)
    }

    fn create(&mut self, path: &str) -> Result<(), Self::Error> {
        present(self)?.create(path).map_err(MaybeCardError::Card)
    }

    fn append(&mut self, path: &str, data: &[u8]) -> Result<(), Self::Error> {
        present(self)?
            .append(path, data)
            .map_err(MaybeCardError::Card)
    }

    fn delete(&mut self, path: &str) -> Result<bool, Self::Error> {
        present(self)?.delete(path).map_err(MaybeCardError::Card)
    }
}

/// The card, or [`MaybeCardError::NoCard`].
fn present<C>(card: &mut Option<C>) -> Result<&mut C, MaybeCardError<C::Error>>
where
    C: Card,
{
    card.as_mut().ok_or(MaybeCardError::NoCard)
}
