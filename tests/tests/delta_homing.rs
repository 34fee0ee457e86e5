//! G28 on a linear delta in virtual time, as Klipper homes one: the three
//! towers home together, each carriage up to its own endstop, whose
//! trigger stops that tower alone while the others go on; the homing move
//! ends once all three have triggered, then the retract and the second
//! homing move; the toolhead is then at Klipper's home position (every
//! carriage at its endstop). A tower whose endstop never triggers fails
//! G28 with Klipper's message.

use onechip_host::{Options, Start, Summary};
use onechip_tests::sd_folder;
use std::path::{Path, PathBuf};

/// Arm length and delta radius, mm.
const ARM: f64 = 333.0;
const RADIUS: f64 = 174.75;
/// Tower angles (Klipper's defaults), degrees.
const ANGLES: [f64; 3] = [210.0, 330.0, 90.0];
/// mm per step of every tower (rotation_distance 40, 16 microsteps).
const STEP: f64 = 40.0 / (200.0 * 16.0);
/// example-delta.cfg's position_endstop, mm.
const ENDSTOP: f64 = 297.05;
const NAMES: [&str; 3] = ["stepper_a", "stepper_b", "stepper_c"];

/// Klipper's example-delta.cfg with `endstops` as the towers'
/// position_endstop (mm) and no extruder or heaters.
fn config(endstops: [f64; 3]) -> String {
    let pins = [
        ("PF13", "PF12", "PG6"),
        ("PG0", "PG1", "PG9"),
        ("PF11", "PG3", "PG10"),
    ];
    let mut text = String::new();
    for (k, (step, dir, endstop)) in pins.iter().enumerate() {
        text += &format!(
            "[{}]\nstep_pin: {step}\ndir_pin: {dir}\nmicrosteps: 16\nrotation_distance: 40\n\
             endstop_pin: ^{endstop}\nposition_endstop: {}\n",
            NAMES[k], endstops[k]
        );
        if k == 0 {
            text += "homing_speed: 50\narm_length: 333.0\n";
        }
    }
    text + "[mcu]\nserial: /dev/ttyACM0\n\n[printer]\nkinematics: delta\nmax_velocity: 300\n\
            max_accel: 3000\nmax_z_velocity: 150\ndelta_radius: 174.75\n"
}

fn sd(name: &str, endstops: [f64; 3], gcode: &str) -> PathBuf {
    sd_folder::new(
        &format!("delta-homing-{name}"),
        &config(endstops),
        Some(gcode),
    )
}

fn run(dir: &Path, start: [f64; 3], dead_endstop: Option<usize>) -> Summary {
    onechip_host::run_with(
        dir,
        &Options {
            start: Start::At(start),
            steps_dir: Some(dir.join("steps")),
            dead_endstop,
            ..Options::default()
        },
    )
    .expect("runs")
}

/// Tower `k`'s carriage height for toolhead position `p`, mm.
fn carriage(k: usize, p: [f64; 3]) -> f64 {
    let a = ANGLES[k].to_radians();
    let (dx, dy) = (a.cos() * RADIUS - p[0], a.sin() * RADIUS - p[1]);
    (ARM * ARM - dx * dx - dy * dy).sqrt() + p[2]
}

/// Tower `k`'s carriage height at its endstop, mm.
fn abs_endstop(k: usize, endstops: [f64; 3]) -> f64 {
    endstops[k] + (ARM * ARM - RADIUS * RADIUS).sqrt()
}

/// Print times (s) of the steps of `stepper` written by a run.
fn step_times(dir: &Path, stepper: &str, freq: f64) -> Vec<f64> {
    onechip_golden::steps_file(&dir.join("steps").join(format!("steps-{stepper}.txt")))
        .into_iter()
        .map(|(clock, _)| clock as f64 / freq)
        .collect()
}

/// M114's reply `reply` says X, Y, Z `xyz` and E 0 (a coordinate within
/// 1e-9 of 0 may be written -0.000, as Klipper's `%.3f` would).
fn assert_m114(reply: &str, xyz: [f64; 3]) {
    let values: Vec<f64> = reply
        .split_whitespace()
        .filter_map(|field| field.split_once(':')?.1.parse().ok())
        .collect();
    assert_eq!(values.len(), 4, "{reply}");
    for k in 0..3 {
        assert!((values[k] - xyz[k]).abs() < 0.0006, "{reply} vs {xyz:?}");
    }
    assert_eq!(values[3], 0.0, "{reply}");
}

