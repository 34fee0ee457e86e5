//! Klippy's batch-mode timing, replayed. Run from a file, klippy reads its
//! input in 4096-byte chunks, and two of its decisions depend on how fast
//! it happened to run, not on the G-code: whether its priming timer had
//! expired at the end of a chunk (which plans every queued move, ending
//! the last at rest), and when it restarted from rest (its estimate of
//! the MCU's print time). Given what klippy did (from its planned moves),
//! a run makes the same decisions at the same points, so that its steps
//! can be compared with klippy's one by one. Used by tests only: the
//! product keeps print time from the MCU's clock.

use onechip_host::virtual_mcu::VirtualMcu;
use onechip_host::{HostSession, KLIPPY_LOOKAHEAD, Replay};

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
    /// Print time 0, s (the run's clock origin).
    pub origin: f64,
}

impl Replay<KLIPPY_LOOKAHEAD> for KlippyBatch {
    /// An idle printer whose next toolhead move is one klippy started
    /// from rest starts it no earlier than klippy did.
    fn before_line(&mut self, session: &mut HostSession<'_, KLIPPY_LOOKAHEAD>) {
        let next_move = session.planned().toolhead_moves;
        let printer = session.printer();
        if printer.is_idle()
            && let Some(&(_, at)) = self.starts.iter().find(|s| s.0 == next_move)
        {
            printer.hold_until(self.origin + at);
        }
    }

    /// At the end of an input chunk: fires the priming timer if klippy's
    /// had expired there, which shows as its plan ending at rest on the
    /// last move queued.
    fn after_bytes(
        &mut self,
        read: usize,
        session: &mut HostSession<'_, KLIPPY_LOOKAHEAD>,
        mcu: &mut VirtualMcu,
    ) {
        if !read.is_multiple_of(CHUNK) {
            return;
        }
        let planned = session.planned().toolhead_moves;
        let Some(toolhead_moves) = session.printer().priming_moves() else {
            return;
        };
        let last = (planned + toolhead_moves).checked_sub(1);
        if last.is_some_and(|m| self.stops.contains(&m)) {
            session.prime(mcu);
        }
    }
}
