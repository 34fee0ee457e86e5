//! The whole firmware executes: the `onechip-qemu` image (the board's
//! printer session on QEMU's emulated Cortex-M7) is built with a golden
//! machine's printer.cfg, a golden case's G-code is streamed over the
//! emulated UART with the console protocol (line numbers, checksums, an
//! `ok` awaited per line), and the step edges the TCG plugin logged from
//! the pins are compared with klippy's: the same steps, in the same
//! directions, ending at the same position, for every stepper, none
//! faster than klippy's peak rate; and their intervals.
//!
//! Two more runs: the worst golden case (the delta) with input shaping
//! and pressure advance added must keep up (every line acknowledged, no
//! shutdown, klippy's final positions, at most 25 % of the CPU busy); and
//! single-axis moves at rising step rates find the highest rate the
//! firmware sustains.
//!
//! Timing: klippy's batch run and a streamed print start at different
//! times and can take different lookahead decisions (see
//! golden_end_to_end.rs: klippy's own depended on its processing speed),
//! which re-time a move and shift every later step. So the step
//! intervals are compared: each must equal klippy's within twice the
//! tolerance (max_error, the measured interrupt latency and a 40 ns tick,
//! at either end), but for at most 0.1 % of them (re-timed moves, which
//! are printed with the absolute offsets before the first).
//!
//! The golden machines' extruder heaters cannot heat here (the
//! thermistors read 25 °C): the image's printer.cfg adds
//! `min_extrude_temp: 0`, as klippy's batch mode lets them extrude cold.
//!
//! Figures (printed, `--nocapture`): steps and pin writes, interrupt
//! latency, CPU share of the stepper and heater interrupts, thread code
//! and idle, stack and static RAM.

use onechip_tests::qemu::{self, NS_PER_INSN, Qemu, Run};

/// Klipper's step time tolerance (`MAX_STEPCOMPRESS_ERROR`), s.
const MAX_ERROR: f64 = 0.000_025;

/// A golden machine's printer.cfg, extruding cold.
fn config(case: &str) -> String {
    let machine = onechip_golden::config(onechip_golden::config_for(case));
    format!("{machine}\n[extruder]\nmin_extrude_temp: 0\n")
}

/// Share of the run's instructions spent in `context`, %.
fn share(run: &Run, context: &str) -> f64 {
    let insns = run.cpu(context).map_or(0, |c| c.insns);
    100.0 * insns as f64 / run.total.max(1) as f64
}

/// Seconds of virtual time after `insns` instructions.
fn seconds(insns: u64) -> f64 {
    (insns * NS_PER_INSN) as f64 * 1e-9
}

/// The step intervals (from each step to the stepper's next) that
/// differ from klippy's by more than `2 * tol` s: (klippy time of the
/// step, s; the difference, s), and how many intervals there are.
/// `steppers` holds each stepper's pin steps (instructions) and klippy's
/// (clocks at `freq`).
fn retimed(steppers: &Compared, freq: f64, tol: f64) -> (Vec<(f64, f64)>, usize) {
    let mut outliers = Vec::new();
    let mut intervals = 0;
    for (_, made, golden) in steppers {
        let at = |k: usize| (seconds(made[k].0), golden[k].0 as f64 / freq);
        for k in 1..made.len().min(golden.len()) {
            let ((m, g), (pm, pg)) = (at(k), at(k - 1));
            let error = (m - pm) - (g - pg);
            if error.abs() > 2.0 * tol {
                outliers.push((g, error));
            }
            intervals += 1;
        }
    }
    outliers.sort_by(|a, b| a.0.total_cmp(&b.0));
    (outliers, intervals)
}

/// The least and most offset of a step from klippy's (pin time less
/// klippy's time, s) over the steps klippy made before `until` (s), and
/// how many there are.
fn offsets(steppers: &Compared, freq: f64, until: f64) -> (f64, f64, usize) {
    steppers
        .iter()
        .flat_map(|(_, made, golden)| made.iter().zip(golden))
        .map(|(&(m, _), &(g, _))| (seconds(m), g as f64 / freq))
        .filter(|&(_, g)| g < until)
        .fold(
            (f64::INFINITY, f64::NEG_INFINITY, 0),
            |(lo, hi, n), (m, g)| (lo.min(m - g), hi.max(m - g), n + 1),
        )
}

/// A finished run of golden case `case`'s G-code on printer.cfg
/// `config`, with what the test needs of it.
struct Streamed {
    case: &'static str,
    config: String,
    run: Run,
    lines: usize,
    /// The firmware's measured interrupt latency, most, s.
    latency: f64,
}

