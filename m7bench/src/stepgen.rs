//! The step-generation benchmark of `stepgen_cases`: each golden case's
//! G-code planned outside the measurement, then its moves streamed
//! through the whole pipeline ([`Motion`]: queues, itersolve, input
//! shaping / pressure advance, compression) as one measured region.

use crate::{exit, measure, report};
use core::fmt;
use onechip_config::Config;
use onechip_planner::gcode::parse;
use onechip_planner::gcode_move::GcodeMove;
use onechip_planner::machine::Machine;
use onechip_planner::move_sink::{MoveSink, TrapqMove};
use onechip_stepgen::compress::StepCommand;
use onechip_stepgen::motion::{Motion, StepSink};

/// The golden runs' MCU clock and 25 µs step error at that clock.
const FREQ: f64 = 180_000_000.0;
const MAX_ERROR: u32 = 4500;

/// What the planner produced, in order.
#[derive(Clone, Copy)]
enum Event {
    Toolhead(TrapqMove),
    Extruder(TrapqMove),
    SetPosition([f64; 3]),
}

struct Planned(heapless::Vec<Event, 3200>);

impl MoveSink for Planned {
    fn toolhead(&mut self, m: &TrapqMove) {
        let _ = self.0.push(Event::Toolhead(*m));
    }
    fn extruder(&mut self, m: &TrapqMove) {
        let _ = self.0.push(Event::Extruder(*m));
    }
    fn set_position(&mut self, pos: [f64; 3]) {
        let _ = self.0.push(Event::SetPosition(pos));
    }
}

/// Discards console replies.
struct Quiet;

impl fmt::Write for Quiet {
    fn write_str(&mut self, _: &str) -> fmt::Result {
        Ok(())
    }
}

/// Counts steps and commands (and the planner events they came from).
struct Count {
    steps: u32,
    commands: u32,
    events: usize,
}

impl StepSink for Count {
    fn command(&mut self, _: usize, cmd: StepCommand, _: u64) {
        self.commands += 1;
        if let StepCommand::Steps { count, .. } = cmd {
            self.steps += u32::from(count);
        }
    }
}

/// One golden case: its config (named `config_name`) and G-code.
pub struct Case {
    /// Name in the report (the golden case's).
    pub label: &'static str,
    /// The config's file name (for messages).
    pub config_name: &'static str,
    /// The config's text.
    pub config: &'static str,
    /// The G-code printed.
    pub gcode: &'static str,
}

/// Measures the step generation of each case in turn as region 1, 2, …
/// (its G-code planned before the region), reports each region's steps
/// and commands, and exits.
pub fn run(cases: &[Case]) -> ! {
    measure(0, || 0u32);
    for (region, case) in (1..).zip(cases) {
        let count = case.measure(region);
        report(format_args!(
            "{}: region {region} generates {} steps in {} commands from {} planner events",
            case.label, count.steps, count.commands, count.events
        ));
    }
    exit()
}

impl Case {
    /// Plans the case, then measures its step generation as `region`.
    fn measure(&self, region: u32) -> Count {
        let Ok(config) = Config::parse(self.config_name, self.config) else {
            panic!("config {}", self.config_name)
        };
        let Ok(machine) = Machine::from_config(&config) else {
            panic!("machine {}", self.config_name)
        };
        let mut toolhead = machine.toolhead::<2048>();
        let mut gcode_move = GcodeMove::default();
        let mut planned = Planned(heapless::Vec::new());
        for line in self.gcode.lines() {
            if let Ok(l) = parse(line) {
                let _ = gcode_move.execute(&l, &mut toolhead, &mut planned, &mut Quiet);
            }
        }
        gcode_move.finish(&mut toolhead, &mut planned);
        let events = &planned.0;
        measure(region, || {
            let mut motion = Motion::<256, 512>::new(&machine, FREQ, MAX_ERROR, [0.0; 3]);
            let mut count = Count {
                steps: 0,
                commands: 0,
                events: events.len(),
            };
            let mut sink = motion.sink(&mut count);
            for event in events {
                match event {
                    Event::Toolhead(m) => sink.toolhead(m),
                    Event::Extruder(m) => sink.extruder(m),
                    Event::SetPosition(pos) => sink.set_position(*pos),
                }
            }
            motion.finish(&mut count);
            count
        })
    }
}
