//! Reading files from the SD card: `printer.cfg` at boot, G-code later.
//!
//! Works on any [`BlockDevice`] (the board's SDMMC adapter, an in-memory image
//! in tests) through embedded-sdmmc: MBR partition table, first partition,
//! FAT16 or FAT32, 8.3 file names in the root directory.

use core::fmt;
use embedded_sdmmc::{BlockDevice, Mode, TimeSource, Timestamp, VolumeIdx, VolumeManager};

/// Name of the printer configuration file in the card's root directory.
pub const PRINTER_CFG: &str = "printer.cfg";

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

/// Reads the whole file `name` from the root directory of the card's first
/// partition into `buf`; returns the number of bytes read.
pub fn read_root_file<D: BlockDevice>(
    device: D,
    name: &str,
    buf: &mut [u8],
) -> Result<usize, ReadError<D::Error>> {
    let volumes: VolumeManager<D, NoClock, 1, 1, 1> =
        VolumeManager::new_with_limits(device, NoClock, 0);
    let volume = volumes.open_volume(VolumeIdx(0))?;
    let root = volume.open_root_dir()?;
    let file = root.open_file_in_dir(name, Mode::ReadOnly)?;
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
