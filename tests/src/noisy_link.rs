//! A noisy serial cable for fault-injection tests: a relay between a new
//! pseudo-terminal (the host opens its path) and a peer's device that
//! damages bytes in both directions with a seeded random generator —
//! each byte, with probability `rate`, has one bit flipped or is dropped
//! (half and half), so runs are reproducible for one seed. It can also
//! stall (hold every byte for a while, as a hub or cable that hiccups),
//! and delay every byte by a fixed time (a slow link).

use std::collections::VecDeque;
use std::fs::{File, OpenOptions};
use std::io::{self, Read, Write};
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// How long the relay waits for bytes before looking at its stop flag,
/// ms.
const POLL_MS: i32 = 5;

/// What the cable did to the bytes of one direction.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Damage {
    /// Bytes that went in.
    pub bytes: u64,
    /// Bytes passed on with one bit flipped.
    pub flipped: u64,
    /// Bytes not passed on.
    pub dropped: u64,
}

/// What the cable did: towards the peer and back from it.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Report {
    /// Host to peer.
    pub to_peer: Damage,
    /// Peer to host.
    pub from_peer: Damage,
    /// Why the relay stopped before it was asked to, if it did.
    pub broken: Option<String>,
}

/// A running noisy cable; stopped (and its path removed) when dropped.
pub struct NoisyLink {
    /// The device the host opens (a symlink to the relay's pty).
    pub path: PathBuf,
    stop: Arc<AtomicBool>,
    /// While raised, no byte passes either way (they wait in the ptys).
    held: Arc<AtomicBool>,
    thread: Option<JoinHandle<Report>>,
}

impl NoisyLink {
    /// Starts a cable from a new pty at `path` to the device `peer`,
    /// damaging each byte with probability `rate` (0..1), random
    /// generator seeded with `seed`.
    pub fn start(peer: &Path, path: &Path, rate: f64, seed: u64) -> io::Result<Self> {
        Self::start_with(peer, path, Noise::new(rate, seed), Duration::ZERO)
    }

    /// A cable from a new pty at `path` to the device `peer` that damages
    /// nothing but delays every byte by `delay`, both ways.
    pub fn start_slow(peer: &Path, path: &Path, delay: Duration) -> io::Result<Self> {
        Self::start_with(peer, path, Noise::new(0.0, 1), delay)
    }

    fn start_with(peer: &Path, path: &Path, noise: Noise, delay: Duration) -> io::Result<Self> {
        let peer = open_raw(peer)?;
        let (master, slave) = open_pty()?;
        let name = std::fs::read_link(format!("/proc/self/fd/{}", slave.as_raw_fd()))?;
        match std::fs::remove_file(path) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => return Err(e),
            _ => {}
        }
        std::os::unix::fs::symlink(name, path)?;
        let stop = Arc::new(AtomicBool::new(false));
        let held = Arc::new(AtomicBool::new(false));
        let flags = (Arc::clone(&stop), Arc::clone(&held));
        let thread = std::thread::spawn(move || {
            // The slave stays open here: the master never reads as hung up
            // while the host reopens it, and it stays raw.
            let _slave = slave;
            let ends = [File::from(master), peer];
            relay(ends, noise, delay, &flags.0, &flags.1)
        });
        Ok(Self {
            path: path.to_path_buf(),
            stop,
            held,
            thread: Some(thread),
        })
    }

    /// Stalls the cable for `time`: nothing passes either way meanwhile,
    /// then what waited goes on.
    pub fn stall(&self, time: Duration) {
        self.held.store(true, Ordering::Relaxed);
        std::thread::sleep(time);
        self.held.store(false, Ordering::Relaxed);
    }

    /// Stops the cable: what it did to the bytes.
    pub fn stop(&mut self) -> Report {
        self.stop.store(true, Ordering::Relaxed);
        let report = self
            .thread
            .take()
            .and_then(|t| t.join().ok())
            .unwrap_or_default();
        let _ = std::fs::remove_file(&self.path);
        report
    }
}

