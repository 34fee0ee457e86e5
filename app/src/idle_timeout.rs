//! Klipper's idle timeout: a printer left with nothing to do runs the
//! `[idle_timeout]` G-code (by default `TURN_OFF_HEATERS` and `M84`)
//! `timeout` s (600) after its last move finished, so a host that stops
//! talking mid-print does not leave the heaters on.
//!
//! A pure state machine in one time base, seconds of MCU clock (print
//! time is on the same clock). Its states are Klipper's:
//! - **Idle**: nothing pending; only activity wakes it.
//! - **Printing**: activity was noted ([`IdleTimeout::note_activity`]:
//!   a line that used the toolhead's print time, see [`is_activity`]);
//!   once the lookahead is empty and every queued move has finished for
//!   0.5 s, the printer is
//! - **Ready**: once it has been `timeout` s since the last move finished
//!   (and the lookahead is still empty), [`IdleTimeout::poll`] hands out
//!   the idle G-code; after it has run, Idle.
//!
//! The caller polls it whenever no line is running (between lines, while
//! waiting for input) with the toolhead's state, and runs the lines of
//! the G-code it returns like console lines.

use core::fmt::Write;
use onechip_config::decimal::Fixed;
use onechip_planner::gcode::{Command, Line};
use onechip_planner::gcode_move::CommandError;
use onechip_planner::thermal::IdleTimeoutConfig;

/// Time after the last move finished before Printing becomes Ready, s
/// (Klipper's READY_TIMEOUT).
pub const READY_TIMEOUT: f64 = 0.5;
/// Idle time below which a Ready toolhead still counts as busy, s.
const MIN_IDLE_TIME: f64 = 1.0;
/// Longest look ahead at queued print time while Printing, s.
const MAX_BUFFER_TIME: f64 = 2.0;
/// Delay before retrying an idle G-code that failed, s.
const RETRY_TIME: f64 = 1.0;

/// Klipper's idle_timeout states.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IdleState {
    /// Nothing to do, and the idle G-code has run (or nothing happened
    /// since power-on).
    Idle,
    /// Done printing; the idle G-code runs `timeout` s after the last move
    /// finished.
    Ready,
    /// Moves or heater commands are under way (or the idle G-code is
    /// running).
    Printing,
}

impl IdleState {
    /// The state's name as Klipper reports it (`idle_timeout.state`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Idle => "Idle",
            Self::Ready => "Ready",
            Self::Printing => "Printing",
        }
    }
}

/// What the toolhead is doing at a poll (Klipper's `check_busy`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolheadState {
    /// Print time at the end of everything queued, s (same clock as
    /// `now`).
    pub print_time: f64,
    /// No move waits in the lookahead to be planned.
    pub lookahead_empty: bool,
}

/// The idle G-code to run: one command a line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct IdleGcode<'a>(pub &'a str);

impl<'a> IdleGcode<'a> {
    /// Its commands, trimmed, blank lines skipped.
    pub fn lines(self) -> impl Iterator<Item = &'a str> {
        self.0.lines().map(str::trim).filter(|l| !l.is_empty())
    }
}

/// The idle timeout of one printer.
#[derive(Debug, Clone, PartialEq)]
pub struct IdleTimeout<'a> {
    /// Idle time before the G-code runs, s.
    timeout: f64,
    gcode: &'a str,
    state: IdleState,
    /// When the timer runs next, s (infinite: never).
    check_at: f64,
    /// When the state last became Printing, s.
    print_start: f64,
}

impl<'a> IdleTimeout<'a> {
    /// Idle, as at power-on, with `config`'s timeout and G-code.
    pub fn new(config: &IdleTimeoutConfig<'a>) -> Self {
        Self {
            timeout: config.timeout,
            gcode: config.gcode,
            state: IdleState::Idle,
            check_at: f64::INFINITY,
            print_start: 0.0,
        }
    }

    /// The state now.
    pub fn state(&self) -> IdleState {
        self.state
    }

    /// The idle timeout, s.
    pub fn timeout(&self) -> f64 {
        self.timeout
    }

    /// Time since the state became Printing (0 unless Printing), s.
    pub fn printing_time(&self, now: f64) -> f64 {
        match self.state {
            IdleState::Printing => now - self.print_start,
            _ => 0.0,
        }
    }

