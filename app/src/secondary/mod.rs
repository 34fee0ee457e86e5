//! Secondary MCUs running stock Klipper firmware (`[mcu NAME]`): the host
//! role klippy plays for each one, on [`onechip_secondary_mcu`]'s
//! sans-I/O connection, over a byte link the build supplies
//! ([`SecondaryLink`]: a serial device on the Linux host, a USART on a
//! board). Host time is given by the caller in seconds (the main MCU's
//! clock). Nothing here allocates: each MCU's data dictionary lives in a
//! buffer the build hands over ([`Links::dictionary_buffer`]), messages and
//! config commands in bounded buffers.
//!
//! - [`Secondary`]: one MCU, from identify through the config phase;
//! - [`attached::Secondaries`]: every MCU of the printer, its steppers,
//!   outputs, heaters and homing;
//! - [`homing`]: homing across MCUs with trsync;
//! - [`mcu`]: one MCU role over this board's own and the secondaries';
//! - [`thermal`]: heater and sensor inputs on a secondary;
//! - [`forwarded`]: a firmware's io outputs on secondaries.

// Errors carry their words in bounded buffers (there is no heap to box
// them in); they come once per connection or homing, not per step.
#![allow(clippy::result_large_err)]

pub mod attached;
pub mod forwarded;
pub mod homing;
pub mod mcu;
mod remote_output;
pub mod sent_steps;
pub mod thermal;

use core::fmt::{self, Write as _};
use core::mem::MaybeUninit;
use core::ptr::addr_of_mut;
use onechip_planner::mcu_section::RestartMethod;
use onechip_protocol::codec::{Decoded, Field};
use onechip_protocol::dictionary::Dictionary;
use onechip_protocol::transport::{DEFAULT_RECEIVE_WINDOW, LinkStats, MAX_PENDING_BLOCKS};
use onechip_secondary_mcu::connection::{Connection, Event, Failure, POLL_OUT};
use onechip_secondary_mcu::identify::Identify;

/// How one round of the start-up waits for an answer, s.
const EXCHANGE_WAIT: f64 = 0.005;
/// How long klippy lets an MCU act on a reset command, s.
const RESET_PAUSE: f64 = 0.015;
/// Between two tries to open a device not there yet, s.
const REOPEN_PAUSE: f64 = 0.050;
/// Bytes one poll of the identify phase may write.
const OUT_MAX: usize = 1 + MAX_PENDING_BLOCKS * onechip_protocol::block::MAX_LEN;
/// Bytes read from a link at a time.
const READ_CHUNK: usize = 512;
/// Bytes of one MCU's config commands, one line each (Klipper's for a
/// toolboard or a Mega2560 with four steppers and two heaters are under
/// 2 KB).
pub const CONFIG_TEXT: usize = 4096;
/// Most values in one batched `analog_in_state` (a message carries at most
/// 64 bytes).
pub const MAX_REPORT_VALUES: usize = 32;

/// A message for the user: an error's words (bounded: a longer one is cut
/// short).
pub type Text = heapless::String<160>;

/// `args` as a [`Text`], cut short (at a character) if it does not fit.
pub fn text(args: fmt::Arguments<'_>) -> Text {
    /// Keeps what fits.
    struct Cut(Text);
    impl fmt::Write for Cut {
        fn write_str(&mut self, s: &str) -> fmt::Result {
            for c in s.chars() {
                self.0.push(c).map_err(|_| fmt::Error)?;
            }
            Ok(())
        }
    }
    let mut cut = Cut(Text::new());
    let _ = cut.write_fmt(args);
    cut.0
}

/// Bytes of one command line as text (`name param=value …`; Klipper's
/// longest, `query_analog_in` and `endstop_home`, are under 200).
pub const COMMAND_MAX: usize = 256;

/// A command line as text, for [`Connection::send_text`].
pub type CommandLine = heapless::String<COMMAND_MAX>;

/// `args` as a command line; empty (which no dictionary encodes) if it
/// does not fit, never cut short.
pub fn command(args: fmt::Arguments<'_>) -> CommandLine {
    let mut line = CommandLine::new();
    if line.write_fmt(args).is_err() {
        line.clear();
    }
    line
}

/// Why a link failed: the device's or driver's words.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LinkError(pub Text);

impl fmt::Display for LinkError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

