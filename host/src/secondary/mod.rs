//! Secondary MCUs running stock Klipper firmware, on serial devices: the
//! simulator's side of [`onechip_secondary_mcu`], with real I/O. Host
//! time is given by the caller in seconds (the main MCU's clock).

pub mod attached;
pub mod homing;
pub mod port;
pub mod thermal;

use onechip_planner::mcu_section::RestartMethod;
use onechip_protocol::codec::{Decoded, Field};
use onechip_protocol::dictionary::Dictionary;
use onechip_protocol::transport::{
    DEFAULT_RECEIVE_WINDOW, HostLink, LinkStats, MAX_PENDING_BLOCKS,
};
use onechip_secondary_mcu::connection::{Connection, Event, Failure, POLL_OUT};
use onechip_secondary_mcu::identify::Identify;
use port::Port;
use std::fmt::{self, Write as _};
use std::io;
use std::path::Path;
use std::time::{Duration, Instant};

/// Largest inflated data dictionary accepted, bytes (Klipper's are 10–15 KB).
const DICTIONARY_MAX: usize = 64 * 1024;
/// How long one round of the start-up waits for an answer.
const EXCHANGE_WAIT: Duration = Duration::from_millis(5);
/// How long klippy lets an MCU act on a reset command, s.
const RESET_PAUSE: f64 = 0.015;
/// Between two tries to open a device not there yet.
const REOPEN_PAUSE: Duration = Duration::from_millis(50);
/// Bytes one poll may write.
const OUT_MAX: usize = 1 + MAX_PENDING_BLOCKS * onechip_protocol::block::MAX_LEN;

/// Why a secondary could not be brought up.
#[derive(Debug)]
pub enum ConnectError {
    /// The device could not be opened or read.
    Io(io::Error),
    /// No complete dictionary within the time allowed.
    Timeout(&'static str),
    /// The dictionary is not valid.
    Dictionary(String),
    /// The config phase failed.
    Failed {
        /// The MCU's name.
        mcu: String,
        /// Why (Klipper's message names the MCU).
        why: Failure,
    },
    /// The reset asked for could not be carried out (`restart_method`).
    Reset(String),
    /// printer.cfg asks for something not supported on a secondary yet.
    Unsupported(String),
    /// A secondary could not be brought up.
    Mcu {
        /// Its name (`[mcu NAME]`).
        mcu: String,
        /// Where its `serial` option is: file name, 1-based line.
        at: (String, usize),
        /// Why.
        error: Box<ConnectError>,
    },
}

impl fmt::Display for ConnectError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Io(e) => write!(f, "{e}"),
            Self::Timeout(phase) => write!(f, "Timeout during {phase}"),
            Self::Dictionary(e) => write!(f, "invalid data dictionary: {e}"),
            Self::Failed { mcu, why } => why.write(mcu, f),
            Self::Reset(why) | Self::Unsupported(why) => f.write_str(why),
            Self::Mcu { mcu, at, error } => write!(
                f,
                "{}:{}: option 'serial' in section 'mcu {mcu}': {error}",
                at.0, at.1
            ),
        }
    }
}

/// Why a secondary is being connected (klippy's start reason).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Start {
    /// The printer starts: a config the MCU holds is kept if it is
    /// this one.
    Fresh,
    /// It was just reset: a config it still holds means the reset did
    /// not take.
    Restarted,
}

/// What a secondary said, as text, for the owner to act on.
#[derive(Debug, Clone, PartialEq)]
pub enum Heard {
    /// A response other than the connection's own (`stepper_position …`).
    Response(String),
    /// An ADC input's report ([`AnalogReport`]).
    Analog(AnalogReport),
    /// The MCU shut down: its `shutdown` message.
    Shutdown(String),
    /// The link failed.
    Failed(Failure),
}

/// An ADC input's `analog_in_state`: Klipper's older firmware sends one
/// `value`, newer firmware a batch of them (`values`, two bytes each,
/// little-endian), the last report's sampling ending just before
/// `next_clock`'s.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AnalogReport {
    /// The input's oid.
    pub oid: u8,
    /// When its next sampling starts, the MCU's 32-bit clock.
    pub next_clock: u32,
    /// Each report's sum of readings, oldest first.
    pub values: Vec<u16>,
}