impl Drop for NoisyLink {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Opens a tty device read/write and raw.
fn open_raw(path: &Path) -> io::Result<File> {
    let file = OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(libc::O_NOCTTY)
        .open(path)?;
    make_raw(file.as_raw_fd())?;
    Ok(file)
}

/// A new pseudo-terminal pair, the slave raw.
fn open_pty() -> io::Result<(OwnedFd, OwnedFd)> {
    let (mut master, mut slave) = (-1, -1);
    // SAFETY: openpty writes two descriptors; name, termios and winsize
    // may be null.
    let rc = unsafe {
        libc::openpty(
            &mut master,
            &mut slave,
            std::ptr::null_mut(),
            std::ptr::null(),
            std::ptr::null(),
        )
    };
    if rc != 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: openpty succeeded: both are open descriptors we now own.
    let (master, slave) = unsafe { (OwnedFd::from_raw_fd(master), OwnedFd::from_raw_fd(slave)) };
    make_raw(slave.as_raw_fd())?;
    Ok((master, slave))
}

fn make_raw(fd: i32) -> io::Result<()> {
    // SAFETY: termios is plain data, filled in by tcgetattr.
    let mut termios: libc::termios = unsafe { std::mem::zeroed() };
    // SAFETY: `fd` is open and `termios` valid for the calls.
    unsafe {
        if libc::tcgetattr(fd, &mut termios) != 0 {
            return Err(io::Error::last_os_error());
        }
        libc::cfmakeraw(&mut termios);
        if libc::tcsetattr(fd, libc::TCSANOW, &termios) != 0 {
            return Err(io::Error::last_os_error());
        }
    }
    Ok(())
}

/// Moves bytes both ways between `ends` (host, peer), damaging them and
/// passing each on `delay` after it came, until `stop` is raised or a
/// side is gone; none while `held` is raised.
fn relay(
    mut ends: [File; 2],
    mut noise: Noise,
    delay: Duration,
    stop: &AtomicBool,
    held: &AtomicBool,
) -> Report {
    let mut report = Report::default();
    let mut buf = [0u8; 4096];
    // Per direction (0: to the peer, 1: from it): bytes and when they
    // are due at the other end.
    let mut due: [VecDeque<(Instant, Vec<u8>)>; 2] = Default::default();
    while !stop.load(Ordering::Relaxed) {
        if held.load(Ordering::Relaxed) {
            std::thread::sleep(Duration::from_millis(1));
            continue;
        }
        let next = due.iter().filter_map(|q| q.front().map(|d| d.0)).min();
        let wait = next.map_or(POLL_MS, |at| {
            let ms = at.saturating_duration_since(Instant::now()).as_millis();
            i32::try_from(ms).unwrap_or(POLL_MS).min(POLL_MS)
        });
        let mut fds = ends.each_ref().map(|f| libc::pollfd {
            fd: f.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        });
        // SAFETY: two valid pollfds for the duration of the call.
        let polled = unsafe { libc::poll(fds.as_mut_ptr(), 2, wait) };
        for (way, fd) in fds.iter().enumerate() {
            if polled <= 0 || fd.revents & (libc::POLLIN | libc::POLLHUP | libc::POLLERR) == 0 {
                continue;
            }
            let damage = if way == 0 {
                &mut report.to_peer
            } else {
                &mut report.from_peer
            };
            match read_damaged(&mut ends[way], &mut noise, damage, &mut buf) {
                Ok(kept) => due[way].push_back((Instant::now() + delay, kept)),
                Err(_) => return report,
            }
        }
        let now = Instant::now();
        for (way, queue) in due.iter_mut().enumerate() {
            while queue.front().is_some_and(|d| d.0 <= now) {
                let Some((_, bytes)) = queue.pop_front() else {
                    break;
                };
                if ends[1 - way].write_all(&bytes).is_err() {
                    return report;
                }
            }
        }
    }
    report
}

/// Reads what `from` has: the bytes to pass on, damaged.
fn read_damaged(
    from: &mut File,
    noise: &mut Noise,
    damage: &mut Damage,
    buf: &mut [u8],
) -> io::Result<Vec<u8>> {
    let n = from.read(buf)?;
    if n == 0 {
        return Err(io::ErrorKind::UnexpectedEof.into());
    }
    let mut kept = Vec::with_capacity(n);
    for &byte in &buf[..n] {
        damage.bytes += 1;
        match noise.damage(byte) {
            Some(b) if b == byte => kept.push(b),
            Some(b) => {
                damage.flipped += 1;
                kept.push(b);
            }
            None => damage.dropped += 1,
        }
    }
    Ok(kept)
}

/// Seeded damage: xorshift64* random numbers.
struct Noise {
    state: u64,
    /// Damage threshold on a 32-bit random number.
    threshold: u64,
}

impl Noise {
    fn new(rate: f64, seed: u64) -> Self {
        Self {
            state: seed | 1,
            threshold: (rate.clamp(0.0, 1.0) * f64::from(u32::MAX)) as u64,
        }
    }

    fn next(&mut self) -> u64 {
        self.state ^= self.state >> 12;
        self.state ^= self.state << 25;
        self.state ^= self.state >> 27;
        self.state.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 32
    }

    /// `byte` as the cable passes it on: itself, with one bit flipped, or
    /// nothing.
    fn damage(&mut self, byte: u8) -> Option<u8> {
        if self.next() >= self.threshold {
            return Some(byte);
        }
        let r = self.next();
        if r & 1 == 0 {
            None
        } else {
            Some(byte ^ (1 << ((r >> 1) & 7)))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn about_the_rate_is_damaged_half_flipped_half_dropped() {
        let mut noise = Noise::new(0.01, 7);
        let (mut flipped, mut dropped) = (0, 0);
        for i in 0..1_000_000u32 {
            match noise.damage(i as u8) {
                None => dropped += 1,
                Some(b) if b != i as u8 => flipped += 1,
                Some(_) => {}
            }
        }
        assert!((4_500..5_500).contains(&flipped), "{flipped}");
        assert!((4_500..5_500).contains(&dropped), "{dropped}");
    }
}