/// Where each tower's carriage really is at the end, mm.
fn real_carriages(s: &Summary, start: [f64; 3]) -> [f64; 3] {
    core::array::from_fn(|k| carriage(k, start) + s.steppers[k].position as f64 * STEP)
}

/// The checks every successful G28 passes: two homing moves, in each every
/// tower triggers once, in the order its carriage meets its endstop,
/// stopping there; the towers stopped first stand still until the last
/// triggers while the others go on; the carriages end at their endstops.
fn check_homed(s: &Summary, dir: &Path, start: [f64; 3], endstops: [f64; 3]) {
    assert_eq!(s.errors, []);
    assert_eq!(s.shutdown, None);
    assert_eq!(s.endstops.len(), 6, "{:?}", s.endstops);
    // The first homing move: the tower nearest its endstop first.
    let mut expected = [0, 1, 2];
    let gap = |k: usize| abs_endstop(k, endstops) - carriage(k, start);
    expected.sort_by(|&a, &b| gap(a).total_cmp(&gap(b)));
    let towers: Vec<usize> = s.endstops.iter().map(|e| e.0).collect();
    assert_eq!(towers[..3], expected, "first homing move");
    let mut second = towers[3..].to_vec();
    second.sort();
    assert_eq!(second, [0, 1, 2], "second homing move");
    for &(k, real, time) in &s.endstops {
        let past = carriage(k, real) - abs_endstop(k, endstops);
        assert!(
            (-1e-9..=STEP + 1e-9).contains(&past),
            "tower {k} at {time:.3} s: stopped {past} mm past its endstop"
        );
    }
    let freq = s.mcu_freq;
    for (n, trio) in s.endstops.chunks(3).enumerate() {
        let (first, last) = (trio[0], trio[2]);
        if n == 0 {
            assert!(
                last.2 - first.2 > 0.005,
                "the towers trigger at different times: {trio:?}"
            );
        } else {
            // Each carriage retracted as far as the others from its
            // endstop: they meet their endstops again together.
            assert!(last.2 - first.2 < 0.002, "{trio:?}");
        }
        for (k, name) in NAMES.iter().enumerate() {
            let times = step_times(dir, name, freq);
            let between = times
                .iter()
                .filter(|&&t| t > first.2 && t <= last.2)
                .count();
            if k == first.0 {
                assert_eq!(between, 0, "tower {k} stopped at the first trigger");
            } else if n == 0 {
                assert!(between > 0, "tower {k} went on after the first trigger");
            }
            // After the last trigger the retract (or what follows G28)
            // comes at once, not after the rest of the planned move.
            let next = times.iter().find(|&&t| t > last.2);
            if let Some(next) = next {
                assert!(next - last.2 < 0.050, "tower {k}: next step at {next:.3} s");
            }
        }
    }
    let real = real_carriages(s, start);
    for (k, real) in real.iter().enumerate() {
        let past = real - abs_endstop(k, endstops);
        assert!(
            past.abs() <= STEP + 1e-9,
            "tower {k} ends {past} mm from its endstop"
        );
    }
}

