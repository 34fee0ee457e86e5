//! Step compression is at least as good as Klipper's: every golden case's
//! planned moves, streamed through step generation with the board's queue
//! sizes ([`profile::MOTION_QUEUE`] segments, compressors of
//! [`profile::COMPRESS_QUEUE`]) and generated after every move as the
//! session generates after every line (homing moves dripped, as the
//! session runs them, to their end as in klippy's batch mode), give each
//! stepper no more commands (`queue_step`, `set_next_step_dir`,
//! `reset_step_clock`) than klippy sent it, and the same steps as klippy's
//! within max_error.
//!
//! `cargo test -p onechip-tests --test compression -- --nocapture` prints
//! the counts.

use onechip_app::session::profile;
use onechip_config::Config;
use onechip_golden::{Trapq, TrapqAppend, summary_steppers, summary_value, trapq_moves};
use onechip_planner::gcode::parse;
use onechip_planner::gcode_move::GcodeMove;
use onechip_planner::machine::Machine;
use onechip_planner::move_sink::{HomingEnd, HomingMove, MoveSink, TrapqMove};
use onechip_secondary_mcu::step_commands::StepCommandEncoder;
use onechip_stepgen::compress::{StepCommand, expand};
use onechip_stepgen::motion::{Motion, StepSink};

/// What the planner hands step generation.
#[derive(Clone, Copy)]
enum Event {
    Toolhead(TrapqMove),
    Extruder(TrapqMove),
    SetPosition([f64; 3]),
    /// A homing move's segments have all been handed over.
    Homing(HomingMove),
}

impl Event {
    /// The move's start (set_position, homing: none), s.
    fn print_time(&self) -> Option<f64> {
        match self {
            Self::Toolhead(m) | Self::Extruder(m) => Some(m.print_time),
            Self::SetPosition(_) | Self::Homing(_) => None,
        }
    }
}

/// Records the planner's events.
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
    fn homing_move_end(&mut self, homing: &HomingMove) -> HomingEnd {
        self.0.push(Event::Homing(*homing));
        HomingEnd {
            position: homing.target,
            stopped_at: None,
            untriggered: None,
            comms_timeout: false,
        }
    }
}

/// Each stepper's commands, with the 64-bit clock of each one's first
/// step (a direction change: of the step before it).
struct Commands(Vec<Vec<(StepCommand, u64)>>);

impl StepSink for Commands {
    fn command(&mut self, index: usize, cmd: StepCommand, clock: u64) {
        self.0[index].push((cmd, clock));
    }
}

/// The machine `case` ran on (its config text leaked: a few kB a case).
fn machine(case: &str) -> Machine<'static> {
    let name = onechip_golden::config_for(case);
    let text = onechip_golden::config(name).leak();
    let config = Config::parse(name, text).unwrap_or_else(|e| panic!("{case}: {e}"));
    Machine::from_config(&config).unwrap_or_else(|e| panic!("{case}: {e}"))
}

/// The case's planned moves in the order klippy appended them. moves.tsv
/// has no set_position nor homing: a case that homes is planned again here
/// (the planner matches klippy's moves), with klippy's start times (a
/// homing move's times moved as its segments' are).
fn events(case: &str) -> Vec<Event> {
    let golden = |trapq| -> Vec<TrapqMove> {
        trapq_moves(case, trapq)
            .iter()
            .map(TrapqAppend::trapq_move)
            .collect()
    };
    let (toolhead, extruder) = (golden(Trapq::Toolhead), golden(Trapq::Extruder));
    let program = onechip_golden::gcode(case);
    if !program.lines().any(|l| l.trim_start().starts_with("G28")) {
        let mut events: Vec<Event> = toolhead.into_iter().map(Event::Toolhead).collect();
        events.extend(extruder.into_iter().map(Event::Extruder));
        // By start time, a G1's toolhead part before its extruder part.
        events.sort_by(|a, b| {
            let t = |e: &Event| e.print_time().unwrap_or(f64::NEG_INFINITY);
            t(a).total_cmp(&t(b))
        });
        return events;
    }
    let machine = machine(case);
    let mut toolhead_planner = machine.toolhead::<1024>();
    let mut gcode = GcodeMove::default();
    let mut planned = Planned(Vec::new());
    let mut replies = String::new();
    for (n, line) in program.lines().enumerate() {
        let parsed = parse(line).unwrap_or_else(|e| panic!("{case}:{}: {e}", n + 1));
        gcode
            .execute(&parsed, &mut toolhead_planner, &mut planned, &mut replies)
            .unwrap_or_else(|e| panic!("{case}:{}: {e}", n + 1));
    }
    gcode.finish(&mut toolhead_planner, &mut planned);
    let (mut toolhead, mut extruder) = (toolhead.into_iter(), extruder.into_iter());
    // How much later klippy started the last toolhead move, s.
    let mut delay = 0.0;
    for event in &mut planned.0 {
        let (m, golden) = match event {
            Event::Toolhead(m) => {
                let golden = toolhead.next().expect("klippy planned as many moves");
                delay = golden.print_time - m.print_time;
                (m, golden)
            }
            Event::Extruder(m) => (m, extruder.next().expect("klippy planned as many moves")),
            Event::SetPosition(_) => continue,
            Event::Homing(h) => {
                (h.start_time, h.end_time) = (h.start_time + delay, h.end_time + delay);
                continue;
            }
        };
        m.print_time = golden.print_time;
    }
    planned.0
}

