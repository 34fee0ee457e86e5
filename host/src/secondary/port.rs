//! A secondary MCU's serial device (a tty, or the pseudo-terminal of a
//! peer process), raw and non-blocking.

use crate::serial::pty::make_raw;
use onechip_app::secondary::{LinkError, SecondaryLink};
use std::fs::{File, OpenOptions};
use std::io::{self, Read, Write};
use std::os::fd::{AsRawFd, OwnedFd};
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;
use std::time::Duration;

/// How long a write waits for a full device to take bytes again.
const WRITE_STALL: Duration = Duration::from_secs(1);
/// How long one wait for room lasts.
const WRITE_POLL: Duration = Duration::from_millis(10);

/// An open serial device.
pub struct Port {
    file: File,
}

impl Port {
    /// Opens `path` read/write, raw and non-blocking.
    pub fn open(path: &Path) -> io::Result<Self> {
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(libc::O_NOCTTY | libc::O_NONBLOCK)
            .open(path)?;
        let fd = OwnedFd::from(file.try_clone()?);
        make_raw(&fd)?;
        Ok(Self { file })
    }

    /// Reads what has arrived: `Ok(0)` if nothing, an error once the other
    /// side is gone.
    pub fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        match self.file.read(buf) {
            Ok(0) => Err(io::ErrorKind::UnexpectedEof.into()),
            Ok(n) => Ok(n),
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => Ok(0),
            Err(e) if e.raw_os_error() == Some(libc::EIO) => {
                Err(io::ErrorKind::UnexpectedEof.into())
            }
            Err(e) => Err(e),
        }
    }

    /// Writes all of `bytes`, waiting while the device's buffer is full;
    /// an error if it stays full for [`WRITE_STALL`] (the other side no
    /// longer reads).
    pub fn write_all(&mut self, mut bytes: &[u8]) -> io::Result<()> {
        let mut stalled = Duration::ZERO;
        while !bytes.is_empty() {
            match self.file.write(bytes) {
                Ok(n) => {
                    bytes = &bytes[n..];
                    stalled = Duration::ZERO;
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    if stalled >= WRITE_STALL {
                        return Err(io::Error::new(
                            io::ErrorKind::TimedOut,
                            "the device takes no more bytes",
                        ));
                    }
                    self.wait(libc::POLLOUT, WRITE_POLL)?;
                    stalled += WRITE_POLL;
                }
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }

    /// Pulses the modem lines as klippy resets an Arduino-style board
    /// (its DTR is wired to the chip's reset): DTR raised then dropped,
    /// 100 ms apart. With `cheetah`, as klippy's Fysetc Cheetah reset:
    /// RTS held raised over a first pulse, then a second pulse. An error
    /// if the device has no modem lines (a pseudo-terminal).
    pub fn pulse_dtr(&mut self, cheetah: bool) -> io::Result<()> {
        let step = Duration::from_millis(100);
        let set = |line: libc::c_int, on: bool| -> io::Result<()> {
            let request = if on { libc::TIOCMBIS } else { libc::TIOCMBIC };
            // SAFETY: the fd is open; the request reads one c_int.
            if unsafe { libc::ioctl(self.file.as_raw_fd(), request, &line) } < 0 {
                return Err(io::Error::last_os_error());
            }
            Ok(())
        };
        let pulse = || -> io::Result<()> {
            set(libc::TIOCM_DTR, true)?;
            std::thread::sleep(step);
            set(libc::TIOCM_DTR, false)?;
            std::thread::sleep(step);
            Ok(())
        };
        if cheetah {
            set(libc::TIOCM_RTS, true)?;
            pulse()?;
            set(libc::TIOCM_RTS, false)?;
            std::thread::sleep(step);
        }
        pulse()
    }

    fn wait(&self, events: libc::c_short, timeout: Duration) -> io::Result<()> {
        let mut poll = libc::pollfd {
            fd: self.file.as_raw_fd(),
            events,
            revents: 0,
        };
        let millis = libc::c_int::try_from(timeout.as_millis()).unwrap_or(libc::c_int::MAX);
        // SAFETY: one valid pollfd, for the duration of the call.
        if unsafe { libc::poll(&mut poll, 1, millis) } < 0 {
            let e = io::Error::last_os_error();
            if e.kind() != io::ErrorKind::Interrupted {
                return Err(e);
            }
        }
        Ok(())
    }
}

/// `e` in a link's words.
pub fn link_error(e: &io::Error) -> LinkError {
    LinkError(onechip_app::secondary::text(format_args!("{e}")))
}

impl SecondaryLink for Port {
    fn write_all(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        Port::write_all(self, bytes).map_err(|e| link_error(&e))
    }

    fn read(&mut self, buf: &mut [u8]) -> Result<usize, LinkError> {
        Port::read(self, buf).map_err(|e| link_error(&e))
    }

    fn wait_readable(&mut self, timeout: f64) -> Result<(), LinkError> {
        let timeout = Duration::from_secs_f64(timeout.max(0.0));
        self.wait(libc::POLLIN, timeout).map_err(|e| link_error(&e))
    }

    fn pulse_reset(&mut self, cheetah: bool) -> Result<(), LinkError> {
        self.pulse_dtr(cheetah).map_err(|e| link_error(&e))
    }
}
