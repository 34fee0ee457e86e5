//! Step generation against klippy's own steps: the golden planned moves
//! (`moves.tsv`, which the planner reproduces) through our solver and
//! compressor give, per stepper, the same number of steps, the same
//! directions, and every step clock within `max_error` ticks of klippy's
//! (as the MCU's 32-bit clock sees it); also with the print starting 24 h
//! in and across the MCU clock's 32-bit wrap. cart_move_g28 (homing) runs
//! from our planner's events, which include the set_positions that
//! moves.tsv does not show.

use onechip_config::Config;
use onechip_golden::{Trapq, config_for, summary_value, trapq_moves};
use onechip_planner::gcode::parse;
use onechip_planner::gcode_move::GcodeMove;
use onechip_planner::kinematics::StepperKinematics;
use onechip_planner::machine::Machine;
use onechip_planner::move_sink::{MoveSink, TrapqMove};
use onechip_stepgen::compress::{Compressor, StepCommand, expand};
use onechip_stepgen::extruder::{self, PressureAdvance};
use onechip_stepgen::motion::{Motion, StepSink};
use onechip_stepgen::segment::{Segment, fill_gaps, segments};
use onechip_stepgen::shaper::StepperShaper;
use onechip_stepgen::solver::{Margins, PositionFn, StepSolver};

/// The golden trapq entries of `trapq`.
fn moves(case: &str, trapq: Trapq) -> Vec<TrapqMove> {
    trapq_moves(case, trapq)
        .iter()
        .map(onechip_golden::TrapqAppend::trapq_move)
        .collect()
}

/// The machine `case` ran on. A machine borrows its config text, which is
/// leaked here (a few kB a call).
fn machine(case: &str) -> Machine<'static> {
    let name = config_for(case);
    let text = onechip_golden::config(name).leak();
    let config = Config::parse(name, text).unwrap_or_else(|e| panic!("{case}: {e}"));
    Machine::from_config(&config).unwrap_or_else(|e| panic!("{case}: {e}"))
}

/// Segments moving from where the last set_position (or the start) put
/// the toolhead, which is `start` (mm).
struct Run {
    start: [f64; 3],
    segs: Vec<Segment>,
}

/// Our steps for one stepper: (clock, positive direction). Also checks
/// that the commands expand to our own ideal steps, each in
/// `[ideal - max_error, ideal]`, and respect the MCU's limits.
/// `position(segs, i, t)` is the stepper's position at `t` s into `segs[i]`.
fn our_steps(
    runs: &[Run],
    margins: Margins,
    position: impl Fn(&[Segment], usize, f64) -> f64,
    kin: StepperKinematics,
    step_dist: f64,
    freq: f64,
    max_error: u32,
) -> Vec<(u64, bool)> {
    let Some(first) = runs.first() else {
        return Vec::new();
    };
    let mut solver = StepSolver::new(kin, step_dist, first.start);
    let mut compressor = Compressor::<4096>::new(max_error, freq);
    let mut commands = Vec::new();
    let mut ideal = Vec::new();
    let mut out = |c: StepCommand, _| commands.push(c);
    for (k, run) in runs.iter().enumerate() {
        solver.set_position(run.start);
        let segs = &run.segs;
        // Up to the next set_position: everything this run moves.
        let until = match runs.get(k + 1) {
            Some(_) => segs.last().map_or(f64::NEG_INFINITY, |s| s.end_time()) + margins.after,
            None => f64::INFINITY,
        };
        solver.generate_until(
            segs,
            margins,
            until,
            |i| {
                let position = &position;
                move |t| position(segs, i, t)
            },
            |s| {
                ideal.push(((s.time * freq + 0.5) as u64, s.dir));
                compressor.append(s.time, s.dir, &mut out);
            },
        );
    }
    compressor.flush(&mut out);
    assert!(
        commands
            .iter()
            .all(|c| !matches!(c, StepCommand::Steps { count: 0, .. })),
        "empty sequence"
    );
    let mut steps = Vec::new();
    expand(&commands, |clock, dir| steps.push((clock, dir)));
    // Walk both in order: each expanded step is its ideal step moved at most
    // max_error earlier; ideal steps skipped on the way are pairs the
    // step+dir+step filter removed (a step and its immediate reversal).
    let mut j = 0;
    for (i, &(clock, dir)) in steps.iter().enumerate() {
        let start = j;
        while j < ideal.len() {
            let (c, d) = ideal[j];
            let early = c.wrapping_sub(clock) as u32;
            if d == dir && early <= max_error {
                break;
            }
            j += 1;
        }
        assert!(j < ideal.len(), "expanded step {i} matches no ideal step");
        let skipped = &ideal[start..j];
        assert!(
            skipped.len() % 2 == 0,
            "step {i}: {} ideal steps skipped",
            skipped.len()
        );
        assert!(
            skipped.chunks(2).all(|p| p[0].1 != p[1].1),
            "step {i}: skipped steps are not reversals"
        );
        j += 1;
    }
    steps
}