impl AnalogReport {
    /// `msg` as a report, if it is an `analog_in_state`.
    fn from_message(msg: &Decoded<'_, '_, '_>) -> Option<Self> {
        if msg.message.name() != "analog_in_state" {
            return None;
        }
        let oid = u8::try_from(msg.int("oid")?).ok()?;
        let next_clock = msg.int("next_clock")? as u32;
        let values = match msg.int("value") {
            Some(v) => vec![u16::try_from(v).ok()?],
            None => {
                let mut fields = msg.message.params().zip(&msg.fields);
                let bytes = fields.find_map(|((name, _), f)| match f {
                    Field::Bytes(b) if name == "values" => Some(*b),
                    _ => None,
                })?;
                let pairs = bytes.chunks_exact(2);
                pairs.map(|p| u16::from_le_bytes([p[0], p[1]])).collect()
            }
        };
        Some(Self {
            oid,
            next_clock,
            values,
        })
    }
}

/// A configured secondary MCU.
pub struct Secondary {
    /// Its name in printer.cfg (`[mcu NAME]`).
    pub name: String,
    port: Port,
    conn: Connection<'static>,
    /// The MCU's move queue length (`get_config`'s `move_count`).
    pub move_count: u16,
}

impl Secondary {
    /// Opens `path`, fetches the dictionary, synchronises the clock and
    /// sends `config(CLOCK_FREQ)` (klippy's config commands for an MCU of
    /// that clock, Hz, `allocate_oids` first; nothing more to send if the
    /// MCU holds that config already); `now` gives host time in seconds.
    /// Gives up after `timeout`.
    pub fn connect(
        name: &str,
        path: &Path,
        config: &dyn Fn(f64) -> Vec<String>,
        now: &dyn Fn() -> f64,
        timeout: Duration,
    ) -> Result<Self, ConnectError> {
        Self::connect_as(name, path, config, now, timeout, Start::Fresh)
    }

    /// [`Self::connect`], and as klippy's automated firmware restart: an
    /// MCU that holds another config (its CRC differs) is reset by
    /// `restart` and configured anew.
    pub fn connect_or_restart(
        name: &str,
        path: &Path,
        restart: RestartMethod,
        config: &dyn Fn(f64) -> Vec<String>,
        now: &dyn Fn() -> f64,
        timeout: Duration,
    ) -> Result<Self, ConnectError> {
        let deadline = now() + timeout.as_secs_f64();
        let mut secondary = Self::identified(name, path, now, deadline)?;
        match secondary.configure(config, now, deadline, Start::Fresh) {
            Err(ConnectError::Failed {
                why: Failure::CrcMismatch,
                ..
            }) => {
                secondary.reset(restart, now)?;
                drop(secondary);
                Self::connect_as(name, path, config, now, timeout, Start::Restarted)
            }
            Err(e) => Err(e),
            Ok(()) => Ok(secondary),
        }
    }

    /// [`Self::connect`] of an MCU that was just reset when `start` says
    /// so: then one still configured is [`Failure::NotReset`].
    pub fn connect_as(
        name: &str,
        path: &Path,
        config: &dyn Fn(f64) -> Vec<String>,
        now: &dyn Fn() -> f64,
        timeout: Duration,
        start: Start,
    ) -> Result<Self, ConnectError> {
        let deadline = now() + timeout.as_secs_f64();
        let mut secondary = Self::identified(name, path, now, deadline)?;
        secondary.configure(config, now, deadline, start)?;
        Ok(secondary)
    }

    /// Opens `path` and fetches the dictionary, by host time `deadline`
    /// (s): the MCU before its config phase.
    fn identified(
        name: &str,
        path: &Path,
        now: &dyn Fn() -> f64,
        deadline: f64,
    ) -> Result<Self, ConnectError> {
        // As klippy's serial connect: a device that is not there yet, or
        // goes before it answered (the old one of an MCU being reset), is
        // tried again until the deadline.
        let (port, link, dict) = loop {
            let mut port = open_when_there(path, now, deadline)?;
            match identify(&mut port, now, deadline) {
                Ok((link, dict)) => break (port, link, dict),
                Err(ConnectError::Io(_)) if now() < deadline => {
                    std::thread::sleep(REOPEN_PAUSE);
                }
                Err(e) => return Err(e),
            }
        };
        Ok(Self {
            name: name.to_string(),
            port,
            conn: Connection::new(dict, link),
            move_count: 0,
        })
    }