/// A byte link to one secondary MCU: a serial device, a USART. Waits are
/// sleeps (a poll, an interrupt), never spins.
pub trait SecondaryLink {
    /// Writes all of `bytes`, waiting while the link's buffer is full.
    fn write_all(&mut self, bytes: &[u8]) -> Result<(), LinkError>;
    /// Reads what has arrived into `buf`: its length, 0 if nothing; an
    /// error once the other side is gone.
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, LinkError>;
    /// Waits until bytes arrive or `timeout` s have passed; may return
    /// early.
    fn wait_readable(&mut self, timeout: f64) -> Result<(), LinkError>;
    /// Resets the MCU by the line's modem signals, as klippy's `arduino`
    /// restart (DTR raised then dropped, 100 ms apart) or with `cheetah`
    /// its Fysetc Cheetah restart (RTS held raised over a first pulse,
    /// then a second); an error if the link has no such lines.
    fn pulse_reset(&mut self, cheetah: bool) -> Result<(), LinkError>;
}

/// What a build supplies to reach its secondaries: their links, by
/// printer.cfg's `serial` option, and room for their dictionaries.
pub trait Links {
    /// The build's link.
    type Link: SecondaryLink;
    /// Opens the link `serial` at `baud` bit/s (printer.cfg's `serial`
    /// and `baud`).
    fn open(&mut self, serial: &str, baud: u32) -> Result<Self::Link, LinkError>;
    /// Waits `s` seconds before another try (a device that is not there
    /// yet, or went as its MCU was reset).
    fn pause(&mut self, s: f64);
    /// A buffer for one MCU's inflated data dictionary, as long as the
    /// printer runs (Klipper's are 10–15 KB); None if none is left.
    fn dictionary_buffer(&mut self) -> Option<&'static mut [u8]>;
    /// Room for one MCU's parsed data dictionary (about 10 KB), as long
    /// as the printer runs; None if none is left.
    fn dictionary_slot(&mut self) -> Option<&'static mut MaybeUninit<Dictionary<'static>>>;
}

/// Why a secondary could not be brought up.
#[derive(Debug, Clone, PartialEq)]
pub enum ConnectError {
    /// The link could not be opened, read or written.
    Link(LinkError),
    /// No complete dictionary or config within the time allowed: the
    /// phase.
    Timeout(&'static str),
    /// The dictionary is not valid, or does not fit.
    Dictionary(Text),
    /// The config phase failed: Klipper's message names the MCU.
    Failed {
        /// The MCU's name.
        mcu: &'static str,
        /// Why.
        why: Failure,
    },
    /// The reset asked for could not be carried out (`restart_method`).
    Reset(Text),
    /// printer.cfg asks for something not supported on a secondary yet.
    Unsupported(Text),
}

impl fmt::Display for ConnectError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Link(e) => write!(f, "{e}"),
            Self::Timeout(phase) => write!(f, "Timeout during {phase}"),
            Self::Dictionary(e) => write!(f, "invalid data dictionary: {e}"),
            Self::Failed { mcu, why } => why.write(mcu, f),
            Self::Reset(why) | Self::Unsupported(why) => f.write_str(why),
        }
    }
}

/// A secondary that could not be brought up, with where printer.cfg
/// names it.
#[derive(Debug, Clone, PartialEq)]
pub struct McuError {
    /// Its name (`[mcu NAME]`).
    pub mcu: &'static str,
    /// The file its `serial` option is in.
    pub file: heapless::String<64>,
    /// That option's line, 1-based.
    pub line: usize,
    /// Why.
    pub error: ConnectError,
}

impl McuError {
    /// Why MCU `mcu` could not be brought up, its `serial` option at
    /// `(file, line)` of printer.cfg (a file name longer than the report
    /// holds is cut short at a character).
    pub fn new(mcu: &'static str, (file, line): (&str, usize), error: ConnectError) -> Self {
        let mut name = heapless::String::new();
        for c in file.chars() {
            if name.push(c).is_err() {
                break;
            }
        }
        Self {
            mcu,
            file: name,
            line,
            error,
        }
    }
}

impl fmt::Display for McuError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}:{}: option 'serial' in section 'mcu {}': {}",
            self.file, self.line, self.mcu, self.error
        )
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

/// What a secondary said, for the owner to act on.
#[derive(Debug)]
pub enum Heard<'e> {
    /// A response other than the connection's own (`stepper_position …`).
    Response(&'e Decoded<'static, 'static, 'e>),
    /// An ADC input's report ([`AnalogReport`]).
    Analog(AnalogReport),
    /// The MCU shut down: its `shutdown` message.
    Shutdown(&'static str),
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
    pub values: heapless::Vec<u16, MAX_REPORT_VALUES>,
}

