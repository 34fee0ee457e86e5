//! Klipper's stock configs (`../shared/klipper-configs`) as users drop them
//! on the card: every `printer-*`, `generic-*`, `example-*` and `kit-*`
//! file is copied unmodified to an SD folder as `printer.cfg` and run
//! through the host build's loader with a short job: `G28`, a Z move and
//! two XY moves (a few mm from the endstops, so the run stays short in
//! virtual time and in real time).
//!
//! Most files are written for other boards than the simulated one (the
//! BigTreeTech Octopus Pro), whose USB, SD card, crystal and SWD pins they
//! may use for steppers or heaters: the files are loaded as on their own
//! board ([`Options::board_pins`] off), and the table notes separately
//! whether their pins also fit this board.
//!
//! Each file must either load, home and move (every endstop found, the
//! toolhead where the firmware thinks it is), or fail with a message that
//! names the file, the line and the option, and says why (a file with no
//! `[printer]` section at all is no printer's config: its message names
//! the file and the missing section). A file that loads but cannot home
//! or move gives the G-code error. The test prints a table (file,
//! result, reason with the line it names, the sections reported
//! unsupported and ignored) and the reasons grouped, and fails if no file
//! is found, a run panics, a refusal does not name file, line and option,
//! a file that loads reports no reason for not homing, or fewer files load
//! (home and move) than [`MIN_LOADED`] ([`MIN_HOMED_AND_MOVED`]).
//!
//! A rail whose endstop is a TMC driver's virtual endstop
//! (`tmc2209_stepper_x:virtual_endstop`) must home on the driver's stall
//! reported on its DIAG pin (sensorless homing), not on a switch; at least
//! [`MIN_SENSORLESS`] files do.

use onechip_app::pin_check;
use onechip_config::Config;
use onechip_host::{Options, SimError, Start, Summary};
use onechip_planner::machine::Machine;
use onechip_planner::toolhead::Travel;
use onechip_tests::sd_folder;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The prefixes of the whole-printer configs (`sample-*` are snippets
/// meant to be included, not printers).
const PREFIXES: [&str; 4] = ["printer-", "generic-", "example-", "kit-"];

/// Files that must load (118 before onechip knew every ADC temperature
/// sensor, 122 after). Three files with an `[mcu NAME]` secondary
/// (generic-cramps, generic-replicape, kit-voron2-250mm) now connect to
/// it, as Klipper does, and are refused naming its `serial` option: no
/// such device exists here (kit-voron2-250mm's, before that, naming its
/// `[probe]` pin on the secondary, which no build drives there yet). 137 since `[probe]`/`[bltouch]` and
/// `probe:z_virtual_endstop` load, 139 with the TMC drivers too; 138 since
/// `[temperature_sensor]` is read, as generic-bigtreetech-gtr's has a
/// MAX31855 (an SPI sensor, refused naming its `sensor_type`); 141 with
/// the SPI sensors (that MAX31855, and the MAX6675 hot ends of
/// generic-mightyboard and printer-flashforge-creator-pro-2018).
const MIN_LOADED: usize = 141;
/// Section kinds supported now, which no file may list as unsupported.
const NOW_SUPPORTED: [&str; 11] = [
    "heater_fan",
    "controller_fan",
    "fan_generic",
    "output_pin",
    "static_digital_output",
    "board_pins",
    "filament_switch_sensor",
    "temperature_sensor",
    "stepper_z1",
    "temperature_fan",
    "extruder_stepper",
];
/// Files that must load, home and move (111 before the sensors, 114 after,
/// less the three above; 129 once Z homes on the probe, with
/// `[safe_z_home]` and `[homing_override]`; 131 with the TMC drivers;
/// 139, every file that loads, once the 8 deltas home their towers
/// together as Klipper does; 138 since `[temperature_sensor]` is read:
/// see [`MIN_LOADED`]; 141 with the SPI sensors; 140 since
/// `[temperature_fan]` runs: generic-duet2-duex.cfg's chamber fan has
/// min_temp 40 and its fan cools the simulated chamber below that, which
/// the MCU's range check shuts down with Klipper's "ADC out of range", as
/// Klipper would in a room that cool).
const MIN_HOMED_AND_MOVED: usize = 140;

/// Files homing some rail on a TMC driver's stall (sensorless homing):
/// generic-prusa-buddy, printer-eryone-er20-2021, printer-hiprecy-leo-2019
/// (TMC2130), printer-prusa-mini-plus-2020 and printer-sovol-sv06-2022,
/// their X and Y.
const MIN_SENSORLESS: usize = 5;

/// Distance of the Z move from the Z endstop, mm.
const Z_MOVE: f64 = 5.0;
/// Distances of the two XY moves from the X and Y endstops, mm.
const XY_MOVES: [f64; 2] = [10.0, 20.0];
/// How far from its endstop each axis starts, mm (inside its range).
const START_OFFSET: f64 = 30.0;
/// How far the toolhead may really be from where the firmware thinks at
/// the end, mm (homing stops within a step of the endstop).
const REAL_TOLERANCE: f64 = 0.1;

fn corpus() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/klipper-configs")
}

