//! The Linux host build: the firmware's shared logic run against a folder
//! that plays the SD card, so users and tests see what the board would do.
//!
//! It reads `printer.cfg` and a G-code file, plans every move exactly as
//! the firmware does (and as Klipper would), generates and compresses the
//! steps, runs them through the MCU role's stepper engine in virtual time
//! ([`virtual_mcu`]), and reports what the printer would do: planned
//! moves, print time, every stepper's steps, peak step rate and final
//! position, and any errors; optionally every step's clock, in the format
//! of Klipper's golden `steps-*.txt`.

pub mod console_printer;
pub mod files;
pub mod host_mcu;
pub mod pace;
pub mod plot;
pub mod probe_physics;
pub mod secondary;
pub mod serial;
pub mod step_log;
pub mod summary_json;
pub mod thermal_plant;
pub mod tmc_sim;
pub mod virtual_mcu;

use host_mcu::{HostMcu, RunMcu};
use onechip_app::console::Console;
use onechip_app::line::{LineAssembler, LineEvent};
use onechip_app::session::Mcu as _;
use onechip_app::session::{Session, Timing, profile};
use onechip_app::setup::PrinterSetup;
use onechip_app::text::ErrorText;
use onechip_planner::machine::{Kinematics, Machine};
use onechip_planner::move_sink::TrapqMove;
use onechip_sched::outputs::Drive;
use pace::Pace;
use secondary::Secondaries;
use std::fmt;
use std::io::{BufReader, Read as _};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use virtual_mcu::{ExtraStepper, Physics, VirtualMcu};

/// Bytes of one USB full-speed bulk packet, as the board's console reads
/// its input.
const USB_PACKET: usize = 64;

/// The session as the host build runs it: the board's queues, with a
/// lookahead of `L` moves (by default the board's).
pub type HostSession<'a, const L: usize = { profile::LOOKAHEAD }> = Session<'a, L>;

/// A lookahead as deep as klippy's needs to be for the golden cases: klippy
/// queues moves for 2 s of their minimum time before its first flush, more
/// than 384 in the circle cases, where the board's lookahead flushes first
/// (so its plan, still within Klipper's limits, differs from klippy's).
pub const KLIPPY_LOOKAHEAD: usize = 1024;

/// How to run.
#[derive(Debug, Clone, PartialEq)]
pub struct Options {
    /// The G-code file; by default the SD folder's only `*.gcode`.
    pub gcode: Option<PathBuf>,
    /// If set, every stepper's steps are written there as
    /// `steps-<stepper>.txt` (`<clock> <dir>` lines), as they are made.
    pub steps_dir: Option<PathBuf>,
    /// MCU clock frequency, Hz.
    pub mcu_freq: f64,
    /// MCU clock at print time 0, ticks (to start near the 32-bit wrap).
    pub clock_origin: u64,
    /// Where the toolhead really is at power-on, which decides where
    /// homing moves meet their endstops.
    pub start: Start,
    /// If set, an SVG of toolhead velocity and step rates over the window
    /// is written to the path.
    pub plot: Option<(PathBuf, plot::Window)>,
    /// Fault injection: from print time `.0` (s) on, heater `.1`'s
    /// thermistor reads as an open circuit.
    pub open_sensor: Option<(f64, usize)>,
    /// Fault injection: from print time `.0` (s) on, SPI input `.1`
    /// (heaters first, then the temperature sensors) reports fault bits
    /// `.2` ([`thermal_plant::Plant::spi_fault`]).
    pub spi_fault: Option<(f64, usize, u32)>,
    /// Fault injection: heater `.0`'s simulated element gives `.1` times
    /// its power (0: it does not heat at all).
    pub weak_heater: Option<(usize, f64)>,
    /// Fault injection: the endstop of motion stepper `k` (a rail's, or
    /// a delta's tower's) never reads pressed (a broken switch or wire).
    pub dead_endstop: Option<usize>,
    /// The rails' extra steppers (`[stepper_z1]`) start this much further
    /// along than their rail's first stepper, mm (a racked gantry).
    pub racked: f64,
    /// The G-code arrives on the console, in USB packets as the board's
    /// console reads them, instead of from the SD card.
    pub console: bool,
    /// The simulated bed under the probe: its height at X = Y = 0 and its
    /// slopes along X and Y (mm, mm/mm): the probe triggers where it
    /// touches it.
    pub bed: [f64; 3],
    /// What is wrong with the simulated BLTouch, if anything.
    pub bltouch_fault: Option<probe_physics::BltouchFault>,
    /// printer.cfg's pins are checked against those the board uses itself
    /// (USB, SD card, crystal, SWD), as on the board; off for a config
    /// written for another board (Klipper's stock `generic-*` configs),
    /// whose other options are still all checked.
    pub board_pins: bool,
}

