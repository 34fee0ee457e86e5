//! A host folder playing the SD card, for the session's config loading
//! ([`onechip_app::config_files::Files`]).

use onechip_app::config_files::Files;
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
