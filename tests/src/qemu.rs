//! The firmware on QEMU's emulated Cortex-M7 (`onechip-qemu` on
//! `mps2-an500`, see qemu/src/main.rs): build the image for a printer.cfg,
//! start QEMU with its console UART on a Unix socket and the `pinlog`
//! plugin, stream G-code with the console protocol, then read what the
//! pins did and where the CPU's time went.
//!
//! Time: QEMU runs with `-icount shift=1,sleep=off`, 2 ns of virtual time
//! per guest instruction (500 M instructions per second, about a 520 MHz
//! STM32H723); the firmware never sleeps, so a pin write's instruction
//! count is its virtual time ([`NS_PER_INSN`]).
//!
//! A run with a secondary MCU ([`Qemu::start_linked`]: UART 1 on a stock
//! Klipper peer's serial device) is in real time instead, as the peer
//! is: QEMU runs without `-icount`, its virtual clock (the timers') is
//! the host's, and the firmware sleeps with `wfi` (see
//! qemu/src/machine.rs). Pin writes are then not timed by their
//! instruction counts; the peer's own pin log times its steps.
//! `ONECHIP_QEMU_REALTIME_ICOUNT` (e.g. `shift=1,sleep=on`) runs such a
//! run with that `-icount` instead, to compare.

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Virtual nanoseconds per guest instruction (`-icount shift=1`).
pub const NS_PER_INSN: u64 = 2;
/// The firmware's step clock (the CMSDK timers' 25 MHz), Hz.
pub const CLOCK_HZ: f64 = 25_000_000.0;
/// Longest a console line may take to be acknowledged (a full step
/// queue waits for the steps), real seconds.
const LINE_TIMEOUT: Duration = Duration::from_secs(300);

/// The workspace's root.
fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Where cargo builds: `CARGO_TARGET_DIR`, or the workspace's `target`.
pub fn target_dir() -> PathBuf {
    std::env::var_os("CARGO_TARGET_DIR").map_or_else(|| root().join("target"), PathBuf::from)
}

/// Builds the firmware with `config` as its printer.cfg and returns the
/// ELF (a copy named after `name`, so images for different configs can
/// live side by side).
///
/// # Panics
///
/// If cargo fails.
pub fn build_firmware(name: &str, config: &str) -> PathBuf {
    // One build at a time: each writes the same ELF before it is copied.
    static BUILD: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _one = BUILD.lock().unwrap_or_else(|e| e.into_inner());
    let dir = target_dir().join("qemu");
    std::fs::create_dir_all(&dir).expect("target/qemu");
    let cfg = dir.join(format!("{name}.cfg"));
    std::fs::write(&cfg, config).expect("write printer.cfg");
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let status = Command::new(cargo)
        .current_dir(root())
        .env("ONECHIP_QEMU_CONFIG", &cfg)
        .args([
            "build",
            "-p",
            "onechip-qemu",
            "--release",
            "--target",
            "thumbv7em-none-eabihf",
        ])
        .status()
        .expect("cargo runs");
    assert!(status.success(), "building onechip-qemu failed");
    let elf = dir.join(format!("{name}.elf"));
    std::fs::copy(
        target_dir().join("thumbv7em-none-eabihf/release/onechip-qemu"),
        &elf,
    )
    .expect("copy the ELF");
    elf
}

/// Builds the pin-logging plugin with the host's gcc (once per change of
/// its source) and returns the shared object.
///
/// # Panics
///
/// If gcc fails.
pub fn build_plugin() -> PathBuf {
    let source = root().join("qemu/plugin/pinlog.c");
    let so = target_dir().join("qemu/libpinlog.so");
    let fresh = |p: &Path| std::fs::metadata(p).and_then(|m| m.modified()).ok();
    if fresh(&so).is_none() || fresh(&so) < fresh(&source) {
        std::fs::create_dir_all(target_dir().join("qemu")).expect("target/qemu");
        let status = Command::new("gcc")
            .args(["-shared", "-fPIC", "-O2", "-Wall", "-o"])
            .arg(&so)
            .arg(&source)
            .status()
            .expect("gcc runs");
        assert!(status.success(), "building the pinlog plugin failed");
    }
    so
}

/// A running QEMU with the firmware, its console connected.
pub struct Qemu {
    child: Child,
    console: BufReader<UnixStream>,
    /// The plugin's log.
    pub pin_log: PathBuf,
    /// QEMU's standard output (the firmware's semihosting reports).
    pub stdout: PathBuf,
    /// The next console line number.
    number: u32,
}

/// One console line's replies, `ok` excluded.
pub type Replies = Vec<String>;