/// Builds the image for `config` (named `name`), streams golden case
/// `case`'s G-code through it on QEMU: every line must be acknowledged
/// without an error, nothing may panic or shut down, the stack guard
/// must be intact.
fn stream(name: &str, case: &'static str, config: String) -> Streamed {
    let elf = qemu::build_firmware(name, &config);
    let mut machine = Qemu::start(&elf, name);
    let transcript = machine.stream(&onechip_golden::gcode(case));
    // As klippy at the end of its input: a 0.5 s dwell. M400 waits for
    // the planned moves' end; shaped and pressure-advanced steps come up
    // to the smoothing windows later.
    machine.send("G4 P500");
    machine.send("M400");
    // A shutdown is reported on the next line.
    let last = machine.send("M114");
    let run = machine.finish();
    assert!(
        !run.reports.contains("panic") && !run.reports.contains("fault"),
        "{}",
        run.reports
    );
    let errors: Vec<_> = transcript
        .iter()
        .filter(|(_, replies)| {
            replies
                .iter()
                .any(|r| r.starts_with("!!") || r.starts_with("Error"))
        })
        .collect();
    assert!(errors.is_empty(), "{name}: {errors:?}");
    assert!(
        last.iter().all(|r| !r.starts_with("!!")),
        "{name}: {last:?}"
    );
    assert_eq!(run.stat("guard"), Some("intact"), "stack guard touched");
    let latency_ticks: f64 = run
        .stat("latency_max_ticks")
        .and_then(|v| v.parse().ok())
        .expect("the firmware's latency report");
    Streamed {
        case,
        config,
        run,
        lines: transcript.len(),
        latency: latency_ticks / qemu::CLOCK_HZ,
    }
}

/// Each stepper's name, steps from the pins and klippy's steps.
type Compared = Vec<(String, Vec<(u64, bool)>, Vec<(u64, bool)>)>;

impl Streamed {
    /// Each stepper's steps, from the pins and from klippy.
    fn steppers(&self) -> Compared {
        qemu::stepper_pins(&self.config)
            .into_iter()
            .map(|pins| {
                let made = self.run.steps(pins.step, pins.dir, pins.dir_inverted);
                let golden = onechip_golden::steps(self.case, &pins.name);
                (pins.name, made, golden)
            })
            .collect()
    }

    /// Asserts every stepper's final position equals klippy's; returns
    /// the steps made in all.
    fn check_positions(&self, steppers: &Compared) -> usize {
        let summaries = onechip_golden::summary_steppers(self.case);
        let position = |s: &[(u64, bool)]| {
            s.iter()
                .map(|&(_, d)| if d { 1i64 } else { -1 })
                .sum::<i64>()
        };
        for (name, made, golden) in steppers {
            let summary = summaries
                .iter()
                .find(|s| &s.name == name)
                .expect("golden stepper");
            assert_eq!(position(made), summary.final_mcu_pos, "{name}: position");
            println!(
                "{} {name}: {} steps (klippy {}), final position {}",
                self.case,
                made.len(),
                golden.len(),
                summary.final_mcu_pos
            );
        }
        steppers.iter().map(|(_, made, _)| made.len()).sum()
    }

    /// Each stepper's steps that came faster than twice klippy's peak
    /// for it in this case (printed with the shortest intervals): steps
    /// due before the interrupt could make them (an underrun, or a burst
    /// of steps queued at one clock) come out back to back, as fast as
    /// the interrupt can make them.
    fn bursts(&self, steppers: &Compared) -> Vec<(String, usize)> {
        let intervals = |s: &[(u64, bool)], ticks: &dyn Fn(u64) -> f64| {
            s.windows(2)
                .map(|w| ticks(w[1].0) - ticks(w[0].0))
                .collect::<Vec<_>>()
        };
        let freq = onechip_golden::summary_value(self.case, "clock_freq");
        steppers
            .iter()
            .map(|(name, made, golden)| {
                let pins = intervals(made, &|i| seconds(i));
                let klippy = intervals(golden, &|c| c as f64 / freq)
                    .into_iter()
                    .fold(f64::INFINITY, f64::min);
                let fast = pins.iter().filter(|&&t| t < klippy / 2.0).count();
                println!(
                    "{} {name}: shortest step interval {:.1} us (klippy {:.1} us), {fast} \
                     steps faster than twice klippy's peak",
                    self.case,
                    pins.iter().copied().fold(f64::INFINITY, f64::min) * 1e6,
                    klippy * 1e6
                );
                (name.clone(), fast)
            })
            .collect()
    }

