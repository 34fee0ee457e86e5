//! Reading files from the SD card: `printer.cfg` and its includes at
//! boot, G-code later.
//!
//! Works on any [`BlockDevice`] (the board's SDMMC adapter, an in-memory image
//! in tests) through embedded-sdmmc: MBR partition table, first partition,
//! FAT16 or FAT32, 8.3 file names (seen in lower case), in the root folder
//! and the folders just below it.

use crate::config_files::{Files, MAX_PATH};
use core::fmt::{self, Write};
use core::ops::ControlFlow;
use embedded_sdmmc::{
    BlockDevice, DirEntry, Mode, ShortFileName, TimeSource, Timestamp, VolumeIdx, VolumeManager,
};

pub use crate::config_files::PRINTER_CFG;

/// Folders below the root that are searched for files.
const MAX_FOLDERS: usize = 16;

/// Why a file could not be read from the card.
#[derive(Debug)]
pub enum ReadError<E: core::error::Error> {
    /// No such file in the root directory.
    NotFound,
    /// The file does not fit the caller's buffer (sizes in bytes).
    TooLarge {
        /// The file's size.
        size: u32,
        /// The buffer's size.
        capacity: usize,
    },
    /// The card, its partition table or its filesystem failed.
    Filesystem(embedded_sdmmc::Error<E>),
    /// A path names folders more than one level deep.
    TooDeep,
}

impl<E: core::error::Error> fmt::Display for ReadError<E> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::NotFound => f.write_str("file not found on the SD card"),
            Self::TooLarge { size, capacity } => {
                write!(
                    f,
                    "file is {size} bytes, larger than the {capacity}-byte buffer"
                )
            }
            Self::Filesystem(e) => write!(f, "SD card: {e}"),
            Self::TooDeep => f.write_str("only the root folder and the folders in it are read"),
        }
    }
}

impl<E: core::error::Error> From<embedded_sdmmc::Error<E>> for ReadError<E> {
    fn from(e: embedded_sdmmc::Error<E>) -> Self {
        match e {
            embedded_sdmmc::Error::NotFound => Self::NotFound,
            other => Self::Filesystem(other),
        }
    }
}

/// File timestamps are only needed for writing; reads get a fixed one.
struct NoClock;

impl TimeSource for NoClock {
    fn get_timestamp(&self) -> Timestamp {
        Timestamp {
            year_since_1970: 0,
            zero_indexed_month: 0,
            zero_indexed_day: 0,
            hours: 0,
            minutes: 0,
            seconds: 0,
        }
    }
}

/// Reads file `name` of folder `dir` whole into `buf`.
fn read_in<D: BlockDevice, const DIRS: usize, const FILES: usize, const VOLS: usize>(
    dir: &embedded_sdmmc::Directory<'_, D, NoClock, DIRS, FILES, VOLS>,
    name: &str,
    buf: &mut [u8],
) -> Result<usize, ReadError<D::Error>> {
    let file = dir.open_file_in_dir(name, Mode::ReadOnly)?;
    let size = file.length();
    let capacity = buf.len();
    let dest = buf
        .get_mut(..size as usize)
        .ok_or(ReadError::TooLarge { size, capacity })?;
    let mut filled = 0;
    while filled < dest.len() {
        match file.read(&mut dest[filled..])? {
            0 => break,
            n => filled += n,
        }
    }
    Ok(filled)
}

/// The card's files, for loading printer.cfg and the files it includes
/// ([`Files`]): paths are lower-case 8.3 names, `name.ext` in the root or
/// `folder/name.ext` one level down.
pub struct SdFiles<D: BlockDevice> {
    volumes: VolumeManager<D, NoClock, 2, 1, 1>,
}

impl<D: BlockDevice> SdFiles<D> {
    /// The files of the card in `device`.
    pub fn new(device: D) -> Self {
        Self {
            volumes: VolumeManager::new_with_limits(device, NoClock, 0),
        }
    }
}

/// `entry`'s name as a path below `folder` (None for the root), lower
/// case; None for folders' own entries and names too long.
fn entry_path(
    folder: Option<&ShortFileName>,
    entry: &DirEntry,
) -> Option<heapless::String<MAX_PATH>> {
    let mut path = heapless::String::new();
    if let Some(folder) = folder {
        write!(path, "{folder}/").ok()?;
    }
    write!(path, "{}", entry.name).ok()?;
    path.make_ascii_lowercase();
    Some(path)
}

impl<D: BlockDevice> Files for SdFiles<D> {
    type Error = ReadError<D::Error>;

    fn each_file(&mut self, f: &mut dyn FnMut(&str)) -> Result<(), Self::Error> {
        let volume = self.volumes.open_volume(VolumeIdx(0))?;
        let root = volume.open_root_dir()?;
        let mut folders: heapless::Vec<ShortFileName, MAX_FOLDERS> = heapless::Vec::new();
        root.iterate_dir(|entry| {
            if entry.attributes.is_volume() || entry.name.base_name().starts_with(b".") {
                // The volume label, `.` and `..`.
            } else if entry.attributes.is_directory() {
                let _ = folders.push(entry.name);
            } else if let Some(path) = entry_path(None, entry) {
                f(&path);
            }
            ControlFlow::Continue(())
        })?;
        for folder in &folders {
            let dir = root.open_dir(folder)?;
            dir.iterate_dir(|entry| {
                if !entry.attributes.is_directory()
                    && !entry.attributes.is_volume()
                    && let Some(path) = entry_path(Some(folder), entry)
                {
                    f(&path);
                }
                ControlFlow::Continue(())
            })?;
        }
        Ok(())
    }

    fn read(&mut self, path: &str, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let volume = self.volumes.open_volume(VolumeIdx(0))?;
        let root = volume.open_root_dir()?;
        match path.split_once('/') {
            None => read_in(&root, path, buf),
            Some((_, rest)) if rest.contains('/') => Err(ReadError::TooDeep),
            Some((folder, name)) => read_in(&root.open_dir(folder)?, name, buf),
        }
    }
}