impl Qemu {
    /// Starts QEMU on `elf` with files named after `name` in
    /// `target/qemu`; connects to its console (up to 10 s).
    ///
    /// # Panics
    ///
    /// If QEMU does not start or its console does not open.
    pub fn start(elf: &Path, name: &str) -> Self {
        Self::launch(elf, name, None)
    }

    /// [`Self::start`] with UART 1 on the host serial device `serial` (a
    /// peer's pseudo-terminal, or the symlink to it), in real time (see
    /// the module's doc).
    ///
    /// # Panics
    ///
    /// As [`Self::start`], or if `serial` does not resolve to a device.
    pub fn start_linked(elf: &Path, name: &str, serial: &Path) -> Self {
        // Once seen a link to nothing, for a moment after the peer made it.
        let deadline = Instant::now() + Duration::from_secs(5);
        let device = loop {
            match std::fs::canonicalize(serial) {
                Ok(device) => break device,
                Err(e) if Instant::now() > deadline => panic!("{}: {e}", serial.display()),
                Err(_) => std::thread::sleep(Duration::from_millis(20)),
            }
        };
        Self::launch(elf, name, Some(&device))
    }

    fn launch(elf: &Path, name: &str, uart1: Option<&Path>) -> Self {
        let dir = target_dir().join("qemu");
        let socket = dir.join(format!("{name}.sock"));
        let pin_log = dir.join(format!("{name}.pins"));
        let stdout = dir.join(format!("{name}.out"));
        let _ = std::fs::remove_file(&socket);
        let plugin = build_plugin();
        let mut qemu = Command::new("qemu-system-arm");
        qemu.args(["-M", "mps2-an500", "-nographic", "-monitor", "none"])
            .args(["-semihosting-config", "enable=on,target=native"]);
        match uart1 {
            None => {
                qemu.args(["-icount", "shift=1,sleep=off"]);
            }
            Some(_) => {
                if let Ok(icount) = std::env::var("ONECHIP_QEMU_REALTIME_ICOUNT") {
                    qemu.arg("-icount").arg(icount);
                }
            }
        }
        qemu.arg("-plugin")
            .arg(format!(
                "{},out={}{}",
                plugin.display(),
                pin_log.display(),
                // Every context change in the log too, for debugging.
                if std::env::var_os("ONECHIP_QEMU_TRACE").is_some() {
                    ",trace=1"
                } else {
                    ""
                }
            ))
            .arg("-serial")
            .arg(format!("unix:{},server=on,wait=on", socket.display()));
        if let Some(device) = uart1 {
            // A path under /dev/: QEMU's tty backend (raw mode).
            qemu.arg("-serial").arg(device);
        }
        let child = qemu
            .arg("-kernel")
            .arg(elf)
            .stdin(Stdio::null())
            .stdout(std::fs::File::create(&stdout).expect("QEMU's stdout file"))
            .stderr(Stdio::inherit())
            .spawn()
            .expect("qemu-system-arm runs (apt-get install qemu-system-arm)");
        let deadline = Instant::now() + Duration::from_secs(10);
        let stream = loop {
            match UnixStream::connect(&socket) {
                Ok(stream) => break stream,
                Err(e) if Instant::now() > deadline => panic!("QEMU's console: {e}"),
                Err(_) => std::thread::sleep(Duration::from_millis(20)),
            }
        };
        stream
            .set_read_timeout(Some(LINE_TIMEOUT))
            .expect("socket timeout");
        Self {
            child,
            console: BufReader::new(stream),
            pin_log,
            stdout,
            number: 0,
        }
    }

    /// Sends `line` as Marlin hosts do (`N<n> <line>*<checksum>`) and
    /// returns the replies before its `ok` (`busy` keepalives left out),
    /// and what the `ok` line carries after it, if anything (M105's
    /// `ok T:…`).
    ///
    /// # Panics
    ///
    /// If the console closes or stays silent for [`LINE_TIMEOUT`].
    pub fn send(&mut self, line: &str) -> Replies {
        let numbered = format!("N{} {line}", self.number);
        let sum = numbered.bytes().fold(0u8, |a, b| a ^ b);
        self.number += 1;
        self.console
            .get_mut()
            .write_all(format!("{numbered}*{sum}\n").as_bytes())
            .expect("console write");
        let mut replies = Vec::new();
        loop {
            let mut reply = String::new();
            let n = self
                .console
                .read_line(&mut reply)
                .unwrap_or_else(|e| panic!("no reply to {line:?}: {e}"));
            assert!(n > 0, "console closed after {line:?}");
            let reply = reply.trim_end();
            if reply == "ok" {
                return replies;
            }
            // An answer on the ok line (M105's `ok T:…`) is one too.
            if let Some(answer) = reply.strip_prefix("ok ") {
                replies.push(answer.to_string());
                return replies;
            }
            if reply != "echo:busy: processing" {
                replies.push(reply.to_string());
            }
        }
    }

