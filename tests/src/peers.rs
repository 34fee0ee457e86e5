//! Stock Klipper MCU firmware as test peers (`../shared/peers`, its README
//! says how they work): a peer is started on a fresh pseudo-terminal path
//! and stopped (SIGTERM, which removes the path) when dropped.

use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::{Duration, Instant};

/// The peers' folder: `ONECHIP_PEERS`, or `../shared/peers`.
pub fn peers_dir() -> PathBuf {
    std::env::var_os("ONECHIP_PEERS").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/peers"),
        PathBuf::from,
    )
}

/// Where peers keep their device link and pin log: `/dev/shm` if there
/// is one (the Linux peer writes a log line per pin edge as it steps; on a
/// disk, a write may wait tens of ms for the file system's journal, which
/// stalls the MCU past trsync's 25 ms), else the system's temp dir.
fn scratch_dir() -> PathBuf {
    let shm = Path::new("/dev/shm");
    if shm.is_dir() {
        shm.to_path_buf()
    } else {
        std::env::temp_dir()
    }
}

/// Which stock firmware.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Firmware {
    /// Klipper's Linux MCU process, 50 MHz, fake GPIO chips.
    Linux,
    /// The atmega2560 firmware in simavr, 16 MHz, 250000 baud.
    Avr,
}

/// A stepper's pins on a peer, as the firmware names them.
#[derive(Debug, Clone, Copy)]
pub struct StepperPins {
    /// Step.
    pub step: &'static str,
    /// Direction.
    pub dir: &'static str,
    /// Enable (written inverted in printer.cfg).
    pub enable: &'static str,
}

/// The pins [`printer_with_extruder_on`] gives the extruder on `firmware`.
pub const fn extruder_pins(firmware: Firmware) -> StepperPins {
    match firmware {
        Firmware::Linux => StepperPins {
            step: "gpiochip0/gpio10",
            dir: "gpiochip0/gpio11",
            enable: "gpiochip0/gpio12",
        },
        Firmware::Avr => StepperPins {
            step: "PA4",
            dir: "PA6",
            enable: "PA2",
        },
    }
}

/// An SD folder `dir`: the shipped printer.cfg with each of `edits` made
/// (every place of its first text replaced by its second), the secondary
/// MCUs `mcus` (name, serial device, `restart_method`) added, and `gcode`
/// as its one G-code file.
///
/// # Panics
///
/// If the shipped printer.cfg no longer has an edit's text, or the folder
/// cannot be written.
pub fn shipped_printer(
    dir: &Path,
    edits: &[(&str, &str)],
    mcus: &[(&str, &Path, &str)],
    gcode: &str,
) {
    let mut cfg = crate::sd_folder::shipped_cfg();
    for (from, to) in edits {
        assert!(
            cfg.contains(from),
            "the shipped printer.cfg changed: {from:?}"
        );
        cfg = cfg.replace(from, to);
    }
    for (name, serial, restart_method) in mcus {
        let section = format!(
            "[mcu {name}]\nserial: {}\nrestart_method: {restart_method}\n\n[printer]",
            serial.display()
        );
        cfg = cfg.replace("[printer]", &section);
    }
    crate::sd_folder::write(dir, &cfg, Some(gcode));
}

/// [`shipped_printer`] with its extruder on the secondary MCU `ext`
/// (`firmware`, at `serial`, reset by `restart_method`) on
/// [`extruder_pins`], cold extrusion allowed.
pub fn printer_with_extruder_on(
    firmware: Firmware,
    dir: &Path,
    serial: &Path,
    restart_method: &str,
    gcode: &str,
) {
    let pins = extruder_pins(firmware);
    let extruder = format!(
        "[extruder]\nstep_pin: ext:{}\ndir_pin: ext:{}\nenable_pin: !ext:{}\n\
         min_extrude_temp: 0\n",
        pins.step, pins.dir, pins.enable
    );
    let edits = [(
        "[extruder]\nstep_pin: PF9\ndir_pin: PF10\nenable_pin: !PG2\n",
        extruder.as_str(),
    )];
    shipped_printer(dir, &edits, &[("ext", serial, restart_method)], gcode);
}