/// What the planner hands step generation.
#[derive(Clone, Copy)]
enum Event {
    Toolhead(TrapqMove),
    Extruder(TrapqMove),
    SetPosition([f64; 3]),
}

/// The golden planned moves (klippy's trapq appends) as events. They carry
/// no set_position: only for cases whose only one is the prologue's.
fn golden_events(case: &str) -> Vec<Event> {
    let mut events: Vec<Event> = moves(case, Trapq::Toolhead)
        .into_iter()
        .map(Event::Toolhead)
        .collect();
    events.extend(
        moves(case, Trapq::Extruder)
            .into_iter()
            .map(Event::Extruder),
    );
    events
}

struct Planned(Vec<Event>);

impl MoveSink for Planned {
    fn toolhead(&mut self, m: &TrapqMove) {
        self.0.push(Event::Toolhead(*m));
    }
    fn extruder(&mut self, m: &TrapqMove) {
        self.0.push(Event::Extruder(*m));
    }
    fn set_position(&mut self, pos: [f64; 3]) {
        self.0.push(Event::SetPosition(pos));
    }
}

/// Our planner's events for a case's G-code (moves and set_position), with
/// each move's start time taken from golden: klippy's batch-mode flushing
/// can delay a restart from rest (the planner's golden test explains and
/// bounds this); durations and positions must match.
fn planned_events(case: &str) -> Vec<Event> {
    let machine = machine(case);
    let mut toolhead = machine.toolhead::<1024>();
    let mut gcode = GcodeMove::default();
    let mut planned = Planned(Vec::new());
    let mut replies = String::new();
    let program = onechip_golden::gcode(case);
    for (n, line) in program.lines().enumerate() {
        let parsed = parse(line).unwrap_or_else(|e| panic!("{case}:{}: {e}", n + 1));
        gcode
            .execute(&parsed, &mut toolhead, &mut planned, &mut replies)
            .unwrap_or_else(|e| panic!("{case}:{}: {e}", n + 1));
    }
    gcode.finish(&mut toolhead, &mut planned);
    let (mut golden_toolhead, mut golden_extruder) = (
        moves(case, Trapq::Toolhead).into_iter(),
        moves(case, Trapq::Extruder).into_iter(),
    );
    for event in &mut planned.0 {
        let (m, golden) = match event {
            Event::Toolhead(m) => (m, golden_toolhead.next()),
            Event::Extruder(m) => (m, golden_extruder.next()),
            Event::SetPosition(_) => continue,
        };
        let golden = golden.expect("golden has as many moves");
        let duration = |m: &TrapqMove| m.accel_t + m.cruise_t + m.decel_t;
        assert!((duration(m) - duration(&golden)).abs() < 1e-9);
        assert!((0..3).all(|k| (m.start_pos[k] - golden.start_pos[k]).abs() < 1e-6));
        m.print_time = golden.print_time;
    }
    assert!(golden_toolhead.next().is_none() && golden_extruder.next().is_none());
    planned.0
}

