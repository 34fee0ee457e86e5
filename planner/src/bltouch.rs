//! The BLTouch: a probe whose pin a servo signal on `control_pin` lowers
//! and raises, timed as Klipper's `bltouch` module times it. Each command
//! is a pulse of its width repeated every [`SIGNAL_PERIOD`], held for at
//! least [`MIN_CMD_TIME`] (longer for the pin's moves: `pin_move_time`),
//! then the signal goes off; the next command starts no earlier than the
//! end of this one's action and [`MIN_CMD_TIME`] after its signal stopped.
//! The toolhead waits (a dwell) for the pin before it moves.

use crate::move_sink::MoveSink;
use crate::reader::{Read, Reader};
use crate::toolhead::Toolhead;
use onechip_config::Bounds;

/// Servo signal period, s.
pub const SIGNAL_PERIOD: f64 = 0.020;
/// Shortest time a command's signal is held, s.
pub const MIN_CMD_TIME: f64 = 5.0 * SIGNAL_PERIOD;
/// Time between two tests of the sensor (pin up, touch mode: it must read
/// triggered), s.
pub const TEST_TIME: f64 = 5.0 * 60.0;
/// How long a reset is held before the pin is raised again, s.
const RETRY_RESET_TIME: f64 = 1.0;
/// After a command's action, how long the sensor is given to read as it
/// should, s (Klipper's check of the sensor state).
const VERIFY_WINDOW: f64 = 0.100;
/// Tries to raise the pin before [`NOT_RAISED`].
const RAISE_TRIES: usize = 3;
/// Klipper's error when the sensor does not read triggered in touch mode
/// with the pin up (a clone that cannot: `pin_up_touch_mode_reports_triggered:
/// False`).
pub const NOT_VERIFIED: &str = "BLTouch failed to verify sensor state";
/// Klipper's error when the sensor still reads triggered after the pin
/// was raised [`RAISE_TRIES`] times.
pub const NOT_RAISED: &str = "BLTouch failed to raise probe";
/// Klipper's note before it resets the BLTouch and raises the pin again.
const RAISE_RETRY: &str = "// Failed to verify BLTouch probe is raised; retrying.";

/// A BLTouch command (Klipper's names, `BLTOUCH_DEBUG COMMAND=`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Command {
    /// Lower the pin.
    PinDown,
    /// Touch switch mode (the pin stays down, the output is a switch).
    TouchMode,
    /// Raise the pin.
    PinUp,
    /// The BLTouch's self-test.
    SelfTest,
    /// Clear an alarm.
    Reset,
    /// Output in 5 V logic.
    Set5vOutputMode,
    /// Open-drain output.
    SetOdOutputMode,
    /// Store the output mode.
    OutputModeStore,
}

impl Command {
    /// Every command, in Klipper's (sorted) order of names.
    pub const ALL: [Self; 8] = [
        Self::OutputModeStore,
        Self::PinDown,
        Self::PinUp,
        Self::Reset,
        Self::SelfTest,
        Self::Set5vOutputMode,
        Self::SetOdOutputMode,
        Self::TouchMode,
    ];

    /// The pulse width that selects it, s.
    pub fn pulse_width(self) -> f64 {
        match self {
            Self::PinDown => 0.000_650,
            Self::TouchMode => 0.001_165,
            Self::PinUp => 0.001_475,
            Self::SelfTest => 0.001_780,
            Self::Reset => 0.002_190,
            Self::Set5vOutputMode => 0.001_988,
            Self::SetOdOutputMode => 0.002_091,
            Self::OutputModeStore => 0.001_884,
        }
    }

    /// Klipper's name.
    pub fn name(self) -> &'static str {
        match self {
            Self::PinDown => "pin_down",
            Self::TouchMode => "touch_mode",
            Self::PinUp => "pin_up",
            Self::SelfTest => "self_test",
            Self::Reset => "reset",
            Self::Set5vOutputMode => "set_5V_output_mode",
            Self::SetOdOutputMode => "set_OD_output_mode",
            Self::OutputModeStore => "output_mode_store",
        }
    }

    /// The command named `name`.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|c| c.name() == name)
    }
}