    /// Resets the MCU as klippy's `microcontroller_restart` does for
    /// `method`: `command` sends `reset`, or (an MCU without it, as
    /// Klipper's Linux MCU) `emergency_stop` then `config_reset`, each
    /// followed by 15 ms for it to act; `arduino` and `cheetah` pulse the
    /// serial line's DTR (RTS too for the Cheetah) in 100 ms steps. The
    /// link is given up after: connect again.
    pub fn reset(
        &mut self,
        method: RestartMethod,
        now: &dyn Fn() -> f64,
    ) -> Result<(), ConnectError> {
        let dict = self.conn.dictionary();
        let has = |name: &str| dict.by_name(name).is_some();
        let send = |secondary: &mut Self, line: &str| -> Result<(), ConnectError> {
            let queued = secondary.conn.send_text(line, 0);
            queued.map_err(|_| {
                ConnectError::Reset(format!("MCU '{}': {line} not sent", secondary.name))
            })?;
            let until = now() + RESET_PAUSE;
            while now() < until {
                // Its device may go as it resets (the Linux MCU's does).
                if secondary
                    .service(now(), EXCHANGE_WAIT, &mut Vec::new())
                    .is_err()
                {
                    break;
                }
            }
            Ok(())
        };
        let by_line = |why: io::Error| {
            ConnectError::Reset(format!(
                "MCU '{}': unable to reset by the serial line: {why}",
                self.name
            ))
        };
        match method {
            RestartMethod::Command if has("reset") => send(self, "reset"),
            RestartMethod::Command if has("config_reset") => {
                send(self, "emergency_stop")?;
                send(self, "config_reset")
            }
            // klippy logs that it cannot and goes on: the MCU then
            // answers as not reset.
            RestartMethod::Command => Ok(()),
            RestartMethod::Arduino => self.port.pulse_dtr(false).map_err(by_line),
            RestartMethod::Cheetah => self.port.pulse_dtr(true).map_err(by_line),
            RestartMethod::RpiUsb => Err(ConnectError::Reset(format!(
                "MCU '{}': restart_method rpi_usb needs a Raspberry Pi's USB hub",
                self.name
            ))),
        }
    }

    /// The MCU's nominal clock (`CLOCK_FREQ`), Hz.
    pub fn clock_freq(&self) -> f64 {
        self.conn
            .dictionary()
            .constant_int("CLOCK_FREQ")
            .map_or(0.0, |f| f as f64)
    }

    /// The MCU's data dictionary.
    pub fn dictionary(&self) -> &'static Dictionary<'static> {
        self.conn.dictionary()
    }