    /// When [`Self::poll`] has something to do next, s (None: only after
    /// activity).
    pub fn next_check(&self) -> Option<f64> {
        self.check_at.is_finite().then_some(self.check_at)
    }

    /// A line used print time at `now` (s), with everything queued ending
    /// at `print_time` (s): Klipper's `toolhead:sync_print_time`. From Idle
    /// or Ready the state becomes Printing; while Printing (also while the
    /// idle G-code runs) nothing changes.
    pub fn note_activity(&mut self, now: f64, print_time: f64) {
        if self.state == IdleState::Printing {
            return;
        }
        self.state = IdleState::Printing;
        self.print_start = now;
        self.check_at = print_time + READY_TIMEOUT;
    }

    /// Klipper's idle timer at `now` (s), if due, against `toolhead`:
    /// Printing becomes Ready, or Ready hands out the idle G-code (the
    /// state is Printing until [`Self::idle_gcode_done`]). Call it whenever
    /// no line is running; it does nothing before [`Self::next_check`].
    pub fn poll(&mut self, now: f64, toolhead: ToolheadState) -> Option<IdleGcode<'a>> {
        if now < self.check_at {
            return None;
        }
        let ToolheadState {
            print_time,
            lookahead_empty,
        } = toolhead;
        match self.state {
            IdleState::Ready => {
                let idle_time = now - print_time;
                if !lookahead_empty || idle_time < MIN_IDLE_TIME {
                    self.check_at = now + self.timeout;
                } else if idle_time < self.timeout {
                    self.check_at = now + self.timeout - idle_time;
                } else {
                    // Printing while the G-code runs, as Klipper.
                    self.state = IdleState::Printing;
                    self.print_start = now;
                    self.check_at = f64::INFINITY;
                    return Some(IdleGcode(self.gcode));
                }
            }
            IdleState::Printing => {
                let buffer_time = (print_time - now).min(MAX_BUFFER_TIME);
                if !lookahead_empty {
                    self.check_at = now + READY_TIMEOUT + buffer_time.max(0.0);
                } else if buffer_time > -READY_TIMEOUT {
                    self.check_at = now + READY_TIMEOUT + buffer_time;
                } else {
                    self.state = IdleState::Ready;
                    self.check_at = now + self.timeout;
                }
            }
            IdleState::Idle => self.check_at = f64::INFINITY,
        }
        None
    }

    /// The idle G-code handed out by [`Self::poll`] has run at `now` (s):
    /// Idle if every line succeeded, else Ready again, retried a second
    /// later (as Klipper).
    pub fn idle_gcode_done(&mut self, now: f64, ok: bool) {
        if ok {
            self.state = IdleState::Idle;
            self.check_at = f64::INFINITY;
        } else {
            self.state = IdleState::Ready;
            self.check_at = now + RETRY_TIME;
        }
    }

    /// Sets the timeout to `timeout` s at `now` (s); when Ready, the next
    /// check is `timeout` s from now.
    pub fn set_timeout(&mut self, now: f64, timeout: f64) {
        self.timeout = timeout;
        if self.state == IdleState::Ready {
            self.check_at = now + timeout;
        }
    }

    /// Carries out `SET_IDLE_TIMEOUT [TIMEOUT=<s>]` at `now` (s), replying
    /// on `out` as Klipper does; Ok(false) if `line` is another command.
    pub fn command<'l>(
        &mut self,
        line: &Line<'l>,
        now: f64,
        out: &mut impl Write,
    ) -> Result<bool, CommandError<'l>> {
        let Command::Extended(e) = line.command else {
            return Ok(false);
        };
        if !e.name.eq_ignore_ascii_case("SET_IDLE_TIMEOUT") {
            return Ok(false);
        }
        let timeout = e.float("TIMEOUT")?.unwrap_or(self.timeout);
        if timeout <= 0.0 || !timeout.is_finite() {
            return Err(CommandError::Invalid {
                param: "TIMEOUT",
                rule: "must be above 0",
            });
        }
        self.set_timeout(now, timeout);
        let _ = writeln!(
            out,
            "// idle_timeout: Timeout set to {} s",
            Fixed(timeout, 2)
        );
        Ok(true)
    }
}