/// Where the toolhead really is at power-on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Start {
    /// Mid-travel on every rail; endstops stop homing moves.
    MidTravel,
    /// At this toolhead position, mm; endstops stop homing moves.
    At([f64; 3]),
    /// Unknown: homing moves run to their end, as in klippy's batch mode
    /// (no endstops), which the golden data follows.
    Ideal,
}

impl Default for Options {
    fn default() -> Self {
        Self {
            gcode: None,
            steps_dir: None,
            mcu_freq: profile::STEP_CLOCK_HZ,
            clock_origin: 0,
            start: Start::MidTravel,
            plot: None,
            open_sensor: None,
            spi_fault: None,
            weak_heater: None,
            dead_endstop: None,
            racked: 0.0,
            bed: [0.0; 3],
            bltouch_fault: None,
            console: false,
            board_pins: true,
        }
    }
}

/// What one stepper did.
#[derive(Debug, Clone, PartialEq)]
pub struct StepperSummary {
    /// Section name.
    pub name: String,
    /// Steps made.
    pub steps: usize,
    /// Final position in steps from the start (+1 per positive step).
    pub position: i64,
    /// Highest step rate (inverse of the shortest step interval), steps/s.
    pub peak_rate: f64,
    /// Clock of the last step, ticks.
    pub last_step: Option<u64>,
}

/// What one heater did.
#[derive(Debug, Clone, PartialEq)]
pub struct HeaterSummary {
    /// Section name.
    pub name: String,
    /// Target at the end, °C.
    pub target: f64,
    /// Temperature at the end as the firmware measured it (smoothed), °C.
    pub temperature: f64,
    /// Highest temperature the simulated heater reached, °C.
    pub peak: f64,
    /// Share of the run the heater output was on, 0..1.
    pub duty: f64,
    /// The heater output is on at the end.
    pub on_at_end: bool,
}

/// Bytes of console output a [`Summary`] keeps as its transcript (a
/// print's `ok`s would grow it by 3 bytes a line).
pub const TRANSCRIPT_MAX: usize = 64 * 1024;

/// What a run of the host build did.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    /// The printer.cfg that was read.
    pub config_path: PathBuf,
    /// The machine's kinematics.
    pub kinematics: Kinematics,
    /// Sections of printer.cfg that onechip does not support yet.
    pub unsupported: Vec<String>,
    /// The input shapers configured, as `axis: type freq`.
    pub input_shaper: Vec<String>,
    /// The G-code file that was run.
    pub gcode_path: PathBuf,
    /// Lines executed (comment-only lines excluded).
    pub lines: usize,
    /// Planned toolhead (XYZ) moves.
    pub toolhead_moves: usize,
    /// Planned extruder moves.
    pub extruder_moves: usize,
    /// Highest planned cruise speed, mm/s.
    pub peak_velocity: f64,
    /// Print time at the end, s.
    pub print_time: f64,
    /// G-code position at the end (X, Y, Z, E), mm.
    pub final_position: [f64; 4],
    /// Replies other than `ok` and temperature reports (M114, M115), by
    /// line number.
    pub replies: Vec<(usize, String)>,
    /// Temperature reports (M105, and each second of M109/M190), by line
    /// number.
    pub temperatures: Vec<(usize, String)>,
    /// Errors (`!!` replies), by line number.
    pub errors: Vec<(usize, String)>,
    /// Everything the console printed, `ok`s included, up to
    /// [`TRANSCRIPT_MAX`] bytes: the answers to the lines up to there.
    pub transcript: String,
    /// Bytes of console output past the transcript's end, not kept.
    pub transcript_dropped: usize,
    /// Every stepper's steps.
    pub steppers: Vec<StepperSummary>,
    /// The MCU role's shutdown message, if it shut down.
    pub shutdown: Option<String>,
    /// MCU clock frequency, Hz.
    pub mcu_freq: f64,
    /// Endstop triggers while homing: axis (a delta: tower), the
    /// toolhead's real position when the steppers stopped (mm), print
    /// time (s).
    pub endstops: Vec<(usize, [f64; 3], f64)>,
    /// The axes of those triggers that were a TMC driver's stall reported
    /// on its DIAG pin (sensorless homing), in order.
    pub stalls: Vec<usize>,
    /// Where the toolhead really is at the end, mm (when the power-on
    /// position is known, see [`Start`]).
    pub real_position: Option<[f64; 3]>,
    /// Every heater, simulated.
    pub heaters: Vec<HeaterSummary>,
    /// The fan's speed at the end (0..1), if there is a fan.
    pub fan_speed: Option<f64>,
    /// Time spent waiting for heaters (M109, M190), s.
    pub heat_wait: f64,
    /// Each stepper on a secondary MCU: its name and every step's clock
    /// on that MCU, as sent (ticks).
    pub secondary_steps: Vec<(String, Vec<u64>)>,
    /// Each secondary MCU's name and link counters at the end.
    pub secondary_links: Vec<(String, onechip_protocol::transport::LinkStats)>,
    /// When (wall clock) a secondary's shutdown or silence was noticed.
    pub secondary_fault_at: Option<std::time::Instant>,
    /// Homing moves across MCUs ended by a communication timeout (an MCU
    /// heard no relayed report for 25 ms; klippy's "Communication timeout
    /// during homing"): each ended where its steppers stopped, as if
    /// triggered there.
    pub homing_timeouts: usize,
}

