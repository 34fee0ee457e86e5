//! One secondary MCU after identify, sans I/O, as klippy's `mcu.py` and
//! serial queue drive it: clock synchronisation (`get_uptime`, eight
//! `get_clock`s 50 ms apart, then one every [`QUERY_PERIOD`]), the config
//! phase (`get_config`, the config commands and `finalize_config` with
//! their CRC, `get_config` again), then commands queued by the caller,
//! each held until the MCU's clock reaches its `min_clock` (a free move
//! slot) and packed several to a block.
//!
//! The caller writes what [`Connection::poll`] returns, feeds what it
//! reads to [`Connection::receive`], and hears back through [`Event`]s.
//! Times are host seconds (see [`crate::clock_sync`]).

use crate::clock_sync::{ClockSync, QUERY_PERIOD};
use crate::crc32;
use crate::identify::{RETRY_TIME, micros};
use core::fmt;
use onechip_protocol::block::{MAX_PAYLOAD, MIN_LEN};
use onechip_protocol::codec::Decoded;
use onechip_protocol::dictionary::Dictionary;
use onechip_protocol::transport::{HostLink, LinkStats};

/// Longest message queued, bytes (a `queue_step` is at most 17).
pub const MAX_MESSAGE: usize = 32;
/// Messages the outbox holds before [`Full`].
pub const OUTBOX: usize = 128;
/// Sync bytes written ahead of a retransmission: one block's worth, so
/// that an MCU waiting for the rest of a block whose length byte was
/// damaged gets its bytes, finds the CRC wrong and resynchronises before
/// the retransmitted blocks come (an MCU ignores leading sync bytes).
pub const RETRANSMIT_PADDING: usize = onechip_protocol::block::MAX_LEN;
/// Bytes [`Connection::poll`] may write: padding, a sync byte and every
/// unacknowledged block.
pub const POLL_OUT: usize = RETRANSMIT_PADDING
    + 1
    + onechip_protocol::transport::MAX_PENDING_BLOCKS * onechip_protocol::block::MAX_LEN;
/// Longest block payload while the link is noisy, bytes: a block of
/// this size still gets through a link that damages one byte in a hundred
/// four times in five, where a full block (64 bytes) gets through half
/// the time, and every loss costs a retransmission of all blocks behind
/// it.
const NOISY_PAYLOAD: usize = 16;
/// How long the link counts as noisy after a retransmission, s.
const NOISY_HOLD: f64 = 2.0;
/// `get_clock`s before the config phase, as klippy's connect.
const START_SAMPLES: u8 = 8;
/// Time between the start samples, s.
const START_SAMPLE_PERIOD: f64 = 0.050;

/// The outbox is full: try again after [`Connection::poll`] has sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Full;

/// Why a connection failed, with Klipper's wording (see [`Self::write`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Failure {
    /// Configured before with other commands (and not restarted).
    CrcMismatch,
    /// Still configured after it was to be reset (klippy's firmware
    /// restart did not take).
    NotReset,
    /// `get_config` still says unconfigured after the config was sent.
    NotConfigured,
    /// The MCU is shut down, so it cannot take a config.
    ShutDown,
    /// The MCU stopped answering its clock queries.
    Lost,
    /// A config command does not fit the MCU's dictionary.
    BadCommand,
}

impl Failure {
    /// Klipper's message for MCU `name`.
    pub fn write(&self, name: &str, f: &mut impl fmt::Write) -> fmt::Result {
        match self {
            Self::CrcMismatch => write!(f, "MCU '{name}' CRC does not match config"),
            Self::NotReset => write!(f, "Failed automated reset of MCU '{name}'"),
            Self::NotConfigured => write!(f, "Unable to configure MCU '{name}'"),
            Self::ShutDown => write!(f, "Can not update MCU '{name}' config as it is shutdown"),
            Self::Lost => write!(f, "Lost communication with MCU '{name}'"),
            Self::BadCommand => write!(f, "MCU '{name}' does not accept its config commands"),
        }
    }
}

/// What the connection reports to its owner.
pub enum Event<'e, 'd> {
    /// The MCU answered `get_config`: send the config with
    /// [`Connection::configure`]. `Some(crc)` if it is configured already.
    Configure(Option<u32>),
    /// Configured and synchronised; `move_count` step commands fit its
    /// move queue.
    Ready {
        /// The MCU's move queue length.
        move_count: u16,
    },
    /// The MCU shut down (`shutdown` or `is_shutdown`): its message.
    Shutdown(&'e Decoded<'d, 'd, 'e>),
    /// Any other response (`stepper_position`, `trsync_state`, …).
    Response(&'e Decoded<'d, 'd, 'e>),
    /// The connection cannot go on.
    Failed(Failure),
}

