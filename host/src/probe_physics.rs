//! The simulated Z probe: it triggers where its tip, `x_offset`,
//! `y_offset` from the nozzle, touches the simulated bed, that is when the
//! nozzle is `z_offset` above the bed under the probe. The bed is a plane
//! ([`crate::Options::bed`]); the probe is read by the engine's endstop
//! check through its own slot's pins, as the board reads the probe pin.

use onechip_planner::bltouch::Command;
use onechip_planner::machine::Machine;

/// Where the simulated probe triggers.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbePhysics {
    /// The probe's x_offset, y_offset, z_offset, mm.
    pub offsets: [f64; 3],
    /// The bed: height at X = Y = 0 (mm) and slopes along X and Y.
    pub bed: [f64; 3],
    /// A BLTouch: how long its pin takes to move, ticks. Its sensor reads
    /// the bed only once the pin is down; with the pin up it reads open,
    /// or triggered in touch mode (its self-test).
    pub bltouch: Option<u64>,
    /// What is wrong with the BLTouch, if anything.
    pub fault: Option<BltouchFault>,
}

/// A faulty BLTouch, for tests of Klipper's checks of its sensor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BltouchFault {
    /// A clone whose sensor does not read triggered in touch mode with
    /// the pin up (Klipper's `pin_up_touch_mode_reports_triggered: False`).
    NoTouchModeReport,
    /// The sensor reads triggered whatever the pin does (a pin stuck
    /// down, an alarm that a reset does not clear).
    StuckTriggered,
}

impl ProbePhysics {
    /// The bed's height at (`x`, `y`), mm.
    pub fn bed_height(&self, x: f64, y: f64) -> f64 {
        self.bed[0] + self.bed[1] * x + self.bed[2] * y
    }

    /// True while the probe's input reads triggered at clock `now`, with
    /// the toolhead (nozzle) really at `toolhead` (mm) and the control pin
    /// given `servo` (clock, pulse width s) so far.
    pub fn pressed(&self, toolhead: [f64; 3], now: u64, servo: &[(u64, f64)]) -> bool {
        let [xo, yo, zo] = self.offsets;
        let touching = toolhead[2] <= self.bed_height(toolhead[0] + xo, toolhead[1] + yo) + zo;
        let Some(move_ticks) = self.bltouch else {
            return touching;
        };
        if self.fault == Some(BltouchFault::StuckTriggered) {
            return true;
        }
        // The pin: down since a clock, or up; touch mode since the last
        // pin command.
        let (mut down_since, mut touch) = (None, false);
        for &(clock, width) in servo.iter().filter(|c| c.0 <= now && c.1 > 0.0) {
            match Command::ALL.into_iter().find(|c| c.pulse_width() == width) {
                Some(Command::PinDown) => (down_since, touch) = (Some(clock), false),
                Some(Command::PinUp | Command::Reset) => (down_since, touch) = (None, false),
                Some(Command::TouchMode) => touch = true,
                _ => {}
            }
        }
        match down_since {
            Some(at) => now >= at + move_ticks && touching,
            None => touch && self.fault != Some(BltouchFault::NoTouchModeReport),
        }
    }
}

/// The probe of `machine` over the bed `bed` (a BLTouch with `fault`, if
/// any), with its engine slot, on a clock of `freq` Hz.
pub fn for_machine(
    machine: &Machine<'_>,
    bed: [f64; 3],
    fault: Option<BltouchFault>,
    freq: f64,
) -> Option<(usize, ProbePhysics)> {
    let probe = machine.probe.as_ref()?;
    let slot = machine.probe_slot()?;
    Some((
        slot,
        ProbePhysics {
            offsets: probe.offsets,
            bed,
            bltouch: probe
                .bltouch
                .map(|b| (b.pin_move_time * freq).ceil() as u64),
            fault,
        },
    ))
}