impl fmt::Display for Summary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "config:       {} ({:?})",
            self.config_path.display(),
            self.kinematics
        )?;
        if !self.input_shaper.is_empty() {
            writeln!(f, "input shaper: {}", self.input_shaper.join(", "))?;
        }
        if !self.unsupported.is_empty() {
            writeln!(
                f,
                "not yet supported (ignored): [{}]",
                self.unsupported.join("], [")
            )?;
        }
        writeln!(
            f,
            "gcode:        {} ({} lines)",
            self.gcode_path.display(),
            self.lines
        )?;
        for (line, reply) in &self.replies {
            writeln!(f, "reply:        line {line}: {reply}")?;
        }
        if let Some((line, last)) = self.temperatures.last() {
            writeln!(
                f,
                "temperatures: {} reports, the last (line {line}): {last}",
                self.temperatures.len()
            )?;
        }
        for (line, error) in &self.errors {
            writeln!(f, "error:        line {line}: {error}")?;
        }
        writeln!(
            f,
            "planned:      {} toolhead moves, {} extruder moves",
            self.toolhead_moves, self.extruder_moves
        )?;
        writeln!(f, "peak speed:   {:.1} mm/s", self.peak_velocity)?;
        writeln!(f, "print time:   {:.3} s", self.print_time)?;
        let p = self.final_position;
        writeln!(
            f,
            "final:        X:{:.3} Y:{:.3} Z:{:.3} E:{:.3}",
            p[0], p[1], p[2], p[3]
        )?;
        for st in &self.steppers {
            writeln!(
                f,
                "{:<13} {} steps, final position {} steps, peak {:.0} steps/s",
                format!("{}:", st.name),
                st.steps,
                st.position,
                st.peak_rate
            )?;
        }
        if let Some(last) = self.steppers.iter().filter_map(|s| s.last_step).max() {
            writeln!(f, "last step:    {:.6} s", last as f64 / self.mcu_freq)?;
        }
        for (axis, real, time) in &self.endstops {
            writeln!(
                f,
                "endstop:      {} triggered at {time:.3} s, toolhead really at X:{:.4} Y:{:.4} Z:{:.4}{}",
                match self.kinematics {
                    Kinematics::Delta => ["a", "b", "c"],
                    _ => ["x", "y", "z"],
                }
                .get(*axis)
                .unwrap_or(&"?"),
                real[0],
                real[1],
                real[2],
                // A rail's input is a DIAG pin for all its triggers or none.
                if self.stalls.contains(axis) {
                    " (the driver's stall, on its DIAG pin)"
                } else {
                    ""
                }
            )?;
        }
        for h in &self.heaters {
            writeln!(
                f,
                "{:<13} {:.1} °C (target {:.1}), peak {:.1} °C, on {:.0}% of the time",
                format!("{}:", h.name),
                h.temperature,
                h.target,
                h.peak,
                h.duty * 100.0
            )?;
        }
        if let Some(speed) = self.fan_speed {
            writeln!(f, "fan:          {:.0}% at the end", speed * 100.0)?;
        }
        if self.heat_wait > 0.0 {
            writeln!(f, "heat wait:    {:.1} s", self.heat_wait)?;
        }
        if let Some(reason) = &self.shutdown {
            writeln!(f, "SHUTDOWN:     {reason}")?;
        }
        write!(f, "errors:       {}", self.errors.len())
    }
}

/// Why the host build could not run.
#[derive(Debug)]
pub enum SimError {
    /// A file could not be read (or a steps file written).
    Read(PathBuf, std::io::Error),
    /// printer.cfg is invalid (the message names file, line and option).
    Config(String),
    /// The SD folder has no G-code file, or several and none was named.
    NoGcode(PathBuf),
    /// The serial port could not be set up or served.
    Serial(PathBuf, std::io::Error),
    /// A secondary MCU could not be brought up (Klipper's message).
    Secondary(String),
}

impl fmt::Display for SimError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Read(path, e) => write!(f, "{}: {e}", path.display()),
            Self::Config(message) => f.write_str(message),
            Self::NoGcode(dir) => write!(
                f,
                "{}: expected exactly one *.gcode file (or name one as the second argument)",
                dir.display()
            ),
            Self::Serial(path, e) => write!(f, "serial port {}: {e}", path.display()),
            Self::Secondary(message) => f.write_str(message),
        }
    }
}

impl std::error::Error for SimError {}

/// Runs the firmware logic on the SD folder `sd`, with `gcode` or else the
/// folder's only `*.gcode` file, on the board's clock.
pub fn run(sd: &Path, gcode: Option<&Path>) -> Result<Summary, SimError> {
    run_with(
        sd,
        &Options {
            gcode: gcode.map(Path::to_path_buf),
            ..Options::default()
        },
    )
}

