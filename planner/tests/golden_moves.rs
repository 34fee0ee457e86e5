//! The planner against klippy's own planned moves (`moves.tsv` of the
//! golden cases): same moves in the same order, times within 1 µs,
//! velocities within 1e-4 relative (or 1e-3 mm/s), positions within 1 µm.
//! Each case also runs with the print starting 24 h in, with the same
//! tolerances (time stamps are large then; durations must not drift).

use onechip_planner::config::Config;
use onechip_planner::gcode::parse;
use onechip_planner::gcode_move::GcodeMove;
use onechip_planner::machine::Machine;
use onechip_planner::toolhead::{MoveSink, TrapqMove};
use std::path::PathBuf;

fn golden_dir() -> PathBuf {
    std::env::var_os("ONECHIP_GOLDEN").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/golden"),
        PathBuf::from,
    )
}

#[derive(Default, Clone)]
struct Recorder(Vec<(&'static str, TrapqMove)>);

impl MoveSink for Recorder {
    fn toolhead(&mut self, m: &TrapqMove) {
        self.0.push(("toolhead", *m));
    }
    fn extruder(&mut self, m: &TrapqMove) {
        self.0.push(("extruder", *m));
    }
}

fn config_for(case: &str) -> &'static str {
    match case.split('_').next() {
        Some("corexy") => "corexy.cfg",
        Some("delta") => "delta.cfg",
        Some("shaper") => "cartesian_shaper.cfg",
        Some("avr") => "cartesian_avr.cfg",
        Some("h723") => "cartesian_h723.cfg",
        _ => "cartesian.cfg",
    }
}

/// Plans a case's G-code as klippy's batch mode reads it: in 4096-byte
/// chunks. Between chunks klippy's reactor may run its priming timer, which
/// flushes the whole lookahead; whether it has expired depends on klippy's
/// own processing speed, so the timer is fired at the chunk boundaries where
/// the golden plan stops exactly at the last move queued so far.
/// `time_origin` starts the clock that many seconds in.
fn plan(case: &str, time_origin: f64) -> Vec<(&'static str, TrapqMove)> {
    let dir = golden_dir();
    let cfg_text =
        std::fs::read_to_string(dir.join("configs").join(config_for(case))).expect("config");
    let config = Config::parse(config_for(case), &cfg_text).expect("config parses");
    let machine = Machine::from_config(&config).unwrap_or_else(|e| panic!("{case}: {e}"));
    let mut toolhead = machine.toolhead::<4096>().with_time_origin(time_origin);
    let mut gcode = GcodeMove::default();
    let mut rec = Recorder::default();
    let golden_stops = golden_stops(case);
    let program = std::fs::read(dir.join("gcode").join(format!("{case}.gcode"))).expect("gcode");
    let mut replies = String::new();
    let mut pending = Vec::new();
    let mut line_no = 0;
    for chunk in program.chunks(4096) {
        pending.extend_from_slice(chunk);
        let complete = pending
            .iter()
            .rposition(|&b| b == b'\n')
            .map_or(0, |p| p + 1);
        let text = String::from_utf8(pending.drain(..complete).collect()).expect("UTF-8");
        for line in text.lines() {
            line_no += 1;
            let parsed = parse(line).unwrap_or_else(|e| panic!("{case}:{line_no}: {e}"));
            gcode
                .execute(&parsed, &mut toolhead, &mut rec, &mut replies)
                .unwrap_or_else(|e| panic!("{case}:{line_no}: {line}: {e}"));
        }
        let mut trial = (toolhead.clone(), Recorder(rec.0.clone()));
        trial.0.priming_timeout(&mut trial.1);
        let last_toolhead_move = trial
            .1
            .0
            .iter()
            .filter(|(q, _)| *q == "toolhead")
            .count()
            .checked_sub(1);
        if trial.1.0.len() > rec.0.len()
            && last_toolhead_move.is_some_and(|i| golden_stops.contains(&i))
        {
            (toolhead, rec) = trial;
        }
    }
    gcode.finish(&mut toolhead, &mut rec);
    rec.0
}

/// Indices of golden toolhead moves that end at rest.
fn golden_stops(case: &str) -> Vec<usize> {
    golden_moves(case)
        .iter()
        .filter(|(q, _)| q == "toolhead")
        .enumerate()
        .filter(|(_, (_, g))| (g[11] - g[12] * g[3]).abs() < 1e-9)
        .map(|(i, _)| i)
        .collect()
}

fn golden_moves(case: &str) -> Vec<(String, [f64; 13])> {
    let text =
        std::fs::read_to_string(golden_dir().join(case).join("moves.tsv")).expect("moves.tsv");
    text.lines()
        .skip(1)
        .map(|l| {
            let mut f = l.split('\t');
            let name = f.next().expect("trapq").to_string();
            let v: Vec<f64> = f.map(|x| x.parse().expect("float")).collect();
            (name, v.try_into().expect("13 numbers"))
        })
        .collect()
}

fn check_case(case: &str, time_origin: f64) {
    let mut ours = plan(case, time_origin);
    let golden = golden_moves(case);
    assert_eq!(ours.len(), golden.len(), "{case}: number of planned moves");
    // When the queue is idle, klippy restarts only once its batch-mode step
    // flushing lets it, and that flushing runs on its reactor's schedule
    // (after input chunks, during homing waits). So at a move that starts
    // from rest a later golden start (by less than 0.5 s) is taken as given
    // and counted; every other time, and every duration, must match.
    let mut shift = 0.0;
    let mut resyncs = 0;
    for (i, (_, m)) in ours.iter_mut().enumerate() {
        let planned = m.print_time - time_origin + shift;
        let lag = golden[i].1[0] - planned;
        let new_move = i == 0 || golden[i].1[0] != golden[i - 1].1[0];
        if m.start_v == 0.0 && new_move && lag > 1e-6 && lag < 0.5 {
            shift += lag;
            resyncs += 1;
        }
        m.print_time = m.print_time - time_origin + shift;
    }
    assert!(
        resyncs <= 2,
        "{case}: {resyncs} restarts later than planned"
    );
    for (i, ((name, m), (gname, g))) in ours.iter().zip(&golden).enumerate() {
        let ctx = format!("{case} move {i} ({gname}): ours {m:?}\n golden {g:?}");
        assert_eq!(name, gname, "{ctx}");
        let time = |a: f64, b: f64| (a - b).abs() <= 1e-6;
        let vel = |a: f64, b: f64| (a - b).abs() <= 1e-3 || (a - b).abs() <= 1e-4 * b.abs();
        let pos = |a: f64, b: f64| (a - b).abs() <= 1e-3; // 1 µm
        assert!(time(m.print_time, g[0]), "print_time {ctx}");
        assert!(
            time(m.accel_t, g[1]) && time(m.cruise_t, g[2]) && time(m.decel_t, g[3]),
            "phases {ctx}"
        );
        for k in 0..3 {
            assert!(pos(m.start_pos[k], g[4 + k]), "start_pos[{k}] {ctx}");
            assert!((m.axes_r[k] - g[7 + k]).abs() <= 1e-9, "axes_r[{k}] {ctx}");
        }
        assert!(
            vel(m.start_v, g[10]) && vel(m.cruise_v, g[11]),
            "velocities {ctx}"
        );
        assert!(vel(m.accel, g[12]), "accel {ctx}");
    }
}

macro_rules! golden_cases {
    ($($name:ident),* $(,)?) => {$(
        #[test]
        fn $name() {
            // A 4096-move lookahead lives inline (about 1 MB): give it room.
            std::thread::Builder::new()
                .stack_size(64 << 20)
                .spawn(|| {
                    check_case(stringify!($name), 0.0);
                    // The same print starting 24 h after the MCU did.
                    check_case(stringify!($name), 86_400.0);
                })
                .expect("thread")
                .join()
                .expect("case passes");
        }
    )*};
}

golden_cases!(
    cart_square,
    cart_circle,
    cart_extrude,
    cart_move_g28,
    corexy_square,
    corexy_circle,
    corexy_extrude,
    delta_square,
    delta_circle,
    delta_extrude,
    shaper_square,
    shaper_circle,
    shaper_extrude,
    avr_cart_extrude,
    h723_cart_extrude,
);

/// Each stepper's position functions against klippy's: the final toolhead
/// position of every case maps to the commanded position klippy's
/// itersolve reports for each motion stepper, and back. That report is
/// where step generation last evaluated the stepper, which on a delta can
/// be off the exact end point by less than half a step; hence the
/// half-step tolerance (cartesian-style machines agree to 1e-9 mm).
#[test]
fn stepper_positions_match_klippy_at_the_end_of_every_case() {
    use onechip_planner::kinematics::calc_position;
    for entry in std::fs::read_dir(golden_dir()).expect("golden folder") {
        let dir = entry.expect("entry").path();
        let Ok(summary) = std::fs::read_to_string(dir.join("summary.txt")) else {
            continue;
        };
        let case = dir
            .file_name()
            .and_then(|n| n.to_str())
            .expect("name")
            .to_string();
        let cfg_text =
            std::fs::read_to_string(golden_dir().join("configs").join(config_for(&case)))
                .expect("config");
        let config = Config::parse(config_for(&case), &cfg_text).expect("config parses");
        let machine = Machine::from_config(&config).expect("machine");
        let field = |line: &str, key: &str| -> f64 {
            let words: Vec<&str> = line.split_whitespace().collect();
            let at = words.iter().position(|w| *w == key).expect("key");
            words[at + 1].parse().expect("number")
        };
        let final_pos: Vec<f64> = summary
            .lines()
            .find_map(|l| l.strip_prefix("toolhead_final_position "))
            .expect("final position")
            .split_whitespace()
            .map(|v| v.parse().expect("number"))
            .collect();
        let p = [final_pos[0], final_pos[1], final_pos[2]];
        let steppers: Vec<f64> = summary
            .lines()
            .filter(|l| l.starts_with("stepper ") && !l.starts_with("stepper extruder"))
            .map(|l| field(l, "commanded_pos"))
            .collect();
        for (i, kin) in machine.stepper_kinematics.iter().enumerate() {
            let ours = kin.position(p);
            let half_step = machine.steppers[i].step_dist / 2.0;
            assert!(
                (ours - steppers[i]).abs() < half_step,
                "{case} stepper {i}: {ours} vs {}",
                steppers[i]
            );
        }
        let back = calc_position(
            &machine.stepper_kinematics,
            [steppers[0], steppers[1], steppers[2]],
        );
        for a in 0..3 {
            assert!(
                (back[a] - p[a]).abs() < 0.02,
                "{case} axis {a}: {back:?} vs {p:?}"
            );
        }
    }
}
