//! Host planning throughput on the golden circle case (1416 moves of 0.2 mm
//! at 200 mm/s): G-code text to planned trapezoids.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use onechip_config::Config;
use onechip_planner::gcode::parse;
use onechip_planner::gcode_move::GcodeMove;
use onechip_planner::machine::Machine;
use onechip_planner::move_sink::{MoveSink, TrapqMove};
use std::path::PathBuf;

fn golden(path: &str) -> String {
    let dir = std::env::var_os("ONECHIP_GOLDEN").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/golden"),
        PathBuf::from,
    );
    std::fs::read_to_string(dir.join(path)).expect("golden data (set ONECHIP_GOLDEN)")
}

struct Count(u64);

impl MoveSink for Count {
    fn toolhead(&mut self, _: &TrapqMove) {
        self.0 += 1;
    }
    fn extruder(&mut self, _: &TrapqMove) {}
}

fn plan(c: &mut Criterion) {
    let cfg = golden("configs/cartesian.cfg");
    let program = golden("gcode/cart_circle.gcode");
    let config = Config::parse("cartesian.cfg", &cfg).expect("config");
    let machine = Machine::from_config(&config).expect("machine");
    let mut group = c.benchmark_group("cart_circle");
    group.throughput(Throughput::Elements(1416));
    group.bench_function("plan moves", |b| {
        b.iter(|| {
            let mut toolhead = Box::new(machine.toolhead::<2048>());
            let mut gcode = GcodeMove::default();
            let mut count = Count(0);
            let mut replies = String::new();
            for line in program.lines() {
                let parsed = parse(line).expect("valid");
                gcode
                    .execute(&parsed, &mut toolhead, &mut count, &mut replies)
                    .expect("plans");
            }
            gcode.finish(&mut toolhead, &mut count);
            assert_eq!(count.0, 1416);
        })
    });
    group.finish();
}

criterion_group!(benches, plan);
criterion_main!(benches);
