//! A homing move whose steppers count on different MCUs' clocks (a
//! stepper on a secondary MCU): when the endstop stops the move, each
//! stepper's step clock restarts at the stop on its own clock, as klippy
//! resets each MCU's stepper after a homing across MCUs.

use onechip_config::Config;
use onechip_golden::config_for;
use onechip_planner::machine::{MAX_STEPPERS, Machine};
use onechip_planner::move_sink::{HomingMove, MoveSink, TrapqMove};
use onechip_stepgen::compress::StepCommand;
use onechip_stepgen::motion::{HomingStop, Motion, StepSink};

/// The main MCU's clock, Hz.
const FREQ: f64 = 100e6;
/// Stepper 1's MCU: its clock, Hz, and the print time at its clock 0, s.
const OTHER_FREQ: f64 = 16e6;
const OTHER_OFFSET: f64 = 0.25;
/// Print time the endstop stops the move at, s.
const STOP: f64 = 2.0;

/// Records every command; the endstop stops the move at [`STOP`].
#[derive(Default)]
struct Steps {
    commands: Vec<(usize, StepCommand, u64)>,
}

impl StepSink for Steps {
    fn command(&mut self, index: usize, cmd: StepCommand, clock: u64) {
        self.commands.push((index, cmd, clock));
    }

    fn home(&mut self, _: &HomingMove, _: u64, until_clock: u64) -> Option<HomingStop> {
        let stop = (STOP * FREQ) as u64;
        (until_clock > stop).then_some(HomingStop {
            clock: stop,
            overshoot: [0; MAX_STEPPERS],
            stopped: true,
            untriggered: None,
            comms_timeout: false,
        })
    }
}

#[test]
fn each_stepper_restarts_at_the_stop_on_its_own_clock() {
    let name = config_for("cart_move_g28");
    let text = onechip_golden::config(name).leak();
    let config = Config::parse(name, text).unwrap_or_else(|e| panic!("{e}"));
    let machine = Machine::from_config(&config).unwrap_or_else(|e| panic!("{e}"));
    let mut motion: Box<Motion<128, 512>> = Box::new(Motion::new(
        &machine,
        FREQ,
        (0.000_025 * FREQ) as u32,
        [0.0; 3],
    ));
    motion.set_clock(1, OTHER_OFFSET, OTHER_FREQ);
    let mut steps = Steps::default();
    // X and Y together, 10 mm/s for 2 s from print time 1 s.
    let m = TrapqMove {
        print_time: 1.0,
        accel_t: 0.0,
        cruise_t: 2.0,
        decel_t: 0.0,
        start_pos: [0.0; 3],
        axes_r: [0.6, 0.8, 0.0],
        start_v: 10.0,
        cruise_v: 10.0,
        accel: 0.0,
    };
    let mut sink = motion.sink(&mut steps);
    sink.toolhead(&m);
    let end = sink.homing_move_end(&HomingMove {
        axis: 0,
        target: [12.0, 16.0, 0.0],
        position_endstop: 12.0,
        positive_dir: true,
        speed: 10.0,
        probe: false,
        towers: false,
        start_time: 1.0,
        end_time: 3.0,
    });
    assert_eq!(end.stopped_at, Some(STOP));
    let reset = |i: usize| {
        steps
            .commands
            .iter()
            .rev()
            .find_map(|&(j, cmd, _)| match cmd {
                StepCommand::ResetClock(c) if j == i => Some(c),
                _ => None,
            })
            .unwrap_or_else(|| panic!("stepper {i} was not reset"))
    };
    assert_eq!(reset(0), (STOP * FREQ) as u32, "main clock");
    let other = ((STOP - OTHER_OFFSET) * OTHER_FREQ) as i64;
    assert!(
        (i64::from(reset(1)) - other).abs() <= 1,
        "stepper 1 restarts at {} on its clock, not {other}",
        reset(1)
    );
    // Both stepped until the stop, on their own clocks.
    for (i, freq, offset) in [(0, FREQ, 0.0), (1, OTHER_FREQ, OTHER_OFFSET)] {
        let last = steps
            .commands
            .iter()
            .filter(|&&(j, cmd, _)| j == i && matches!(cmd, StepCommand::Steps { .. }))
            .map(|&(_, _, clock)| clock)
            .max()
            .unwrap_or_else(|| panic!("stepper {i} never stepped"));
        assert!(
            last as f64 / freq + offset <= STOP + 0.05,
            "stepper {i}: a command from {} s",
            last as f64 / freq + offset
        );
    }
}
