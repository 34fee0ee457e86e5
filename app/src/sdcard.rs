//! Reading files from the SD card: `printer.cfg` and its includes at
//! boot, G-code later.
//!
//! Works on any [`BlockDevice`] (the board's SDMMC adapter, an in-memory image
//! in tests) through embedded-sdmmc: MBR partition table, first partition,
//! FAT16 or FAT32, 8.3 file names (seen in lower case, with their long
//! names for listings), in the root folder and the folders just below it;
//! files can be created, appended to and deleted ([`Card`]).

use crate::card::{Card, Entry};
use crate::config_files::{Files, MAX_PATH};
use core::fmt::{self, Write};
use core::ops::ControlFlow;
use embedded_sdmmc::{
    BlockDevice, DirEntry, LfnBuffer, Mode, ShortFileName, TimeSource, Timestamp, VolumeIdx,
    VolumeManager,
};

/// Longest long file name read, bytes of UTF-8.
const MAX_LONG_NAME: usize = 128;

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
    fill(&file, dest)
}

/// Reads from `file`'s position into `buf` until it is full or the file
/// ends; returns how many bytes were read.
fn fill<D: BlockDevice, const DIRS: usize, const FILES: usize, const VOLS: usize>(
    file: &embedded_sdmmc::File<'_, D, NoClock, DIRS, FILES, VOLS>,
    buf: &mut [u8],
) -> Result<usize, ReadError<D::Error>> {
    let mut filled = 0;
    while filled < buf.len() {
        match file.read(&mut buf[filled..])? {
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
        self.each_entry(&mut |entry| f(entry.path))
    }

    fn read(&mut self, path: &str, buf: &mut [u8]) -> Result<usize, Self::Error> {
        self.in_folder(path, |dir, name| read_in(dir, name, buf))
    }
}

/// A folder of the card, as embedded-sdmmc opens it.
type Dir<'v, D> = embedded_sdmmc::Directory<'v, D, NoClock, 2, 1, 1>;

impl<D: BlockDevice> SdFiles<D> {
    /// Runs `f` on the folder holding `path` (the root, or a folder in
    /// it) with the file's own name.
    fn in_folder<R>(
        &mut self,
        path: &str,
        f: impl FnOnce(&Dir<'_, D>, &str) -> Result<R, ReadError<D::Error>>,
    ) -> Result<R, ReadError<D::Error>> {
        let volume = self.volumes.open_volume(VolumeIdx(0))?;
        let root = volume.open_root_dir()?;
        match path.split_once('/') {
            None => f(&root, path),
            Some((_, rest)) if rest.contains('/') => Err(ReadError::TooDeep),
            Some((folder, name)) => f(&root.open_dir(folder)?, name),
        }
    }
}

/// Calls `f` with each file of `dir` (below `folder`, None for the root)
/// and its long name; collects the folders into `folders` if given.
fn list_in<D: BlockDevice>(
    dir: &Dir<'_, D>,
    folder: Option<&ShortFileName>,
    mut folders: Option<&mut heapless::Vec<ShortFileName, MAX_FOLDERS>>,
    f: &mut dyn FnMut(&Entry<'_>),
) -> Result<(), ReadError<D::Error>> {
    let mut storage = [0u8; MAX_LONG_NAME];
    let mut lfn = LfnBuffer::new(&mut storage);
    dir.iterate_dir_lfn(&mut lfn, |entry, long| {
        if entry.attributes.is_volume() || entry.name.base_name().starts_with(b".") {
            // The volume label, `.` and `..`.
        } else if entry.attributes.is_directory() {
            if let Some(folders) = folders.as_deref_mut() {
                let _ = folders.push(entry.name);
            }
        } else if let Some(path) = entry_path(folder, entry) {
            let short = path.rsplit('/').next().unwrap_or(&path);
            f(&Entry {
                path: &path,
                size: entry.size,
                long_name: long.unwrap_or(short),
            });
        }
        ControlFlow::Continue(())
    })?;
    Ok(())
}

impl<D: BlockDevice> Card for SdFiles<D> {
    fn each_entry(&mut self, f: &mut dyn FnMut(&Entry<'_>)) -> Result<(), Self::Error> {
        let volume = self.volumes.open_volume(VolumeIdx(0))?;
        let root = volume.open_root_dir()?;
        let mut folders = heapless::Vec::new();
        list_in(&root, None, Some(&mut folders), f)?;
        for folder in &folders {
            list_in(&root.open_dir(folder)?, Some(folder), None, f)?;
        }
        Ok(())
    }

    fn read_at(&mut self, path: &str, offset: u32, buf: &mut [u8]) -> Result<usize, Self::Error> {
        self.in_folder(path, |dir, name| {
            let file = dir.open_file_in_dir(name, Mode::ReadOnly)?;
            if offset >= file.length() {
                return Ok(0);
            }
            file.seek_from_start(offset)?;
            fill(&file, buf)
        })
    }

    fn create(&mut self, path: &str) -> Result<(), Self::Error> {
        self.in_folder(path, |dir, name| {
            dir.open_file_in_dir(name, Mode::ReadWriteCreateOrTruncate)?
                .close()?;
            Ok(())
        })
    }

    fn append(&mut self, path: &str, data: &[u8]) -> Result<(), Self::Error> {
        self.in_folder(path, |dir, name| {
            let file = dir.open_file_in_dir(name, Mode::ReadWriteAppend)?;
            file.write(data)?;
            file.close()?;
            Ok(())
        })
    }

    fn delete(&mut self, path: &str) -> Result<bool, Self::Error> {
        match self.in_folder(path, |dir, name| Ok(dir.delete_entry_in_dir(name)?)) {
            Ok(()) => Ok(true),
            Err(ReadError::NotFound) => Ok(false),
            Err(e) => Err(e),
        }
    }
}
