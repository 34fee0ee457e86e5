//! The printer both boards run: a streamed move waits in the lookahead
//! until more moves arrive or input pauses for the priming time.

use onechip_app::printer::Printer;
use onechip_config::Config;
use onechip_planner::gcode;
use onechip_planner::machine::Machine;
use onechip_planner::move_sink::{MoveSink, TrapqMove};

const CFG: &str = "[printer]\nkinematics: cartesian\nmax_velocity: 300\nmax_accel: 3000\n\
[stepper_x]\nstep_pin: PF13\ndir_pin: PF12\nmicrosteps: 16\nrotation_distance: 40\nposition_endstop: 0\nposition_max: 200\n\
[stepper_y]\nstep_pin: PG0\ndir_pin: PG1\nmicrosteps: 16\nrotation_distance: 40\nposition_endstop: 0\nposition_max: 200\n\
[stepper_z]\nstep_pin: PF11\ndir_pin: PG3\nmicrosteps: 16\nrotation_distance: 8\nposition_endstop: 0\nposition_max: 200\n";

#[derive(Default)]
struct Moves(Vec<TrapqMove>);

impl MoveSink for Moves {
    fn toolhead(&mut self, m: &TrapqMove) {
        self.0.push(*m);
    }
    fn extruder(&mut self, _: &TrapqMove) {}
}

#[test]
fn a_streamed_move_is_released_by_the_priming_timeout() {
    let config = Config::parse("printer.cfg", CFG).expect("config");
    let machine = Machine::from_config(&config).expect("machine");
    let mut printer = Box::new(Printer::<64>::new(&machine));
    let mut moves = Moves::default();
    let mut replies = String::new();
    for line in ["SET_KINEMATIC_POSITION X=0 Y=0 Z=0", "G1 X10 F6000"] {
        let line = gcode::parse(line).expect("parses");
        printer
            .execute(&line, &mut moves, &mut replies)
            .expect("runs");
    }
    assert!(moves.0.is_empty(), "a single move waits for lookahead");
    printer.priming_timeout(&mut moves);
    assert_eq!(moves.0.len(), 1);
    let m = moves.0[0];
    assert_eq!((m.start_v, m.cruise_v), (0.0, 100.0));
    assert_eq!(m.print_time, 0.25);
    // Nothing left to release: a second timeout changes nothing.
    printer.priming_timeout(&mut moves);
    assert_eq!(moves.0.len(), 1);
}