/// Toolhead runs between set_position events, and the extruder's segments.
fn split(events: &[Event]) -> (Vec<Run>, Vec<Segment>) {
    let mut runs: Vec<Run> = Vec::new();
    let mut extruder = Vec::new();
    for event in events {
        match event {
            Event::SetPosition(pos) => runs.push(Run {
                start: *pos,
                segs: Vec::new(),
            }),
            Event::Toolhead(m) => {
                if runs.is_empty() {
                    runs.push(Run {
                        start: m.start_pos,
                        segs: Vec::new(),
                    });
                }
                if let Some(run) = runs.last_mut() {
                    run.segs.extend(segments(m));
                }
            }
            Event::Extruder(m) => extruder.extend(segments(m)),
        }
    }
    (runs, extruder)
}

fn check(case: &str, with_extruder: bool) {
    check_events(case, with_extruder, &golden_events(case));
}

/// Checks a case three times: as klippy ran it, with the print starting
/// 24 h in, and with the MCU clock 1 s before its 32-bit wrap at the start
/// (the print then crosses it).
fn check_events(case: &str, with_extruder: bool, events: &[Event]) {
    let freq = summary_value(case, "clock_freq");
    let day = (86_400.0 * freq) as u64;
    let before_wrap = (1u64 << 32) - freq as u64;
    for origin_ticks in [0, day, before_wrap] {
        let origin = origin_ticks as f64 / freq;
        let shifted: Vec<Event> = events
            .iter()
            .map(|e| match *e {
                Event::Toolhead(m) => Event::Toolhead(TrapqMove {
                    print_time: m.print_time + origin,
                    ..m
                }),
                Event::Extruder(m) => Event::Extruder(TrapqMove {
                    print_time: m.print_time + origin,
                    ..m
                }),
                other => other,
            })
            .collect();
        check_from(case, with_extruder, &shifted, origin_ticks);
    }
}

/// Checks our steps for `events` against golden's, `origin_ticks` later.
fn check_from(case: &str, with_extruder: bool, events: &[Event], origin_ticks: u64) {
    let machine = machine(case);
    let freq = summary_value(case, "clock_freq");
    let max_error = summary_value(case, "max_error_ticks") as u32;
    let (mut runs, extruder_segs) = split(events);
    let mut steppers: Vec<(&str, Vec<(u64, bool)>)> = Vec::new();
    for (i, kin) in machine.stepper_kinematics.iter().enumerate() {
        let s = &machine.steppers[i];
        let shaper = StepperShaper::new(&machine.input_shaper, *kin);
        let steps = if shaper.is_active() {
            for run in &mut runs {
                let mut filled = Vec::new();
                fill_gaps(&run.segs, machine.scan_delay(), |s| filled.push(s));
                run.segs = filled;
            }
            let position =
                |segs: &[Segment], j: usize, t: f64| shaper.on_segment(segs, j, *kin).at(t);
            let margins = shaper.margins();
            our_steps(&runs, margins, position, *kin, s.step_dist, freq, max_error)
        } else {
            let position = |segs: &[Segment], j: usize, t: f64| kin.position(segs[j].position(t));
            let margins = Margins::default();
            our_steps(&runs, margins, position, *kin, s.step_dist, freq, max_error)
        };
        steppers.push((s.name, steps));
    }
    if with_extruder
        && let Some(e) = machine.steppers.get(3)
        && let Some(config) = machine.extruder_stepper(3)
    {
        let pa = PressureAdvance::new(config.pressure_advance, config.smooth_time);
        let mut filled = Vec::new();
        fill_gaps(&extruder_segs, pa.half_smooth_time, |s| filled.push(s));
        let runs = [Run {
            start: [filled.first().map_or(0.0, |s| s.start_pos[0]), 0.0, 0.0],
            segs: filled,
        }];
        let position = |segs: &[Segment], j: usize, t: f64| extruder::position(segs, j, t, &pa);
        let kin = StepperKinematics::Axis(0);
        steppers.push((
            e.name,
            our_steps(
                &runs,
                Margins::both(pa.half_smooth_time),
                position,
                kin,
                e.step_dist,
                freq,
                max_error,
            ),
        ));
    }
    for (name, ours) in steppers {
        let golden = onechip_golden::steps(case, name);
        assert_eq!(ours.len(), golden.len(), "{case} {name}: step count");
        let mut deviations = Vec::with_capacity(ours.len());
        for (i, (o, g)) in ours.iter().zip(&golden).enumerate() {
            assert_eq!(o.1, g.1, "{case} {name}: direction of step {i}");
            // The MCU counts in 32 bits; a step more than 2^32 ticks after
            // the previous one is sent modulo 2^32 (as klippy does), so
            // compare as the MCU sees clocks.
            let d = i64::from(o.0.wrapping_sub(g.0 + origin_ticks) as u32 as i32);
            deviations.push(d.unsigned_abs());
            assert!(
                d.abs() <= i64::from(max_error),
                "{case} {name}: step {i} at {} vs golden {} ({d} ticks)",
                o.0,
                g.0
            );
        }
        deviations.sort_unstable();
        let us = |q: f64| {
            let i = ((deviations.len() as f64 - 1.0) * q) as usize;
            deviations.get(i).map_or(0.0, |&d| d as f64 / freq * 1e6)
        };
        println!(
            "{case} (from tick {origin_ticks}) {name}: {} steps, deviation from golden p50 {:.2} us, p99 {:.2} us, max {:.2} us",
            ours.len(),
            us(0.5),
            us(0.99),
            us(1.0)
        );
    }
}

