//! The console as Marlin-family hosts (OctoPrint, Pronterface, Cura,
//! Repetier-Host) drive it, over the board's USB CDC and the simulator's
//! serial port alike.
//!
//! Every console line gets exactly one `ok` (for M105 it carries the
//! temperatures, `ok T:…`), after any reply text; errors are `!! ` lines
//! as in Klipper, refused lines Marlin's `Error:` + `Resend:` ([`crate::line_protocol`]).
//! The console answers what concerns the console itself (M110, M115,
//! M105, auto-reports with M155 and M27 S, M117/M118/M73), the SD card
//! ([`crate::sd_print`]), M112 and restarts; every other command runs in
//! the [`Session`](crate::session::Session). While a file prints from the card, [`Console::poll`]
//! runs its lines one at a time between console lines.

use crate::card::Card;
use crate::filament::FilamentEvent;
use crate::line::{LineEvent, command_word};
use crate::line_protocol::{Checked, LineNumbers, write_refusal};
use crate::sd_print::{SdError, SdPrint};
use crate::session::{ConsoleSession, Mcu, profile::MAX_LINE};
use crate::text::ErrorText;
use core::fmt::{self, Write};
use onechip_config::decimal;
use onechip_sched::shutdown::Shutdown;

/// What the firmware can do, as M115's `Cap:` lines tell hosts.
const CAPABILITIES: &[(&str, bool)] = &[
    ("SERIAL_XON_XOFF", false),
    ("BINARY_FILE_TRANSFER", false),
    ("EEPROM", false),
    ("AUTOREPORT_TEMP", true),
    ("AUTOREPORT_SD_STATUS", true),
    ("EMERGENCY_PARSER", true),
    ("EXTENDED_M20", true),
    ("PROGRESS", false),
    ("AUTOLEVEL", false),
    ("Z_PROBE", false),
    ("SOFTWARE_POWER", false),
    ("TOGGLE_LIGHTS", false),
    ("CASE_LIGHT_BRIGHTNESS", false),
    ("HOST_ACTION_COMMANDS", false),
];

/// How often the session's idle work runs while no line comes, s: the
/// thread code may wake at every step interrupt, the work need not.
const IDLE_PERIOD: f64 = 0.010;

/// Where a line came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Source {
    /// The host: acknowledged with `ok`.
    Console,
    /// A file printing from the card: not acknowledged.
    File,
}

/// A report repeated every `period` ticks of the step clock.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Every {
    period: u64,
    next: u64,
}

/// The console's state: line numbering, auto-reports, when the session's timers run,
/// the SD card's print.
#[derive(Debug)]
pub struct Console {
    /// The step clock, Hz.
    freq: f64,
    numbers: LineNumbers,
    /// The clock from which the session's idle work is due again.
    idle_due: u64,
    /// M155: temperature reports.
    temperatures: Option<Every>,
    /// M27 S: SD print status reports.
    sd_status: Option<Every>,
    sd: SdPrint,
    /// M999 or FIRMWARE_RESTART asked for a restart not yet taken.
    restart: bool,
    /// The MCU role's shutdown has been reported.
    shutdown_reported: bool,
}

/// A `!! ` error line.
fn error_line(out: &mut impl Write, e: &impl fmt::Display) -> fmt::Result {
    writeln!(out, "!! {e}")
}

impl Console {
    /// A console on a step clock of `freq` Hz, no line yet.
    pub const fn new(freq: f64) -> Self {
        Self {
            freq,
            numbers: LineNumbers::new(),
            idle_due: 0,
            temperatures: None,
            sd_status: None,
            sd: SdPrint::new(),
            restart: false,
            shutdown_reported: false,
        }
    }

    /// Runs `auto0.g`, `auto1.g`, ... from the card as soon as nothing
    /// else prints (to call once at boot).
    pub fn autostart(&mut self) {
        self.sd.autostart();
    }

    /// True while a file prints from the card: the caller keeps calling
    /// [`Self::poll`] rather than sleeping.
    pub fn is_printing(&self) -> bool {
        self.sd.is_printing()
    }