/// Decisions a run takes at points of its input rather than from time:
/// tests replay klippy's batch-mode timing with it (the session then keeps
/// [`Timing::Batch`]).
pub trait Replay<const L: usize> {
    /// Before each line is run.
    fn before_line(&mut self, session: &mut HostSession<'_, L>);
    /// After `read` bytes of the G-code file have been read.
    fn after_bytes(&mut self, read: usize, session: &mut HostSession<'_, L>, mcu: &mut VirtualMcu);
}

/// Runs the firmware logic on the SD folder `sd` as `options` say.
pub fn run_with(sd: &Path, options: &Options) -> Result<Summary, SimError> {
    run_replaying::<{ profile::LOOKAHEAD }>(sd, options, None)
}

/// [`run_with`] with a lookahead of `L` moves, and `replay`'s decisions at
/// its points of the input.
pub fn run_replaying<const L: usize>(
    sd: &Path,
    options: &Options,
    mut replay: Option<&mut dyn Replay<L>>,
) -> Result<Summary, SimError> {
    with_session::<L>(sd, options, |run| {
        run.summary.gcode_path = match options.gcode.as_deref() {
            Some(path) => path.to_path_buf(),
            None => only_gcode_file(sd)?,
        };
        let (program, program_len) = open(&run.summary.gcode_path)?;
        if replay.is_some() {
            run.session.set_timing(Timing::Batch);
        }
        let freq = options.mcu_freq;
        let origin = options.clock_origin as f64 / freq;
        let mut assembler = LineAssembler::<{ profile::MAX_LINE }>::new();
        let mut progress = Progress::new(program_len);
        for (at, byte) in program.enumerate() {
            let byte = byte.map_err(|e| SimError::Read(run.summary.gcode_path.clone(), e))?;
            let mut ran = false;
            if let Some(event) = assembler.push(byte) {
                progress.note(at, run.session.printer().print_time() - origin);
                if let Some(replay) = replay.as_deref_mut() {
                    replay.before_line(run.session);
                }
                run.line(&event, &mut NoOutput);
                ran = true;
            }
            if options.console && (at + 1) % USB_PACKET == 0 {
                // The end of a USB packet: the console looks at the clock.
                run.poll(&mut NoOutput);
                ran = true;
            }
            if let Some(replay) = replay.as_deref_mut() {
                replay.after_bytes(at + 1, run.session, run.mcu.main_mut());
                ran = true;
            }
            if ran {
                if run.mcu.main().is_paced() {
                    keep_ahead(run, freq);
                } else {
                    // The MCU runs the steps as far as they have all been sent.
                    run.mcu.run_until(clock_at(run.session.sent_until(), freq));
                }
                if stopped(run.session, run.mcu, run.summary) {
                    break;
                }
            }
        }
        Ok(())
    })
}

/// Longest sleep between two runs of the session's timers while a paced
/// run reads ahead, s.
const READ_AHEAD_POLL: f64 = 0.1;

/// In real time (secondary MCUs run in it): the next line is read once
/// less than klippy's `BUFFER_TIME_HIGH` of steps is sent ahead of the
/// clock, and the session's timers (lookahead flush, priming) run
/// meanwhile, so steps reach every MCU well before they are due.
fn keep_ahead<const L: usize>(run: &mut Run<'_, '_, L>, freq: f64) {
    loop {
        run.poll(&mut NoOutput);
        let now = run.mcu.now();
        let ahead = run.session.sent_until() - onechip_planner::toolhead::BUFFER_TIME_HIGH;
        let until = clock_at(ahead, freq);
        if now >= until || run.mcu.shutdown_reason().is_some() {
            return;
        }
        run.mcu
            .run_until(until.min(now + (READ_AHEAD_POLL * freq) as u64));
    }
}

/// A printer set up for a run, as its input drives it: the machine, the
/// session, the virtual MCU, the console with the SD folder as its card,
/// and the summary its replies go to.
pub(crate) struct Run<'r, 'm, const L: usize> {
    pub(crate) machine: &'r Machine<'m>,
    pub(crate) session: &'r mut HostSession<'m, L>,
    pub(crate) mcu: &'r mut HostMcu,
    pub(crate) summary: &'r mut Summary,
    console: Console,
    card: files::Folder,
}

impl<const L: usize> Run<'_, '_, L> {
    /// Answers one console line, counts it and files its replies, which
    /// also go to `out` as they come (a failing `out` loses nothing here);
    /// carries out a restart it asks for.
    pub(crate) fn line(&mut self, event: &LineEvent<'_>, out: &mut impl fmt::Write) {
        self.summary.lines += 1;
        let mut tee = Tee::new(out);
        // The tee never fails.
        let _ = self.console.line(
            Some(self.session),
            &ErrorText::new(),
            event,
            &mut self.card,
            self.mcu,
            &mut tee,
        );
        let freq = self.summary.mcu_freq;
        restart_if_asked(
            &mut self.console,
            self.machine,
            self.mcu,
            self.session,
            freq,
        );
        self.summary.note_reply(&tee.kept);
    }

    /// The console's work between lines (priming, the flush timer, the
    /// idle timeout, auto-reports, the card's print); what it writes goes
    /// to `out` and the summary.
    pub(crate) fn poll(&mut self, out: &mut impl fmt::Write) {
        let mut tee = Tee::new(out);
        let _ = self
            .console
            .poll(Some(self.session), &mut self.card, self.mcu, &mut tee);
        self.summary.note_reply(&tee.kept);
    }

    /// Runs `auto0.g`, `auto1.g`, ... from the card, as the board at boot.
    pub(crate) fn autostart(&mut self) {
        self.console.autostart();
    }

    /// True while a file prints from the card.
    pub(crate) fn is_printing(&self) -> bool {
        self.console.is_printing()
    }
}

/// A reply kept as it goes to `out`.
struct Tee<'o, W> {
    out: &'o mut W,
    kept: String,
}

impl<'o, W: fmt::Write> Tee<'o, W> {
    fn new(out: &'o mut W) -> Self {
        Self {
            out,
            kept: String::new(),
        }
    }
}

impl<W: fmt::Write> fmt::Write for Tee<'_, W> {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        self.kept.push_str(s);
        // The host may have gone; the summary still gets the reply.
        let _ = self.out.write_str(s);
        Ok(())
    }
}

