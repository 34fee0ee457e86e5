//! Printing from the SD card: Klipper's virtual_sdcard with the Marlin
//! commands hosts send (M20 list, M23 select, M24 start or resume, M25
//! pause, M26 position, M27 status, M28/M29 upload, M30 delete) and
//! Marlin's autostart files (`auto0.g`, `auto1.g`, ... at boot).
//!
//! The file is read a block at a time into the same bounded line assembly
//! as the console, and its lines run one per [`SdPrint::next_line`] call,
//! so console lines are served between them.

use crate::card::{Card, Entry};
use crate::config_files::MAX_PATH;
use crate::line::{LineAssembler, LineEvent};
use crate::session::profile::MAX_LINE;
use core::fmt::{self, Write};

/// Bytes read from the card at a time (one FAT block).
const BLOCK: usize = 512;
/// Autostart files tried at boot: `auto0.g` to `auto9.g`.
const AUTOSTART_FILES: u8 = 10;

/// A path on the card.
pub type Path = heapless::String<MAX_PATH>;

/// Why an SD command failed.
#[derive(Debug)]
pub enum SdError<E> {
    /// No file of that name (Marlin's `open failed`).
    NotFound(Path),
    /// Printing: the command would change the file being printed.
    Busy,
    /// M24 without a selected file.
    NoFile,
    /// RESUME while not paused.
    NotPaused,
    /// PAUSE while paused.
    AlreadyPaused,
    /// A name longer than a path can be.
    NameTooLong,
    /// The card failed.
    Card(E),
}

impl<E: fmt::Display> fmt::Display for SdError<E> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::NotFound(name) => write!(f, "open failed, File: {name}."),
            Self::Busy => f.write_str("SD busy"),
            Self::NoFile => f.write_str("No file selected (M23 NAME first)"),
            Self::NotPaused => f.write_str("Print is not paused"),
            Self::AlreadyPaused => f.write_str("Print already paused"),
            Self::NameTooLong => write!(f, "file name longer than {MAX_PATH} bytes"),
            Self::Card(e) => write!(f, "SD card: {e}"),
        }
    }
}

/// Whether the selected file is being printed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    Stopped,
    Printing,
    Paused,
}

/// The file selected for printing.
#[derive(Debug, Clone)]
struct Selected {
    path: Path,
    size: u32,
}

/// A file being written (M28 to M29).
#[derive(Debug)]
struct Upload {
    path: Path,
    /// Lines not yet written to the card.
    pending: heapless::Vec<u8, BLOCK>,
}

/// The virtual SD card's state.
#[derive(Debug)]
pub struct SdPrint {
    selected: Option<Selected>,
    state: State,
    /// The file offset of `block[0]`, bytes.
    block_at: u32,
    block: [u8; BLOCK],
    block_len: usize,
    /// Bytes of `block` already taken into lines.
    block_pos: usize,
    lines: LineAssembler<MAX_LINE>,
    upload: Option<Upload>,
    /// The next autostart file to try, if autostart is on.
    autostart: Option<u8>,
}

impl Default for SdPrint {
    fn default() -> Self {
        Self::new()
    }
}

impl SdPrint {
    /// No file selected.
    pub const fn new() -> Self {
        Self {
            selected: None,
            state: State::Stopped,
            block_at: 0,
            block: [0; BLOCK],
            block_len: 0,
            block_pos: 0,
            lines: LineAssembler::new(),
            upload: None,
            autostart: None,
        }
    }

    /// True while a file is printing (not paused).
    pub fn is_printing(&self) -> bool {
        self.state == State::Printing
    }

    /// True while a file is printing or paused.
    pub fn is_active(&self) -> bool {
        self.state != State::Stopped
    }

    /// True between M28 and M29: lines go to the file.
    pub fn is_uploading(&self) -> bool {
        self.upload.is_some()
    }

    /// Bytes of the selected file run so far, and its size.
    pub fn progress(&self) -> Option<(u32, u32)> {
        let s = self.selected.as_ref()?;
        Some((self.position(), s.size))
    }

    /// The file offset of the next byte to take into a line.
    fn position(&self) -> u32 {
        self.block_at + self.block_pos as u32
    }

    /// Looks for `auto0.g`, `auto1.g`, ... from now on, whenever nothing is
    /// printing (Marlin's autostart; called once at boot).
    pub fn autostart(&mut self) {
        self.autostart = Some(0);
    }