    /// True once after M999 or FIRMWARE_RESTART: the caller restarts the
    /// printer (the board resets; the simulator rebuilds the session and
    /// its MCU role).
    pub fn take_restart(&mut self) -> bool {
        core::mem::take(&mut self.restart)
    }

    /// Answers one console event: through `session`, or without a printer
    /// (no valid printer.cfg) with `no_printer` as the error of every
    /// command that needs one.
    // Not inlined (nor is `poll`): in the board's serve loop their frames
    // added up past short stack addressing.
    #[inline(never)]
    pub fn line(
        &mut self,
        session: Option<&mut dyn ConsoleSession<'_>>,
        no_printer: &ErrorText,
        event: &LineEvent<'_>,
        card: &mut impl Card,
        mcu: &mut impl Mcu,
        out: &mut impl Write,
    ) -> fmt::Result {
        let checked = match event {
            LineEvent::Complete(line) => self.numbers.check(line),
            LineEvent::TooLong { len } => self.numbers.too_long(*len),
        };
        let mut acked = false;
        match checked {
            Checked::Repeat => {}
            Checked::Resend {
                refusal,
                last,
                resend,
            } => {
                let resend = self.numbers.host_numbers_lines().then_some(resend);
                write_refusal(out, refusal, last, resend)?;
            }
            Checked::Run(bytes) => match core::str::from_utf8(bytes) {
                Err(_) => error_line(out, &"line is not valid UTF-8, ignored")?,
                Ok(text) if self.sd.is_uploading() => self.upload(text, card, out)?,
                Ok(text) => {
                    acked =
                        self.command(text, Source::Console, session, no_printer, card, mcu, out)?;
                }
            },
        }
        self.report_shutdown(mcu, out)?;
        if !acked {
            out.write_str("ok\n")?;
        }
        Ok(())
    }

    /// To call whenever woken without a console line: the session's timers
    /// ([`Session::idle`](crate::session::Session::idle), every [`IDLE_PERIOD`] at most), the auto-reports
    /// that are due, and the next line of a file printing from the card.
    // Not inlined: see `line`.
    #[inline(never)]
    pub fn poll(
        &mut self,
        mut session: Option<&mut dyn ConsoleSession<'_>>,
        card: &mut impl Card,
        mcu: &mut impl Mcu,
        out: &mut impl Write,
    ) -> fmt::Result {
        self.report_shutdown(mcu, out)?;
        let now = mcu.now();
        if let Some(session) = session.as_deref_mut()
            && now >= self.idle_due
        {
            session.idle(mcu, out);
            self.idle_due = now + (IDLE_PERIOD * self.freq) as u64;
            if let Some(event) = session.filament_event(mcu, self.sd.is_printing()) {
                self.filament(event, session, card, mcu, out)?;
            }
        }
        if due(&mut self.temperatures, now) {
            mcu.report_temperatures(out)?;
            out.write_char('\n')?;
        }
        if due(&mut self.sd_status, now) {
            self.sd.report(out)?;
        }
        let mut line = heapless::String::<MAX_LINE>::new();
        match self.sd.next_line(card, out) {
            Ok(Some(LineEvent::Complete(bytes))) => match core::str::from_utf8(bytes) {
                Ok(text) => {
                    let _ = line.push_str(text);
                }
                Err(_) => return self.file_error(out, &"line is not valid UTF-8"),
            },
            Ok(Some(LineEvent::TooLong { len })) => {
                return self.file_error(out, &format_args!("line too long ({len} bytes)"));
            }
            Ok(None) => return Ok(()),
            Err(e) => return self.file_error(out, &e),
        }
        let text = strip_comment(&line);
        if text.is_empty() {
            return Ok(());
        }
        let no_printer = ErrorText::new();
        self.command(text, Source::File, session, &no_printer, card, mcu, out)?;
        Ok(())
    }

    /// Reports a shutdown of the MCU role once, when it is seen (an M112,
    /// a heater fault, a step too late), as Klipper does: its hint lines,
    /// then the reason; a print from the card stops.
    fn report_shutdown(&mut self, mcu: &mut impl Mcu, out: &mut impl Write) -> fmt::Result {
        match mcu.shutdown_reason() {
            Some(reason) if !self.shutdown_reported => {
                self.shutdown_reported = true;
                self.sd.reset();
                for hint in reason.hint() {
                    writeln!(out, "// {hint}")?;
                }
                writeln!(out, "// Nothing moves or heats until FIRMWARE_RESTART.")?;
                error_line(out, &reason)
            }
            Some(_) => Ok(()),
            None => {
                self.shutdown_reported = false;
                Ok(())
            }
        }
    }