/// `[bltouch]`'s own options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BltouchConfig<'a> {
    /// control_pin: the servo signal, as written.
    pub control_pin: &'a str,
    /// pin_move_time: how long the pin takes to move, s.
    pub pin_move_time: f64,
    /// stow_on_each_sample: raise the pin between samples.
    pub stow_on_each_sample: bool,
    /// probe_with_touch_mode: touch mode after lowering the pin.
    pub probe_with_touch_mode: bool,
    /// pin_up_reports_not_triggered.
    pub pin_up_reports_not_triggered: bool,
    /// pin_up_touch_mode_reports_triggered: the sensor can be tested.
    pub pin_up_touch_mode_reports_triggered: bool,
    /// set_output_mode, if set.
    pub output_mode: Option<Command>,
}

/// Reads `[bltouch]`'s own options.
pub(crate) fn read<'a>(section: &Reader<'_, '_, 'a>) -> Read<BltouchConfig<'a>> {
    let output_mode = match section.get_opt("set_output_mode") {
        None => None,
        Some(_) => Some(
            match section.get_choice("set_output_mode", &["5V", "OD"], None)? {
                "5V" => Command::Set5vOutputMode,
                _ => Command::SetOdOutputMode,
            },
        ),
    };
    Ok(BltouchConfig {
        control_pin: section.get("control_pin")?,
        pin_move_time: section.float("pin_move_time", 0.680, Bounds::POSITIVE)?,
        stow_on_each_sample: section.get_bool("stow_on_each_sample", true)?,
        probe_with_touch_mode: section.get_bool("probe_with_touch_mode", false)?,
        pin_up_reports_not_triggered: section.get_bool("pin_up_reports_not_triggered", true)?,
        pin_up_touch_mode_reports_triggered: section
            .get_bool("pin_up_touch_mode_reports_triggered", true)?,
        output_mode,
    })
}

/// The BLTouch's command timing, in print time (s).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Bltouch {
    /// When the next command may start.
    next_cmd_time: f64,
    /// When the last command's action ends.
    action_end_time: f64,
    /// When the sensor is next tested before lowering.
    next_test_time: f64,
}

impl Bltouch {
    /// When the last command's action ends, s.
    pub fn action_end_time(&self) -> f64 {
        self.action_end_time
    }

    /// Sends `cmd` for `duration` s from the next command time: its pulses,
    /// then the signal off.
    pub fn send(&mut self, cmd: Command, duration: f64, sink: &mut impl MoveSink) {
        let start = self.next_cmd_time;
        let held = ((duration - MIN_CMD_TIME) / SIGNAL_PERIOD) as i64 as f64 * SIGNAL_PERIOD;
        let end = start + held.max(MIN_CMD_TIME);
        sink.probe_pin(start, cmd.pulse_width());
        sink.probe_pin(end, 0.0);
        self.action_end_time = start + duration;
        self.next_cmd_time = self.action_end_time.max(end + MIN_CMD_TIME);
    }

    /// Commands start no earlier than [`MIN_CMD_TIME`] after `now` (the
    /// MCU's print time, s).
    fn sync_mcu(&mut self, now: f64) {
        self.next_cmd_time = self.next_cmd_time.max(now + MIN_CMD_TIME);
    }

    /// The toolhead waits for the commands sent, or commands start after
    /// its moves.
    pub fn sync_print_time<const N: usize>(
        &mut self,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
    ) {
        let print_time = toolhead.last_move_time(sink);
        if self.next_cmd_time > print_time {
            toolhead.dwell(self.next_cmd_time - print_time, sink);
        } else {
            self.next_cmd_time = print_time;
        }
    }

    /// Start-up: the output mode if set, then the pin up.
    pub fn connect(&mut self, cfg: &BltouchConfig<'_>, now: f64, sink: &mut impl MoveSink) {
        self.sync_mcu(now);
        self.next_cmd_time += 0.200;
        if let Some(mode) = cfg.output_mode {
            self.send(mode, MIN_CMD_TIME, sink);
        }
        self.raise_signal(cfg, now, sink);
    }

    fn raise_signal(&mut self, cfg: &BltouchConfig<'_>, now: f64, sink: &mut impl MoveSink) {
        self.sync_mcu(now);
        if !cfg.pin_up_reports_not_triggered {
            self.send(Command::Reset, MIN_CMD_TIME, sink);
        }
        self.send(Command::PinUp, cfg.pin_move_time, sink);
    }

    /// True if the sensor reads `triggered` within [`VERIFY_WINDOW`] of
    /// the last command's action end, the moves before all run; commands
    /// then start after the MCU's time at the check's end.
    fn verify<const N: usize>(
        &mut self,
        triggered: bool,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
    ) -> bool {
        toolhead.flush_step_generation(sink);
        let from = self.action_end_time;
        let (read, ended) = sink.probe_reads(from, from + VERIFY_WINDOW, triggered);
        self.sync_mcu(ended);
        read
    }