/// Where the connection stands.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    /// `get_uptime` asked.
    Uptime,
    /// This many start samples answered.
    Sampling(u8),
    /// `get_config` asked before configuring.
    Config,
    /// Waiting for [`Connection::configure`].
    Configuring,
    /// `get_config` asked after configuring, expecting this CRC.
    Checking(u32),
    /// Running.
    Ready,
    /// Failed or shut down: only clock queries go on.
    Stopped,
}

/// A message waiting for a block.
#[derive(Debug, Clone, Copy)]
struct Queued {
    /// Held until the MCU's clock reaches this, ticks.
    min_clock: u64,
    len: u8,
    bytes: [u8; MAX_MESSAGE],
}

impl Queued {
    /// `message`, held until clock `min_clock`; None if it is longer than
    /// [`MAX_MESSAGE`].
    fn new(message: &[u8], min_clock: u64) -> Option<Self> {
        let mut bytes = [0; MAX_MESSAGE];
        bytes.get_mut(..message.len())?.copy_from_slice(message);
        Some(Self {
            min_clock,
            len: message.len() as u8,
            bytes,
        })
    }

    /// `line`, a message of `dict` as text, encoded and held until clock
    /// `min_clock`; None if it is not a message of `dict` or is longer
    /// than [`MAX_MESSAGE`].
    fn encode(dict: &Dictionary<'_>, line: &str, min_clock: u64) -> Option<Self> {
        let mut bytes = [0; MAX_MESSAGE];
        let len = dict.encode_text(line, &mut bytes).ok()?;
        Some(Self {
            min_clock,
            len: len as u8,
            bytes,
        })
    }

    fn message(&self) -> &[u8] {
        self.bytes.get(..usize::from(self.len)).unwrap_or_default()
    }
}

/// The host side of one secondary MCU.
pub struct Connection<'d> {
    dict: &'d Dictionary<'d>,
    link: HostLink,
    phase: Phase,
    /// When the current question was asked, host s.
    asked_at: f64,
    sync: Option<ClockSync>,
    /// When the unanswered `get_clock` went out (None: several out).
    clock_query_sent: Option<f64>,
    next_clock_query: f64,
    outbox: heapless::Deque<Queued, OUTBOX>,
    /// Until this host time (s) blocks are kept small: the link had to
    /// retransmit.
    noisy_until: f64,
}

impl<'d> Connection<'d> {
    /// Goes on from identify with the MCU's dictionary and the link.
    pub fn new(dict: &'d Dictionary<'d>, link: HostLink) -> Self {
        Self {
            dict,
            link,
            phase: Phase::Uptime,
            asked_at: f64::NEG_INFINITY,
            sync: None,
            clock_query_sent: None,
            next_clock_query: f64::INFINITY,
            outbox: heapless::Deque::new(),
            noisy_until: f64::NEG_INFINITY,
        }
    }

    /// The MCU's dictionary.
    pub fn dictionary(&self) -> &'d Dictionary<'d> {
        self.dict
    }

    /// The clock synchronisation, once the MCU has told its uptime.
    pub fn clock(&self) -> Option<&ClockSync> {
        self.sync.as_ref()
    }

    /// The same, to re-fit its print time line.
    pub fn clock_mut(&mut self) -> Option<&mut ClockSync> {
        self.sync.as_mut()
    }

    /// The link's counters: bytes written and retransmitted, timeouts
    /// and naks.
    pub fn link_stats(&self) -> LinkStats {
        self.link.stats
    }

    /// Messages queued and not yet sent.
    pub fn queued(&self) -> usize {
        self.outbox.len()
    }

    /// Queues a message written as text (`name param=value …`), to go out
    /// once the MCU's clock reaches `min_clock`.
    pub fn send_text(&mut self, line: &str, min_clock: u64) -> Result<(), SendTextError> {
        let queued = Queued::encode(self.dict, line, min_clock).ok_or(SendTextError::Encode)?;
        self.outbox
            .push_back(queued)
            .map_err(|_| SendTextError::Full)
    }

    /// Queues an encoded message, to go out once the MCU's clock reaches
    /// `min_clock` (0: at once).
    pub fn send(&mut self, message: &[u8], min_clock: u64) -> Result<(), Full> {
        let queued = Queued::new(message, min_clock).ok_or(Full)?;
        self.outbox.push_back(queued).map_err(|_| Full)
    }