    /// A filament sensor's event, as Klipper's runout helper: on runout
    /// the print pauses (a print from the card as PAUSE does; a host's
    /// print is told `action:paused`), then the event's G-code runs, each
    /// line as a file line would.
    fn filament(
        &mut self,
        event: FilamentEvent<'_>,
        session: &mut dyn ConsoleSession<'_>,
        card: &mut impl Card,
        mcu: &mut impl Mcu,
        out: &mut impl Write,
    ) -> fmt::Result {
        let gcode = match event {
            FilamentEvent::Runout { pause, gcode } => {
                if pause && self.sd.is_printing() {
                    let _ = self.sd.pause::<()>();
                } else if pause {
                    writeln!(out, "// action:paused")?;
                }
                gcode
            }
            FilamentEvent::Insert { gcode } => Some(gcode),
        };
        let no_printer = ErrorText::new();
        for line in gcode.into_iter().flat_map(str::lines) {
            let line = strip_comment(line);
            if !line.is_empty() {
                self.command(
                    line,
                    Source::File,
                    Some(&mut *session),
                    &no_printer,
                    card,
                    mcu,
                    out,
                )?;
            }
        }
        Ok(())
    }

    /// A file line failed: the print pauses after reporting it (RESUME or
    /// M24 goes on with the next line).
    fn file_error(&mut self, out: &mut impl Write, e: &impl fmt::Display) -> fmt::Result {
        let _ = self.sd.pause::<()>();
        error_line(out, e)?;
        writeln!(out, "// SD print paused")
    }

    /// Between M28 and M29: the line goes to the file.
    fn upload(&mut self, text: &str, card: &mut impl Card, out: &mut impl Write) -> fmt::Result {
        let result = if command_word(text.as_bytes()).eq_ignore_ascii_case(b"M29") {
            self.sd.end_upload(card, out)
        } else {
            self.sd.upload_line(card, text.as_bytes())
        };
        match result {
            Ok(()) => Ok(()),
            Err(e) => error_line(out, &SdError::Card(e)),
        }
    }