/// Commands that use the toolhead's print time, after which the caller
/// notes activity ([`IdleTimeout::note_activity`]): moves, dwells and
/// waits, homing, setting the position, and heater and fan commands (in
/// Klipper they all sync print time). Queries (M105, M114, M115, ...)
/// are not activity: a host polling temperatures does not keep an idle
/// printer's heaters on.
pub fn is_activity(line: &Line<'_>) -> bool {
    match line.command {
        Command::Traditional(t) => matches!(
            (t.letter, t.number),
            (b'G', 0..=4 | 28) | (b'M', 18 | 84 | 104 | 106 | 107 | 109 | 140 | 190 | 400)
        ),
        Command::Extended(e) => [
            "SET_HEATER_TEMPERATURE",
            "TURN_OFF_HEATERS",
            "TEMPERATURE_WAIT",
            "SET_FAN_SPEED",
            "SET_KINEMATIC_POSITION",
            "SET_GCODE_OFFSET",
            "FORCE_MOVE",
            "MANUAL_STEPPER",
        ]
        .iter()
        .any(|name| e.name.eq_ignore_ascii_case(name)),
        Command::Empty => false,
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use onechip_planner::gcode;
    use std::string::String;
    use std::vec::Vec;

    fn defaults() -> IdleTimeout<'static> {
        IdleTimeout::new(&IdleTimeoutConfig::default())
    }

    /// The toolhead with every move queued ending at `print_time` s and
    /// none waiting in the lookahead.
    fn done_at(print_time: f64) -> ToolheadState {
        ToolheadState {
            print_time,
            lookahead_empty: true,
        }
    }

    /// Polls every `step` s from `from` to `to` with `toolhead(now)`; the
    /// time and G-code of the first poll that hands out the idle G-code.
    fn first_fire(
        idle: &mut IdleTimeout<'static>,
        from: f64,
        to: f64,
        step: f64,
        toolhead: impl Fn(f64) -> ToolheadState,
    ) -> Option<(f64, Vec<&'static str>)> {
        let mut now = from;
        while now <= to {
            if let Some(gcode) = idle.poll(now, toolhead(now)) {
                return Some((now, gcode.lines().collect()));
            }
            now += step;
        }
        None
    }

    #[test]
    fn klippers_defaults_and_nothing_happens_until_activity() {
        let mut idle = defaults();
        assert_eq!(idle.timeout(), 600.0);
        assert_eq!(
            IdleGcode(IdleTimeoutConfig::default().gcode)
                .lines()
                .collect::<Vec<_>>(),
            ["TURN_OFF_HEATERS", "M84"]
        );
        assert_eq!(idle.state(), IdleState::Idle);
        assert_eq!(idle.next_check(), None);
        assert_eq!(first_fire(&mut idle, 0.0, 5000.0, 1.0, done_at), None);
        assert_eq!(idle.state(), IdleState::Idle);
    }

    #[test]
    fn a_host_that_stops_talking_mid_print_gets_its_heaters_off_600_s_after_the_last_move() {
        let mut idle = defaults();
        // Lines arrive from t = 10 s; the last at t = 100 s queues moves
        // that finish at t = 120 s, then the host goes silent. The printer
        // polls every 10 ms while waiting for input.
        idle.note_activity(10.0, 10.25);
        assert_eq!(idle.state(), IdleState::Printing);
        let toolhead = |now: f64| ToolheadState {
            print_time: if now < 100.0 { now + 2.0 } else { 120.0 },
            lookahead_empty: now >= 100.1,
        };
        let (at, gcode) = first_fire(&mut idle, 10.0, 2000.0, 0.01, toolhead).expect("fires");
        assert_eq!(gcode, ["TURN_OFF_HEATERS", "M84"]);
        // Ready 0.5 s after the last move, then the 600 s timeout.
        assert!((720.0..=720.6).contains(&at), "{at}");
        assert_eq!(idle.state(), IdleState::Printing);
        // While the idle G-code runs, its own lines are no new activity.
        idle.note_activity(at, 121.0);
        idle.idle_gcode_done(at, true);
        assert_eq!(idle.state(), IdleState::Idle);
        assert_eq!(first_fire(&mut idle, at, 5000.0, 1.0, done_at), None);
    }

    #[test]
    fn the_state_follows_the_moves() {
        let mut idle = defaults();
        idle.note_activity(0.0, 0.25);
        // Moves queued to t = 30 s: Printing until 0.5 s after they end.
        assert_eq!(idle.poll(0.75, done_at(30.0)), None);
        assert_eq!(idle.state(), IdleState::Printing);
        assert_eq!(idle.printing_time(10.0), 10.0);
        // (Polled every 0.25 s: exact times.)
        let ready = first_fire(&mut idle, 0.75, 31.0, 0.25, |_| done_at(30.0));
        assert_eq!(ready, None);
        assert_eq!(idle.state(), IdleState::Ready);
        assert_eq!(idle.printing_time(31.0), 0.0);
        // A move waiting in the lookahead keeps a Ready printer from
        // timing out; the timer looks again a timeout later.
        let waiting = ToolheadState {
            print_time: 30.0,
            lookahead_empty: false,
        };
        assert_eq!(idle.poll(630.5, waiting), None);
        assert_eq!(idle.state(), IdleState::Ready);
        assert_eq!(idle.next_check(), Some(1230.5));
        assert!(idle.poll(1230.5, done_at(30.0)).is_some());
    }

    #[test]
    fn activity_while_ready_starts_over() {
        let mut idle = defaults();
        idle.note_activity(0.0, 0.25);
        assert_eq!(first_fire(&mut idle, 0.0, 400.0, 0.1, done_at_10), None);
        assert_eq!(idle.state(), IdleState::Ready);
        // At 400 s a heater command (no moves: print time stays 10 s).
        idle.note_activity(400.0, 10.0);
        assert_eq!(idle.state(), IdleState::Printing);
        let (at, _) = first_fire(&mut idle, 400.0, 2000.0, 0.1, done_at_10).expect("fires");
        // Ready at once, then a whole timeout from there.
        assert!((1000.0..1000.2).contains(&at), "{at}");
    }

    fn done_at_10(_: f64) -> ToolheadState {
        done_at(10.0)
    }

    #[test]
    fn a_failed_idle_gcode_is_retried_a_second_later() {
        let mut idle = defaults();
        idle.note_activity(0.0, 0.0);
        let (at, _) = first_fire(&mut idle, 0.0, 700.0, 0.5, done_at_10).expect("fires");
        idle.idle_gcode_done(at, false);
        assert_eq!(idle.state(), IdleState::Ready);
        assert_eq!(idle.poll(at + 0.9, done_at(10.0)), None);
        assert!(idle.poll(at + 1.0, done_at(10.0)).is_some());
    }

    #[test]
    fn set_idle_timeout_replies_as_klipper_and_reschedules_a_ready_printer() {
        let mut idle = defaults();
        let mut out = String::new();
        let mut run = |idle: &mut IdleTimeout<'static>, text: &str, now: f64| {
            let line = gcode::parse(text).expect("parses");
            idle.command(&line, now, &mut out)
                .map_err(|e| std::string::ToString::to_string(&e))
        };
        assert_eq!(run(&mut idle, "M105", 0.0), Ok(false));
        idle.note_activity(0.0, 0.0);
        assert_eq!(idle.poll(1.0, done_at(0.0)), None);
        assert_eq!(idle.state(), IdleState::Ready);
        assert_eq!(run(&mut idle, "SET_IDLE_TIMEOUT TIMEOUT=30", 5.0), Ok(true));
        assert_eq!(idle.timeout(), 30.0);
        assert_eq!(idle.next_check(), Some(35.0));
        assert!(idle.poll(35.0, done_at(0.0)).is_some());
        assert_eq!(
            run(&mut idle, "set_idle_timeout timeout=0", 40.0),
            Err("TIMEOUT must be above 0".into())
        );
        assert_eq!(run(&mut idle, "SET_IDLE_TIMEOUT", 40.0), Ok(true));
        assert_eq!(
            out,
            "// idle_timeout: Timeout set to 30.00 s\n// idle_timeout: Timeout set to 30.00 s\n"
        );
    }

    #[test]
    fn queries_are_not_activity() {
        let activity = |text: &str| is_activity(&gcode::parse(text).expect("parses"));
        for text in [
            "G1 X10",
            "G28",
            "G4 P100",
            "M104 S200",
            "M190 S60",
            "M106 S255",
            "M400",
            "turn_off_heaters",
        ] {
            assert!(activity(text), "{text}");
        }
        for text in ["M105", "M114", "M115", "M27", "G90", "SET_IDLE_TIMEOUT", ""] {
            assert!(!activity(text), "{text}");
        }
    }
}