/// What happened to one file.
#[derive(Debug, Clone, PartialEq)]
enum Outcome {
    /// Loaded, homed and made every move.
    HomedAndMoved,
    /// Loaded, but the job did not home or move as asked.
    LoadedOnly(String),
    /// Refused at load.
    Refused(String),
    /// The run panicked.
    Panicked(String),
}

/// The job for `machine`: home, then move Z and twice XY away from the
/// endstops; and where the toolhead then is (X, Y, Z, mm), and where it
/// starts.
fn job(machine: &Machine<'_>) -> (String, [f64; 3], [f64; 3]) {
    let mut end = [0.0; 3];
    let mut start = [0.0; 3];
    let mut xy = [[0.0; 2]; 2];
    if let Travel::Delta(delta) = &machine.travel {
        // Delta homing ends at the top; move down (far enough below the
        // top that the XY moves stay inside the radius that tapers
        // there), then across. The toolhead starts off-centre, lower.
        let top = delta.max_z;
        end[2] = top - Z_MOVE - XY_MOVES[1];
        xy = [[XY_MOVES[0], 0.0], [0.0, XY_MOVES[0]]];
        start = [5.0, -5.0, top - START_OFFSET];
    } else {
        for axis in 0..3 {
            let Some(info) = machine.travel.homing_info(axis) else {
                continue;
            };
            let (min, max) = info.range;
            let inward = if info.positive_dir { -1.0 } else { 1.0 };
            let at = |d: f64| (info.position_endstop + inward * d).clamp(min, max);
            start[axis] = at(START_OFFSET);
            if axis == 2 {
                end[2] = at(Z_MOVE);
            } else {
                xy[0][axis] = at(XY_MOVES[0]);
                xy[1][axis] = at(XY_MOVES[1]);
            }
        }
    }
    end[0] = xy[1][0];
    end[1] = xy[1][1];
    let gcode = format!(
        "G28\nG1 Z{:.3} F600\nG1 X{:.3} Y{:.3} F3000\nG1 X{:.3} Y{:.3}\nM400\n",
        end[2], xy[0][0], xy[0][1], xy[1][0], xy[1][1]
    );
    (gcode, end, start)
}

/// What one file did: its outcome, the sections reported unsupported,
/// if its pins do not fit the simulated board, why, and the axes that
/// homed on a TMC driver's stall.
type RunResult = (Outcome, Vec<String>, Option<String>, Vec<usize>);

/// The axes of `machine` whose rail homes on a TMC driver's virtual
/// endstop.
fn sensorless_axes(machine: &Machine<'_>) -> Vec<usize> {
    (0..3)
        .filter(|&axis| machine.stall_driver(axis).is_some())
        .collect()
}

/// Runs `file` as printer.cfg in the SD folder `dir`.
fn run(file: &Path, dir: &Path) -> RunResult {
    let text = std::fs::read_to_string(file).expect("a stock config is text");
    // The job's targets come from the machine the planner reads; if it
    // refuses the file the loader refuses it too, and the job is moot.
    let config = Config::parse("printer.cfg", &text).ok();
    let machine = config.as_ref().and_then(|c| Machine::from_config(c).ok());
    let planned = machine.as_ref().map(job);
    let (gcode, end, start) = planned.unwrap_or_else(|| ("G28\n".into(), [0.0; 3], [0.0; 3]));
    let board_pins = machine
        .as_ref()
        .and_then(|m| pin_check::check(m, pin_check::BOARD_RESERVED).err())
        .map(|conflict| conflict.to_string());
    let sensorless = machine.as_ref().map(sensorless_axes).unwrap_or_default();
    match run_in(dir, &text, &gcode, start) {
        Err(SimError::Config(message)) => (
            Outcome::Refused(message),
            Vec::new(),
            board_pins,
            Vec::new(),
        ),
        Err(other) => (
            Outcome::Refused(other.to_string()),
            Vec::new(),
            board_pins,
            Vec::new(),
        ),
        Ok(summary) => {
            let unsupported = summary.unsupported.clone();
            let outcome = judge(&summary, end, &sensorless);
            (outcome, unsupported, board_pins, summary.stalls)
        }
    }
}

