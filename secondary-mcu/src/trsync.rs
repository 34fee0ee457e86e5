//! Homing across MCUs, as klippy's `MCU_trsync` and trigger dispatch do
//! it: every MCU taking part runs a `trsync` that stops its steppers when
//! it triggers; the endstop's MCU triggers its own when the endstop is
//! hit; each MCU reports `trsync_state` every [`REPORT_FRACTION`] of
//! [`TIMEOUT`], and the host relays: a report that still can trigger moves
//! every MCU's timeout on (an MCU that hears nothing for [`TIMEOUT`] stops
//! by itself), a report that has triggered triggers every other MCU.
//!
//! The main MCU takes part as one more member ([`Member::local`]), as
//! klippy's main MCU does: its "reports" are the host's own news (it is
//! alive while the host serves the links), its timeout is kept by the
//! host, and its trigger is the engine's stop ([`Relay::Triggered`] lists
//! only the secondaries' commands; the host stops the main's steppers
//! itself when another member triggered).
//!
//! Sans I/O: [`Dispatch`] takes the reports and returns the commands to
//! send, as text for each MCU's dictionary; times are host seconds.

use crate::clock_sync::ClockSync;
use core::fmt::Write;

/// Why a trsync triggered (klippy's `REASON_*`).
pub mod reason {
    /// The endstop was hit.
    pub const ENDSTOP_HIT: u8 = 1;
    /// No report relayed in time: the MCU stopped by itself.
    pub const COMMS_TIMEOUT: u8 = 2;
    /// The host asked (another MCU triggered, or homing ended).
    pub const HOST_REQUEST: u8 = 3;
    /// The homing move ended without a trigger.
    pub const PAST_END_TIME: u8 = 4;
}

/// How long an MCU may go without a relayed report before it stops its
/// steppers, s (klippy's `TRSYNC_TIMEOUT`).
pub const TIMEOUT: f64 = 0.025;
/// The same with one MCU only (klippy's `TRSYNC_SINGLE_MCU_TIMEOUT`).
pub const SINGLE_MCU_TIMEOUT: f64 = 0.250;
/// Share of the timeout between two reports of an MCU.
pub const REPORT_FRACTION: f64 = 0.4;
/// Most MCUs one homing spans.
pub const MAX_MCUS: usize = 4;

/// One command line (`trsync_start oid=…`), text of the MCU's dictionary.
pub type Line = heapless::String<96>;

/// One MCU's part in a homing.
#[derive(Debug, Clone, Copy)]
pub struct Member {
    /// Its trsync's object id.
    pub trsync: u8,
    /// Its clock, for converting times.
    pub sync: ClockSync,
    /// Host time of its last report that could still trigger (or of the
    /// start), s.
    last_report: f64,
    /// Host time its trsync expires at, as last sent, s.
    expire: f64,
    /// The main MCU (no command lines: the host acts on it directly).
    local: bool,
    /// Its clock at the homing's start (its trsync's first report), ticks.
    start_clock: u64,
    /// A report of this homing came: every later one is (the link keeps
    /// their order).
    current: bool,
}

impl Member {
    /// The MCU with trsync `trsync` and clock `sync`.
    pub fn new(trsync: u8, sync: ClockSync) -> Self {
        Self {
            trsync,
            sync,
            last_report: 0.0,
            expire: 0.0,
            local: false,
            start_clock: 0,
            current: false,
        }
    }

    /// The main MCU, whose clock of `freq` Hz is host time (host time is
    /// the main clock in seconds): no lines are made for it; the host
    /// gives its news with [`Dispatch::on_news`], reads its timeout with
    /// [`Dispatch::expire`] and stops its steppers itself.
    pub fn local(freq: f64) -> Self {
        Self {
            local: true,
            ..Self::new(u8::MAX, ClockSync::new(freq, 0, 0.0))
        }
    }

    /// True for the main MCU ([`Self::local`]).
    pub fn is_local(&self) -> bool {
        self.local
    }
}

/// What the host must send after a report.
#[derive(Debug, Clone, PartialEq)]
pub enum Relay {
    /// Nothing.
    None,
    /// Every MCU's new timeout, `(member, line)` each.
    Extend(heapless::Vec<(usize, Line), MAX_MCUS>),
    /// An MCU triggered at host time `.0` (s) for reason `.1`: the
    /// `trsync_trigger` for every other one but the main MCU,
    /// `(member, line)` each.
    Triggered(f64, u8, heapless::Vec<(usize, Line), MAX_MCUS>),
}