    /// M20: the G-code files (`.gcode`, `.g`, `.gco`), with their long
    /// names if `long` (`M20 L`).
    pub fn list<C: Card>(card: &mut C, long: bool, out: &mut impl Write) -> Result<(), C::Error> {
        let _ = writeln!(out, "Begin file list");
        let result = card.each_entry(&mut |e: &Entry<'_>| {
            if is_gcode(e.path) || is_gcode(e.long_name) {
                let _ = if long {
                    writeln!(out, "{} {} {}", e.path, e.size, e.long_name)
                } else {
                    writeln!(out, "{} {}", e.path, e.size)
                };
            }
        });
        let _ = writeln!(out, "End file list");
        result
    }

    /// M23: selects file `name` (its path or long name, any case, a
    /// leading `/` ignored) for printing, from its start.
    pub fn select<C: Card>(
        &mut self,
        card: &mut C,
        name: &str,
        out: &mut impl Write,
    ) -> Result<(), SdError<C::Error>> {
        if self.is_active() {
            return Err(SdError::Busy);
        }
        let (path, size) = find(card, name)?;
        let _ = writeln!(out, "File opened: {path} Size: {size}");
        let _ = writeln!(out, "File selected");
        self.selected = Some(Selected { path, size });
        self.seek(0);
        Ok(())
    }

    /// M24, RESUME: starts or resumes the selected file.
    pub fn start<E>(&mut self) -> Result<(), SdError<E>> {
        if self.selected.is_none() {
            return Err(SdError::NoFile);
        }
        self.state = State::Printing;
        Ok(())
    }

    /// M25, PAUSE: pauses the print after the line running now.
    pub fn pause<E>(&mut self) -> Result<(), SdError<E>> {
        match self.state {
            State::Printing => {
                self.state = State::Paused;
                Ok(())
            }
            State::Paused => Err(SdError::AlreadyPaused),
            State::Stopped => Err(SdError::NotPaused),
        }
    }

    /// RESUME: resumes a paused print.
    pub fn resume<E>(&mut self) -> Result<(), SdError<E>> {
        match self.state {
            State::Paused => self.start(),
            _ => Err(SdError::NotPaused),
        }
    }

    /// M26 S: the next line is read from byte `position`.
    pub fn set_position<E>(&mut self, position: u32) -> Result<(), SdError<E>> {
        if self.is_printing() {
            return Err(SdError::Busy);
        }
        self.seek(position);
        Ok(())
    }

    /// SDCARD_RESET_FILE, CANCEL_PRINT: stops and forgets the file.
    pub fn reset(&mut self) {
        self.state = State::Stopped;
        self.selected = None;
        self.seek(0);
    }

    /// M27: `SD printing byte X/Y`, or `Not SD printing.`.
    pub fn report(&self, out: &mut impl Write) -> fmt::Result {
        match self.progress() {
            Some((at, size)) if self.is_active() => writeln!(out, "SD printing byte {at}/{size}"),
            _ => writeln!(out, "Not SD printing."),
        }
    }

    /// M28: creates file `name` and writes the lines that follow into it,
    /// up to M29.
    pub fn begin_upload<C: Card>(
        &mut self,
        card: &mut C,
        name: &str,
        out: &mut impl Write,
    ) -> Result<(), SdError<C::Error>> {
        let path = path_of(name)?;
        if self.selected.as_ref().is_some_and(|s| s.path == path) && self.is_active() {
            return Err(SdError::Busy);
        }
        card.create(&path).map_err(SdError::Card)?;
        let _ = writeln!(out, "Writing to file: {path}");
        self.upload = Some(Upload {
            path,
            pending: heapless::Vec::new(),
        });
        Ok(())
    }

    /// A line to write into the uploaded file.
    pub fn upload_line<C: Card>(&mut self, card: &mut C, line: &[u8]) -> Result<(), C::Error> {
        let Some(upload) = &mut self.upload else {
            return Ok(());
        };
        for &byte in line.iter().chain(b"\n") {
            if upload.pending.push(byte).is_err() {
                card.append(&upload.path, &upload.pending)?;
                upload.pending.clear();
                let _ = upload.pending.push(byte);
            }
        }
        Ok(())
    }

    /// M29: ends the upload.
    pub fn end_upload<C: Card>(
        &mut self,
        card: &mut C,
        out: &mut impl Write,
    ) -> Result<(), C::Error> {
        let Some(upload) = self.upload.take() else {
            return Ok(());
        };
        if !upload.pending.is_empty() {
            card.append(&upload.path, &upload.pending)?;
        }
        let _ = writeln!(out, "Done saving file.");
        Ok(())
    }

    /// M30: deletes file `name`.
    pub fn delete<C: Card>(
        &mut self,
        card: &mut C,
        name: &str,
        out: &mut impl Write,
    ) -> Result<(), SdError<C::Error>> {
        let (path, _) = find(card, name)?;
        if self.selected.as_ref().is_some_and(|s| s.path == path) {
            if self.is_active() {
                return Err(SdError::Busy);
            }
            self.reset();
        }
        if card.delete(&path).map_err(SdError::Card)? {
            let _ = writeln!(out, "File deleted:{path}");
        } else {
            let _ = writeln!(out, "Deletion failed, File: {path}.");
        }
        Ok(())
    }

    /// While printing: the next line of the file, or None at its end
    /// (after `Done printing file` is written to `out`). Starts the next
    /// autostart file when there is one and nothing is printing.
    pub fn next_line<C: Card>(
        &mut self,
        card: &mut C,
        out: &mut impl Write,
    ) -> Result<Option<LineEvent<'_>>, SdError<C::Error>> {
        if self.state == State::Stopped {
            self.start_autostart(card, out)?;
        }
        if !self.is_printing() {
            return Ok(None);
        }
        let Some(selected) = &self.selected else {
            return Ok(None);
        };
        let mut at_end = false;
        loop {
            if self.block_pos == self.block_len {
                self.block_at += self.block_len as u32;
                self.block_pos = 0;
                self.block_len = if self.block_at < selected.size {
                    card.read_at(&selected.path, self.block_at, &mut self.block)
                        .map_err(SdError::Card)?
                } else {
                    0
                };
                if self.block_len == 0 {
                    at_end = true;
                    break;
                }
            }
            let byte = self.block[self.block_pos];
            self.block_pos += 1;
            if byte == b'\n' || byte == b'\r' {
                if self.lines.is_empty() {
                    continue;
                }
                break;
            }
            let _ = self.lines.push(byte);
        }
        if at_end {
            let _ = writeln!(out, "Done printing file");
            self.state = State::Stopped;
            self.selected = None;
            self.block_at = 0;
            if self.lines.is_empty() {
                return Ok(None);
            }
        }
        // The line's end (or the file's, after a last line without one).
        Ok(self.lines.push(b'\n'))
    }

    /// Starts the next autostart file on the card, if any is left.
    fn start_autostart<C: Card>(
        &mut self,
        card: &mut C,
        out: &mut impl Write,
    ) -> Result<(), SdError<C::Error>> {
        while let Some(n) = self.autostart.filter(|&n| n < AUTOSTART_FILES) {
            self.autostart = Some(n + 1);
            let mut name = Path::new();
            let _ = write!(name, "auto{n}.g");
            match self.select(card, &name, out) {
                Ok(()) => return self.start(),
                Err(SdError::NotFound(_)) => {
                    // Marlin stops at the first missing number.
                    self.autostart = None;
                }
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }

    /// Reads from byte `position` on.
    fn seek(&mut self, position: u32) {
        self.block_at = position;
        self.block_len = 0;
        self.block_pos = 0;
        self.lines = LineAssembler::new();
    }
}

/// True for a G-code file name.
fn is_gcode(name: &str) -> bool {
    let ext = name.rsplit_once('.').map_or("", |(_, ext)| ext);
    ["gcode", "g", "gco"]
        .iter()
        .any(|g| ext.eq_ignore_ascii_case(g))
}

/// `name` as a card path: without a leading `/`.
fn path_of<E>(name: &str) -> Result<Path, SdError<E>> {
    let name = name.trim().trim_start_matches('/');
    Path::try_from(name).map_err(|_| SdError::NameTooLong)
}

/// `path` split at its last `/`: the folder (empty in the root) and the
/// name.
fn split_folder(path: &str) -> (&str, &str) {
    path.rsplit_once('/').unwrap_or(("", path))
}

/// The path and size of the file that `name` names (its path, or its
/// folder and long name, any case).
fn find<C: Card>(card: &mut C, name: &str) -> Result<(Path, u32), SdError<C::Error>> {
    let wanted = path_of(name)?;
    let (want_folder, want_name) = split_folder(&wanted);
    let mut found = None;
    card.each_entry(&mut |e: &Entry<'_>| {
        let (folder, _) = split_folder(e.path);
        let matches = e.path.eq_ignore_ascii_case(&wanted)
            || folder.eq_ignore_ascii_case(want_folder)
                && e.long_name.eq_ignore_ascii_case(want_name);
        if found.is_none() && matches {
            found = Path::try_from(e.path).ok().map(|p| (p, e.size));
        }
    })
    .map_err(SdError::Card)?;
    found.ok_or(SdError::NotFound(wanted))
}