/// Runs `text` unmodified as printer.cfg with `job` (G-code) in the SD
/// folder `dir`, the toolhead starting at `start` (mm), as on its own
/// board (its pins not checked against the simulated board's).
fn run_in(dir: &Path, text: &str, job: &str, start: [f64; 3]) -> Result<Summary, SimError> {
    sd_folder::write(dir, text, Some(job));
    let options = Options {
        start: Start::At(start),
        board_pins: false,
        ..Options::default()
    };
    onechip_host::run_with(dir, &options)
}

/// Whether a run that loaded homed and ended where the job says, the
/// `sensorless` axes on a TMC driver's stall.
fn judge(s: &Summary, end: [f64; 3], sensorless: &[usize]) -> Outcome {
    if let Some((line, error)) = s.errors.first() {
        return Outcome::LoadedOnly(format!("job line {line}: {error}"));
    }
    if let Some(reason) = &s.shutdown {
        return Outcome::LoadedOnly(format!("shutdown: {reason}"));
    }
    let off = (0..3).find(|&k| (s.final_position[k] - end[k]).abs() > 1e-6);
    if let Some(k) = off {
        return Outcome::LoadedOnly(format!(
            "ended at {:?}, not {end:?} (axis {k})",
            &s.final_position[..3]
        ));
    }
    // Every axis' endstop (a delta: every tower's) triggered.
    let homed: Vec<usize> = s.endstops.iter().map(|e| e.0).collect();
    if (0..3).any(|axis| !homed.contains(&axis)) {
        return Outcome::LoadedOnly(format!("endstops triggered on axes {homed:?} only"));
    }
    if let Some(axis) = sensorless.iter().find(|a| !s.stalls.contains(a)) {
        return Outcome::LoadedOnly(format!(
            "axis {axis} homes on a TMC virtual endstop but no stall triggered it"
        ));
    }
    // Homing found the endstops where printer.cfg puts them: the
    // toolhead really is where the firmware thinks (within a step).
    let real = s.real_position;
    let there = real.is_some_and(|r| (0..3).all(|k| (r[k] - end[k]).abs() < REAL_TOLERANCE));
    if !there {
        return Outcome::LoadedOnly(format!("really at {real:?}, not {end:?}"));
    }
    Outcome::HomedAndMoved
}

/// True if `message` names the file and line (`printer.cfg:12:`) and an
/// option (`option 'x' in section 'y'`, or a pin check's `[y] x`).
fn names_file_line_option(message: &str) -> bool {
    let line = message
        .strip_prefix("printer.cfg:")
        .and_then(|rest| rest.split_once(':'))
        .is_some_and(|(n, _)| n.parse::<usize>().is_ok_and(|n| n > 0));
    let option = message.contains("option '")
        || message.split('[').skip(1).any(|rest| {
            rest.split_once("] ")
                .is_some_and(|(_, after)| after.starts_with(|c: char| c.is_ascii_lowercase()))
        });
    line && option
}

/// True if `message` says the config has no section `[name]` at all (it
/// is no printer's config): there is no line or option to name.
fn names_missing_section(message: &str) -> bool {
    message.starts_with("printer.cfg: section '") && message.ends_with("' is required")
}

/// The line of `text` that `message` names (`printer.cfg:12: ...`),
/// trimmed.
fn quoted_line<'t>(text: &'t str, message: &str) -> Option<&'t str> {
    let n: usize = message
        .strip_prefix("printer.cfg:")?
        .split_once(':')?
        .0
        .parse()
        .ok()?;
    text.lines().nth(n.checked_sub(1)?).map(str::trim)
}