#[test]
fn cart_square() {
    check("cart_square", true);
}

#[test]
fn cart_circle() {
    check("cart_circle", true);
}

#[test]
fn cart_extrude() {
    check("cart_extrude", true);
}

#[test]
fn corexy_square() {
    check("corexy_square", false);
}

#[test]
fn corexy_circle() {
    check("corexy_circle", false);
}

#[test]
fn avr_and_h723_clocks() {
    check("avr_cart_extrude", true);
    check("h723_cart_extrude", true);
}

#[test]
fn delta_square_and_circle() {
    check("delta_square", true);
    check("delta_circle", true);
}

#[test]
fn delta_and_shaperless_extrude() {
    check("delta_extrude", true);
}

#[test]
fn corexy_extrude_with_pressure_advance() {
    check("corexy_extrude", true);
}

#[test]
fn cart_move_g28_with_homing() {
    let events = planned_events("cart_move_g28");
    assert!(
        events
            .iter()
            .filter(|e| matches!(e, Event::SetPosition(_)))
            .count()
            > 3,
        "homing sets positions"
    );
    check_events("cart_move_g28", true, &events);
}

#[test]
fn shaper_square() {
    check("shaper_square", true);
}

#[test]
fn shaper_circle() {
    check("shaper_circle", true);
}

#[test]
fn shaper_extrude() {
    check("shaper_extrude", true);
}

/// Collects each stepper's commands with their first steps' 64-bit clocks.
struct Commands(Vec<Vec<(StepCommand, u64)>>);

impl StepSink for Commands {
    fn command(&mut self, index: usize, cmd: StepCommand, clock: u64) {
        self.0[index].push((cmd, clock));
    }
}

/// Expands commands with 64-bit clocks: each sequence from the clock given
/// with it (which a far step's 32-bit interval does not carry).
fn expand_64(cmds: &[(StepCommand, u64)]) -> Vec<(u64, bool)> {
    let mut steps = Vec::new();
    let mut dir = true;
    for &(cmd, first) in cmds {
        match cmd {
            StepCommand::Dir(d) => dir = d,
            StepCommand::ResetClock(_) => {}
            StepCommand::Steps {
                interval,
                count,
                add,
            } => {
                let (mut clock, mut interval) = (first, interval);
                for k in 0..count {
                    if k > 0 {
                        interval = interval.wrapping_add(add as u32);
                        clock += u64::from(interval);
                    }
                    steps.push((clock, dir));
                }
            }
        }
    }
    steps
}