impl AnalogReport {
    /// `msg` as a report, if it is an `analog_in_state`.
    fn from_message(msg: &Decoded<'_, '_, '_>) -> Option<Self> {
        if msg.message.name() != "analog_in_state" {
            return None;
        }
        let oid = u8::try_from(msg.int("oid")?).ok()?;
        let next_clock = msg.int("next_clock")? as u32;
        let mut values = heapless::Vec::new();
        match msg.int("value") {
            Some(v) => values.push(u16::try_from(v).ok()?).ok()?,
            None => {
                let mut fields = msg.message.params().zip(&msg.fields);
                let bytes = fields.find_map(|((name, _), f)| match f {
                    Field::Bytes(b) if name == "values" => Some(*b),
                    _ => None,
                })?;
                for p in bytes.chunks_exact(2) {
                    values.push(u16::from_le_bytes([p[0], p[1]])).ok()?;
                }
            }
        }
        Some(Self {
            oid,
            next_clock,
            values,
        })
    }
}

/// One MCU's config commands, written for it as its data dictionary
/// describes it (its clock, its PWM_MAX): `config(dictionary, out)` calls
/// `out` once per line, `allocate_oids` first.
pub type ConfigWriter<'a> = &'a dyn Fn(&Dictionary<'_>, &mut dyn FnMut(&str));

/// The clock frequency (Hz) an MCU's data dictionary tells (0 if none).
pub fn clock_freq(dict: &Dictionary<'_>) -> f64 {
    dict.constant_int("CLOCK_FREQ").map_or(0.0, |f| f as f64)
}

/// Room for a dictionary fetch while an MCU connects (about 12 KB, most
/// of it the inflate state): a firmware keeps it in a static, beside the
/// secondaries, instead of on its stack.
pub type FetchRoom = MaybeUninit<Identify<'static>>;

/// A configured secondary MCU on its link.
pub struct Secondary<L> {
    /// Its name in printer.cfg (`[mcu NAME]`).
    pub name: &'static str,
    link: L,
    conn: Connection<'static>,
    /// The MCU's move queue length (`get_config`'s `move_count`).
    pub move_count: u16,
    /// The MCU held this config already, so none was sent (klippy then
    /// sends its restart commands: the hardware PWM outputs' start
    /// values).
    pub config_kept: bool,
}

impl<L: SecondaryLink> Secondary<L> {
    /// Opens `serial` at `baud`, fetches the dictionary, synchronises the
    /// clock and sends `config`'s commands for the MCU's clock (nothing
    /// more if the MCU holds that config already), within `timeout` s of
    /// host time `now()`. `how`: whether the MCU was just reset (then one
    /// still configured is [`Failure::NotReset`]), and, as klippy's
    /// automated firmware restart, how to reset one that holds another
    /// config (its CRC differs) to configure it anew (None: it is an
    /// error).
    pub fn connect<O: Links<Link = L>>(
        name: &'static str,
        serial: (&str, u32),
        links: &mut O,
        config: ConfigWriter<'_>,
        now: &dyn Fn() -> f64,
        timeout: f64,
        how: (Start, Option<RestartMethod>),
    ) -> Result<Self, ConnectError> {
        let (mut slot, mut room) = (MaybeUninit::uninit(), MaybeUninit::uninit());
        let rooms = (&mut slot, &mut room);
        Self::connect_in(rooms, name, serial, links, config, now, timeout, how)?;
        // SAFETY: `connect_in` initialised it.
        Ok(unsafe { slot.assume_init() })
    }

    /// [`Self::connect`] built in place in `slot`, fetching the dictionary
    /// in `room`: a
    /// [`Secondary`] is several KB, which a microcontroller's stack should
    /// not carry copies of. On an error the slot is left empty (what was
    /// made of it dropped, its link closed).
    #[allow(clippy::too_many_arguments)]
    pub fn connect_in<'s, O: Links<Link = L>>(
        (slot, room): (&'s mut MaybeUninit<Self>, &mut FetchRoom),
        name: &'static str,
        serial: (&str, u32),
        links: &mut O,
        config: ConfigWriter<'_>,
        now: &dyn Fn() -> f64,
        timeout: f64,
        (start, reset_other): (Start, Option<RestartMethod>),
    ) -> Result<&'s mut Self, ConnectError> {
        let (mut start, mut reset_other) = (start, reset_other);
        loop {
            let deadline = now() + timeout;
            Self::identified_in((&mut *slot, &mut *room), name, serial, links, now, deadline)?;
            // SAFETY: `identified_in` initialised it.
            let secondary = unsafe { slot.assume_init_mut() };
            let error = match secondary.configure(config, now, deadline, start) {
                Ok(()) => break,
                Err(error) => error,
            };
            let reset = match (&error, reset_other) {
                (
                    ConnectError::Failed {
                        why: Failure::CrcMismatch,
                        ..
                    },
                    Some(method),
                ) => secondary.reset(method, now),
                _ => Err(error),
            };
            // SAFETY: initialised above and dropped once: the slot is
            // empty again.
            unsafe { slot.assume_init_drop() };
            reset?;
            (start, reset_other) = (Start::Restarted, None);
        }
        // SAFETY: initialised by the last `identified_in`, not dropped.
        Ok(unsafe { slot.assume_init_mut() })
    }

    /// Opens the link and fetches the dictionary (in `room`), by host time
    /// `deadline` (s): the MCU before its config phase, written into
    /// `slot` (initialised if and only if this succeeds).
    fn identified_in<O: Links<Link = L>>(
        (slot, room): (&mut MaybeUninit<Self>, &mut FetchRoom),
        name: &'static str,
        (serial, baud): (&str, u32),
        links: &mut O,
        now: &dyn Fn() -> f64,
        deadline: f64,
    ) -> Result<(), ConnectError> {
        let no_room = || ConnectError::Dictionary(text(format_args!("no room for it")));
        let buffer = links.dictionary_buffer().ok_or_else(no_room)?;
        let fetch = Identify::init_in(room, buffer, DEFAULT_RECEIVE_WINDOW);
        // As klippy's serial connect: a device that is not there yet, or
        // goes before it answered (the old one of an MCU being reset), is
        // tried again until the deadline.
        let link = loop {
            let mut link = match links.open(serial, baud) {
                Ok(link) => link,
                Err(e) if now() > deadline => return Err(ConnectError::Link(e)),
                Err(_) => {
                    links.pause(REOPEN_PAUSE);
                    continue;
                }
            };
            match identify(&mut link, fetch, now, deadline) {
                Ok(()) => break link,
                Err(ConnectError::Link(_)) if now() < deadline => {
                    fetch.restart();
                    links.pause(REOPEN_PAUSE);
                }
                Err(e) => return Err(e),
            }
        };
        let (host_link, text_bytes) = fetch.finish();
        let invalid = |e: &dyn fmt::Display| ConnectError::Dictionary(text(format_args!("{e}")));
        let dict_text = core::str::from_utf8(text_bytes).map_err(|e| invalid(&e))?;
        let dict_slot = links.dictionary_slot().ok_or_else(no_room)?;
        let dict: &'static Dictionary<'static> =
            Dictionary::parse_in(dict_slot, dict_text).map_err(|e| invalid(&e))?;
        let p = slot.as_mut_ptr();
        // SAFETY: `p` is valid for writes; each field is written once, in
        // place.
        unsafe {
            addr_of_mut!((*p).name).write(name);
            addr_of_mut!((*p).link).write(link);
            addr_of_mut!((*p).conn).write(Connection::new(dict, host_link));
            addr_of_mut!((*p).move_count).write(0);
            addr_of_mut!((*p).config_kept).write(false);
        }
        Ok(())
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
        let name = self.name;
        let send = |secondary: &mut Self, line: &str| -> Result<(), ConnectError> {
            let queued = secondary.conn.send_text(line, 0);
            queued.map_err(|_| {
                ConnectError::Reset(text(format_args!("MCU '{name}': {line} not sent")))
            })?;
            let until = now() + RESET_PAUSE;
            // Its device may go as it resets (the Linux MCU's does).
            while now() < until && secondary.service(now, EXCHANGE_WAIT, &mut |_| {}).is_ok() {}
            Ok(())
        };
        let by_line = |why: LinkError| {
            ConnectError::Reset(text(format_args!(
                "MCU '{name}': unable to reset by the serial line: {why}"
            )))
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
            RestartMethod::Arduino => self.link.pulse_reset(false).map_err(by_line),
            RestartMethod::Cheetah => self.link.pulse_reset(true).map_err(by_line),
            RestartMethod::RpiUsb => Err(ConnectError::Reset(text(format_args!(
                "MCU '{name}': restart_method rpi_usb needs a Raspberry Pi's USB hub"
            )))),
        }
    }

    /// The MCU's nominal clock (`CLOCK_FREQ`), Hz.
    pub fn clock_freq(&self) -> f64 {
        clock_freq(self.conn.dictionary())
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

    /// Runs the config phase to its end with `config`'s commands for the
    /// MCU's clock; `start` says whether it was just reset.
    fn configure(
        &mut self,
        config: ConfigWriter<'_>,
        now: &dyn Fn() -> f64,
        deadline: f64,
        start: Start,
    ) -> Result<(), ConnectError> {
        let mut lines = heapless::String::<CONFIG_TEXT>::new();
        let mut fits = true;
        config(self.conn.dictionary(), &mut |line| {
            fits &= lines.push_str(line).is_ok() && lines.push('\n').is_ok();
        });
        if !fits {
            return Err(ConnectError::Unsupported(text(format_args!(
                "MCU '{}': its config commands exceed {CONFIG_TEXT} bytes",
                self.name
            ))));
        }
        let mcu = self.name;
        let failed = |why| ConnectError::Failed { mcu, why };
        while self.move_count == 0 {
            if now() > deadline {
                return Err(ConnectError::Timeout("config"));
            }
            let (mut configure, mut ready, mut failure) = (None, None, None);
            self.io(now, EXCHANGE_WAIT, &mut |event| match event {
                Event::Configure(crc) => configure = Some(crc),
                Event::Ready { move_count } => ready = Some(move_count),
                Event::Failed(why) => failure = Some(why),
                Event::Shutdown(_) => failure = Some(Failure::ShutDown),
                Event::Response(_) => {}
            })
            .map_err(ConnectError::Link)?;
            match configure {
                Some(Some(_)) if start == Start::Restarted => failure = Some(Failure::NotReset),
                Some(crc) => {
                    if let Err(why) = self.conn.configure(lines.lines(), crc) {
                        failure = Some(why);
                    }
                    self.config_kept = crc.is_some();
                }
                None => {}
            }
            if let Some(why) = failure {
                return Err(failed(why));
            }
            if let Some(n) = ready {
                self.move_count = n;
            }
        }
        Ok(())
    }

    /// One round of I/O: writes what is due at host time `now()`, waits up
    /// to `wait` s for bytes and takes them in; what the MCU said goes to
    /// `heard`.
    pub fn service(
        &mut self,
        now: &dyn Fn() -> f64,
        wait: f64,
        heard: &mut dyn FnMut(Heard<'_>),
    ) -> Result<(), LinkError> {
        let reasons = self.conn.dictionary().enumeration_for("static_string_id");
        let mut on_event = |event: Event<'_, 'static>| match event {
            Event::Response(msg) => heard(match AnalogReport::from_message(msg) {
                Some(report) => Heard::Analog(report),
                None => Heard::Response(msg),
            }),
            Event::Shutdown(msg) => {
                // The message is the MCU's static string for the id.
                let id = msg.int("static_string_id");
                let reason = (id.zip(reasons)).and_then(|(id, names)| names.name_of(id));
                heard(Heard::Shutdown(
                    reason.unwrap_or("Shutdown of unknown reason"),
                ));
            }
            Event::Failed(why) => heard(Heard::Failed(why)),
            Event::Configure(_) | Event::Ready { .. } => {}
        };
        self.io(now, wait, &mut on_event)
    }

    fn io(
        &mut self,
        now: &dyn Fn() -> f64,
        wait: f64,
        on_event: &mut dyn FnMut(Event<'_, 'static>),
    ) -> Result<(), LinkError> {
        let mut out = [0u8; POLL_OUT];
        let n = self.conn.poll(now(), &mut out, &mut *on_event);
        self.link.write_all(&out[..n])?;
        if wait > 0.0 {
            self.link.wait_readable(wait)?;
        }
        let mut buf = [0u8; READ_CHUNK];
        loop {
            let got = self.link.read(&mut buf)?;
            if got == 0 {
                return Ok(());
            }
            // Stamped when it arrived, as klippy's serial queue stamps
            // what it reads: a clock query answered within this wait has
            // a true round trip, not none.
            self.conn.receive(&buf[..got], now(), &mut *on_event);
        }
    }
}

/// Fetches the dictionary over `link` into `fetch`, by host time
/// `deadline` (s).
fn identify(
    link: &mut impl SecondaryLink,
    fetch: &mut Identify<'static>,
    now: &dyn Fn() -> f64,
    deadline: f64,
) -> Result<(), ConnectError> {
    let mut out = [0u8; OUT_MAX];
    let mut input = [0u8; READ_CHUNK];
    loop {
        let t = now();
        if t > deadline {
            return Err(ConnectError::Timeout("identify"));
        }
        let n = fetch.poll(t, &mut out);
        link.write_all(&out[..n]).map_err(ConnectError::Link)?;
        link.wait_readable(EXCHANGE_WAIT)
            .map_err(ConnectError::Link)?;
        loop {
            let got = link.read(&mut input).map_err(ConnectError::Link)?;
            if got == 0 {
                break;
            }
            match fetch.receive(&input[..got], now()) {
                Ok(Some(_)) => return Ok(()),
                Ok(None) => {}
                Err(e) => return Err(ConnectError::Dictionary(text(format_args!("{e}")))),
            }
        }
    }
}