/// Where replies go when only the summary keeps them.
struct NoOutput;

impl fmt::Write for NoOutput {
    fn write_str(&mut self, _: &str) -> fmt::Result {
        Ok(())
    }
}

/// Reads printer.cfg (and its includes) from the SD folder `sd` into
/// `buf` and the machine from it (`scratch` indexes the config meanwhile),
/// its pins checked as `options` say.
fn load_setup<'b>(
    sd: &Path,
    options: &Options,
    buf: &'b mut [u8],
    scratch: &mut std::mem::MaybeUninit<onechip_app::setup::Config<'b>>,
) -> Result<PrinterSetup<'b>, SimError> {
    let texts = onechip_app::config_files::load(&mut files::Folder::new(sd), buf)
        .map_err(|e| SimError::Config(e.to_string()))?;
    let reserved = match options.board_pins {
        true => onechip_app::pin_check::BOARD_RESERVED,
        false => &[],
    };
    PrinterSetup::load(&texts, reserved, scratch).map_err(|e| SimError::Config(e.to_string()))
}

/// The virtual MCU for `machine` as `options` say: heaters, physics (where
/// the toolhead starts), plot window, step files, injected faults.
fn virtual_mcu(machine: &Machine<'_>, options: &Options) -> Result<VirtualMcu, SimError> {
    let freq = options.mcu_freq;
    let origin = options.clock_origin as f64 / freq;
    let mut mcu = VirtualMcu::new(machine.steppers.len(), options.clock_origin)
        .with_heaters(machine, freq)
        .with_tmc(machine, freq);
    if let Some(physics) = physics(machine, options) {
        mcu = mcu.with_physics(physics);
    }
    if let Some((_, w)) = &options.plot {
        let window = plot::Window {
            from: w.from + origin,
            to: w.to + origin,
        };
        mcu = mcu.with_plot(window, freq);
    }
    if let Some(dir) = &options.steps_dir {
        let names = machine.steppers.iter().map(|s| s.name);
        mcu = mcu.with_step_files(dir, names).map_err(write_error)?;
    }
    if let (Some((t, heater)), Some((_, plant))) = (options.open_sensor, mcu.thermal()) {
        plant.open_sensor = Some((clock_at(t + origin, freq), heater));
    }
    if let (Some((t, input, bits)), Some((_, plant))) = (options.spi_fault, mcu.thermal()) {
        plant.spi_fault = Some((clock_at(t + origin, freq), input, bits));
    }
    if let (Some((heater, factor)), Some((_, plant))) = (options.weak_heater, mcu.thermal()) {
        plant.weaken(heater, factor);
    }
    Ok(mcu)
}

/// The session's MCU role: `mcu`, and the secondary MCUs of `setup`
/// connected, if it has any; virtual time then follows the wall clock, as
/// theirs does.
fn with_secondaries(
    setup: &PrinterSetup<'_>,
    options: &Options,
    mut mcu: VirtualMcu,
) -> Result<HostMcu, SimError> {
    let freq = options.mcu_freq;
    if setup.machine().secondaries.is_empty() {
        return Ok(HostMcu::new(mcu, None, freq));
    }
    let pace = Pace::new(
        options.clock_origin,
        freq,
        1.0,
        Arc::new(AtomicBool::new(false)),
    );
    let wall = pace.clone();
    let now = move || wall.clock_now() as f64 / freq;
    // Kept for the life of the process, as the firmware keeps its own in
    // a static.
    let secondaries = Box::leak(Box::new(Secondaries::new(
        freq,
        crate::thermal_plant::mcu_sensor(),
    )));
    let links = &mut secondary::SerialDevices;
    (secondaries.connect(setup, &secondary::leak, links, &now))
        .map_err(|e| SimError::Secondary(e.to_string()))?;
    mcu.set_pace(pace);
    mcu.with_secondaries();
    let mut mcu = HostMcu::new(mcu, Some(secondaries), freq);
    mcu.run_to_wall_clock();
    Ok(mcu)
}

