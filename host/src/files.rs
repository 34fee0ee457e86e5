//! A host folder playing the SD card: for the session's config loading
//! ([`onechip_app::config_files::Files`]) and for printing from the card
//! ([`onechip_app::card::Card`]: M20 lists it, M28 writes into it).

use onechip_app::card::{Card, Entry};
use onechip_app::config_files::Files;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

/// Bytes of config text (printer.cfg and its includes, with their names)
/// the host build reads, as the board's buffer holds.
pub const CONFIG_BUFFER: usize = 64 * 1024;
/// Folder levels below the root searched for included files.
const MAX_DEPTH: usize = 3;

/// The SD card's files in a host folder.
#[derive(Debug, Clone)]
pub struct Folder {
    root: PathBuf,
}

impl Folder {
    /// The card whose root is `root`.
    pub fn new(root: &Path) -> Self {
        Self {
            root: root.to_path_buf(),
        }
    }

    /// The host path of card path `path`; refuses paths that leave the
    /// folder (`..`, absolute paths).
    fn host_path(&self, path: &str) -> std::io::Result<PathBuf> {
        let inside = Path::new(path)
            .components()
            .all(|c| matches!(c, std::path::Component::Normal(_)));
        if !inside || path.is_empty() {
            return Err(std::io::Error::other(format!(
                "{path}: not a path on the card"
            )));
        }
        Ok(self.root.join(path))
    }
}

impl Card for Folder {
    fn each_entry(&mut self, f: &mut dyn FnMut(&Entry<'_>)) -> Result<(), Self::Error> {
        let root = self.root.clone();
        self.each_file(&mut |path| {
            let size = std::fs::metadata(root.join(path)).map_or(0, |m| m.len());
            let long_name = path.rsplit('/').next().unwrap_or(path);
            f(&Entry {
                path,
                size: u32::try_from(size).unwrap_or(u32::MAX),
                long_name,
            });
        })
    }

    fn read_at(&mut self, path: &str, offset: u32, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let mut file = std::fs::File::open(self.host_path(path)?)?;
        file.seek(SeekFrom::Start(u64::from(offset)))?;
        file.read(buf)
    }

    fn create(&mut self, path: &str) -> Result<(), Self::Error> {
        std::fs::File::create(self.host_path(path)?).map(drop)
    }

    fn append(&mut self, path: &str, data: &[u8]) -> Result<(), Self::Error> {
        let mut file = std::fs::OpenOptions::new()
            .append(true)
            .open(self.host_path(path)?)?;
        file.write_all(data)
    }

    fn delete(&mut self, path: &str) -> Result<bool, Self::Error> {
        match std::fs::remove_file(self.host_path(path)?) {
            Ok(()) => Ok(true),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(false),
            Err(e) => Err(e),
        }
    }
}

impl Files for Folder {
    type Error = std::io::Error;

    fn each_file(&mut self, f: &mut dyn FnMut(&str)) -> Result<(), Self::Error> {
        let mut folders = vec![(self.root.clone(), String::new(), 0)];
        while let Some((dir, prefix, depth)) = folders.pop() {
            let mut entries: Vec<_> = std::fs::read_dir(&dir)?.filter_map(Result::ok).collect();
            entries.sort_by_key(|e| e.file_name());
            for entry in entries {
                let name = format!("{prefix}{}", entry.file_name().to_string_lossy());
                if entry.path().is_dir() {
                    if depth < MAX_DEPTH {
                        folders.push((entry.path(), format!("{name}/"), depth + 1));
                    }
                } else {
                    f(&name);
                }
            }
        }
        Ok(())
    }

    fn read(&mut self, path: &str, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let bytes = std::fs::read(self.root.join(path))?;
        let left = buf.len();
        let dest = buf.get_mut(..bytes.len()).ok_or_else(|| {
            std::io::Error::other(format!(
                "file is {} bytes, more than the {left} left of the config buffer",
                bytes.len()
            ))
        })?;
        dest.copy_from_slice(&bytes);
        Ok(bytes.len())
    }
}