/// How a peer's inputs read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Inputs {
    /// Always this level.
    Level(u8),
    /// What the test writes to a file (Linux MCU only).
    File,
}

/// The Linux MCU's GPIO shim with inputs read from a file, built once per
/// test process.
fn driven_shim() -> PathBuf {
    static SHIM: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    SHIM.get_or_init(|| {
        let so = scratch_dir().join(format!("onechip-fakegpio-driven-{}.so", std::process::id()));
        let source = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("peer-shim/inputs_from_file.c");
        let status = Command::new("cc")
            .args(["-shared", "-fPIC", "-O2", "-I"])
            .arg(peers_dir().join("linux"))
            .arg("-o")
            .arg(&so)
            .arg(source)
            .arg("-ldl")
            .status()
            .expect("cc");
        assert!(status.success(), "building the driven GPIO shim failed");
        so
    })
    .clone()
}

/// A running peer.
pub struct Peer {
    child: Child,
    /// Its serial device (a symlink to the pty).
    pub path: PathBuf,
    /// Its pin-edge log.
    pub pin_log: PathBuf,
    /// The file its inputs read, if a test drives them
    /// ([`Self::start_driven`]).
    inputs: Option<PathBuf>,
    /// The folder standing in for its IIO device, if a test drives its
    /// ADC ([`Self::adc`]).
    iio: Option<PathBuf>,
    /// The folder of its SPI devices' registers, if a test drives them
    /// ([`Self::spi`]).
    spi: Option<PathBuf>,
}

/// One ADC channel of a driven Linux MCU (`analogN` in its pin names): the
/// file the peer-shim wrapper serves as the channel's IIO file.
#[derive(Debug, Clone)]
pub struct AdcChannel {
    path: PathBuf,
}

impl AdcChannel {
    /// The channel reads `raw` (0..=4095, the Linux MCU's ADC_MAX) from
    /// now on. The file is rewritten in place at a fixed width, never
    /// truncated: the MCU keeps it open and reads it from offset 0 at each
    /// sample (an empty read would shut it down).
    pub fn set(&self, raw: u16) -> std::io::Result<()> {
        use std::os::unix::fs::FileExt;
        let file = std::fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(false)
            .open(&self.path)?;
        file.write_all_at(format!("{raw:05}\n").as_bytes(), 0)
    }
}

/// An SPI device of a driven Linux MCU (`spidevB.D`), a register chip as
/// the peer-shim wrapper serves it: the file holding its registers.
#[derive(Debug, Clone)]
pub struct SpiRegisters {
    path: PathBuf,
}

impl SpiRegisters {
    /// Registers `address` on read `bytes` from now on. The file is
    /// rewritten in place (the wrapper reads it at each transfer).
    pub fn set(&self, address: u8, bytes: &[u8]) -> std::io::Result<()> {
        use std::os::unix::fs::FileExt;
        let file = std::fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(false)
            .open(&self.path)?;
        file.write_all_at(bytes, u64::from(address))
    }
}

impl Peer {
    /// Starts `firmware` in a fresh folder under the system's temp dir
    /// named after `test`; waits (up to 5 s) for its device to appear.
    ///
    /// # Panics
    ///
    /// If the peer cannot be started: the test cannot run.
    pub fn start(firmware: Firmware, test: &str) -> Self {
        Self::start_with_inputs(firmware, test, 0)
    }

    /// [`Self::start`] with every input pin reading `level` (the Linux
    /// MCU's fake GPIO; the AVR's inputs always read 0): an endstop that
    /// triggers at that level is pressed from the start, so it triggers
    /// as soon as its `endstop_home` starts sampling.
    ///
    /// # Panics
    ///
    /// As [`Self::start`].
    pub fn start_with_inputs(firmware: Firmware, test: &str, level: u8) -> Self {
        Self::launch(firmware, test, Inputs::Level(level))
    }

    /// A Linux MCU whose inputs the test sets while it runs
    /// ([`Self::set_inputs`]; they read 0 at first), through the project's
    /// wrapper of the peer's GPIO shim (`tests/peer-shim`, built with `cc`),
    /// which also logs each output's level when it is set up.
    ///
    /// # Panics
    ///
    /// As [`Self::start`], or if the wrapper cannot be built.
    pub fn start_driven(test: &str) -> Self {
        Self::launch(Firmware::Linux, test, Inputs::File)
    }