    /// After [`Event::Configure`]: sends `lines` (klippy's config commands,
    /// `allocate_oids` first) and `finalize_config` with their CRC if the
    /// MCU is not configured (nothing if it is configured with the same
    /// CRC); then checks with `get_config`.
    pub fn configure<'l>(
        &mut self,
        lines: impl Iterator<Item = &'l str> + Clone,
        configured: Option<u32>,
    ) -> Result<(), Failure> {
        let crc = config_crc(lines.clone());
        let commands_ok = match configured {
            Some(old) if old != crc => return self.fail(Failure::CrcMismatch),
            Some(_) => true,
            None => {
                let mut fin = heapless::String::<32>::new();
                let _ = fmt::write(&mut fin, format_args!("finalize_config crc={crc}"));
                lines.map(|l| self.send_text(l, 0)).all(|r| r.is_ok())
                    && self.send_text(&fin, 0).is_ok()
            }
        };
        if !commands_ok {
            return self.fail(Failure::BadCommand);
        }
        self.phase = Phase::Checking(crc);
        self.asked_at = f64::NEG_INFINITY;
        Ok(())
    }

    fn fail(&mut self, why: Failure) -> Result<(), Failure> {
        self.phase = Phase::Stopped;
        Err(why)
    }

    /// Writes into `out` what must go to the MCU now: retransmissions,
    /// questions of the start-up, clock queries and queued messages;
    /// returns the length. `out` needs [`POLL_OUT`] bytes. Reports a lost
    /// link through `on_event`.
    pub fn poll(
        &mut self,
        now: f64,
        out: &mut [u8],
        mut on_event: impl FnMut(Event<'_, 'd>),
    ) -> usize {
        let pad = RETRANSMIT_PADDING.min(out.len());
        if let Some(n) = self.link.poll(micros(now), &mut out[pad..]) {
            self.clock_query_sent = None;
            self.noisy_until = now + NOISY_HOLD;
            out[..pad].fill(onechip_protocol::block::SYNC);
            return pad + n;
        }
        let question = match self.phase {
            Phase::Uptime => Some("get_uptime"),
            Phase::Sampling(_) => Some("get_clock"),
            Phase::Config | Phase::Checking(_) => Some("get_config"),
            Phase::Configuring | Phase::Ready | Phase::Stopped => None,
        };
        if let Some(q) = question
            && now >= self.asked_at + self.retry_time()
            && self.ask(q, false).is_ok()
        {
            self.asked_at = now;
            if q == "get_clock" {
                self.clock_query_sent = Some(now);
            }
        }
        if matches!(
            self.phase,
            Phase::Ready | Phase::Stopped | Phase::Checking(_)
        ) && now >= self.next_clock_query
        {
            self.next_clock_query = now + QUERY_PERIOD;
            if let Some(sync) = self.sync.as_mut() {
                let first = sync.is_active();
                sync.query_sent();
                if first && !sync.is_active() {
                    self.phase = Phase::Stopped;
                    on_event(Event::Failed(Failure::Lost));
                }
            }
            self.clock_query_sent = self.clock_query_sent.xor(Some(now));
            let _ = self.ask("get_clock", true);
        }
        self.write_queued(now, out)
    }

    /// Seconds before a start-up question is asked again.
    fn retry_time(&self) -> f64 {
        match self.phase {
            Phase::Sampling(n) if n > 0 => START_SAMPLE_PERIOD,
            _ => RETRY_TIME,
        }
    }

    /// Queues a parameterless question (`get_config`, …): behind what is
    /// queued (the config commands before it must run first), or at the
    /// front for a clock query (its round trip should be short).
    fn ask(&mut self, name: &str, front: bool) -> Result<(), Full> {
        let queued = Queued::encode(self.dict, name, 0).ok_or(Full)?;
        if front {
            self.outbox.push_front(queued)
        } else {
            self.outbox.push_back(queued)
        }
        .map_err(|_| Full)
    }

    /// Packs the messages that are due into blocks while the link's
    /// window allows.
    fn write_queued(&mut self, now: f64, out: &mut [u8]) -> usize {
        let clock = self.sync.as_ref().map_or(0, |s| s.clock_at(now));
        let limit = if now < self.noisy_until {
            NOISY_PAYLOAD
        } else {
            MAX_PAYLOAD
        };
        let mut written = 0;
        loop {
            // The messages due at the front that fill one block.
            let (mut count, mut len) = (0, 0);
            for q in self.outbox.iter() {
                let n = usize::from(q.len);
                if q.min_clock > clock || len + n > limit {
                    break;
                }
                (count, len) = (count + 1, len + n);
            }
            if len == 0 || !self.link.can_send(len) || out.len() - written < len + MIN_LEN {
                return written;
            }
            let mut payload = [0u8; MAX_PAYLOAD];
            let mut at = 0;
            for q in self.outbox.iter().take(count) {
                let message = q.message();
                if let Some(dest) = payload.get_mut(at..at + message.len()) {
                    dest.copy_from_slice(message);
                }
                at += message.len();
            }
            let payload = payload.get(..len).unwrap_or_default();
            let Ok(block) = self.link.send(payload, micros(now)) else {
                return written;
            };
            // The room for it was checked above.
            let Some(dest) = out.get_mut(written..written + block.len()) else {
                return written;
            };
            dest.copy_from_slice(block);
            written += block.len();
            for _ in 0..count {
                self.outbox.pop_front();
            }
        }
    }

    /// Takes bytes from the MCU.
    pub fn receive(&mut self, bytes: &[u8], now: f64, mut on_event: impl FnMut(Event<'_, 'd>)) {
        let dict = self.dict;
        let mut link = core::mem::take(&mut self.link);
        link.receive(bytes, micros(now), |payload| {
            let mut at = 0;
            while let Some(rest) = payload.get(at..).filter(|r| !r.is_empty()) {
                let Ok((msg, n)) = dict.decode(rest) else {
                    break;
                };
                at += n;
                self.on_message(&msg, now, &mut on_event);
            }
        });
        self.link = link;
    }

    fn on_message(
        &mut self,
        msg: &Decoded<'d, 'd, '_>,
        now: f64,
        on_event: &mut impl FnMut(Event<'_, 'd>),
    ) {
        let int = |name| msg.int(name).unwrap_or(0);
        match msg.message.name() {
            "uptime" if self.phase == Phase::Uptime => {
                let clock = (int("high") as u64) << 32 | (int("clock") as u64 & 0xffff_ffff);
                let freq = self.dict.constant_int("CLOCK_FREQ").unwrap_or(0) as f64;
                self.sync = Some(ClockSync::new(freq, clock, self.asked_at));
                self.phase = Phase::Sampling(0);
                self.asked_at = now;
            }
            "clock" => {
                let sent = self.clock_query_sent.take();
                if let Some(sync) = self.sync.as_mut() {
                    sync.on_clock(int("clock") as u32, sent, now);
                }
                if let Phase::Sampling(n) = self.phase {
                    self.phase = if n + 1 >= START_SAMPLES {
                        self.asked_at = f64::NEG_INFINITY;
                        self.next_clock_query = now + QUERY_PERIOD;
                        Phase::Config
                    } else {
                        Phase::Sampling(n + 1)
                    };
                }
            }
            "config" => self.on_config(msg, on_event),
            "shutdown" | "is_shutdown" => {
                if self.phase != Phase::Ready {
                    self.phase = Phase::Stopped;
                }
                on_event(Event::Shutdown(msg));
            }
            _ => on_event(Event::Response(msg)),
        }
    }

    fn on_config(&mut self, msg: &Decoded<'d, 'd, '_>, on_event: &mut impl FnMut(Event<'_, 'd>)) {
        let int = |name| msg.int(name).unwrap_or(0);
        let (is_config, crc) = (int("is_config") != 0, int("crc") as u32);
        match self.phase {
            Phase::Config if int("is_shutdown") != 0 => {
                self.phase = Phase::Stopped;
                on_event(Event::Failed(Failure::ShutDown));
            }
            Phase::Config => {
                self.phase = Phase::Configuring;
                on_event(Event::Configure(is_config.then_some(crc)));
            }
            Phase::Checking(expected) if is_config && crc == expected => {
                self.phase = Phase::Ready;
                on_event(Event::Ready {
                    move_count: int("move_count") as u16,
                });
            }
            Phase::Checking(_) => {
                self.phase = Phase::Stopped;
                on_event(Event::Failed(Failure::NotConfigured));
            }
            _ => {}
        }
    }
}

/// Why [`Connection::send_text`] failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SendTextError {
    /// Not a message of the MCU's dictionary, or a bad value.
    Encode,
    /// The outbox is full.
    Full,
}

/// klippy's config CRC: CRC-32 of the config commands joined by newlines.
pub fn config_crc<'l>(lines: impl Iterator<Item = &'l str>) -> u32 {
    let mut crc = 0;
    for (i, line) in lines.enumerate() {
        if i > 0 {
            crc = crc32::update(crc, b"\n");
        }
        crc = crc32::update(crc, line.as_bytes());
    }
    crc
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::string::{String, ToString};
    use std::vec::Vec;

    #[test]
    fn the_config_crc_is_klippys_on_the_golden_avr_case() {
        let log =
            onechip_golden::read_string(std::path::Path::new("avr_cart_extrude/mcu-commands.txt"));
        let lines: Vec<&str> = log
            .lines()
            .take_while(|l| !l.starts_with("finalize_config"))
            .collect();
        let fin: String = log
            .lines()
            .find_map(|l| l.strip_prefix("finalize_config crc="))
            .expect("finalize_config")
            .into();
        assert!(lines.len() > 10);
        assert_eq!(config_crc(lines.iter().copied()).to_string(), fin);
    }
}
