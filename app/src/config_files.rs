//! Loading `printer.cfg` and the files its `[include]` sections name from
//! a file system both builds supply (the board's SD card, the host's SD
//! folder), into one caller-owned buffer, for
//! [`onechip_config::Config::parse_files`].

use core::fmt;
use onechip_config::{ConfigFile, MAX_FILES, glob_match};

/// Name of the printer configuration file in the card's root folder.
pub const PRINTER_CFG: &str = "printer.cfg";
/// Longest file path (relative to the root) an include may name, bytes.
pub const MAX_PATH: usize = 64;

/// A read-only file system: the SD card's, or a host folder playing it.
/// Paths are relative to the root and `/`-separated.
pub trait Files {
    /// Why a listing or a read failed.
    type Error: fmt::Display;
    /// Calls `f` with the path of every file (folders searched a few
    /// levels deep).
    fn each_file(&mut self, f: &mut dyn FnMut(&str)) -> Result<(), Self::Error>;
    /// Reads file `path` whole into `buf`; returns its length. A file
    /// larger than `buf` is an error.
    fn read(&mut self, path: &str, buf: &mut [u8]) -> Result<usize, Self::Error>;
}

/// Why the config files could not be loaded.
#[derive(Debug)]
pub enum LoadError<E> {
    /// printer.cfg or an included file could not be read.
    Read {
        /// The file.
        path: heapless::String<MAX_PATH>,
        /// Why.
        error: E,
    },
    /// A file is not UTF-8 text.
    NotText(heapless::String<MAX_PATH>),
    /// More than [`MAX_FILES`] files, or a path longer than [`MAX_PATH`].
    TooMany,
    /// The card could not be listed.
    List(E),
}

impl<E: fmt::Display> fmt::Display for LoadError<E> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Read { path, error } => write!(f, "{path}: {error}"),
            Self::NotText(path) => write!(f, "{path}: not UTF-8 text"),
            Self::TooMany => write!(
                f,
                "config: more than {MAX_FILES} files or a path over {MAX_PATH} bytes"
            ),
            Self::List(error) => write!(f, "listing the card: {error}"),
        }
    }
}

/// The loaded files, printer.cfg first.
pub type ConfigFiles<'b> = heapless::Vec<ConfigFile<'b>, MAX_FILES>;

/// Reads printer.cfg and, transitively, every file its `[include]`
/// patterns match (as Klipper, patterns are relative to the root and may
/// use `*` and `?`), each once, names and texts stored in `buf`.
// Not inlined: its path list (1 KB) would sit in the caller's frame for
// the whole printer set-up.
#[inline(never)]
pub fn load<'b, F: Files>(
    fs: &mut F,
    buf: &'b mut [u8],
) -> Result<ConfigFiles<'b>, LoadError<F::Error>> {
    let mut files = ConfigFiles::new();
    let mut rest = buf;
    let mut wanted: heapless::Vec<heapless::String<MAX_PATH>, MAX_FILES> = heapless::Vec::new();
    push_path(&mut wanted, PRINTER_CFG)?;
    let mut next = 0;
    while let Some(path) = wanted.get(next).cloned() {
        next += 1;
        let (file, tail) = read_into(fs, &path, rest)?;
        rest = tail;
        for pattern in include_patterns(file.text) {
            let mut failed = false;
            fs.each_file(&mut |name| {
                let known = wanted.iter().any(|w| w.as_str() == name);
                if !known
                    && glob_match(pattern, name)
                    && push_path::<F::Error>(&mut wanted, name).is_err()
                {
                    failed = true;
                }
            })
            .map_err(LoadError::List)?;
            if failed {
                return Err(LoadError::TooMany);
            }
        }
        files.push(file).map_err(|_| LoadError::TooMany)?;
    }
    Ok(files)
}

fn push_path<E>(
    paths: &mut heapless::Vec<heapless::String<MAX_PATH>, MAX_FILES>,
    path: &str,
) -> Result<(), LoadError<E>> {
    let path = heapless::String::try_from(path).map_err(|_| LoadError::TooMany)?;
    paths.push(path).map_err(|_| LoadError::TooMany)
}