/// The reason for a file's result, grouped: the message without its
/// location, or what it comes to (`kinematics not implemented: polar`).
fn group_of(text: &str, reason: &str) -> String {
    // Without its location (`printer.cfg:12: `, `job line 1: `).
    let message = ["printer.cfg:", "job line "]
        .iter()
        .find_map(|p| reason.strip_prefix(p))
        .map_or(reason, |rest| {
            rest.split_once(": ").map_or(rest, |(_, r)| r)
        })
        .trim();
    let quoted = quoted_line(text, reason).unwrap_or("");
    if message.contains("option 'kinematics'") {
        format!("kinematics not implemented ({quoted})")
    } else if message.contains("'position_endstop' in section 'stepper_z' must be specified")
        && text.contains("probe:z_virtual_endstop")
    {
        "probe as Z endstop ([probe] not supported yet)".into()
    } else if let Some((_, by)) = message.split_once("is used by the board (") {
        let by = ["SD card", "USB"]
            .into_iter()
            .find(|what| by.starts_with(what))
            .unwrap_or(by.trim_end_matches(')'));
        format!("a pin this board keeps for itself ({by})")
    } else if message.contains("option 'sensor_type'") {
        format!("{message} ({quoted})")
    } else if message.starts_with("Homing is not supported for this kinematics") {
        "homing not implemented for these kinematics (G28)".into()
    } else if message.starts_with("No trigger on ") {
        format!("an endstop never triggered while homing ({message})")
    } else {
        message.to_string()
    }
}

/// One file's row of the table.
struct Row {
    name: String,
    text: String,
    outcome: Outcome,
    unsupported: Vec<String>,
    /// Why its pins do not fit the simulated board, if they do not.
    board_pins: Option<String>,
    /// The axes that homed on a TMC driver's stall.
    stalls: Vec<usize>,
}