/// The whole pipeline as the firmware runs it: moves streamed in time
/// order through [`Motion`] with queues of only 64 segments (so generation
/// runs while moves arrive and the queues are pruned behind it), its
/// commands expanded as the MCU does, against golden.
fn check_motion(case: &str, events: &[Event]) {
    let machine = machine(case);
    let freq = summary_value(case, "clock_freq");
    let max_error = summary_value(case, "max_error_ticks") as u32;
    let start = events
        .iter()
        .find_map(|e| match e {
            Event::Toolhead(m) => Some(m.start_pos),
            _ => None,
        })
        .unwrap_or([0.0; 3]);
    let mut motion = Motion::<64, 512>::new(&machine, freq, max_error, start);
    let mut commands = Commands(vec![Vec::new(); machine.steppers.len()]);
    let mut sink = motion.sink(&mut commands);
    for event in events {
        match event {
            Event::Toolhead(m) => sink.toolhead(m),
            Event::Extruder(m) => sink.extruder(m),
            Event::SetPosition(pos) => sink.set_position(*pos),
        }
    }
    motion.finish(&mut commands);
    assert_eq!(motion.error(), None);
    for (stepper, cmds) in machine.steppers.iter().zip(&commands.0) {
        let mut ours = Vec::new();
        let plain: Vec<StepCommand> = cmds.iter().map(|c| c.0).collect();
        expand(&plain, |clock, dir| ours.push((clock, dir)));
        let golden = onechip_golden::steps(case, stepper.name);
        // The clocks given with the commands place every step exactly as
        // the 32-bit expansion does, but in 64 bits, also after far steps.
        let with_clocks = expand_64(cmds);
        assert!(
            with_clocks
                .iter()
                .zip(&ours)
                .all(|(a, b)| a.0 as u32 == b.0 as u32 && a.1 == b.1)
        );
        assert!(
            with_clocks
                .iter()
                .zip(&golden)
                .all(|(a, g)| a.0.abs_diff(g.0) <= u64::from(max_error)),
            "{case} {}: 64-bit clocks",
            stepper.name
        );
        assert_eq!(
            ours.len(),
            golden.len(),
            "{case} {}: step count",
            stepper.name
        );
        for (i, (o, g)) in ours.iter().zip(&golden).enumerate() {
            let d = (o.0.wrapping_sub(g.0) as u32 as i32).unsigned_abs();
            assert!(
                o.1 == g.1 && d <= max_error,
                "{case} {}: step {i} ours {o:?} golden {g:?}",
                stepper.name
            );
        }
    }
}

/// Golden moves in the order klippy appends them: by start time, a G1's
/// toolhead part before its extruder part.
fn time_ordered(mut events: Vec<Event>) -> Vec<Event> {
    let start = |e: &Event| match e {
        Event::Toolhead(m) | Event::Extruder(m) => m.print_time,
        Event::SetPosition(_) => f64::NEG_INFINITY,
    };
    events.sort_by(|a, b| start(a).total_cmp(&start(b)));
    events
}

#[test]
fn streamed_through_small_queues() {
    let cases = onechip_golden::cases();
    for case in &cases {
        // Homing sets positions, which only our planner's events carry.
        let events = if case == "cart_move_g28" {
            planned_events(case)
        } else {
            time_ordered(golden_events(case))
        };
        check_motion(case, &events);
    }
    assert!(cases.iter().any(|c| c == "cart_move_g28"), "{cases:?}");
}

#[test]
fn a_queue_too_small_for_the_shaper_window_is_an_error_not_a_panic() {
    let machine = machine("shaper_circle");
    // 12 segments cannot hold the shaper's ~30 ms look-back of 1 ms moves.
    let mut motion = Motion::<12, 64>::new(&machine, 180e6, 4500, [100.0, 100.0, 10.0]);
    let mut commands = Commands(vec![Vec::new(); machine.steppers.len()]);
    let mut sink = motion.sink(&mut commands);
    for event in time_ordered(golden_events("shaper_circle")) {
        match event {
            Event::Toolhead(m) => sink.toolhead(&m),
            Event::Extruder(m) => sink.extruder(&m),
            Event::SetPosition(pos) => sink.set_position(pos),
        }
    }
    assert_eq!(
        motion.error(),
        Some(onechip_stepgen::motion::MotionError::QueueTooSmall)
    );
}
