//! Secondary MCUs on this machine's serial devices: the I/O shell of
//! [`onechip_app::secondary`] (the host role for each MCU, shared with the
//! firmware). A `serial` option names a device path (a tty, or a peer's
//! pseudo-terminal); each dictionary is kept for the life of the process.

// The shared layer's errors, bounded (see onechip_app::secondary).
#![allow(clippy::result_large_err)]

pub mod port;

use onechip_app::secondary::{
    self, AnalogReport, ConnectError, Heard, LinkError, Links, Start, clock_freq,
};
use onechip_planner::mcu_section::{MAX_SECONDARIES, RestartMethod};
use onechip_protocol::dictionary::Dictionary;
use onechip_secondary_mcu::connection::Failure;
use port::Port;
use std::mem::MaybeUninit;
use std::path::Path;
use std::time::Duration;

/// One secondary MCU on a serial device.
pub type Secondary = secondary::Secondary<Port>;
/// Every secondary MCU of a printer, on serial devices (as many as a
/// printer.cfg may have).
pub type Secondaries = secondary::attached::Secondaries<Port, MAX_SECONDARIES>;

/// Largest inflated data dictionary accepted, bytes (Klipper's are 10–15 KB).
const DICTIONARY_MAX: usize = 64 * 1024;

/// Serial devices by path; dictionaries kept for the life of the process
/// (one per connection: a FIRMWARE_RESTART fetches them again).
pub struct SerialDevices;

impl Links for SerialDevices {
    type Link = Port;

    fn open(&mut self, serial: &str, _baud: u32) -> Result<Port, LinkError> {
        // A pseudo-terminal has no rate; a tty keeps the one it was set to.
        Port::open(Path::new(serial)).map_err(|e| port::link_error(&e))
    }

    fn pause(&mut self, s: f64) {
        std::thread::sleep(Duration::from_secs_f64(s));
    }

    fn dictionary_buffer(&mut self) -> Option<&'static mut [u8]> {
        Some(Box::leak(vec![0u8; DICTIONARY_MAX].into_boxed_slice()))
    }

    fn dictionary_slot(&mut self) -> Option<&'static mut MaybeUninit<Dictionary<'static>>> {
        Some(Box::leak(Box::new(MaybeUninit::uninit())))
    }
}

/// Connects the MCU `name` on device `path` and configures it with the
/// commands `config(freq)` gives for its clock (`allocate_oids` first);
/// `now` is host time, s.
pub fn connect(
    name: &str,
    path: &Path,
    config: &dyn Fn(f64) -> Vec<String>,
    now: &dyn Fn() -> f64,
    timeout: Duration,
) -> Result<Secondary, ConnectError> {
    connect_on(name, path, None, config, now, timeout)
}

/// [`connect`], and as klippy's automated firmware restart: an MCU that
/// holds another config is reset by `restart` and configured anew.
pub fn connect_or_restart(
    name: &str,
    path: &Path,
    restart: RestartMethod,
    config: &dyn Fn(f64) -> Vec<String>,
    now: &dyn Fn() -> f64,
    timeout: Duration,
) -> Result<Secondary, ConnectError> {
    connect_on(name, path, Some(restart), config, now, timeout)
}

/// [`connect`], resetting by `restart` an MCU that holds another config
/// if given.
fn connect_on(
    name: &str,
    path: &Path,
    restart: Option<RestartMethod>,
    config: &dyn Fn(f64) -> Vec<String>,
    now: &dyn Fn() -> f64,
    timeout: Duration,
) -> Result<Secondary, ConnectError> {
    let (name, serial) = (leak(name), path.to_string_lossy());
    let (serial, links, timeout) = ((&*serial, 0), &mut SerialDevices, timeout.as_secs_f64());
    let config = lines(config);
    let how = (Start::Fresh, restart);
    Secondary::connect(name, serial, links, &config, now, timeout, how)
}

/// `config`'s lines (for the MCU's clock frequency, Hz) as the host role
/// takes them, one call each.
fn lines(
    config: &dyn Fn(f64) -> Vec<String>,
) -> impl Fn(&Dictionary<'_>, &mut dyn FnMut(&str)) + '_ {
    move |dict, out| config(clock_freq(dict)).iter().for_each(|l| out(l))
}

/// `text` for as long as the process runs (an MCU's name in its shutdown
/// messages).
pub fn leak(text: &str) -> &'static str {
    Box::leak(text.to_string().into_boxed_str())
}

/// What a secondary said ([`Heard`]), kept: its responses as text.
#[derive(Debug, Clone, PartialEq)]
pub enum Said {
    /// A response, as text (`stepper_position oid=0 pos=100`).
    Response(String),
    /// An ADC input's report.
    Analog(AnalogReport),
    /// The MCU shut down: its message.
    Shutdown(String),
    /// The link failed.
    Failed(Failure),
}

impl From<Heard<'_>> for Said {
    fn from(heard: Heard<'_>) -> Self {
        match heard {
            Heard::Response(msg) => Self::Response(msg.to_string()),
            Heard::Analog(report) => Self::Analog(report),
            Heard::Shutdown(reason) => Self::Shutdown(reason.to_string()),
            Heard::Failed(why) => Self::Failed(why),
        }
    }
}

/// Serves `mcu`'s link once at host time `now()`, waiting up to `wait`:
/// what it said.
pub fn serve(
    mcu: &mut Secondary,
    now: &dyn Fn() -> f64,
    wait: Duration,
) -> Result<Vec<Said>, LinkError> {
    let mut said = Vec::new();
    mcu.service(now, wait.as_secs_f64(), &mut |h| said.push(Said::from(h)))?;
    Ok(said)
}