#[test]
fn every_stock_klipper_config_loads_homes_and_moves_or_says_why_not() {
    let mut files: Vec<PathBuf> = std::fs::read_dir(corpus())
        .expect("the shared config folder")
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.ends_with(".cfg") && PREFIXES.iter().any(|p| n.starts_with(p)))
        })
        .collect();
    files.sort();
    assert!(!files.is_empty(), "no configs in {}", corpus().display());

    let root = std::env::temp_dir().join(format!("onechip-klipper-configs-{}", std::process::id()));
    let rows: Vec<Row> = files
        .iter()
        .enumerate()
        .map(|(i, file)| {
            let dir = root.join(i.to_string());
            let (outcome, unsupported, board_pins, stalls) =
                std::panic::catch_unwind(|| run(file, &dir)).unwrap_or_else(|panic| {
                    let text = panic
                        .downcast_ref::<String>()
                        .cloned()
                        .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                        .unwrap_or_default();
                    (Outcome::Panicked(text), Vec::new(), None, Vec::new())
                });
            Row {
                name: file
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default(),
                text: std::fs::read_to_string(file).unwrap_or_default(),
                outcome,
                unsupported,
                board_pins,
                stalls,
            }
        })
        .collect();
    std::fs::remove_dir_all(&root).ok();

    println!(
        "{:<50} {:<13} reason / unsupported sections (ignored)",
        "file", "result"
    );
    let mut groups: BTreeMap<String, usize> = BTreeMap::new();
    let (mut loaded, mut homed) = (0, 0);
    let mut bad = Vec::new();
    for row in &rows {
        let (result, reason) = match &row.outcome {
            Outcome::HomedAndMoved => ("homed, moved", ""),
            Outcome::LoadedOnly(r) => ("loaded only", r.as_str()),
            Outcome::Refused(r) => ("refused", r.as_str()),
            Outcome::Panicked(r) => ("PANICKED", r.as_str()),
        };
        let quoted = quoted_line(&row.text, reason).map(|l| format!(" [{l}]"));
        println!(
            "{:<50} {result:<13} {reason}{}",
            row.name,
            quoted.unwrap_or_default()
        );
        if !row.unsupported.is_empty() {
            println!("{:<64} unsupported: [{}]", "", row.unsupported.join("], ["));
        }
        if let Some(pins) = &row.board_pins {
            println!("{:<64} not on this board: {pins}", "");
        }
        if !row.stalls.is_empty() {
            println!(
                "{:<64} homed on a driver's stall: axes {:?}",
                "", row.stalls
            );
        }
        let name = &row.name;
        match &row.outcome {
            Outcome::HomedAndMoved => {
                loaded += 1;
                homed += 1;
            }
            Outcome::LoadedOnly(r) => {
                loaded += 1;
                let group = format!("loads, does not home and move: {}", group_of(&row.text, r));
                *groups.entry(group).or_default() += 1;
                if r.is_empty() {
                    bad.push(format!("{name}: loads but gives no reason"));
                }
            }
            Outcome::Refused(r) => {
                *groups
                    .entry(format!("refused: {}", group_of(&row.text, r)))
                    .or_default() += 1;
                if !names_file_line_option(r) && !names_missing_section(r) {
                    bad.push(format!(
                        "{name}: refusal does not name file, line, option: {r}"
                    ));
                }
            }
            Outcome::Panicked(r) => bad.push(format!("{name}: panicked: {r}")),
        }
    }
    println!();
    let fit = |r: &&Row| r.board_pins.is_none();
    let homed_here = rows
        .iter()
        .filter(|r| r.outcome == Outcome::HomedAndMoved)
        .filter(fit)
        .count();
    println!(
        "{} files: {loaded} load, {homed} home and move ({homed_here} of them with pins that \
         also fit this board), {} refused",
        rows.len(),
        rows.len() - loaded
    );
    let sensorless = rows
        .iter()
        .filter(|r| r.outcome == Outcome::HomedAndMoved && !r.stalls.is_empty())
        .count();
    println!("{sensorless} of them home some rail on a TMC driver's stall (sensorless)");
    let mut grouped: Vec<_> = groups.into_iter().collect();
    grouped.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    for (reason, count) in &grouped {
        println!("{count:>4}  {reason}");
    }
    // Sections still unsupported, by kind: how many files list each.
    let mut kinds: BTreeMap<&str, usize> = BTreeMap::new();
    for row in &rows {
        let mut seen: Vec<&str> = row
            .unsupported
            .iter()
            .filter_map(|s| s.split_whitespace().next())
            .collect();
        seen.sort();
        seen.dedup();
        for kind in seen {
            *kinds.entry(kind).or_default() += 1;
            if NOW_SUPPORTED.contains(&kind) {
                bad.push(format!("{}: [{kind}] reported unsupported", row.name));
            }
        }
    }
    let mut kinds: Vec<_> = kinds.into_iter().collect();
    kinds.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(b.0)));
    let listing = rows.iter().filter(|r| !r.unsupported.is_empty()).count();
    println!("{listing} files list an unsupported section; the most common (files):");
    for (kind, count) in kinds.iter().take(12) {
        println!("{count:>4}  [{kind}]");
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
    assert!(
        loaded >= MIN_LOADED,
        "{loaded} load, expected at least {MIN_LOADED}"
    );
    assert!(
        homed >= MIN_HOMED_AND_MOVED,
        "{homed} home and move, expected at least {MIN_HOMED_AND_MOVED}"
    );
    assert!(
        sensorless >= MIN_SENSORLESS,
        "{sensorless} home on a driver's stall, expected at least {MIN_SENSORLESS}"
    );
}

/// The stock printer configs with `[screws_tilt_adjust]` and a probe:
/// G28, then SCREWS_TILT_CALCULATE probes every screw and reports a turn
/// for each but the base, as Klipper; a config whose screw lies beyond
/// its axis' range gets Klipper's "Move out of range" for it, as Klipper
/// would (printer-creality-ender3-v2-neo-2022.cfg: screw2 at X 237.6,
/// stepper_x's position_max 235).
#[test]
fn stock_screws_tilt_adjust_sections_probe_their_screws() {
    let mut tried = 0;
    for (name, text) in stock_configs_with("[screws_tilt_adjust]") {
        let config = Config::parse("printer.cfg", &text).expect("parses");
        let machine = Machine::from_config(&config).unwrap_or_else(|e| panic!("{name}: {e}"));
        let (Some(screws), Some(_)) = (machine.screws_tilt, machine.probe) else {
            continue;
        };
        tried += 1;
        let points: Vec<[f64; 2]> = screws.screws().iter().map(|s| s.at).collect();
        let summary = run_job(
            &text,
            &format!("screws-{tried}"),
            "G28\nSCREWS_TILT_CALCULATE\n",
        );
        let adjusted = summary.transcript.matches(" : adjust ").count();
        if !refused_beyond_travel(&name, &machine, &points, &summary) {
            assert!(summary.errors.is_empty(), "{name}: {:?}", summary.errors);
            assert_eq!(adjusted, points.len() - 1, "{name}: {}", summary.transcript);
        }
        println!("{name}: {} screws, {adjusted} adjusted", points.len());
    }
    assert!(
        tried >= 6,
        "only {tried} stock configs with [screws_tilt_adjust] and a probe"
    );
}

