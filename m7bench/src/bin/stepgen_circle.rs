//! Instructions per generated and compressed step on a Cortex-M7: the
//! golden circle case planned, then its X and Y steps found (half-step
//! crossings) and compressed into (interval, count, add) sequences.
#![no_std]
#![no_main]

use core::fmt;
use cortex_m_rt::entry;
use onechip_m7bench::{exit, measure, report};
use onechip_planner::config::Config;
use onechip_planner::gcode::parse;
use onechip_planner::gcode_move::GcodeMove;
use onechip_planner::machine::Machine;
use onechip_planner::toolhead::{MoveSink, TrapqMove};
use onechip_stepgen::compress::{Compressor, StepCommand};
use onechip_stepgen::segment::segments;
use onechip_stepgen::solver::StepSolver;

const CONFIG: &str = include_str!("../../../../shared/golden/configs/cartesian.cfg");
const GCODE: &str = include_str!("../../../../shared/golden/gcode/cart_circle.gcode");
/// The golden runs' MCU clock and 25 µs step error at that clock.
const FREQ: f64 = 180_000_000.0;
const MAX_ERROR: u32 = 4500;

/// Keeps the planned toolhead moves.
struct Planned(heapless::Vec<TrapqMove, 1600>);

impl MoveSink for Planned {
    fn toolhead(&mut self, m: &TrapqMove) {
        let _ = self.0.push(*m);
    }
    fn extruder(&mut self, _: &TrapqMove) {}
}

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
    let mut planned = Planned(heapless::Vec::new());
    for line in GCODE.lines() {
        if let Ok(l) = parse(line) {
            let _ = gcode.execute(&l, &mut toolhead, &mut planned, &mut Quiet);
        }
    }
    gcode.finish(&mut toolhead, &mut planned);
    let moves = &planned.0;
    let Some(first) = moves.first() else {
        panic!("no moves")
    };

    measure(0, || 0u32);
    let (steps, commands) = measure(1, || {
        let (mut steps, mut commands) = (0u32, 0u32);
        for (kin, stepper) in machine
            .stepper_kinematics
            .iter()
            .zip(&machine.steppers)
            .take(2)
        {
            let mut solver = StepSolver::new(*kin, stepper.step_dist, first.start_pos);
            let mut compressor = Compressor::<512>::new(MAX_ERROR, FREQ);
            let mut sink = |c: StepCommand| {
                commands += 1;
                if let StepCommand::Steps { count, .. } = c {
                    steps += u32::from(count);
                }
            };
            for m in moves {
                for seg in segments(m) {
                    if solver.is_active(&seg) {
                        solver.generate(&seg, seg.print_time, seg.end_time(), |s| {
                            compressor.append(s.time, s.dir, &mut sink)
                        });
                    }
                }
            }
            compressor.flush(&mut sink);
        }
        (steps, commands)
    });
    report(format_args!(
        "stepgen_circle: region 1 generates {steps} steps in {commands} commands from {} moves",
        moves.len()
    ));
    exit()
}