/// Each stepper's commands for `case` (with their first step's clock), its
/// moves streamed through step generation with the board's queue sizes,
/// steps generated after every move.
fn commands(case: &str) -> Vec<Vec<(StepCommand, u64)>> {
    let machine = machine(case);
    let freq = summary_value(case, "clock_freq");
    let max_error = summary_value(case, "max_error_ticks") as u32;
    let events = events(case);
    let start = events
        .iter()
        .find_map(|e| match e {
            Event::Toolhead(m) => Some(m.start_pos),
            _ => None,
        })
        .unwrap_or([0.0; 3]);
    let mut motion = Box::new(Motion::<
        { profile::MOTION_QUEUE },
        { profile::COMPRESS_QUEUE },
    >::new(&machine, freq, max_error, start));
    let mut commands = Commands(vec![Vec::new(); machine.steppers.len()]);
    for event in &events {
        let mut sink = motion.sink(&mut commands);
        match event {
            Event::Toolhead(m) => sink.toolhead(m),
            Event::Extruder(m) => sink.extruder(m),
            Event::SetPosition(pos) => sink.set_position(*pos),
            Event::Homing(homing) => {
                sink.homing_move_end(homing);
            }
        }
        motion.generate(f64::INFINITY, &mut commands);
    }
    motion.finish(&mut commands);
    assert_eq!(motion.error(), None, "{case}");
    commands.0
}

/// The commands run as the MCU runs them give klippy's steps, each within
/// max_error (as the MCU's 32-bit clock sees it).
fn check_steps(case: &str, stepper: &str, cmds: &[(StepCommand, u64)]) {
    let max_error = summary_value(case, "max_error_ticks") as u32;
    let cmds: Vec<StepCommand> = cmds.iter().map(|c| c.0).collect();
    let mut ours = Vec::new();
    expand(&cmds, |clock, dir| ours.push((clock, dir)));
    let golden = onechip_golden::steps(case, stepper);
    assert_eq!(ours.len(), golden.len(), "{case} {stepper}: step count");
    for (i, (o, g)) in ours.iter().zip(&golden).enumerate() {
        let d = (o.0.wrapping_sub(g.0) as u32 as i32).unsigned_abs();
        assert!(
            o.1 == g.1 && d <= max_error,
            "{case} {stepper}: step {i} ours {o:?} golden {g:?}"
        );
    }
}

#[test]
fn no_more_step_commands_than_klipper_with_the_board_queues() {
    let cases = onechip_golden::cases();
    assert!(!cases.is_empty(), "no golden case");
    let mut worse = Vec::new();
    let (mut ours_total, mut klippy_total) = (0, 0);
    println!(
        "{:<18} {:<10} {:>6} {:>6} {:>6}",
        "case", "stepper", "ours", "klippy", "ratio"
    );
    for case in &cases {
        let commands = commands(case);
        let steppers = summary_steppers(case);
        assert_eq!(steppers.len(), commands.len(), "{case}: steppers");
        let (mut ours_case, mut klippy_case) = (0, 0);
        for (stepper, cmds) in steppers.iter().zip(&commands) {
            check_steps(case, &stepper.name, cmds);
            let (ours, klippy) = (cmds.len() as u64, stepper.queue_cmds);
            println!(
                "{case:<18} {:<10} {ours:>6} {klippy:>6} {:>6.3}",
                stepper.name,
                ours as f64 / klippy.max(1) as f64
            );
            if ours > klippy {
                worse.push(format!("{case} {}: {ours} > {klippy}", stepper.name));
            }
            (ours_case, klippy_case) = (ours_case + ours, klippy_case + klippy);
        }
        println!(
            "{case:<18} {:<10} {ours_case:>6} {klippy_case:>6} {:>6.3}",
            "(all)",
            ours_case as f64 / klippy_case as f64
        );
        (ours_total, klippy_total) = (ours_total + ours_case, klippy_total + klippy_case);
    }
    println!(
        "{:<18} {:<10} {ours_total:>6} {klippy_total:>6} {:>6.3}",
        "(all cases)",
        "",
        ours_total as f64 / klippy_total as f64
    );
    assert!(worse.is_empty(), "more commands than klippy: {worse:#?}");
}