/// The stock printer configs with `[bed_screws]`: G28, BED_SCREWS_ADJUST
/// and an ACCEPT at every screw (and fine-adjust point) end with
/// Klipper's "Bed screws tool completed successfully", or Klipper's "Move
/// out of range" for a screw beyond its axis' travel.
#[test]
fn stock_bed_screws_sections_walk_their_screws() {
    let mut tried = 0;
    for (name, text) in stock_configs_with("[bed_screws]") {
        let config = Config::parse("printer.cfg", &text).expect("parses");
        let Ok(machine) = Machine::from_config(&config) else {
            continue;
        };
        let Some(tool) = machine.bed_screws else {
            continue;
        };
        tried += 1;
        let stops: Vec<[f64; 2]> = (tool.round(false).iter().chain(tool.round(true)))
            .map(|s| s.at)
            .collect();
        let job = format!("G28\nBED_SCREWS_ADJUST\n{}", "ACCEPT\n".repeat(stops.len()));
        let summary = run_job(&text, &format!("bed-screws-{tried}"), &job);
        if !refused_beyond_travel(&name, &machine, &stops, &summary) {
            assert!(summary.errors.is_empty(), "{name}: {:?}", summary.errors);
            let prompts = summary
                .transcript
                .matches("Then run ACCEPT, ADJUSTED, or ABORT")
                .count();
            assert_eq!(prompts, stops.len(), "{name}: {}", summary.transcript);
            assert!(
                summary
                    .transcript
                    .contains("// Bed screws tool completed successfully"),
                "{name}: {}",
                summary.transcript
            );
        }
        println!("{name}: {} stops", stops.len());
    }
    assert!(tried >= 10, "only {tried} stock configs with [bed_screws]");
}

/// The whole-printer stock configs (file name, text) with a `section`
/// header line (`[bed_screws]`).
fn stock_configs_with(section: &str) -> Vec<(String, String)> {
    let mut found: Vec<(String, String)> = std::fs::read_dir(corpus())
        .expect("the shared config folder")
        .filter_map(|entry| {
            let file = entry.ok()?.path();
            let name = file.file_name()?.to_string_lossy().into_owned();
            let text = std::fs::read_to_string(&file).ok()?;
            let whole = PREFIXES.iter().any(|p| name.starts_with(p));
            (whole && text.contains(&format!("\n{section}"))).then_some((name, text))
        })
        .collect();
    found.sort();
    found
}

/// True if one of the nozzle's `points` (X, Y, mm) lies beyond the
/// machine's X or Y travel; the run must then have stopped with Klipper's
/// "Move out of range" for the first such point, as Klipper would.
fn refused_beyond_travel(
    name: &str,
    machine: &Machine<'_>,
    points: &[[f64; 2]],
    summary: &Summary,
) -> bool {
    let range = |axis| machine.travel.homing_info(axis).expect("a rail").range;
    let Some(at) = points
        .iter()
        .find(|at| (0..2).any(|a| at[a] < range(a).0 || at[a] > range(a).1))
    else {
        return false;
    };
    let error = summary.errors.first().map_or("", |(_, e)| e.as_str());
    let expected = format!("Move out of range: {:.3} {:.3}", at[0], at[1]);
    assert!(
        error.starts_with(&expected),
        "{name}: {error:?} vs {expected}"
    );
    true
}

/// Runs stock config `text` with `job` in a temporary SD folder named
/// after `name` ([`run_in`], the toolhead starting at 50, 50, 30).
fn run_job(text: &str, name: &str, job: &str) -> Summary {
    let dir = std::env::temp_dir().join(format!("onechip-{name}-{}", std::process::id()));
    let summary =
        run_in(&dir, text, job, [50.0, 50.0, 30.0]).unwrap_or_else(|e| panic!("{name}: {e}"));
    std::fs::remove_dir_all(&dir).ok();
    summary
}
