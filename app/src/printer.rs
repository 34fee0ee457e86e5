//! The printer as both boards run it: G-code lines in, planned moves out.
//!
//! Holds the toolhead (with a lookahead of `N` moves) and the G-code state;
//! each line is parsed and executed, and replies follow Klipper's console
//! conventions (`!! ` for errors, `// ` for information).

use core::fmt::Write;
use onechip_planner::gcode;
use onechip_planner::gcode_move::{CommandError, GcodeMove};
use onechip_planner::machine::Machine;
use onechip_planner::toolhead::{MoveSink, Toolhead};

/// Idle input time after which queued moves are released, s (Klipper's
/// priming delay).
pub const PRIMING_TIME: f64 = 0.100;

/// The motion side of a printer.
#[derive(Debug, Clone)]
pub struct Printer<const N: usize> {
    toolhead: Toolhead<N>,
    gcode: GcodeMove,
}

impl<const N: usize> Printer<N> {
    /// A printer for `machine`, at rest at position 0.
    pub fn new(machine: &Machine<'_>) -> Self {
        Self {
            toolhead: machine.toolhead(),
            gcode: GcodeMove::default(),
        }
    }

    /// Starts print time `origin` s after the MCU's clock did (a printer
    /// powered on long before the print).
    pub fn set_time_origin(&mut self, origin: f64) {
        self.toolhead.set_time_origin(origin);
    }

    /// True while nothing is queued or moving.
    pub fn is_idle(&self) -> bool {
        self.toolhead.is_idle()
    }

    /// If idle, the next move starts no earlier than print time `t` s.
    pub fn hold_until(&mut self, t: f64) {
        self.toolhead.hold_until(t);
    }

    /// Runs one line of G-code; replies other than `ok` go to `out`.
    pub fn execute<'l>(
        &mut self,
        line: &'l str,
        sink: &mut impl MoveSink,
        out: &mut impl Write,
    ) -> Result<(), CommandError<'l>> {
        let parsed = gcode::parse(line).map_err(CommandError::Gcode)?;
        self.gcode.execute(&parsed, &mut self.toolhead, sink, out)
    }

    /// If [`Self::priming_timeout`] would plan moves now: how many of them
    /// are toolhead moves.
    pub fn priming_moves(&self) -> Option<usize> {
        self.toolhead.priming_moves()
    }

    /// To call when no input has arrived for [`PRIMING_TIME`] s: plans and
    /// releases moves still waiting for the lookahead to fill, as Klipper's
    /// priming timer does, so a streamed move does not wait for the next.
    pub fn priming_timeout(&mut self, sink: &mut impl MoveSink) {
        self.toolhead.priming_timeout(sink);
    }

    /// Ends the input as klippy does: a 0.5 s dwell, then every move.
    pub fn finish(&mut self, sink: &mut impl MoveSink) {
        self.gcode.finish(&mut self.toolhead, sink);
    }

    /// Print time queued so far, s.
    pub fn print_time(&self) -> f64 {
        self.toolhead.print_time()
    }

    /// The G-code position (X, Y, Z, E), mm.
    pub fn position(&self) -> [f64; 4] {
        self.gcode.gcode_position()
    }
}