    /// Every input of a peer started by [`Self::start_driven`] reads
    /// `level` from now on: returns when, on the Linux peer's pin-log
    /// clock (CLOCK_MONOTONIC, s).
    ///
    /// # Panics
    ///
    /// If the peer's inputs are not driven, or the file cannot be written.
    pub fn set_inputs(&self, level: u8) -> f64 {
        let path = self.inputs.as_ref().expect("a peer started driven");
        std::fs::write(path, level.to_string()).expect("inputs file");
        monotonic_now()
    }

    /// ADC channel `channel` (pin `analog<channel>`) of a peer started by
    /// [`Self::start_driven`]: set its reading before the MCU is
    /// configured (`config_analog_in` opens it; a channel never set is
    /// `Unable to open adc device`).
    ///
    /// # Panics
    ///
    /// If the peer's inputs are not driven.
    pub fn adc(&self, channel: u8) -> AdcChannel {
        let dir = self.iio.as_ref().expect("a peer started driven");
        AdcChannel {
            path: dir.join(format!("in_voltage{channel}_raw")),
        }
    }

    /// SPI device `device` (`spidev0.0`) of a peer started with
    /// [`Self::start_driven`]: a register chip, all zero until set.
    ///
    /// # Panics
    ///
    /// If the peer's inputs are not driven.
    pub fn spi(&self, device: &str) -> SpiRegisters {
        let dir = self.spi.as_ref().expect("a peer started driven");
        SpiRegisters {
            path: dir.join(device),
        }
    }

    /// The file holding SPI device `device`'s registers
    /// ([`Self::spi`]).
    ///
    /// # Panics
    ///
    /// If the peer's inputs are not driven.
    pub fn spi_path(&self, device: &str) -> PathBuf {
        self.spi(device).path
    }

