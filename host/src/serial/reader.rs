//! The console's input side, in a thread of its own as the board's USB
//! reader runs in an interrupt: it reads what the host sends, assembles
//! lines and hands them to the session through a channel of two lines
//! (when it is full, reading stops and the pty's buffer holds the host
//! back: no line is lost).

use super::pty::{self, PortState};
use onechip_app::emergency::EmergencyParser;
use onechip_app::line::{LineAssembler, LineEvent};
use onechip_app::session::profile::MAX_LINE;
use std::fs::File;
use std::io;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;
use std::time::Duration;

/// Lines waiting for the session, as the board's channel holds.
const WAITING_LINES: usize = 2;
/// How often the reader looks at the `ending` flag while the port is
/// quiet.
const POLL: Duration = Duration::from_millis(20);

/// One console line as the session receives it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Incoming {
    /// A line without its end.
    Line(Vec<u8>),
    /// A line longer than [`MAX_LINE`] bytes, dropped: its length.
    TooLong(usize),
}

impl Incoming {
    /// The line as the session takes it.
    pub fn event(&self) -> LineEvent<'_> {
        match self {
            Self::Line(bytes) => LineEvent::Complete(bytes),
            Self::TooLong(len) => LineEvent::TooLong { len: *len },
        }
    }
}

/// Starts reading `master`: lines come out of the receiver, which
/// disconnects once the host has closed the port after opening it, or
/// once `ending` is raised (which the reader raises itself on a hang-up).
/// An `M112` raises `emergency` the moment its bytes arrive.
pub fn spawn(
    master: File,
    ending: Arc<AtomicBool>,
    emergency: Arc<AtomicBool>,
) -> (Receiver<Incoming>, JoinHandle<io::Result<()>>) {
    let (lines, rx) = sync_channel(WAITING_LINES);
    let reader = std::thread::spawn(move || {
        let read = read_lines(&master, &ending, &emergency, &lines);
        // The session runs what is queued to its end without waiting
        // for the wall clock.
        ending.store(true, Ordering::Relaxed);
        read
    });
    (rx, reader)
}

/// Reads lines from `master` into `lines` until the host, having opened
/// the port, closes it, or `ending` is raised.
fn read_lines(
    master: &File,
    ending: &AtomicBool,
    emergency: &AtomicBool,
    lines: &SyncSender<Incoming>,
) -> io::Result<()> {
    let mut assembler = LineAssembler::<MAX_LINE>::new();
    let mut parser = EmergencyParser::new();
    let mut buf = [0u8; 256];
    let mut opened = false;
    while !ending.load(Ordering::Relaxed) {
        let n = match pty::wait(master, POLL)? {
            PortState::Quiet => 0,
            PortState::Readable => match pty::read(master, &mut buf)? {
                Some(n) => n,
                None => return Ok(()),
            },
            PortState::Closed => {
                if opened {
                    return Ok(());
                }
                // Not opened yet: wait for a host.
                std::thread::sleep(POLL);
                continue;
            }
        };
        opened = true;
        for &byte in buf.get(..n).unwrap_or_default() {
            if parser.push(byte) {
                // Now, before the line waits its turn.
                emergency.store(true, Ordering::Relaxed);
            }
            let incoming = match assembler.push(byte) {
                Some(LineEvent::Complete(bytes)) => Incoming::Line(bytes.to_vec()),
                Some(LineEvent::TooLong { len }) => Incoming::TooLong(len),
                None => continue,
            };
            if lines.send(incoming).is_err() {
                // The session is gone.
                return Ok(());
            }
        }
    }
    Ok(())
}
