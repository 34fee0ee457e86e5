//! A pseudo-terminal playing the board's USB serial port: the simulator
//! holds the master side, a host program opens the slave through a
//! symlink, as it would open `/dev/ttyACM0`.

use std::fs::File;
use std::io::{self, Read, Write};
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The master side of a pseudo-terminal whose slave `link` points to (the
/// link goes when the pty is dropped).
#[derive(Debug)]
pub struct Pty {
    master: File,
    link: PathBuf,
}

/// What the host side of the port is doing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PortState {
    /// Nobody has the port open.
    Closed,
    /// Open, and bytes have arrived.
    Readable,
    /// Open, and nothing arrived before the time-out.
    Quiet,
}

impl Pty {
    /// A raw (no echo, no line editing, no CR/LF translation)
    /// pseudo-terminal, its slave reachable as `link` (replacing a link
    /// or file already there).
    pub fn open(link: &Path) -> io::Result<Self> {
        let (mut master, mut slave) = (-1, -1);
        // SAFETY: openpty writes two descriptors into the pointers; the
        // name, termios and window-size arguments may be null.
        let status = unsafe {
            libc::openpty(
                &mut master,
                &mut slave,
                std::ptr::null_mut(),
                std::ptr::null(),
                std::ptr::null(),
            )
        };
        if status != 0 {
            return Err(io::Error::last_os_error());
        }
        // SAFETY: openpty succeeded: both are open descriptors we own.
        let (master, slave) =
            unsafe { (OwnedFd::from_raw_fd(master), OwnedFd::from_raw_fd(slave)) };
        make_raw(&slave)?;
        let name = std::fs::read_link(format!("/proc/self/fd/{}", slave.as_raw_fd()))?;
        match std::fs::remove_file(link) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => return Err(e),
            _ => {}
        }
        std::os::unix::fs::symlink(&name, link)?;
        // The slave is closed here: until a host opens it, the master
        // reads as hung up ([`PortState::Closed`]).
        drop(slave);
        Ok(Self {
            master: File::from(master),
            link: link.to_path_buf(),
        })
    }

    /// A second handle on the master, for a thread that reads while
    /// another writes.
    pub fn try_clone(&self) -> io::Result<File> {
        self.master.try_clone()
    }

    /// The symlink to the slave.
    pub fn link(&self) -> &Path {
        &self.link
    }
}

impl Drop for Pty {
    fn drop(&mut self) {
        // The link points to a pty that is gone.
        let _ = std::fs::remove_file(&self.link);
    }
}

impl Write for &Pty {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        (&self.master).write(buf)
    }

    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

/// Waits up to `timeout` for the host side of the pty whose master is
/// `master` to send bytes, and tells what it is doing.
pub fn wait(master: &File, timeout: Duration) -> io::Result<PortState> {
    let mut poll = libc::pollfd {
        fd: master.as_raw_fd(),
        events: libc::POLLIN,
        revents: 0,
    };
    let millis = libc::c_int::try_from(timeout.as_millis()).unwrap_or(libc::c_int::MAX);
    // SAFETY: one valid pollfd, for the duration of the call.
    match unsafe { libc::poll(&mut poll, 1, millis) } {
        -1 => {
            let e = io::Error::last_os_error();
            if e.kind() == io::ErrorKind::Interrupted {
                Ok(PortState::Quiet)
            } else {
                Err(e)
            }
        }
        0 => Ok(PortState::Quiet),
        // Bytes first: a host that wrote and closed is read to the end.
        _ if poll.revents & libc::POLLIN != 0 => Ok(PortState::Readable),
        _ if poll.revents & (libc::POLLHUP | libc::POLLERR) != 0 => Ok(PortState::Closed),
        _ => Ok(PortState::Quiet),
    }
}

/// Reads what the host sent: the byte count, or `None` once it has closed
/// the port (the master reads EIO then).
pub fn read(mut master: &File, buf: &mut [u8]) -> io::Result<Option<usize>> {
    match master.read(buf) {
        Err(e) if e.raw_os_error() == Some(libc::EIO) => Ok(None),
        Ok(0) => Ok(None),
        other => other.map(Some),
    }
}

/// Sets the terminal `fd` to raw mode.
pub(crate) fn make_raw(fd: &OwnedFd) -> io::Result<()> {
    // SAFETY: termios is plain data; tcgetattr fills it in.
    let mut termios: libc::termios = unsafe { std::mem::zeroed() };
    // SAFETY: `fd` is an open terminal and `termios` a valid termios.
    if unsafe { libc::tcgetattr(fd.as_raw_fd(), &mut termios) } != 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: as above.
    unsafe { libc::cfmakeraw(&mut termios) };
    // SAFETY: as above.
    if unsafe { libc::tcsetattr(fd.as_raw_fd(), libc::TCSANOW, &termios) } != 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs::OpenOptions;

    fn link(name: &str) -> PathBuf {
        std::env::temp_dir().join(format!("onechip-pty-{name}-{}", std::process::id()))
    }

    #[test]
    fn bytes_cross_raw_both_ways_and_a_hang_up_is_seen() {
        let path = link("both-ways");
        let pty = Pty::open(&path).expect("pty");
        let master = pty.try_clone().expect("clone");
        assert_eq!(
            wait(&master, Duration::from_millis(10)).expect("poll"),
            PortState::Closed
        );
        let mut host = OpenOptions::new()
            .read(true)
            .write(true)
            .open(&path)
            .expect("open the slave");
        assert_eq!(
            wait(&master, Duration::from_millis(10)).expect("poll"),
            PortState::Quiet
        );
        // CR stays CR (no translation), and nothing is echoed back.
        host.write_all(b"M105\r\n").expect("write");
        assert_eq!(
            wait(&master, Duration::from_secs(5)).expect("poll"),
            PortState::Readable
        );
        let mut buf = [0u8; 64];
        let n = read(&master, &mut buf).expect("read");
        assert_eq!(buf.get(..n.expect("open")), Some(&b"M105\r\n"[..]));
        (&pty).write_all(b"ok\n").expect("reply");
        let n = host.read(&mut buf).expect("host reads");
        assert_eq!(&buf[..n], b"ok\n");
        drop(host);
        assert_eq!(
            wait(&master, Duration::from_secs(5)).expect("poll"),
            PortState::Closed
        );
        assert_eq!(read(&master, &mut buf).expect("read"), None);
        drop(pty);
        assert!(!path.exists(), "the link goes with the pty");
    }

    #[test]
    fn a_stale_link_is_replaced() {
        let path = link("stale");
        std::fs::write(&path, "old").expect("stale file");
        let pty = Pty::open(&path).expect("pty");
        assert!(
            std::fs::read_link(&path)
                .expect("a link")
                .starts_with("/dev/pts")
        );
        assert_eq!(pty.link(), path);
    }
}