    fn launch(firmware: Firmware, test: &str, inputs: Inputs) -> Self {
        let dir = scratch_dir().join(format!("onechip-peer-{test}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("peer folder");
        let path = dir.join("mcu");
        let pin_log = dir.join("pins.log");
        let input_file = dir.join("inputs");
        let iio = dir.join("iio");
        let spi = dir.join("spi");
        let mut cmd = match firmware {
            Firmware::Linux => {
                let mut c = Command::new(peers_dir().join("start-linux-mcu"));
                c.arg(&path).env("FAKEGPIO_LOG", &pin_log);
                match inputs {
                    Inputs::Level(level) => c.env("FAKEGPIO_IN", level.to_string()),
                    Inputs::File => {
                        std::fs::write(&input_file, "0").expect("inputs file");
                        std::fs::create_dir_all(&iio).expect("iio folder");
                        std::fs::create_dir_all(&spi).expect("spi folder");
                        c.env("FAKEGPIO_SO", driven_shim())
                            .env("FAKEGPIO_IN_FILE", &input_file)
                            .env("FAKEIIO_DIR", &iio)
                            .env("FAKESPI_DIR", &spi)
                    }
                };
                // Real-time priority keeps its steps punctual; it needs root.
                // SAFETY: geteuid has no preconditions.
                if unsafe { libc::geteuid() } == 0 {
                    c.arg("-r");
                }
                c
            }
            Firmware::Avr => {
                let mut c = Command::new(peers_dir().join("start-avr-mcu"));
                c.arg(&path).arg("-l").arg(&pin_log);
                c
            }
        };
        let child = cmd
            .spawn()
            .unwrap_or_else(|e| panic!("{}: {e} (set ONECHIP_PEERS)", peers_dir().display()));
        if firmware == Firmware::Avr {
            // The simulator keeps the AVR's time only while it gets the
            // CPU: at real-time priority when allowed, as the Linux peer
            // runs with `-r` (else a loaded machine makes its clock lag
            // and its trsync reports come late).
            let param = libc::sched_param { sched_priority: 1 };
            if let Ok(pid) = i32::try_from(child.id()) {
                // SAFETY: a valid sched_param, for a process we started.
                unsafe { libc::sched_setscheduler(pid, libc::SCHED_FIFO, &param) };
            }
        }
        let start = Instant::now();
        while !path.exists() {
            assert!(
                start.elapsed() < Duration::from_secs(5),
                "peer did not create {}",
                path.display()
            );
            std::thread::sleep(Duration::from_millis(5));
        }
        Self {
            child,
            path,
            pin_log,
            inputs: (inputs == Inputs::File).then_some(input_file),
            iio: (inputs == Inputs::File).then_some(iio),
            spi: (inputs == Inputs::File).then_some(spi),
        }
    }

    /// The firmware's own process (the Linux MCU, or the simulator): the
    /// launcher's child if it has one, else the launcher itself (the AVR
    /// launcher `exec`s the simulator).
    pub fn mcu_pid(&self) -> i32 {
        let launcher = i32::try_from(self.child.id()).unwrap_or(0);
        let children = format!("/proc/{launcher}/task/{launcher}/children");
        std::fs::read_to_string(children)
            .ok()
            .and_then(|c| c.split_whitespace().next()?.parse().ok())
            .unwrap_or(launcher)
    }

    /// Sends `signal` to the firmware's process (SIGKILL: it dies as a
    /// board pulled off its cable; SIGSTOP/SIGCONT: it freezes and goes
    /// on, as a board whose clock stopped).
    pub fn signal_mcu(&self, signal: i32) {
        // SAFETY: signalling a process this peer started.
        unsafe { libc::kill(self.mcu_pid(), signal) };
    }

    /// Where the stepper on pins `step`/`dir` went, by the pin log: +1 for
    /// each rising step edge while `dir` is high, −1 while low.
    pub fn position(&self, step: &str, dir: &str) -> i64 {
        self.position_until(step, dir, f64::INFINITY)
    }

    /// [`Self::position`] by the edges up to time `until` (s, the pin
    /// log's time: see [`Self::rising_edges`]).
    pub fn position_until(&self, step: &str, dir: &str, until: f64) -> i64 {
        let text = std::fs::read_to_string(&self.pin_log).unwrap_or_default();
        let mut forward = false;
        let mut position = 0;
        for change in changes(&text).take_while(|c| c.time <= until) {
            if change.name == dir {
                forward = change.high;
            } else if change.name == step && change.rising {
                position += if forward { 1 } else { -1 };
            }
        }
        position
    }

    /// Waits until `pin` has made `count` rising edges, up to `timeout`;
    /// false if it did not.
    pub fn wait_for_edges(&self, pin: &str, count: usize, timeout: Duration) -> bool {
        let start = Instant::now();
        while start.elapsed() < timeout {
            if self.rising_edges(pin).len() >= count {
                return true;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        false
    }

    /// Stops the peer at once (SIGKILL to the launcher's MCU process is
    /// not used: SIGTERM stops it and removes the device).
    pub fn stop(&mut self) {
        // A frozen MCU would hold the signal until it runs again.
        self.signal_mcu(libc::SIGCONT);
        if let Ok(pid) = i32::try_from(self.child.id()) {
            // SAFETY: signalling our own child.
            unsafe { libc::kill(pid, libc::SIGTERM) };
        }
        let _ = self.child.wait();
    }

    /// Every change of `pin`'s level in the pin log (its first write
    /// counts as one): the time (s, as [`Self::rising_edges`]) and the new
    /// level.
    pub fn levels(&self, pin: &str) -> Vec<(f64, bool)> {
        let text = std::fs::read_to_string(&self.pin_log).unwrap_or_default();
        changes(&text)
            .filter(|c| c.name == pin && c.edge)
            .map(|c| (c.time, c.high))
            .collect()
    }

    /// Every write of `pin` in the pin log, a level it already had too
    /// (the Linux MCU writes an output at each of its updates): the time
    /// (s, as [`Self::rising_edges`]) and the level.
    pub fn writes(&self, pin: &str) -> Vec<(f64, bool)> {
        let text = std::fs::read_to_string(&self.pin_log).unwrap_or_default();
        changes(&text)
            .filter(|c| c.name == pin)
            .map(|c| (c.time, c.high))
            .collect()
    }

    /// Every value written to `file` (a hardware PWM channel's file as
    /// the driven shim logs it, `pwmchip0/pwm0/duty_cycle`): the time (s,
    /// CLOCK_MONOTONIC) and the value.
    pub fn values(&self, file: &str) -> Vec<(f64, u64)> {
        let text = std::fs::read_to_string(&self.pin_log).unwrap_or_default();
        text.lines()
            .filter_map(|line| {
                let mut words = line.split_whitespace();
                let (ns, name, value) = (words.next()?, words.next()?, words.next()?);
                let value = value.parse().ok().filter(|_| name == file)?;
                Some((ns.parse::<f64>().ok()? * 1e-9, value))
            })
            .collect()
    }

    /// The rising edges in the pin log for `pin`: their times in seconds
    /// (Linux peer: CLOCK_MONOTONIC; AVR peer: its MCU clock / 16 MHz).
    pub fn rising_edges(&self, pin: &str) -> Vec<f64> {
        edges(&self.pin_log, pin)
    }
}

impl Drop for Peer {
    fn drop(&mut self) {
        self.stop();
        if let Some(dir) = self.path.parent() {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
}

/// The calling thread at real-time priority (`SCHED_FIFO`, one level
/// above the AVR simulator's) while this lives, if the process may (root): a host serving
/// real-time peers under deadlines (trsync's 25 ms) on a loaded machine,
/// as the Linux peer runs with `-r`.
pub struct RealtimeGuard {
    raised: bool,
}

impl RealtimeGuard {
    /// Raises the calling thread's priority (nothing if not allowed).
    pub fn new() -> Self {
        let param = libc::sched_param { sched_priority: 2 };
        // SAFETY: a valid sched_param for the calling thread (pid 0).
        let raised = unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) } == 0;
        Self { raised }
    }

    /// True if the thread runs at real-time priority.
    pub fn is_raised(&self) -> bool {
        self.raised
    }
}

impl Default for RealtimeGuard {
    fn default() -> Self {
        Self::new()
    }
}

impl Drop for RealtimeGuard {
    fn drop(&mut self) {
        if self.raised {
            let param = libc::sched_param { sched_priority: 0 };
            // SAFETY: as in `new`.
            unsafe { libc::sched_setscheduler(0, libc::SCHED_OTHER, &param) };
        }
    }
}

/// CLOCK_MONOTONIC now, s: the Linux peer's pin-log clock.
pub fn monotonic_now() -> f64 {
    let mut now = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: a valid timespec for the call to fill.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut now) };
    now.tv_sec as f64 + now.tv_nsec as f64 * 1e-9
}

/// Rising edges of `pin` in a pin log, s.
fn edges(log: &Path, pin: &str) -> Vec<f64> {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    changes(&text)
        .filter(|c| c.name == pin && c.rising)
        .map(|c| c.time)
        .collect()
}

/// One line of a pin log.
struct Change<'t> {
    /// When, s (Linux peer: CLOCK_MONOTONIC; AVR peer: its MCU clock / 16
    /// MHz).
    time: f64,
    name: &'t str,
    high: bool,
    /// Low (or unknown) before, high now.
    rising: bool,
    /// Another level (or unknown) before.
    edge: bool,
}

/// The pin log's lines as changes (a write of the level a pin already
/// has is no edge).
fn changes(text: &str) -> impl Iterator<Item = Change<'_>> {
    let mut levels: std::collections::HashMap<&str, bool> = std::collections::HashMap::new();
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(move |line| {
            let words: Vec<&str> = line.split_whitespace().collect();
            // Linux: "<ns> gpiochipN/gpioM <v>"; AVR: "<cycle> <clock> P<x><n> <v>".
            let (time, name, value) = match words[..] {
                [ns, name, v] => (ns.parse::<f64>().ok()? * 1e-9, name, v),
                [_, clock, name, v] => (clock.parse::<f64>().ok()? / 16e6, name, v),
                _ => return None,
            };
            let high = value == "1";
            let was = levels.insert(name, high);
            Some(Change {
                time,
                name,
                high,
                rising: high && was != Some(true),
                edge: was != Some(high),
            })
        })
}