/// Carries out a restart `console` was asked for (FIRMWARE_RESTART,
/// M999): the MCU role and the session start afresh for `machine`.
fn restart_if_asked<'m, const L: usize>(
    console: &mut Console,
    machine: &Machine<'m>,
    mcu: &mut HostMcu,
    session: &mut HostSession<'m, L>,
    freq: f64,
) {
    if console.take_restart() {
        mcu.restart(machine, freq);
        session.restart(machine, onechip_app::session::Mcu::now(mcu));
    }
}

/// Sets up the printer of the SD folder `sd` as `options` say (its
/// session with a lookahead of `L` moves, the virtual MCU, the console),
/// lets `input` feed it, then finishes the print and sums up what it did.
pub(crate) fn with_session<const L: usize>(
    sd: &Path,
    options: &Options,
    input: impl FnOnce(&mut Run<'_, '_, L>) -> Result<(), SimError>,
) -> Result<Summary, SimError> {
    let config_path = sd.join(onechip_app::config_files::PRINTER_CFG);
    let mut buf = vec![0u8; files::CONFIG_BUFFER];
    let mut scratch = Box::new(std::mem::MaybeUninit::uninit());
    let setup = load_setup(sd, options, &mut buf, &mut scratch)?;
    let machine = setup.machine();
    let freq = options.mcu_freq;
    let origin = options.clock_origin as f64 / freq;
    let mut session = Box::new(HostSession::<L>::new(
        machine,
        freq,
        profile::MAX_STEP_ERROR,
        options.clock_origin,
    ));
    let mcu = virtual_mcu(machine, options)?;
    // Without simulated switches a homing move runs to its end, as in
    // klippy's batch mode.
    session.set_endstops_modelled(mcu.real_position().is_some());
    let mut mcu = with_secondaries(&setup, options, mcu)?;
    let mut summary = Summary {
        config_path,
        kinematics: machine.kinematics,
        unsupported: machine.unsupported.iter().map(|s| s.to_string()).collect(),
        input_shaper: [("x", machine.input_shaper.x), ("y", machine.input_shaper.y)]
            .iter()
            .filter_map(|(axis, s)| s.map(|s| format!("{axis}: {} {} Hz", s.kind.name(), s.freq)))
            .collect(),
        gcode_path: PathBuf::new(),
        lines: 0,
        toolhead_moves: 0,
        extruder_moves: 0,
        peak_velocity: 0.0,
        print_time: 0.0,
        final_position: [0.0; 4],
        replies: Vec::new(),
        temperatures: Vec::new(),
        errors: Vec::new(),
        transcript: String::new(),
        transcript_dropped: 0,
        steppers: Vec::new(),
        shutdown: None,
        mcu_freq: freq,
        endstops: Vec::new(),
        stalls: Vec::new(),
        real_position: None,
        heaters: Vec::new(),
        fan_speed: None,
        heat_wait: 0.0,
        secondary_steps: Vec::new(),
        secondary_links: Vec::new(),
        secondary_fault_at: None,
        homing_timeouts: 0,
    };
    input(&mut Run {
        machine,
        session: &mut session,
        mcu: &mut mcu,
        summary: &mut summary,
        console: Console::new(freq),
        card: files::Folder::new(sd),
    })?;
    session.finish(&mut mcu);
    mcu.run_until(u64::MAX);
    // The heaters run on to the end of the print (its last dwell).
    let end = clock_at(session.printer().print_time(), freq);
    if end > mcu.now() {
        mcu.run_until(end);
    }
    stopped(&session, &mut mcu, &mut summary);
    let planned = session.planned();
    summary.toolhead_moves = planned.toolhead_moves;
    summary.extruder_moves = planned.extruder_moves;
    summary.peak_velocity = planned.peak_velocity;
    summary.heat_wait = session.heat_wait();
    summary.print_time = session.printer().print_time();
    summary.final_position = session.printer().position();
    summary.real_position = mcu.main().real_position();
    let run_ticks = mcu.now().saturating_sub(options.clock_origin).max(1) as f64;
    if let Some((heaters, plant)) = mcu.main_mut().thermal() {
        plant.finish();
        for (i, h) in machine.heaters.iter().enumerate() {
            let (temperature, target) = heaters.temperature(i).unwrap_or_default();
            summary.heaters.push(HeaterSummary {
                name: h.name.to_string(),
                target,
                temperature,
                peak: plant.temperature(i).map_or(0.0, |t| t.1),
                duty: plant.outputs.get(i).map_or(0.0, |o| o.on_ticks / run_ticks),
                on_at_end: plant
                    .outputs
                    .get(i)
                    .is_some_and(|o| o.drive == Some(Drive::Level(true))),
            });
        }
        summary.fan_speed = heaters.fan_speed();
    }
    let clock_origin = options.clock_origin;
    summary.endstops = mcu
        .main()
        .triggers()
        .iter()
        .map(|&(axis, real, clock)| (axis, real, (clock - clock_origin) as f64 / freq))
        .collect();
    summary.stalls = mcu.main().stalls().to_vec();
    mcu.main_mut().flush_steps().map_err(write_error)?;
    if let Some(secondaries) = mcu.secondaries() {
        summary.secondary_fault_at = mcu.main().secondary_fault_at();
        summary.homing_timeouts = secondaries.homing_timeouts();
        let links = secondaries
            .links()
            .map(|(name, stats)| (name.to_string(), stats));
        summary.secondary_links = links.collect();
    }
    for (i, (stepper, log)) in machine.steppers.iter().zip(mcu.main().logs()).enumerate() {
        let sent = mcu
            .secondaries()
            .filter(|s| s.routes(i))
            .and_then(|s| s.sent(i));
        let (steps, position) = match sent {
            Some(sent) => {
                let name = stepper.name.to_string();
                let clocks = mcu.main().secondary_steps(i).unwrap_or_default().to_vec();
                summary.secondary_steps.push((name, clocks));
                (sent.count as usize, sent.position)
            }
            None => (log.count, log.position),
        };
        summary.steppers.push(StepperSummary {
            name: stepper.name.to_string(),
            steps,
            position,
            peak_rate: log.min_interval.map_or(0.0, |i| freq / i as f64),
            last_step: log.last,
        });
    }
    if let Some((path, window)) = &options.plot {
        // Plotted in print time from the start of the print.
        let steppers: Vec<(&str, Vec<f64>)> = machine
            .steppers
            .iter()
            .zip(mcu.main().logs())
            .map(|(st, log)| {
                let times = log
                    .window_steps()
                    .iter()
                    .map(|&clock| clock as f64 / freq - origin)
                    .collect();
                (st.name, times)
            })
            .collect();
        let moves: Vec<TrapqMove> = mcu
            .main()
            .plan()
            .iter()
            .map(|m| TrapqMove {
                print_time: m.print_time - origin,
                ..*m
            })
            .collect();
        let svg = plot::svg(&moves, &steppers, *window);
        std::fs::write(path, svg).map_err(|e| SimError::Read(path.clone(), e))?;
    }
    Ok(summary)
}