    /// Prints the run's figures and checks the CPU accounting saw the
    /// interrupts and some idle time.
    fn report(&self, steps: usize) {
        let (case, run) = (self.case, &self.run);
        let edges = qemu::stepper_pins(&self.config)
            .iter()
            .map(|p| {
                run.writes
                    .iter()
                    .filter(|w| w.pin == p.step || w.pin == p.dir)
                    .count()
            })
            .sum::<usize>();
        println!(
            "{case} on QEMU mps2-an500: {} lines, {steps} steps, {edges} step/dir pin writes, \
             {:.3} s virtual ({} M instructions)",
            self.lines,
            seconds(run.total),
            run.total / 1_000_000
        );
        for context in ["stepper", "heaters", "console", "thread", "idle"] {
            if let Some(c) = run.cpu(context) {
                println!(
                    "{case} cpu {context}: {:.2} % ({} runs, longest {} instructions = {:.2} us \
                     at {:.4} s)",
                    share(run, context),
                    c.runs,
                    c.longest,
                    seconds(c.longest) * 1e6,
                    seconds(c.longest_at)
                );
            }
        }
        let stepper = run.cpu("stepper").expect("stepper interrupt accounted");
        println!(
            "{case} stepper interrupt: {:.0} instructions per step (with the 2 us step pulse)",
            stepper.insns as f64 / steps.max(1) as f64
        );
        println!(
            "{case} stepper interrupt latency: most {:.2} us, mean {} ticks of 40 ns; stack \
             used {} bytes (guard {}), static RAM {} bytes",
            self.latency * 1e6,
            run.stat("latency_mean_ticks").unwrap_or("?"),
            run.stat("stack_used").unwrap_or("?"),
            run.stat("guard").unwrap_or("?"),
            run.static_ram.unwrap_or(0)
        );
        assert!(stepper.runs as usize >= steps / 64, "the engine ran");
        assert!(share(run, "idle") > 0.0, "the CPU was never idle");
    }
}

#[test]
#[ignore = "needs qemu-system-arm and gcc (CI: .ci/run)"]
fn a_golden_print_streamed_over_the_uart_steps_the_pins_as_klippy() {
    let case = "cart_extrude";
    let streamed = stream(case, case, config(case));
    let steppers = streamed.steppers();
    for (name, made, golden) in &steppers {
        assert_eq!(made.len(), golden.len(), "{name}: steps");
        let dirs = |s: &[(u64, bool)]| s.iter().map(|&(_, d)| d).collect::<Vec<_>>();
        assert!(dirs(made) == dirs(golden), "{name}: directions");
    }
    let steps = streamed.check_positions(&steppers);
    for (name, fast) in streamed.bursts(&steppers) {
        assert_eq!(
            fast, 0,
            "{name}: steps faster than klippy's peak (an underrun)"
        );
    }

    let tol = MAX_ERROR + streamed.latency + 1.0 / qemu::CLOCK_HZ;
    let freq = onechip_golden::summary_value(case, "clock_freq");
    let (outliers, intervals) = retimed(&steppers, freq, tol);
    let until = outliers.first().map_or(f64::INFINITY, |o| o.0);
    let (lo, hi, timed) = offsets(&steppers, freq, until);
    println!(
        "{case}: {} of {intervals} step intervals differ from klippy's by more than {:.2} us \
         (re-timed moves: {:?}); the {timed} steps before the first lie within {:.2} us of \
         klippy's after an offset of {:.6} s",
        outliers.len(),
        2.0 * tol * 1e6,
        &outliers[..outliers.len().min(8)],
        (hi - lo) / 2.0 * 1e6,
        (hi + lo) / 2.0,
    );
    assert!(
        outliers.len() * 1000 <= intervals,
        "more than 0.1 % of the step intervals differ from klippy's"
    );
    streamed.report(steps);
}

/// The goal for the CPU's busy share over a print at 520 MHz-equivalent
/// (issue 18), %.
const BUSY_GOAL: f64 = 25.0;