/// Stores `path` and then the file's text at the start of `buf`; returns
/// the file and the rest of `buf`.
fn read_into<'b, F: Files>(
    fs: &mut F,
    path: &heapless::String<MAX_PATH>,
    buf: &'b mut [u8],
) -> Result<(ConfigFile<'b>, &'b mut [u8]), LoadError<F::Error>> {
    let too_large = || LoadError::TooMany;
    if buf.len() < path.len() {
        return Err(too_large());
    }
    let (name, buf) = buf.split_at_mut(path.len());
    name.copy_from_slice(path.as_bytes());
    let len = fs.read(path, buf).map_err(|error| LoadError::Read {
        path: path.clone(),
        error,
    })?;
    let (text, rest) = buf.split_at_mut(len);
    let name: &'b [u8] = name;
    let text: &'b [u8] = text;
    let not_text = || LoadError::NotText(path.clone());
    Ok((
        ConfigFile {
            name: core::str::from_utf8(name).map_err(|_| not_text())?,
            text: core::str::from_utf8(text).map_err(|_| not_text())?,
        },
        rest,
    ))
}

/// The patterns of the `[include PATTERN]` section headers in `text`.
fn include_patterns(text: &str) -> impl Iterator<Item = &str> {
    text.lines().filter_map(|line| {
        let header = line.trim().strip_prefix('[')?;
        let (inside, _) = header.split_once(']')?;
        inside.trim().strip_prefix("include ").map(str::trim)
    })
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::string::{String, ToString};
    use std::vec::Vec;

    /// Files in memory.
    struct Memory(Vec<(&'static str, &'static str)>);

    impl Files for Memory {
        type Error = &'static str;
        fn each_file(&mut self, f: &mut dyn FnMut(&str)) -> Result<(), Self::Error> {
            self.0.iter().for_each(|(name, _)| f(name));
            Ok(())
        }
        fn read(&mut self, path: &str, buf: &mut [u8]) -> Result<usize, Self::Error> {
            let (_, text) = self
                .0
                .iter()
                .find(|(name, _)| *name == path)
                .ok_or("file not found")?;
            let dest = buf.get_mut(..text.len()).ok_or("file too large")?;
            dest.copy_from_slice(text.as_bytes());
            Ok(text.len())
        }
    }

    fn names(files: &ConfigFiles<'_>) -> Vec<String> {
        files.iter().map(|f| f.name.to_string()).collect()
    }

    #[test]
    fn includes_are_read_transitively_and_unrelated_files_are_not() {
        let mut fs = Memory(std::vec![
            ("printer.cfg", "[include macros/*.cfg]\n[printer]\n"),
            ("macros/a.cfg", "[include extra.cfg]\n"),
            ("macros/b.cfg", "[gcode_macro B]\n"),
            ("extra.cfg", "[fan]\npin: PA8\n"),
            ("unrelated.cfg", "[printer]\n"),
        ]);
        let mut buf = [0u8; 512];
        let files = load(&mut fs, &mut buf).expect("loads");
        assert_eq!(
            names(&files),
            ["printer.cfg", "macros/a.cfg", "macros/b.cfg", "extra.cfg"]
        );
        assert_eq!(files[3].text, "[fan]\npin: PA8\n");
    }

    #[test]
    fn a_missing_printer_cfg_or_a_full_buffer_is_a_clear_error() {
        let mut buf = [0u8; 64];
        let e = load(&mut Memory(std::vec![]), &mut buf).expect_err("no printer.cfg");
        assert_eq!(e.to_string(), "printer.cfg: file not found");
        let mut fs = Memory(std::vec![(
            "printer.cfg",
            "[printer]\nkinematics: cartesian\n"
        )]);
        let mut small = [0u8; 16];
        let e = load(&mut fs, &mut small).expect_err("too small");
        assert_eq!(e.to_string(), "printer.cfg: file too large");
    }

    #[test]
    fn a_missing_include_is_left_to_the_config_reader() {
        // The reader reports it with the including file and line.
        let mut fs = Memory(std::vec![("printer.cfg", "[include nope.cfg]\n")]);
        let mut buf = [0u8; 64];
        let files = load(&mut fs, &mut buf).expect("loads");
        assert_eq!(names(&files), ["printer.cfg"]);
        let e = onechip_config::Config::parse_files(&files).expect_err("missing");
        assert!(e.to_string().contains("include file does not exist"), "{e}");
    }
}