impl Summary {
    /// Files the console's answer to the last line: `!!` lines as errors,
    /// temperature reports apart (M105's on its `ok` line), other text as
    /// replies, `ok` and busy lines dropped (the transcript has them).
    fn note_reply(&mut self, reply: &str) {
        if self.transcript_dropped == 0 && self.transcript.len() + reply.len() <= TRANSCRIPT_MAX {
            self.transcript.push_str(reply);
        } else {
            self.transcript_dropped += reply.len();
        }
        let keepalive = |l: &&str| *l == "ok" || *l == onechip_app::session::BUSY_LINE;
        for line in reply.lines().filter(|l| !keepalive(l)) {
            // M105's temperatures come on its `ok` line.
            let line = line.strip_prefix("ok ").unwrap_or(line);
            let entry = |text: &str| (self.lines, text.to_string());
            if let Some(error) = line.strip_prefix("!! ") {
                self.errors.push(entry(error));
            } else if line.starts_with("T:") || line.starts_with("B:") {
                self.temperatures.push(entry(line));
            } else {
                self.replies.push(entry(line));
            }
        }
    }
}

/// G-code files at least this long report progress, bytes.
const PROGRESS_MIN_BYTES: usize = 256 * 1024;

/// Reports how far a long run is, on stderr, every tenth of the file.
struct Progress {
    len: usize,
    next_tenth: usize,
}

impl Progress {
    fn new(len: usize) -> Self {
        Self {
            len,
            next_tenth: if len >= PROGRESS_MIN_BYTES { 1 } else { 11 },
        }
    }

    /// Notes that `at` bytes are read and `print_time` s are planned.
    fn note(&mut self, at: usize, print_time: f64) {
        if self.next_tenth <= 10 && at * 10 >= self.len * self.next_tenth {
            eprintln!(
                "progress: {}% of the G-code, {:.0} s of print planned",
                self.next_tenth * 10,
                print_time
            );
            self.next_tenth += 1;
        }
    }
}