#[test]
fn towers_home_together_each_stopped_by_its_own_endstop() {
    let endstops = [ENDSTOP; 3];
    let dir = sd("stock", endstops, "M119\nG28\nM114\nM119\n");
    let start = [40.0, -25.0, 150.0];
    let s = run(&dir, start, None);
    check_homed(&s, &dir, start, endstops);
    // Klipper's home position: every carriage at its endstop, which with
    // equal endstops and arms is straight above the centre.
    assert_m114(&s.replies[1].1, [0.0, 0.0, ENDSTOP]);
    // M119 names the towers' endstops as Klipper does; after G28 every
    // carriage rests on its switch.
    assert_eq!(s.replies[0].1, "a:open b:open c:open");
    assert_eq!(s.replies[2].1, "a:TRIGGERED b:TRIGGERED c:TRIGGERED");
    let expected = [0.0, 0.0, ENDSTOP];
    for (p, e) in s.final_position.iter().zip(expected) {
        assert!((p - e).abs() < 1e-6, "{:?}", s.final_position);
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn calibrated_endstops_home_to_where_every_carriage_meets_its_own() {
    // As after DELTA_CALIBRATE: the endstops differ, the home position
    // is off-centre and its Z above the lowest endstop.
    let endstops = [297.05, 296.4, 297.6];
    let dir = sd("calibrated", endstops, "G28\nM114\nG1 Z280 F3000\nM114\n");
    let start = [-30.0, 50.0, 100.0];
    let s = run(&dir, start, None);
    let p = s.final_position;
    // The move to Z 280 kept X and Y: before it, every carriage was at
    // its endstop.
    let home = [p[0], p[1], 0.0];
    let home_z: Vec<f64> = (0..3)
        .map(|k| abs_endstop(k, endstops) - carriage(k, home))
        .collect();
    for z in &home_z {
        assert!((z - home_z[0]).abs() < 1e-6, "{home_z:?} at {p:?}");
    }
    assert!(home[0].abs() > 0.05 || home[1].abs() > 0.05, "off-centre");
    assert!(home_z[0] > 296.4 && home_z[0] < 297.6, "{home_z:?}");
    assert_eq!(
        s.replies[0].1,
        format!("X:{:.3} Y:{:.3} Z:{:.3} E:0.000", p[0], p[1], home_z[0])
    );
    assert_eq!(
        s.replies[1].1,
        format!("X:{:.3} Y:{:.3} Z:280.000 E:0.000", p[0], p[1])
    );
    // Homing as above, checked on a run that ends with G28.
    let dir2 = sd("calibrated-g28", endstops, "G28\n");
    let s2 = run(&dir2, start, None);
    check_homed(&s2, &dir2, start, endstops);
    // And the toolhead really is where the firmware thinks.
    let real = s.real_position.expect("known start");
    for k in 0..3 {
        assert!((real[k] - p[k]).abs() < 0.05, "real {real:?} vs {p:?}");
    }
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_dir_all(&dir2).ok();
}

#[test]
fn a_tower_whose_endstop_never_triggers_fails_g28_with_klippers_message() {
    let endstops = [ENDSTOP; 3];
    let dir = sd("dead", endstops, "G28\nG1 Z100 F3000\n");
    let start = [20.0, 10.0, 120.0];
    let s = run(&dir, start, Some(1));
    assert_eq!(s.shutdown, None);
    let errors: Vec<&str> = s.errors.iter().map(|e| e.1.as_str()).collect();
    assert_eq!(errors.len(), 2, "{errors:?}");
    assert_eq!(errors[0], "No trigger on b after full movement");
    // G28 failed: the delta must be homed again before it moves.
    assert!(errors[1].starts_with("Must home first"), "{errors:?}");
    // A and C stopped at their endstops; B ran the whole move.
    let towers: Vec<usize> = s.endstops.iter().map(|e| e.0).collect();
    let mut sorted = towers.clone();
    sorted.sort();
    assert_eq!(sorted, [0, 2], "{towers:?}");
    let real = real_carriages(&s, start);
    for k in [0, 2] {
        let past = real[k] - abs_endstop(k, endstops);
        assert!((0.0..=STEP + 1e-9).contains(&past), "tower {k}: {past}");
    }
    assert!(
        real[1] > abs_endstop(1, endstops) + 100.0,
        "B ran on: {real:?}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn without_simulated_endstops_delta_homing_runs_its_moves_whole_as_klippy_batch() {
    let dir = sd("ideal", [ENDSTOP; 3], "G28\nM114\n");
    let s = onechip_host::run_with(
        &dir,
        &Options {
            start: Start::Ideal,
            ..Options::default()
        },
    )
    .expect("runs");
    assert_eq!((s.errors.len(), s.shutdown.as_ref()), (0, None));
    assert_eq!(s.endstops, []);
    assert_m114(&s.replies[0].1, [0.0, 0.0, ENDSTOP]);
    std::fs::remove_dir_all(&dir).ok();
}

/// What the planner hands out while homing, in order.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Planned {
    SetPosition([f64; 3]),
    Move { start: [f64; 3], cruise_v: f64 },
    Homing(onechip_planner::move_sink::HomingMove),
}

#[derive(Default)]
struct Recorder(Vec<Planned>);

impl onechip_planner::move_sink::MoveSink for Recorder {
    fn toolhead(&mut self, m: &onechip_planner::move_sink::TrapqMove) {
        self.0.push(Planned::Move {
            start: m.start_pos,
            cruise_v: m.cruise_v,
        });
    }
    fn extruder(&mut self, _: &onechip_planner::move_sink::TrapqMove) {}
    fn set_position(&mut self, pos: [f64; 3]) {
        self.0.push(Planned::SetPosition(pos));
    }
    fn homing_move_end(
        &mut self,
        homing: &onechip_planner::move_sink::HomingMove,
    ) -> onechip_planner::move_sink::HomingEnd {
        self.0.push(Planned::Homing(*homing));
        onechip_planner::move_sink::HomingEnd {
            position: homing.target,
            stopped_at: None,
            untriggered: None,
            comms_timeout: false,
        }
    }
}

#[test]
fn the_planner_homes_a_delta_with_klippers_forcepos_speeds_and_retract() {
    let text = config([ENDSTOP; 3]) + "[stepper_a]\nhoming_retract_dist: 4\n";
    // A second header adds the option to stepper_a (sections merge).
    let config = onechip_config::Config::parse("printer.cfg", &text).expect("parses");
    let machine = onechip_planner::machine::Machine::from_config(&config).expect("a delta");
    let mut toolhead = machine.toolhead::<16>();
    let mut sink = Recorder::default();
    toolhead.home(&[0], &mut sink).expect("homes");
    // delta.py: max_xy2 = min(print_radius, min_arm - radius,
    // ratio_to_xy(4 * SLOW_RATIO))^2, forcepos z = -1.5 sqrt(arm2 - max_xy2).
    let half_step = STEP / 2.0;
    let ratio_to_xy = |r: f64| {
        r * (ARM * ARM / (r * r + 1.0) - half_step * half_step).sqrt() + half_step - RADIUS
    };
    let max_xy = RADIUS.min(ARM - RADIUS).min(ratio_to_xy(12.0));
    let force_z = -1.5 * (ARM * ARM - max_xy * max_xy).sqrt();
    let positions: Vec<[f64; 3]> = sink
        .0
        .iter()
        .filter_map(|e| match e {
            Planned::SetPosition(p) => Some(*p),
            _ => None,
        })
        .collect();
    let near = |a: [f64; 3], b: [f64; 3]| (0..3).all(|k| (a[k] - b[k]).abs() < 1e-9);
    assert!(near(positions[0], [0.0, 0.0, force_z]), "{positions:?}");
    let homings: Vec<_> = sink
        .0
        .iter()
        .filter_map(|e| match e {
            Planned::Homing(h) => Some(*h),
            _ => None,
        })
        .collect();
    assert_eq!(homings.len(), 2);
    for (h, speed) in homings.iter().zip([50.0, 25.0]) {
        // Every tower on its own endstop, up to the home position at
        // stepper_a's homing_speed, then at half of it.
        assert!(h.towers && !h.probe);
        assert!(near(h.target, [0.0, 0.0, ENDSTOP]), "{h:?}");
        assert_eq!(h.speed, speed);
    }
    // Between them: the retract (4 mm down at the homing speed, which
    // homing_retract_speed defaults to), and the position set 4 mm below
    // that.
    let second = sink
        .0
        .iter()
        .position(|e| matches!(e, Planned::Homing(_)))
        .expect("first homing move");
    let retract = sink.0[second + 1..]
        .iter()
        .find_map(|e| match e {
            Planned::Move { start, cruise_v } => Some((*start, *cruise_v)),
            _ => None,
        })
        .expect("retract");
    assert!(near(retract.0, [0.0, 0.0, ENDSTOP]), "{retract:?}");
    assert!(retract.1 <= 50.0 + 1e-9, "{retract:?}");
    assert!(
        positions
            .iter()
            .any(|&p| near(p, [0.0, 0.0, ENDSTOP - 8.0])),
        "{positions:?}"
    );
}