/// A homing's trsyncs on every MCU taking part.
#[derive(Debug, Clone)]
pub struct Dispatch {
    members: heapless::Vec<Member, MAX_MCUS>,
    /// Host time and reason of the first trigger, once one came.
    triggered: Option<(f64, u8)>,
}

impl Dispatch {
    /// A homing over `members` (at most [`MAX_MCUS`]; more are left out)
    /// whose trsyncs start at host time `start` (s): until each reports,
    /// its news is that start, as klippy's dispatch counts it.
    pub fn new(members: &[Member], start: f64) -> Self {
        let mut all = heapless::Vec::new();
        for m in members.iter().take(MAX_MCUS) {
            let _ = all.push(Member {
                last_report: start,
                start_clock: m.sync.clock_at(start),
                expire: start
                    + if members.len() > 1 {
                        TIMEOUT
                    } else {
                        SINGLE_MCU_TIMEOUT
                    },
                ..*m
            });
        }
        Self {
            members: all,
            triggered: None,
        }
    }

    /// The timeout the MCUs run with, s.
    pub fn timeout(&self) -> f64 {
        if self.members.len() > 1 {
            TIMEOUT
        } else {
            SINGLE_MCU_TIMEOUT
        }
    }

    /// The commands that start member `index`'s trsync at host time
    /// `start` (s), before its steppers are tied to it and its endstop
    /// armed: `trsync_start` (reports every [`REPORT_FRACTION`] of the
    /// timeout, `COMMS_TIMEOUT` when it expires) and `trsync_set_timeout`.
    pub fn start_lines(&self, index: usize, start: f64) -> [Line; 2] {
        let mut lines = [Line::new(), Line::new()];
        if let Some(m) = self.members.get(index).filter(|m| !m.local) {
            let freq = m.sync.mcu_freq();
            let report_ticks = (self.timeout() * REPORT_FRACTION * freq) as u32;
            let clock = m.sync.clock_at(start) as u32;
            let expire = m.sync.clock_at(start + self.timeout()) as u32;
            let _ = write!(
                lines[0],
                "trsync_start oid={} report_clock={clock} report_ticks={report_ticks} expire_reason={}",
                m.trsync,
                reason::COMMS_TIMEOUT
            );
            let _ = write!(
                lines[1],
                "trsync_set_timeout oid={} clock={expire}",
                m.trsync
            );
        }
        lines
    }

    /// The first trigger: host time (s) and reason.
    pub fn triggered(&self) -> Option<(f64, u8)> {
        self.triggered
    }

    /// The homing ends untriggered at host time `at` (s; its move ran to
    /// its end): every secondary's trsync is triggered ([`reason::HOST_REQUEST`]),
    /// the `trsync_trigger` lines as for a trigger. Nothing once triggered.
    pub fn end(&mut self, at: f64) -> Relay {
        if self.triggered.is_some() {
            return Relay::None;
        }
        self.triggered = Some((at, reason::HOST_REQUEST));
        Relay::Triggered(at, reason::HOST_REQUEST, self.trigger_lines(None))
    }

    /// `trsync_trigger` ([`reason::HOST_REQUEST`]) for every secondary but
    /// member `except`, `(member, line)` each.
    fn trigger_lines(&self, except: Option<usize>) -> heapless::Vec<(usize, Line), MAX_MCUS> {
        let mut lines = heapless::Vec::new();
        let others = self.members.iter().enumerate();
        for (j, m) in others.filter(|(j, m)| Some(*j) != except && !m.local) {
            let mut line = Line::new();
            let _ = write!(
                line,
                "trsync_trigger oid={} reason={}",
                m.trsync,
                reason::HOST_REQUEST
            );
            let _ = lines.push((j, line));
        }
        lines
    }

    /// Host time (s) member `index`'s trsync expires at, as last set: the
    /// main MCU ([`Member::local`]) stops its steppers by itself
    /// ([`reason::COMMS_TIMEOUT`]) once the host's time passes it.
    pub fn expire(&self, index: usize) -> Option<f64> {
        self.members.get(index).map(|m| m.expire)
    }