    /// Reads the console's lines (sent without a command: a shutdown's
    /// `!!` line) until one contains `needle`, for up to `timeout`: every
    /// line read, Ok if the last one has it.
    ///
    /// # Errors
    ///
    /// The lines read if none had it in time.
    pub fn wait_for(
        &mut self,
        needle: &str,
        timeout: Duration,
    ) -> Result<Vec<String>, Vec<String>> {
        let deadline = Instant::now() + timeout;
        let mut lines = Vec::new();
        let stream = self.console.get_ref();
        let _ = stream.set_read_timeout(Some(Duration::from_millis(100)));
        let found = loop {
            let mut line = String::new();
            match self.console.read_line(&mut line) {
                Ok(0) => break false,
                Ok(_) => {
                    let line = line.trim_end().to_string();
                    let has = line.contains(needle);
                    lines.push(line);
                    if has {
                        break true;
                    }
                }
                Err(_) if Instant::now() < deadline => {}
                Err(_) => break false,
            }
        };
        let _ = self.console.get_ref().set_read_timeout(Some(LINE_TIMEOUT));
        if found { Ok(lines) } else { Err(lines) }
    }

    /// Streams `gcode` line by line (comments and blank lines left out,
    /// as hosts do), after `M110 N0`; returns every line with its
    /// replies.
    pub fn stream(&mut self, gcode: &str) -> Vec<(String, Replies)> {
        self.send("M110 N0");
        self.number = 1;
        gcode
            .lines()
            .map(|l| l.split(';').next().unwrap_or_default().trim())
            .filter(|l| !l.is_empty())
            .map(|l| (l.to_string(), self.send(l)))
            .collect()
    }

    /// Stops QEMU (SIGTERM: the plugin writes its totals) and reads the
    /// pin log and the firmware's reports.
    ///
    /// # Panics
    ///
    /// If QEMU does not stop within 10 s or the logs are unreadable.
    pub fn finish(mut self) -> Run {
        // SAFETY: a signal to the child this struct started and still owns.
        unsafe { libc::kill(self.child.id() as i32, libc::SIGTERM) };
        let deadline = Instant::now() + Duration::from_secs(10);
        while self.child.try_wait().expect("QEMU's status").is_none() {
            assert!(Instant::now() < deadline, "QEMU did not stop");
            std::thread::sleep(Duration::from_millis(20));
        }
        let log = std::fs::read_to_string(&self.pin_log).expect("pin log");
        let reports = std::fs::read_to_string(&self.stdout).expect("QEMU's output");
        Run::parse(&log, &reports)
    }
}

impl Drop for Qemu {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One pin store the plugin logged.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PinWrite {
    /// Guest instructions before it (× [`NS_PER_INSN`]: virtual time).
    pub insns: u64,
    /// Port (0 = A) and pin number.
    pub pin: Pin,
    /// Driven high.
    pub high: bool,
}

/// A port (0 = A) and pin number.
pub type Pin = (u8, u8);

/// Instructions one context took over the run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CpuShare {
    /// `stepper`, `heaters`, `console`, `idle` or `thread`.
    pub context: String,
    /// Instructions executed in it.
    pub insns: u64,
    /// Times it was entered.
    pub runs: u64,
    /// Its longest run, instructions.
    pub longest: u64,
    /// When that run started, instructions.
    pub longest_at: u64,
}

/// What a run did: the pin stores, the CPU's time and the firmware's own
/// figures.
#[derive(Debug, Clone)]
pub struct Run {
    /// Every pin store, in order.
    pub writes: Vec<PinWrite>,
    /// Instructions per context.
    pub cpu: Vec<CpuShare>,
    /// Instructions in all.
    pub total: u64,
    /// The firmware's last `stats` line's `key=value` pairs.
    pub stats: Vec<(String, String)>,
    /// The firmware's static RAM, bytes.
    pub static_ram: Option<u64>,
    /// QEMU's standard output (the firmware's reports, a panic).
    pub reports: String,
}