    /// Runs one command; returns true if it wrote its own `ok`.
    #[allow(clippy::too_many_arguments)]
    fn command(
        &mut self,
        text: &str,
        from: Source,
        session: Option<&mut dyn ConsoleSession<'_>>,
        no_printer: &ErrorText,
        card: &mut impl Card,
        mcu: &mut impl Mcu,
        out: &mut impl Write,
    ) -> Result<bool, fmt::Error> {
        let (word, rest) = split_word(text);
        let is = |name: &str| word.eq_ignore_ascii_case(name);
        let sd = &mut self.sd;
        let sd_result = if is("M110") || is("M117") || is("M73") || is("M21") {
            if is("M21") {
                writeln!(out, "SD card ok")?;
            }
            Ok(())
        } else if is("M115") {
            writeln!(
                out,
                "FIRMWARE_NAME:{} FIRMWARE_VERSION:{} PROTOCOL_VERSION:1.0 MACHINE_TYPE:{} EXTRUDER_COUNT:1",
                crate::FIRMWARE_NAME,
                crate::FIRMWARE_VERSION,
                crate::FIRMWARE_NAME,
            )?;
            for (name, on) in CAPABILITIES {
                writeln!(out, "Cap:{name}:{}", u8::from(*on))?;
            }
            Ok(())
        } else if is("M105") && from == Source::Console && session.is_some() {
            out.write_str("ok ")?;
            mcu.report_temperatures(out)?;
            out.write_char('\n')?;
            return Ok(true);
        } else if is("M155") {
            self.temperatures = self.every(arg(rest, b'S'), mcu.now());
            Ok(())
        } else if is("M27") {
            match arg(rest, b'S') {
                Some(s) => self.sd_status = self.every(Some(s), mcu.now()),
                None => sd.report(out)?,
            }
            Ok(())
        } else if is("M118") {
            writeln!(out, "echo: {rest}")?;
            Ok(())
        } else if is("M20") {
            let long = rest.split_whitespace().any(|w| w.eq_ignore_ascii_case("L"));
            SdPrint::list(card, long, out).map_err(SdError::Card)
        } else if is("M23") {
            sd.select(card, rest, out)
        } else if is("M24") {
            sd.start()
        } else if is("M25") || is("PAUSE") {
            sd.pause()
        } else if is("RESUME") {
            sd.resume()
        } else if is("M26") {
            match arg(rest, b'S') {
                Some(s) if s >= 0.0 => sd.set_position(s as u32),
                _ => Ok(()),
            }
        } else if is("M28") {
            sd.begin_upload(card, rest, out)
        } else if is("M29") {
            Ok(())
        } else if is("M30") {
            sd.delete(card, rest, out)
        } else if is("SDCARD_RESET_FILE") || is("CANCEL_PRINT") {
            sd.reset();
            Ok(())
        } else if is("SDCARD_PRINT_FILE") {
            match extended_value(rest, "FILENAME") {
                Some(name) => sd.select(card, name, out).and_then(|()| sd.start()),
                None => {
                    error_line(out, &"SDCARD_PRINT_FILE: FILENAME= is required")?;
                    Ok(())
                }
            }
        } else if is("M112") {
            // Reported with the line's answer, as every shutdown.
            mcu.shutdown(Shutdown::EmergencyStop);
            Ok(())
        } else if is("FIRMWARE_RESTART") || is("M999") && mcu.shutdown_reason().is_some() {
            // M999 as Marlin's: a restart after a shutdown, else nothing.
            sd.reset();
            self.restart = true;
            Ok(())
        } else if is("M999") {
            Ok(())
        } else {
            let result = match session {
                Some(session) => session.run(text, mcu, out),
                None => Err(no_printer.clone()),
            };
            if let Err(e) = result {
                error_line(out, &e)?;
                if from == Source::File {
                    let _ = self.sd.pause::<()>();
                    writeln!(out, "// SD print paused")?;
                }
            }
            return Ok(false);
        };
        match sd_result {
            Ok(()) => {}
            Err(e @ SdError::NotFound(_)) => writeln!(out, "{e}")?,
            Err(e) => error_line(out, &e)?,
        }
        Ok(false)
    }

    /// An auto-report every `seconds` s from `now` (None or 0: off).
    fn every(&self, seconds: Option<f64>, now: u64) -> Option<Every> {
        let seconds = seconds.filter(|s| s.is_finite() && *s > 0.0)?;
        let period = (seconds.min(3600.0) * self.freq) as u64;
        Some(Every {
            period,
            next: now + period,
        })
    }
}

/// True if the auto-report `every` is due at `now` (then schedules the
/// next one).
fn due(every: &mut Option<Every>, now: u64) -> bool {
    match every {
        Some(e) if now >= e.next => {
            e.next = now + e.period;
            true
        }
        _ => false,
    }
}

/// The command word and the rest of the line (trimmed).
fn split_word(text: &str) -> (&str, &str) {
    let text = text.trim();
    match text.split_once(|c: char| c.is_ascii_whitespace()) {
        Some((word, rest)) => (word, rest.trim()),
        None => (text, ""),
    }
}

/// A line without its `;` comment.
fn strip_comment(line: &str) -> &str {
    line.split(';').next().unwrap_or_default().trim()
}

/// The number after parameter letter `letter` (`S2` → 2.0).
fn arg(rest: &str, letter: u8) -> Option<f64> {
    rest.split_whitespace().find_map(|word| {
        let (first, value) = word.split_at_checked(1)?;
        first
            .as_bytes()
            .first()
            .is_some_and(|b| b.eq_ignore_ascii_case(&letter))
            .then(|| decimal::parse(value))
            .flatten()
    })
}

/// The value of `KEY=value` in an extended command's parameters.
fn extended_value<'t>(rest: &'t str, key: &str) -> Option<&'t str> {
    rest.split_whitespace().find_map(|word| {
        let (k, v) = word.split_once('=')?;
        k.eq_ignore_ascii_case(key).then_some(v)
    })
}