    /// The connection, for sending commands and reading the clock.
    pub fn connection(&mut self) -> &mut Connection<'static> {
        &mut self.conn
    }

    /// The link's counters (bytes written and retransmitted, timeouts,
    /// naks).
    pub fn link_stats(&self) -> LinkStats {
        self.conn.link_stats()
    }

    /// Runs the config phase to its end with the config for the MCU's
    /// clock; `start` says whether it was just reset.
    fn configure(
        &mut self,
        config: &dyn Fn(f64) -> Vec<String>,
        now: &dyn Fn() -> f64,
        deadline: f64,
        start: Start,
    ) -> Result<(), ConnectError> {
        let config = config(self.clock_freq());
        let mut failure = None;
        while self.move_count == 0 {
            let t = now();
            if t > deadline {
                return Err(ConnectError::Timeout("config"));
            }
            let mut configure = None;
            let mut ready = None;
            self.exchange(t, &mut |event| match event {
                Event::Configure(crc) => configure = Some(crc),
                Event::Ready { move_count } => ready = Some(move_count),
                Event::Failed(why) => failure = Some(why),
                Event::Shutdown(_) => failure = Some(Failure::ShutDown),
                Event::Response(_) => {}
            })?;
            match configure {
                Some(Some(_)) if start == Start::Restarted => failure = Some(Failure::NotReset),
                Some(crc) => {
                    if let Err(why) = self.conn.configure(config.iter().map(String::as_str), crc) {
                        failure = Some(why);
                    }
                }
                None => {}
            }
            if let Some(why) = failure {
                return Err(ConnectError::Failed {
                    mcu: self.name.clone(),
                    why,
                });
            }
            if let Some(n) = ready {
                self.move_count = n;
            }
        }
        Ok(())
    }

    /// One round of I/O at host time `now`: writes what is due, waits up
    /// to `wait` for bytes and feeds them in; what the MCU said goes to
    /// `heard`.
    pub fn service(&mut self, now: f64, wait: Duration, heard: &mut Vec<Heard>) -> io::Result<()> {
        let reasons = self.conn.dictionary().enumeration_for("static_string_id");
        let mut on_event = |event: Event<'_, 'static>| match event {
            Event::Response(msg) => heard.push(match AnalogReport::from_message(msg) {
                Some(report) => Heard::Analog(report),
                None => Heard::Response(msg.to_string()),
            }),
            Event::Shutdown(msg) => {
                // The message is the MCU's static string for the id.
                let mut reason = String::new();
                let _ = match (msg.int("static_string_id"), reasons) {
                    (Some(id), Some(names)) => names.write_name(id, &mut reason),
                    _ => write!(reason, "{msg}"),
                };
                heard.push(Heard::Shutdown(reason));
            }
            Event::Failed(why) => heard.push(Heard::Failed(why)),
            Event::Configure(_) | Event::Ready { .. } => {}
        };
        self.io(now, wait, &mut on_event)
    }

    fn exchange(
        &mut self,
        now: f64,
        on_event: &mut dyn FnMut(Event<'_, 'static>),
    ) -> Result<(), ConnectError> {
        self.io(now, EXCHANGE_WAIT, on_event)
            .map_err(ConnectError::Io)
    }

    fn io(
        &mut self,
        now: f64,
        wait: Duration,
        on_event: &mut dyn FnMut(Event<'_, 'static>),
    ) -> io::Result<()> {
        let mut out = [0u8; POLL_OUT];
        let n = self.conn.poll(now, &mut out, &mut *on_event);
        let mut buf = [0u8; 4096];
        let asked = Instant::now();
        let got = self.port.round_trip(&out[..n], wait, &mut buf)?;
        if got > 0 {
            // Stamped when it arrived, as klippy's serial queue stamps
            // what it reads (host time follows the wall clock while
            // secondaries are served): a clock query answered within this
            // wait has a true round trip, not none.
            let received = now + asked.elapsed().as_secs_f64();
            self.conn.receive(&buf[..got], received, &mut *on_event);
        }
        Ok(())
    }
}

/// Opens `path` once it is there (a reset MCU's device may come back
/// under it a little later), until `deadline` (host time, s).
fn open_when_there(
    path: &Path,
    now: &dyn Fn() -> f64,
    deadline: f64,
) -> Result<Port, ConnectError> {
    loop {
        match Port::open(path) {
            Ok(port) => return Ok(port),
            Err(e) if now() > deadline => return Err(ConnectError::Io(e)),
            Err(_) => std::thread::sleep(REOPEN_PAUSE),
        }
    }
}

/// Fetches the dictionary over `port`; it lives as long as the process
/// (one per connection).
fn identify(
    port: &mut Port,
    now: &dyn Fn() -> f64,
    deadline: f64,
) -> Result<(HostLink, &'static Dictionary<'static>), ConnectError> {
    let buf: &'static mut [u8] = Box::leak(vec![0u8; DICTIONARY_MAX].into_boxed_slice());
    let mut fetch = Identify::new(buf, DEFAULT_RECEIVE_WINDOW);
    let mut out = [0u8; OUT_MAX];
    let mut input = [0u8; 4096];
    loop {
        let t = now();
        if t > deadline {
            return Err(ConnectError::Timeout("identify"));
        }
        let n = fetch.poll(t, &mut out);
        let got = port
            .round_trip(&out[..n], EXCHANGE_WAIT, &mut input)
            .map_err(ConnectError::Io)?;
        match fetch.receive(&input[..got], now()) {
            Ok(Some(_)) => break,
            Ok(None) => {}
            Err(e) => return Err(ConnectError::Dictionary(e.to_string())),
        }
    }
    let (link, text) = fetch.finish();
    let text = std::str::from_utf8(text).map_err(|e| ConnectError::Dictionary(e.to_string()))?;
    let dict = Dictionary::parse(text).map_err(|e| ConnectError::Dictionary(e.to_string()))?;
    Ok((link, Box::leak(Box::new(dict))))
}