impl Run {
    fn parse(log: &str, reports: &str) -> Self {
        let mut run = Self {
            writes: Vec::new(),
            cpu: Vec::new(),
            total: 0,
            stats: Vec::new(),
            static_ram: None,
            reports: reports.to_string(),
        };
        for line in log.lines() {
            let words: Vec<&str> = line.split_whitespace().collect();
            let num = |i: usize| words.get(i).and_then(|w| w.parse::<u64>().ok());
            match words.as_slice() {
                ["cpu", context, ..] => run.cpu.push(CpuShare {
                    context: (*context).to_string(),
                    insns: num(2).expect("cpu insns"),
                    runs: num(3).expect("cpu runs"),
                    longest: num(4).expect("cpu longest"),
                    longest_at: num(5).expect("cpu longest's start"),
                }),
                ["total", _] => run.total = num(1).expect("total"),
                [">" | "<", ..] => {}
                [insns, offset] => {
                    let offset = u64::from_str_radix(offset, 16).expect("pin offset");
                    let (port, word) = (offset / 0x1000, offset % 0x1000 / 4);
                    if word < 32 {
                        run.writes.push(PinWrite {
                            insns: insns.parse().expect("pin insns"),
                            pin: (port as u8, (word % 16) as u8),
                            high: word >= 16,
                        });
                    }
                }
                _ => panic!("pin log: {line:?}"),
            }
        }
        if let Some(stats) = reports.lines().rfind(|l| l.starts_with("stats ")) {
            run.stats = stats
                .split_whitespace()
                .filter_map(|kv| kv.split_once('='))
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect();
        }
        run.static_ram = reports
            .lines()
            .find_map(|l| l.strip_prefix("onechip-qemu: static_ram="))
            .and_then(|v| v.trim().parse().ok());
        run
    }

    /// The firmware's last reported value of `key`.
    pub fn stat(&self, key: &str) -> Option<&str> {
        self.stats
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }

    /// Instructions in `context`, if the plugin reported it.
    pub fn cpu(&self, context: &str) -> Option<&CpuShare> {
        self.cpu.iter().find(|c| c.context == context)
    }

    /// The steps the pins made for a stepper on `step` and `dir` (with
    /// `dir_inverted` as its `!`): one per rising edge of the step pin,
    /// with its instruction count and the direction pin's level then
    /// (true: positive).
    pub fn steps(&self, step: Pin, dir: Pin, dir_inverted: bool) -> Vec<(u64, bool)> {
        let (mut step_high, mut dir_high) = (false, false);
        let mut steps = Vec::new();
        for w in &self.writes {
            if w.pin == dir {
                dir_high = w.high;
            } else if w.pin == step {
                if w.high && !step_high {
                    steps.push((w.insns, dir_high != dir_inverted));
                }
                step_high = w.high;
            }
        }
        steps
    }
}

/// A stepper's pins as printer.cfg names them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StepperPins {
    /// Section name (`stepper_x`, `extruder`).
    pub name: String,
    /// Step pin.
    pub step: Pin,
    /// Direction pin.
    pub dir: Pin,
    /// The direction pin is inverted (`!`).
    pub dir_inverted: bool,
}

/// Port and pin of an STM32 pin name (`PF13`, `!PC1`), and its `!`.
fn parse_pin(text: &str) -> Option<(Pin, bool)> {
    let text = text.trim().trim_start_matches('^');
    let (inverted, text) = match text.strip_prefix('!') {
        Some(rest) => (true, rest),
        None => (false, text),
    };
    let rest = text.strip_prefix('P')?;
    let port = rest.bytes().next()?.checked_sub(b'A')?;
    Some(((port, rest.get(1..)?.parse().ok()?), inverted))
}

/// Every `[stepper_*]` and `[extruder]` section's step and direction
/// pins in `config`.
///
/// # Panics
///
/// If a stepper section lacks a pin or a pin does not parse.
pub fn stepper_pins(config: &str) -> Vec<StepperPins> {
    /// A pin and its `!`, once read.
    type Named = Option<(Pin, bool)>;
    let mut steppers: Vec<(String, Named, Named)> = Vec::new();
    let mut current: Option<usize> = None;
    for line in config.lines() {
        let line = line.split(['#', ';']).next().unwrap_or_default().trim();
        if let Some(section) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
            current =
                (section.starts_with("stepper_") || section == "extruder").then(|| match steppers
                    .iter()
                    .position(|s| s.0 == section)
                {
                    Some(i) => i,
                    None => {
                        steppers.push((section.to_string(), None, None));
                        steppers.len() - 1
                    }
                });
        } else if let (Some(i), Some((key, value))) = (current, line.split_once(':')) {
            match key.trim() {
                "step_pin" => steppers[i].1 = parse_pin(value),
                "dir_pin" => steppers[i].2 = parse_pin(value),
                _ => {}
            }
        }
    }
    steppers
        .into_iter()
        .map(|(name, step, dir)| {
            let (step, _) = step.unwrap_or_else(|| panic!("[{name}] step_pin"));
            let (dir, dir_inverted) = dir.unwrap_or_else(|| panic!("[{name}] dir_pin"));
            StepperPins {
                name,
                step,
                dir,
                dir_inverted,
            }
        })
        .collect()
}
