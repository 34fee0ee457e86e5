//! Host step-generation throughput per kinematics: golden planned moves
//! (klippy's trapq appends) through the whole pipeline ([`Motion`]: queues,
//! itersolve, pressure advance / input shaping, compression), in steps per
//! second of all steppers together.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use onechip_planner::config::Config;
use onechip_planner::machine::Machine;
use onechip_planner::toolhead::{MoveSink, TrapqMove};
use onechip_stepgen::compress::StepCommand;
use onechip_stepgen::motion::{Motion, StepSink};
use std::path::PathBuf;

fn golden(path: &str) -> String {
    let dir = std::env::var_os("ONECHIP_GOLDEN").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/golden"),
        PathBuf::from,
    );
    std::fs::read_to_string(dir.join(path)).expect("golden data (set ONECHIP_GOLDEN)")
}

/// A case's trapq appends in time order: (is_extruder, move).
fn moves(case: &str) -> Vec<(bool, TrapqMove)> {
    let mut out: Vec<(bool, TrapqMove)> = golden(&format!("{case}/moves.tsv"))
        .lines()
        .skip(1)
        .map(|l| {
            let mut f = l.split('\t');
            let queue = f.next().expect("trapq");
            let v: Vec<f64> = f.map(|x| x.parse().expect("float")).collect();
            let m = TrapqMove {
                print_time: v[0],
                accel_t: v[1],
                cruise_t: v[2],
                decel_t: v[3],
                start_pos: [v[4], v[5], v[6]],
                axes_r: [v[7], v[8], v[9]],
                start_v: v[10],
                cruise_v: v[11],
                accel: v[12],
            };
            (queue == "extruder", m)
        })
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
    for (case, config) in [
        ("cart_circle", "cartesian.cfg"),
        ("corexy_circle", "corexy.cfg"),
        ("delta_circle", "delta.cfg"),
        ("shaper_circle", "cartesian_shaper.cfg"),
        ("corexy_extrude", "corexy.cfg"),
    ] {
        let cfg = golden(&format!("configs/{config}"));
        let config = Config::parse(config, &cfg).expect("config");
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
