//! Host step-generation throughput per kinematics: golden planned moves
//! (klippy's trapq appends) through the whole pipeline ([`Motion`]: queues,
//! itersolve, pressure advance / input shaping, compression), in steps per
//! second of all steppers together.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use onechip_config::Config;
use onechip_golden::Trapq;
use onechip_planner::machine::Machine;
use onechip_planner::move_sink::{MoveSink, TrapqMove};
use onechip_stepgen::compress::StepCommand;
use onechip_stepgen::motion::{Motion, StepSink};

/// A case's trapq appends in time order: (is_extruder, move).
fn moves(case: &str) -> Vec<(bool, TrapqMove)> {
    let mut out: Vec<(bool, TrapqMove)> = onechip_golden::moves(case)
        .iter()
        .map(|m| (m.trapq == Trapq::Extruder, m.trapq_move()))
        .collect();
    out.sort_by(|a, b| a.1.print_time.total_cmp(&b.1.print_time));
    out
}

/// Counts steps.
struct Count(u64);

impl StepSink for Count {
    fn command(&mut self, _: usize, cmd: StepCommand, _: u64) {
        if let StepCommand::Steps { count, .. } = cmd {
            self.0 += u64::from(count);
        }
    }
}

fn run(machine: &Machine<'_>, moves: &[(bool, TrapqMove)]) -> u64 {
    let start = moves
        .iter()
        .find(|m| !m.0)
        .map_or([0.0; 3], |m| m.1.start_pos);
    let mut motion = Box::new(Motion::<256, 512>::new(machine, 180e6, 4500, start));
    let mut count = Count(0);
    let mut sink = motion.sink(&mut count);
    for (extruder, m) in moves {
        if *extruder {
            sink.extruder(m);
        } else {
            sink.toolhead(m);
        }
    }
    motion.finish(&mut count);
    count.0
}

fn steps(c: &mut Criterion) {
    let mut group = c.benchmark_group("steps");
    for case in [
        "cart_circle",
        "corexy_circle",
        "delta_circle",
        "shaper_circle",
        "corexy_extrude",
    ] {
        let name = onechip_golden::config_for(case);
        let cfg = onechip_golden::config(name);
        let config = Config::parse(name, &cfg).expect("config");
        let machine = Machine::from_config(&config).expect("machine");
        let moves = moves(case);
        let total = run(&machine, &moves);
        group.throughput(Throughput::Elements(total));
        group.bench_function(case, |b| b.iter(|| run(&machine, &moves)));
    }
    group.finish();
}

criterion_group!(benches, steps);
criterion_main!(benches);
