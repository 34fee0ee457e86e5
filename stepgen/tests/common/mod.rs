//! What the golden tests and the step benches share: klippy's planned moves
//! as the planner hands them to step generation.

use onechip_golden::TrapqAppend;
use onechip_planner::move_sink::TrapqMove;

/// A golden move (a `moves.tsv` line) as a [`TrapqMove`].
pub fn trapq_move(m: &TrapqAppend) -> TrapqMove {
    TrapqMove {
        print_time: m.print_time,
        accel_t: m.accel_t,
        cruise_t: m.cruise_t,
        decel_t: m.decel_t,
        start_pos: m.start_pos(),
        axes_r: m.axes_r(),
        start_v: m.start_v,
        cruise_v: m.cruise_v,
        accel: m.accel,
    }
}