    /// Takes a report of member `index` at `clock` (32-bit, on its MCU):
    /// false if it was sent before its `trsync_start` reached it (the
    /// previous homing's state, still on its way), which says nothing of
    /// this homing. The first report of this homing is its trsync's first
    /// periodic one, at the start's clock (or later); the link keeps their
    /// order, so every report after it is current too (a trigger's reply
    /// to `trsync_trigger` says clock 0).
    pub fn is_current(&mut self, index: usize, clock: u32) -> bool {
        let Some(m) = self.members.get_mut(index) else {
            return false;
        };
        m.current |= m.sync.widen(clock) >= m.start_clock;
        m.current
    }

    /// Takes member `index`'s `trsync_state can_trigger=… trigger_reason=…
    /// clock=…` (`clock` 32-bit on its MCU): what to relay (nothing for a
    /// stale one, see [`Self::is_current`]).
    pub fn on_state(&mut self, index: usize, can_trigger: bool, why: u8, clock: u32) -> Relay {
        if !self.is_current(index, clock) {
            return Relay::None;
        }
        let Some(m) = self.members.get(index) else {
            return Relay::None;
        };
        let at = m.sync.time_at(m.sync.widen(clock));
        self.on_news(index, can_trigger, why, at)
    }

    /// Member `index`'s news at host time `at` (s): it can still trigger,
    /// or it triggered for reason `why` (the main MCU's news, or a report
    /// already converted to host time); what to relay.
    pub fn on_news(&mut self, index: usize, can_trigger: bool, why: u8, at: f64) -> Relay {
        let Some(m) = self.members.get_mut(index) else {
            return Relay::None;
        };
        if !can_trigger {
            if self.triggered.is_some() {
                return Relay::None;
            }
            self.triggered = Some((at, why));
            return Relay::Triggered(at, why, self.trigger_lines(Some(index)));
        }
        if self.triggered.is_some() {
            return Relay::None;
        }
        m.last_report = m.last_report.max(at);
        // Each MCU may run until the oldest news of the others, plus the
        // timeout (none outlives a silent one by more than that; its own
        // news says nothing of the others), and is told only when that
        // moves it on by most of a report period, as klippy's dispatch.
        let timeout = self.timeout();
        let min_extend = timeout * REPORT_FRACTION * 0.8;
        let news: heapless::Vec<f64, MAX_MCUS> =
            self.members.iter().map(|m| m.last_report).collect();
        let mut lines = heapless::Vec::new();
        for (j, m) in self.members.iter_mut().enumerate() {
            let others = news
                .iter()
                .enumerate()
                .filter(|(k, _)| *k != j || news.len() == 1)
                .map(|(_, t)| *t)
                .fold(f64::INFINITY, f64::min);
            let expire = others + timeout;
            if expire - m.expire < min_extend {
                continue;
            }
            m.expire = expire;
            if m.local {
                continue;
            }
            let mut line = Line::new();
            let clock = m.sync.clock_at(expire) as u32;
            let _ = write!(line, "trsync_set_timeout oid={} clock={clock}", m.trsync);
            let _ = lines.push((j, line));
        }
        if lines.is_empty() {
            return Relay::None;
        }
        Relay::Extend(lines)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The clock a `trsync_set_timeout` line names.
    fn clock(line: &Line) -> f64 {
        let value = line.as_str().rsplit('=').next().unwrap_or("");
        value.parse().unwrap_or(f64::NAN)
    }

    fn member(trsync: u8, freq: f64) -> Member {
        Member::new(trsync, ClockSync::new(freq, 0, 0.0))
    }

    #[test]
    fn a_trigger_on_one_mcu_triggers_every_other_once() {
        let mut d = Dispatch::new(&[member(3, 50e6), member(1, 16e6), member(7, 16e6)], 0.0);
        let Relay::Triggered(at, why, lines) = d.on_state(1, false, reason::ENDSTOP_HIT, 16_000)
        else {
            panic!("no trigger");
        };
        assert!((at - 0.001).abs() < 1e-9);
        assert_eq!(why, reason::ENDSTOP_HIT);
        let lines: heapless::Vec<(usize, &str), 4> =
            lines.iter().map(|(j, l)| (*j, l.as_str())).collect();
        assert_eq!(
            lines,
            [
                (0, "trsync_trigger oid=3 reason=3"),
                (2, "trsync_trigger oid=7 reason=3")
            ]
        );
        assert_eq!(d.on_state(0, false, reason::HOST_REQUEST, 0), Relay::None);
    }

    #[test]
    fn a_report_from_before_the_start_is_stale() {
        let mut d = Dispatch::new(&[member(3, 50e6), member(1, 16e6)], 2.0);
        // The previous homing's "triggered", sent before trsync_start.
        assert_eq!(
            d.on_state(0, false, reason::ENDSTOP_HIT, 99_000_000),
            Relay::None
        );
        assert_eq!(d.triggered(), None);
        assert!(!d.is_current(0, 99_000_000));
        assert_eq!(d.on_state(0, true, 0, 100_000_000), Relay::None);
        // From its first report of this homing on, every one counts.
        assert!(d.is_current(0, 0));
        assert!(matches!(
            d.on_state(0, false, reason::ENDSTOP_HIT, 0),
            Relay::Triggered(..)
        ));
    }

    #[test]
    fn reports_move_each_timeout_to_the_others_oldest_news_plus_the_timeout() {
        let mut d = Dispatch::new(&[member(0, 50e6), member(1, 16e6)], 0.5);
        // The 50 MHz one reports at 1 s: the other may run until then +
        // 25 ms; its own timeout waits for the other's news.
        let Relay::Extend(lines) = d.on_state(0, true, 0, 50_000_000) else {
            panic!("no extension");
        };
        assert_eq!(lines.len(), 1);
        assert_eq!(lines[0].0, 1);
        assert!((clock(&lines[0].1) - 1.025 * 16e6).abs() <= 1.0);
        // The 16 MHz one reports at 2 s: the first may run until 2.025 s.
        let Relay::Extend(lines) = d.on_state(1, true, 0, 32_000_000) else {
            panic!("no extension");
        };
        assert_eq!(lines.len(), 1);
        assert!(lines[0].1.starts_with("trsync_set_timeout oid=0 clock="));
        assert!((clock(&lines[0].1) - 2.025 * 50e6).abs() <= 1.0);
        // A report that moves nothing on sends nothing.
        assert_eq!(d.on_state(1, true, 0, 32_000_001), Relay::None);
    }

    #[test]
    fn the_main_mcu_takes_part_without_lines_and_keeps_its_own_timeout() {
        let mut d = Dispatch::new(&[Member::local(260e6), member(4, 16e6)], 1.0);
        assert!(d.start_lines(0, 1.0).iter().all(|l| l.is_empty()));
        assert!(d.start_lines(1, 1.0)[0].starts_with("trsync_start oid=4 "));
        assert_eq!(d.expire(0), Some(1.0 + TIMEOUT));
        // The host's news moves the secondary's timeout on (a line for it
        // alone); the secondary's report moves the main's (no line).
        let Relay::Extend(lines) = d.on_news(0, true, 0, 1.010) else {
            panic!("no extension");
        };
        assert_eq!(lines.len(), 1);
        assert_eq!(lines[0].0, 1);
        assert!((clock(&lines[0].1) - 1.035 * 16e6).abs() <= 1.0);
        assert_eq!(d.on_state(1, true, 0, 16_160_000), Relay::None);
        assert!((d.expire(0).unwrap_or(0.0) - 1.035).abs() < 1e-9);
        // The secondary's trigger: nothing to send (the host stops the
        // main MCU's steppers itself).
        let Relay::Triggered(at, why, lines) =
            d.on_state(1, false, reason::ENDSTOP_HIT, 16_320_000)
        else {
            panic!("no trigger");
        };
        assert!((at - 1.02).abs() < 1e-9);
        assert_eq!(why, reason::ENDSTOP_HIT);
        assert!(lines.is_empty());
        // The main's trigger goes to every secondary.
        let mut d = Dispatch::new(&[member(4, 16e6), Member::local(260e6)], 1.0);
        let Relay::Triggered(_, _, lines) = d.on_news(1, false, reason::ENDSTOP_HIT, 1.5) else {
            panic!("no trigger");
        };
        assert_eq!(lines.len(), 1);
        assert_eq!(
            lines[0],
            (
                0,
                Line::try_from("trsync_trigger oid=4 reason=3").unwrap_or_default()
            )
        );
    }
}
