//! The planner against klippy's own planned moves (`moves.tsv` of the
//! golden cases): same moves in the same order, times within 1 µs,
//! velocities within 1e-4 relative (or 1e-3 mm/s), positions within 1 µm.
//! Each case also runs with the print starting 24 h in, with the same
//! tolerances (time stamps are large then; durations must not drift).

use onechip_config::Config;
use onechip_golden::{Trapq, config, config_for, moves, trapq_moves};
use onechip_planner::gcode::parse;
use onechip_planner::gcode_move::GcodeMove;
use onechip_planner::machine::Machine;
use onechip_planner::move_sink::{MoveSink, TrapqMove};

#[derive(Default, Clone)]
struct Recorder(Vec<(Trapq, TrapqMove)>);

impl MoveSink for Recorder {
    fn toolhead(&mut self, m: &TrapqMove) {
        self.0.push((Trapq::Toolhead, *m));
    }
    fn extruder(&mut self, m: &TrapqMove) {
        self.0.push((Trapq::Extruder, *m));
    }
}

/// Plans a case's G-code as klippy's batch mode reads it: in 4096-byte
/// chunks. Between chunks klippy's reactor may run its priming timer, which
/// flushes the whole lookahead; whether it has expired depends on klippy's
/// own processing speed, so the timer is fired at the chunk boundaries where
/// the golden plan stops exactly at the last move queued so far.
/// `time_origin` starts the clock that many seconds in.
fn plan(case: &str, time_origin: f64) -> Vec<(Trapq, TrapqMove)> {
    let cfg_text = config(config_for(case));
    let config = Config::parse(config_for(case), &cfg_text).expect("config parses");
    let machine = Machine::from_config(&config).unwrap_or_else(|e| panic!("{case}: {e}"));
    let mut toolhead = machine.toolhead::<1024>().with_time_origin(time_origin);
    let mut gcode = GcodeMove::default();
    let mut rec = Recorder::default();
    let golden_stops = golden_stops(case);
    let program = onechip_golden::gcode(case).into_bytes();
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
            .filter(|(q, _)| *q == Trapq::Toolhead)
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
    trapq_moves(case, Trapq::Toolhead)
        .iter()
        .enumerate()
        .filter(|(_, g)| g.ends_at_rest())
        .map(|(i, _)| i)
        .collect()
}

fn check_case(case: &str, time_origin: f64) {
    let mut ours = plan(case, time_origin);
    let golden = moves(case);
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
        let lag = golden[i].print_time - planned;
        let new_move = i == 0 || golden[i].print_time != golden[i - 1].print_time;
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
    for (i, ((trapq, m), g)) in ours.iter().zip(&golden).enumerate() {
        let ctx = format!("{case} move {i}: ours {trapq:?} {m:?}\n golden {g:?}");
        assert_eq!(*trapq, g.trapq, "{ctx}");
        let time = |a: f64, b: f64| (a - b).abs() <= 1e-6;
        let vel = |a: f64, b: f64| (a - b).abs() <= 1e-3 || (a - b).abs() <= 1e-4 * b.abs();
        let pos = |a: f64, b: f64| (a - b).abs() <= 1e-3; // 1 µm
        assert!(time(m.print_time, g.print_time), "print_time {ctx}");
        assert!(
            time(m.accel_t, g.accel_t)
                && time(m.cruise_t, g.cruise_t)
                && time(m.decel_t, g.decel_t),
            "phases {ctx}"
        );
        let (start_pos, axes_r) = (g.start_pos(), g.axes_r());
        for k in 0..3 {
            assert!(pos(m.start_pos[k], start_pos[k]), "start_pos[{k}] {ctx}");
            assert!((m.axes_r[k] - axes_r[k]).abs() <= 1e-9, "axes_r[{k}] {ctx}");
        }
        assert!(
            vel(m.start_v, g.start_v) && vel(m.cruise_v, g.cruise_v),
            "velocities {ctx}"
        );
        assert!(vel(m.accel, g.accel), "accel {ctx}");
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
    let mut checked = 0;
    for case in onechip_golden::cases() {
        let cfg_text = config(config_for(&case));
        let config = Config::parse(config_for(&case), &cfg_text).expect("config parses");
        let machine = Machine::from_config(&config).expect("machine");
        let final_pos = onechip_golden::summary_values(&case, "toolhead_final_position");
        let p = [final_pos[0], final_pos[1], final_pos[2]];
        let steppers: Vec<f64> = onechip_golden::summary_steppers(&case)
            .iter()
            .filter(|s| s.name != "extruder")
            .map(|s| s.commanded_pos)
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
        checked += 1;
    }
    assert!(checked > 0, "no golden case checked");
}
