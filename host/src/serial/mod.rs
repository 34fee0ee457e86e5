//! The simulator on a serial port: a pseudo-terminal speaks the board's
//! USB console, so OctoPrint, Pronterface or any other host can drive the
//! simulated printer as it would the real one, in real time (or `speed`
//! times faster).
//!
//! As on the board, a reader thread assembles the host's lines into a
//! channel of two ([`reader`]); the session answers them one at a time,
//! and between lines the console's idle work runs and virtual time
//! follows the wall clock ([`crate::pace`]). The print ends when the host
//! closes the port, or when told to (SIGINT, SIGTERM): what is queued then
//! runs to its end (unpaced) and the run is summed up.

pub mod pty;
pub mod reader;

use crate::host_mcu::RunMcu;
use crate::pace::Pace;
use crate::{Options, SimError, Summary, with_session};
use onechip_app::printer::PRIMING_TIME;
use onechip_app::session::profile;
use pty::Pty;
use std::fmt;
use std::io::{LineWriter, Write as _};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::sync::mpsc::RecvTimeoutError;
use std::time::Duration;

/// Where and how fast the simulator serves.
#[derive(Debug, Clone, PartialEq)]
pub struct Port {
    /// The symlink to the pty's slave that hosts open.
    pub path: PathBuf,
    /// Virtual time runs this many times as fast as the wall clock.
    pub speed: f64,
}

/// Serves the printer of the SD folder `sd` on `port` until the host
/// closes it or `ending` is raised (the command line raises it on SIGINT
/// and SIGTERM), then finishes the print and sums it up. `ready` is called
/// once the port is there to open.
pub fn serve(
    sd: &Path,
    options: &Options,
    port: &Port,
    ending: &Arc<AtomicBool>,
    ready: impl FnOnce(&Path),
) -> Result<Summary, SimError> {
    let serial_error = |e| SimError::Serial(port.path.clone(), e);
    with_session::<{ profile::LOOKAHEAD }>(sd, options, |run| {
        let pty = Pty::open(&port.path).map_err(serial_error)?;
        run.summary.gcode_path = port.path.clone();
        let master = pty.try_clone().map_err(serial_error)?;
        let emergency = Arc::new(AtomicBool::new(false));
        let (lines, reader) = reader::spawn(master, Arc::clone(ending), Arc::clone(&emergency));
        run.mcu.main_mut().set_emergency(emergency);
        let now = onechip_app::session::Mcu::now(run.mcu);
        run.mcu.main_mut().set_pace(Pace::new(
            now,
            options.mcu_freq,
            port.speed,
            Arc::clone(ending),
        ));
        run.autostart();
        ready(pty.link());
        let idle_poll = idle_poll(port.speed);
        let mut out = Replies(LineWriter::new(&pty));
        loop {
            run.mcu.run_to_wall_clock();
            // While the card prints, its lines run between the host's,
            // without waiting for one.
            let wait = if run.is_printing() {
                Duration::ZERO
            } else {
                idle_poll
            };
            match lines.recv_timeout(wait) {
                Ok(incoming) => {
                    run.mcu.run_to_wall_clock();
                    run.line(&incoming.event(), &mut out);
                }
                Err(RecvTimeoutError::Timeout) => run.poll(&mut out),
                Err(RecvTimeoutError::Disconnected) => {
                    // The host is gone: a print from the card goes on to
                    // its end.
                    while run.is_printing() {
                        run.poll(&mut out);
                    }
                    break;
                }
            }
        }
        reader
            .join()
            .map_err(|_| serial_error(std::io::Error::other("the reader thread panicked")))?
            .map_err(serial_error)
    })
}

/// How long the console waits for a line before its idle work: a tenth
/// of the priming time in virtual time, within 1..10 ms of wall time.
fn idle_poll(speed: f64) -> Duration {
    let wall = PRIMING_TIME / 10.0 / speed;
    Duration::from_secs_f64(wall.clamp(0.001, 0.010))
}

/// Replies to the host, written to the pty a whole line at a time as
/// they come.
struct Replies<'p>(LineWriter<&'p Pty>);

impl fmt::Write for Replies<'_> {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        self.0.write_all(s.as_bytes()).map_err(|_| fmt::Error)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_idle_poll_follows_the_speed_within_bounds() {
        assert_eq!(idle_poll(1.0), Duration::from_millis(10));
        assert_eq!(idle_poll(2.0), Duration::from_secs_f64(0.005));
        assert_eq!(idle_poll(1000.0), Duration::from_millis(1));
    }
}