/// Where the motion steppers really are, and their endstops (a delta's:
/// each tower's carriage at its endstop where the toolhead is at the home
/// position); none with [`Start::Ideal`].
fn physics(machine: &Machine<'_>, options: &Options) -> Option<Physics> {
    let toolhead = match options.start {
        Start::Ideal => return None,
        Start::At(pos) => pos,
        Start::MidTravel => core::array::from_fn(|k| {
            machine
                .steppers
                .get(k)
                .map_or(0.0, |s| 0.5 * (s.position_min + s.position_max))
        }),
    };
    let kinematics = machine.stepper_kinematics;
    let delta = machine.travel.delta_homing();
    Some(Physics {
        kinematics,
        step_dist: core::array::from_fn(|k| machine.steppers.get(k).map_or(1.0, |s| s.step_dist)),
        start: core::array::from_fn(|k| kinematics[k].position(toolhead)),
        endstops: core::array::from_fn(|axis| {
            if options.dead_endstop == Some(axis) {
                return None;
            }
            let info = machine.travel.homing_info(axis)?;
            // A rail homing on the probe has no switch of its own.
            (!info.probe).then_some((info.position_endstop, info.positive_dir))
        }),
        towers: core::array::from_fn(|k| {
            let at = delta.map(|d| kinematics[k].position(d.home));
            at.filter(|_| options.dead_endstop != Some(k))
        }),
        probe: probe_physics::for_machine(
            machine,
            options.bed,
            options.bltouch_fault,
            options.mcu_freq,
        ),
        extras: (3..machine.motion_steppers())
            .filter_map(|slot| {
                let rail = machine.rail_of(slot)?;
                let stepper = machine.steppers.get(slot)?;
                let own = stepper.endstop_pin.is_some() && options.dead_endstop != Some(slot);
                Some(ExtraStepper {
                    slot,
                    step_dist: stepper.step_dist,
                    start: kinematics[rail].position(toolhead) + options.racked,
                    endstop: machine
                        .travel
                        .homing_info(rail)
                        .filter(|info| own && !info.probe)
                        .map(|info| (info.position_endstop, info.positive_dir)),
                })
            })
            .collect(),
    })
}

/// MCU clock at print time `t` (s), ticks (0 before the start).
fn clock_at(t: f64, freq: f64) -> u64 {
    if t.is_finite() {
        (t * freq).max(0.0) as u64
    } else if t > 0.0 {
        u64::MAX
    } else {
        0
    }
}

/// Notes a fault of step generation or the MCU role; true if the run
/// must stop.
fn stopped<const L: usize>(
    session: &HostSession<'_, L>,
    mcu: &mut HostMcu,
    summary: &mut Summary,
) -> bool {
    if summary.shutdown.is_none() {
        summary.shutdown = session
            .motion_error()
            .map(|e| e.to_string())
            .or_else(|| mcu.shutdown_reason().map(|s| s.to_string()));
    }
    summary.shutdown.is_some()
}

/// A steps file that could not be written.
fn write_error((path, e): step_log::FileError) -> SimError {
    SimError::Read(path, e)
}

/// The G-code file's bytes as they are read, then a newline to end its
/// last line; and its length, bytes.
fn open(
    path: &Path,
) -> Result<(impl Iterator<Item = std::io::Result<u8>> + use<>, usize), SimError> {
    let error = |e| SimError::Read(path.to_path_buf(), e);
    let file = std::fs::File::open(path).map_err(error)?;
    let len = file.metadata().map_err(error)?.len();
    let bytes = BufReader::new(file).bytes().chain([Ok(b'\n')]);
    Ok((bytes, usize::try_from(len).unwrap_or(usize::MAX)))
}

fn only_gcode_file(sd: &Path) -> Result<PathBuf, SimError> {
    let entries = std::fs::read_dir(sd).map_err(|e| SimError::Read(sd.to_path_buf(), e))?;
    let mut found: Vec<PathBuf> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| {
            p.extension()
                .is_some_and(|x| x.eq_ignore_ascii_case("gcode"))
        })
        .collect();
    match found.len() {
        1 => Ok(found.remove(0)),
        _ => Err(SimError::NoGcode(sd.to_path_buf())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_transcript_keeps_the_answers_up_to_its_cap() {
        let dir = std::env::temp_dir().join(format!("onechip-transcript-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let shipped =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../sdcard-configs/octopus-pro-h723");
        std::fs::copy(shipped.join("printer.cfg"), dir.join("printer.cfg")).expect("cfg");
        let answer = "X:0.000 Y:0.000 Z:0.000 E:0.000\nok\n";
        // Answers for twice the cap.
        let lines = 2 * TRANSCRIPT_MAX / answer.len();
        std::fs::write(dir.join("long.gcode"), "M114\n".repeat(lines)).expect("gcode");
        let s = run(&dir, None).expect("runs");
        std::fs::remove_dir_all(&dir).ok();
        assert_eq!(s.replies.len(), lines);
        let kept = TRANSCRIPT_MAX / answer.len();
        assert_eq!(s.transcript, answer.repeat(kept));
        assert_eq!(s.transcript_dropped, (lines - kept) * answer.len());
    }
}
