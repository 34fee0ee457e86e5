//! Klippy's batch-mode timing, replayed. Run from a file, klippy reads its
//! input in 4096-byte chunks, and two of its decisions depend on how fast
//! it happened to run, not on the G-code: whether its priming timer had
//! expired at the end of a chunk (which plans every queued move, ending
//! the last at rest), and when it restarted from rest (its estimate of
//! the MCU's print time). Given what klippy did (from its planned moves),
//! a run makes the same decisions at the same points, so that its steps
//! can be compared with klippy's one by one.

use onechip_app::printer::Printer;
use onechip_planner::toolhead::MoveSink;

/// Bytes klippy reads from its input at a time.
pub const CHUNK: usize = 4096;

/// What klippy's batch mode did, by toolhead move (counted from 0 in
/// planning order).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct KlippyBatch {
    /// The moves klippy ended at rest.
    pub stops: Vec<usize>,
    /// The moves klippy started from rest, and their print times (s from
    /// print time 0).
    pub starts: Vec<(usize, f64)>,
}

impl KlippyBatch {
    /// Before a line: an idle printer whose next toolhead move is
    /// `next_move` starts it no earlier than klippy did; `origin` is print
    /// time 0, s.
    pub fn hold<const N: usize>(&self, printer: &mut Printer<N>, next_move: usize, origin: f64) {
        if printer.is_idle()
            && let Some(&(_, at)) = self.starts.iter().find(|s| s.0 == next_move)
        {
            printer.hold_until(origin + at);
        }
    }

    /// At the end of an input chunk, `planned` toolhead moves planned so
    /// far: fires the priming timer if klippy's had expired there, which
    /// shows as its plan ending at rest on the last move queued.
    pub fn chunk_end<const N: usize>(
        &self,
        printer: &mut Printer<N>,
        planned: usize,
        sink: &mut impl MoveSink,
    ) {
        let Some(toolhead_moves) = printer.priming_moves() else {
            return;
        };
        let last = (planned + toolhead_moves).checked_sub(1);
        if last.is_some_and(|m| self.stops.contains(&m)) {
            printer.priming_timeout(sink);
        }
    }
}