    /// Before a probing move: the sensor test if due (pin up, touch mode:
    /// it must read triggered, else [`NOT_VERIFIED`]), then the pin down
    /// (and touch mode); the toolhead waits for it.
    pub fn lower<const N: usize>(
        &mut self,
        cfg: &BltouchConfig<'_>,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
    ) -> Result<(), &'static str> {
        if cfg.pin_up_touch_mode_reports_triggered {
            let print_time = toolhead.last_move_time(sink);
            if print_time < self.next_test_time {
                self.next_test_time = print_time + TEST_TIME;
            } else {
                self.sync_print_time(toolhead, sink);
                self.send(Command::PinUp, cfg.pin_move_time, sink);
                self.send(Command::TouchMode, MIN_CMD_TIME, sink);
                let verified = self.verify(true, toolhead, sink);
                self.sync_print_time(toolhead, sink);
                if !verified {
                    return Err(NOT_VERIFIED);
                }
                self.next_test_time = print_time + TEST_TIME;
            }
        }
        self.sync_print_time(toolhead, sink);
        self.send(Command::PinDown, cfg.pin_move_time, sink);
        if cfg.probe_with_touch_mode {
            self.send(Command::TouchMode, MIN_CMD_TIME, sink);
        }
        self.sync_print_time(toolhead, sink);
        Ok(())
    }

    /// After a probing move: the pin up, from the MCU's time now (the
    /// later of `now` and where the toolhead stopped); the toolhead waits
    /// for it. With `pin_up_reports_not_triggered` the sensor must then
    /// read open: if not, a reset and the pin up again, noted on `out`, at
    /// most [`RAISE_TRIES`] times in all, then [`NOT_RAISED`].
    pub fn raise<const N: usize>(
        &mut self,
        cfg: &BltouchConfig<'_>,
        now: f64,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
        out: &mut dyn core::fmt::Write,
    ) -> Result<(), &'static str> {
        self.raise_signal(cfg, now.max(toolhead.print_time()), sink);
        if cfg.pin_up_reports_not_triggered {
            for tried in 1..=RAISE_TRIES {
                if self.verify(false, toolhead, sink) {
                    break;
                }
                if tried == RAISE_TRIES {
                    self.sync_print_time(toolhead, sink);
                    return Err(NOT_RAISED);
                }
                let _ = writeln!(out, "{RAISE_RETRY}");
                self.send(Command::Reset, RETRY_RESET_TIME, sink);
                self.send(Command::PinUp, cfg.pin_move_time, sink);
            }
        }
        self.sync_print_time(toolhead, sink);
        Ok(())
    }

    /// BLTOUCH_DEBUG: `cmd` for pin_move_time, the toolhead waiting for it.
    pub fn debug<const N: usize>(
        &mut self,
        cfg: &BltouchConfig<'_>,
        cmd: Command,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
    ) {
        self.sync_print_time(toolhead, sink);
        self.send(cmd, cfg.pin_move_time, sink);
        self.sync_print_time(toolhead, sink);
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::move_sink::TrapqMove;

    #[derive(Default)]
    struct Pins(std::vec::Vec<(f64, f64)>);

    impl MoveSink for Pins {
        fn toolhead(&mut self, _: &TrapqMove) {}
        fn extruder(&mut self, _: &TrapqMove) {}
        fn probe_pin(&mut self, print_time: f64, pulse_width: f64) {
            self.0.push((print_time, pulse_width));
        }
    }

    #[test]
    fn a_pin_move_holds_its_signal_whole_periods_and_the_next_waits() {
        let mut b = Bltouch::default();
        let mut pins = Pins::default();
        b.send(Command::PinDown, 0.680, &mut pins);
        b.send(Command::TouchMode, MIN_CMD_TIME, &mut pins);
        let p = &pins.0;
        assert_eq!(p[0], (0.0, 0.000_650));
        // 0.58 s: whole periods of the time past MIN_CMD_TIME.
        assert!((p[1].0 - 0.58).abs() < 1e-9 && p[1].1 == 0.0);
        // The next command after the 0.68 s action.
        assert!((p[2].0 - 0.68).abs() < 1e-9 && p[2].1 == 0.001_165);
        assert!((p[3].0 - 0.78).abs() < 1e-9);
        assert!((b.next_cmd_time - 0.88).abs() < 1e-9);
    }
}