#[test]
#[ignore = "needs qemu-system-arm and gcc (CI: .ci/run)"]
fn the_worst_case_with_input_shaping_and_pressure_advance_keeps_up() {
    // The delta (the most instructions per step) with klippy's cartesian
    // shaper settings and corexy's pressure advance added.
    let case = "delta_extrude";
    let config = format!(
        "{}\n[input_shaper]\nshaper_type_x: mzv\nshaper_freq_x: 40\nshaper_type_y: ei\n\
         shaper_freq_y: 35\n[extruder]\npressure_advance: 0.04\nmin_extrude_temp: 0\n",
        onechip_golden::config(onechip_golden::config_for(case))
    );
    let streamed = stream("delta_shaper_pa", case, config);
    // Shaping and pressure advance move the steps in time (and add back
    // and forth steps), not where each stepper ends.
    let steppers = streamed.steppers();
    let steps = streamed.check_positions(&steppers);
    // No step comes faster than twice klippy's fastest: a move after the
    // toolhead went idle starts after the shaped steps already generated
    // (before that fix, bursts of steps queued at one clock, such as
    // `Steps { interval: 0, count: 13 }`, came out 7 us apart).
    let fast: usize = streamed.bursts(&steppers).iter().map(|b| b.1).sum();
    println!("{case} with input shaping and pressure advance: {fast} steps in bursts");
    assert_eq!(fast, 0, "steps in bursts");
    streamed.report(steps);
    let busy = 100.0 - share(&streamed.run, "idle");
    println!("{case} with input shaping and pressure advance: {busy:.2} % busy");
    assert!(busy <= BUSY_GOAL, "{busy:.2} % busy");
}

/// Step rates tried by [`the_step_rate_limit_is_found`], steps/s of one
/// stepper, in the order tried.
const RATES: [f64; 8] = [
    50_000.0, 100_000.0, 150_000.0, 200_000.0, 250_000.0, 300_000.0, 350_000.0, 400_000.0,
];

#[test]
#[ignore = "needs qemu-system-arm and gcc (CI: .ci/run)"]
fn the_step_rate_limit_is_found() {
    // The golden cartesian machine with 256 microsteps on X (1280 steps
    // per mm) and limits high enough for every rate tried.
    let steps_per_mm = 1280.0;
    let config = format!(
        "{}\n[printer]\nmax_velocity: 400\nmax_accel: 20000\n[stepper_x]\nmicrosteps: 256\n",
        onechip_golden::config("cartesian.cfg")
    );
    let elf = qemu::build_firmware("step_rate", &config);
    let mut machine = Qemu::start(&elf, "step_rate");
    machine.send("M110 N0");
    machine.send("SET_KINEMATIC_POSITION X=0 Y=100 Z=10");
    let mut sent = Vec::new();
    for (k, rate) in RATES.iter().enumerate() {
        let speed = rate / steps_per_mm;
        let x = if k % 2 == 0 { 190 } else { 10 };
        let replies = machine.send(&format!("G1 X{x} F{:.0}", speed * 60.0));
        let done = machine.send("M400");
        let shutdown = replies.iter().chain(&done).any(|r| r.starts_with("!!"));
        println!("{rate} steps/s: {replies:?} {done:?}");
        sent.push(*rate);
        if shutdown {
            break;
        }
    }
    let run = machine.finish();
    let pins = qemu::stepper_pins(&config);
    let x = pins
        .iter()
        .find(|p| p.name == "stepper_x")
        .expect("stepper_x");
    let steps = run.steps(x.step, x.dir, x.dir_inverted);
    // One move per rate, each in one direction (the first from X0, 190
    // mm; then 180 mm): the runs of equal direction are the moves. A move
    // kept up if it made all its steps and, over its middle half (at
    // cruise), its steps came at the planned rate.
    let mut best = 0.0;
    for (k, (rate, chunk)) in sent
        .iter()
        .zip(steps.chunk_by(|a, b| a.1 == b.1))
        .enumerate()
    {
        let planned = if k == 0 { 190.0 } else { 180.0 } * steps_per_mm;
        let n = chunk.len();
        let cruise = seconds(chunk[3 * n / 4].0 - chunk[n / 4].0) / (3 * n / 4 - n / 4) as f64;
        let kept_up = n as f64 == planned && cruise <= 1.01 / rate;
        println!(
            "{rate} steps/s: {n} steps (planned {planned}), mean interval at cruise {:.3} us \
             (planned {:.3} us): {}",
            cruise * 1e6,
            1e6 / rate,
            if kept_up { "kept up" } else { "fell behind" }
        );
        if !kept_up {
            break;
        }
        best = *rate;
    }
    println!(
        "step rate limit: {best} steps/s on one stepper (2 us pulses); over the run: stepper \
         interrupt {:.1} %, thread code {:.1} %, idle {:.1} %",
        share(&run, "stepper"),
        share(&run, "thread"),
        share(&run, "idle")
    );
    assert!(best >= RATES[0], "not even {} steps/s", RATES[0]);
}
