//! Instructions per planned move on a Cortex-M7: the golden circle case
//! (1416 moves of 0.2 mm at 200 mm/s) from G-code text to planned
//! trapezoids — parsing, gcode_move, kinematic checks, junctions and
//! lookahead included.
#![no_std]
#![no_main]

use core::fmt;
use cortex_m_rt::entry;
use onechip_config::Config;
use onechip_m7bench::{exit, measure, report};
use onechip_planner::gcode::parse;
use onechip_planner::gcode_move::GcodeMove;
use onechip_planner::machine::Machine;
use onechip_planner::move_sink::{MoveSink, TrapqMove};

const CONFIG: &str = include_str!("../../../../shared/golden/configs/cartesian.cfg");
const GCODE: &str = include_str!("../../../../shared/golden/gcode/cart_circle.gcode");

/// Counts planned moves and sums their times (so nothing is optimised out).
struct Count(u32, f64);

impl MoveSink for Count {
    fn toolhead(&mut self, m: &TrapqMove) {
        self.0 += 1;
        self.1 += m.cruise_t;
    }
    fn extruder(&mut self, _: &TrapqMove) {}
}

/// Discards console replies.
struct Quiet;

impl fmt::Write for Quiet {
    fn write_str(&mut self, _: &str) -> fmt::Result {
        Ok(())
    }
}

#[entry]
fn main() -> ! {
    let Ok(config) = Config::parse("cartesian.cfg", CONFIG) else {
        panic!("config")
    };
    let Ok(machine) = Machine::from_config(&config) else {
        panic!("machine")
    };
    let mut toolhead = machine.toolhead::<2048>();
    let mut gcode = GcodeMove::default();
    let mut sink = Count(0, 0.0);

    measure(0, || 0u32);
    let errors = measure(1, || {
        let mut errors = 0u32;
        for line in GCODE.lines() {
            let ok = parse(line).is_ok_and(|l| {
                gcode
                    .execute(&l, &mut toolhead, &mut sink, &mut Quiet)
                    .is_ok()
            });
            errors += u32::from(!ok);
        }
        gcode.finish(&mut toolhead, &mut sink);
        errors
    });
    report(format_args!(
        "planner_circle: region 1 plans {} moves ({} errors, cruise sum {:.3} s)",
        sink.0, errors, sink.1
    ));
    exit()
}