/// Klipper's commands for `stepper` of `case` (`queue-<stepper>.txt`),
/// with the clock of each one's first step (a direction change: of the
/// step before it).
fn klippy_commands(case: &str, stepper: &str) -> Vec<(StepCommand, u64)> {
    let text = onechip_golden::read_string(format!("{case}/queue-{stepper}.txt"));
    let mut clock = 0u64;
    let mut out = Vec::new();
    for line in text.lines().filter(|l| !l.starts_with('#')) {
        let words: Vec<&str> = line.split_whitespace().collect();
        let number = |i: usize| -> i64 {
            let word = words
                .get(i)
                .unwrap_or_else(|| panic!("{case} {stepper}: {line}"));
            word.parse()
                .unwrap_or_else(|e| panic!("{case} {stepper}: {line}: {e}"))
        };
        let cmd = match words.first().copied() {
            Some("set_next_step_dir") => StepCommand::Dir(number(2) != 0),
            Some("queue_step") => StepCommand::Steps {
                interval: number(2) as u32,
                count: number(3) as u16,
                add: number(4) as i16,
            },
            _ => panic!("{case} {stepper}: unexpected {line}"),
        };
        out.push((cmd, clock));
        if let StepCommand::Steps {
            interval,
            count,
            add,
        } = cmd
        {
            // Its first step comes an interval after the last one, its
            // last one `count` intervals after, each `add` longer.
            out.last_mut().expect("pushed").1 += u64::from(interval);
            let (n, add) = (i64::from(count), i64::from(add));
            clock = (clock as i64 + i64::from(interval) * n + add * n * (n - 1) / 2) as u64;
        }
    }
    out
}

/// The most message bytes the commands (clock, bytes) need in any second
/// of MCU clock (`freq` Hz), by their first step's clock, in windows 0.1 s
/// apart: bytes per second.
fn peak_rate(mut sent: Vec<(u64, usize)>, freq: f64) -> usize {
    sent.sort_unstable();
    let second = freq as u64;
    let step = second / 10;
    let end = sent.last().map_or(0, |s| s.0);
    (0..=end / step)
        .map(|k| {
            let from = k * step;
            sent.iter()
                .filter(|(c, _)| (from..from + second).contains(c))
                .map(|(_, b)| b)
                .sum()
        })
        .max()
        .unwrap_or(0)
}

/// The AVR is driven over a 250000-baud link (25,000 bytes/s): the step
/// commands of the golden atmega2560 case, encoded with its dictionary as
/// our host role sends them, take no more bytes than Klipper's, in all and
/// in their busiest second (by the clock of each command's first step),
/// which needs less than half the link.
#[test]
fn the_avr_link_carries_no_more_step_bytes_than_klippys() {
    let case = "avr_cart_extrude";
    let freq = summary_value(case, "clock_freq");
    let text = onechip_golden::dict(onechip_golden::dict_for(case));
    let dict = onechip_protocol::dictionary::Dictionary::parse(&text).expect("dictionary");
    let ours = commands(case);
    let (mut ours_sent, mut klippy_sent) = (Vec::new(), Vec::new());
    for (stepper, cmds) in summary_steppers(case).iter().zip(&ours) {
        let oid = u8::try_from(stepper.oid).expect("oid");
        let encoder = StepCommandEncoder::new(&dict, oid, false).expect("step commands");
        let mut buf = [0u8; 32];
        let mut bytes = |cmd: &StepCommand| encoder.encode(cmd, &mut buf).expect("encodes");
        ours_sent.extend(cmds.iter().map(|(cmd, clock)| (*clock, bytes(cmd))));
        let klippy = klippy_commands(case, &stepper.name);
        assert_eq!(klippy.len() as u64, stepper.queue_cmds, "{}", stepper.name);
        klippy_sent.extend(klippy.iter().map(|(cmd, clock)| (*clock, bytes(cmd))));
    }
    let total = |sent: &[(u64, usize)]| sent.iter().map(|s| s.1).sum::<usize>();
    let (ours_total, klippy_total) = (total(&ours_sent), total(&klippy_sent));
    let (ours_peak, klippy_peak) = (peak_rate(ours_sent, freq), peak_rate(klippy_sent, freq));
    println!(
        "{case}: step command bytes {ours_total} (klippy {klippy_total}); peak {ours_peak} B/s \
         (klippy {klippy_peak} B/s) of the link's 25000 B/s, before framing (5 bytes a block \
         of up to 64)"
    );
    assert!(
        ours_total <= klippy_total,
        "{ours_total} > {klippy_total} bytes"
    );
    assert!(
        ours_peak <= klippy_peak,
        "peak {ours_peak} > {klippy_peak} B/s"
    );
    assert!(ours_peak * 64 / 59 < 12_500, "peak {ours_peak} B/s");
}
