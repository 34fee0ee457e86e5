//! The simulator on a serial port, driven by hosts as the board's USB
//! console is.
//!
//! A Rust client talks to [`onechip_host::serial::serve`] run in this
//! process. Real clients (OctoPrint, Printrun's printcore), installed from
//! PyPI into a virtualenv, drive the release simulator through the Python
//! harnesses in `tests/clients/`; they take a minute and need the venv, so
//! they are `#[ignore]`d in a plain `cargo test`: `.ci/run` creates the
//! venv (`tests/clients/setup.sh`) and runs them with
//! `cargo test -p onechip-tests --test clients -- --ignored`. Without the
//! venv they fail, saying how to create it. The venv is
//! `$ONECHIP_CLIENTS_VENV`, by default `target/clients-venv`.

use onechip_host::Options;
use onechip_host::serial::{Port, serve};
use onechip_tests::sd_folder;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

/// The workspace root.
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ is in the workspace")
        .to_path_buf()
}

/// A fresh SD folder with the shipped printer.cfg.
fn sd(name: &str) -> PathBuf {
    sd_folder::new(&format!("clients-{name}"), &sd_folder::shipped_cfg(), None)
}

/// A host on the simulator's port: sends lines, reads replies to `ok`.
struct Host {
    port: std::fs::File,
    replies: BufReader<std::fs::File>,
}

impl Host {
    /// Opens the port at `link` once the simulator has made it.
    fn open(link: &Path) -> Self {
        let deadline = Instant::now() + Duration::from_secs(10);
        let port = loop {
            match std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .open(link)
            {
                Ok(port) => break port,
                Err(e) if Instant::now() > deadline => panic!("{}: {e}", link.display()),
                Err(_) => std::thread::sleep(Duration::from_millis(10)),
            }
        };
        let replies = BufReader::new(port.try_clone().expect("clone"));
        Self { port, replies }
    }

    /// Sends `line` and returns the replies up to and with its `ok` (or
    /// `ok` with text after it).
    fn send(&mut self, line: &str) -> Vec<String> {
        writeln!(self.port, "{line}").expect("write");
        let mut replies: Vec<String> = Vec::new();
        while replies
            .last()
            .is_none_or(|r| r != "ok" && !r.starts_with("ok "))
        {
            let mut reply = String::new();
            let n = self.replies.read_line(&mut reply).expect("read");
            assert!(n > 0, "the port closed; replies so far: {replies:?}");
            replies.push(reply.trim_end().to_string());
        }
        replies
    }
}

/// Serves `dir` on a pty at `speed`× real time in a thread; `client`
/// drives it (and may raise the flag that ends serving, as SIGINT does),
/// and the port is closed when it returns. Returns the summary of the run.
fn served(
    dir: &Path,
    speed: f64,
    client: impl FnOnce(&mut Host, &AtomicBool),
) -> onechip_host::Summary {
    // One at a time: a host that the machine's load holds back is late in
    // virtual time by that much times the speed.
    static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());
    let _turn = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let port = Port {
        path: dir.join("printer.tty"),
        speed,
    };
    let link = port.path.clone();
    let sd = dir.to_path_buf();
    let ending = Arc::new(AtomicBool::new(false));
    let flag = Arc::clone(&ending);
    let server = std::thread::spawn(move || serve(&sd, &Options::default(), &port, &flag, |_| {}));
    let mut host = Host::open(&link);
    client(&mut host, &ending);
    drop(host);
    let summary = server.join().expect("no panic").expect("served");
    assert!(!link.exists(), "the port's link goes with the simulator");
    summary
}

#[test]
fn a_host_gets_each_reply_as_the_board_gives_it_and_closing_the_port_ends_the_print() {
    let dir = sd("replies");
    let start = Instant::now();
    let summary = served(&dir, 10.0, |host, _| {
        let identity = format!(
            "FIRMWARE_NAME:onechip FIRMWARE_VERSION:{}",
            onechip_app::FIRMWARE_VERSION
        );
        let reply = host.send("M115");
        assert!(reply[0].starts_with(&identity), "{reply:?}");
        // Homing from mid-travel takes 34 s: the host hears that the
        // printer is busy every 2 s (Marlin's keepalive) until the `ok`.
        let homing = host.send("G28");
        let (ok, busy) = homing.split_last().expect("replies");
        assert_eq!(ok, "ok");
        assert!(busy.len() >= 15, "{homing:?}");
        assert!(
            busy.iter().all(|l| l == onechip_app::session::BUSY_LINE),
            "{homing:?}"
        );
        assert_eq!(host.send("G1 X20 Y30 Z5 F6000"), ["ok"]);
        assert_eq!(host.send("G1 X1.2.3")[0], "!! unable to parse X=1.2.3");
        let reply = host.send("M105");
        assert!(
            reply.iter().any(|r| r.contains("T:25.0 /0.0 B:25.0 /0.0")),
            "{reply:?}"
        );
        assert_eq!(host.send("M114")[0], "X:20.000 Y:30.000 Z:5.000 E:0.000");
    });
    assert_eq!(summary.lines, 6);
    assert_eq!(summary.errors.len(), 1);
    assert_eq!(summary.endstops.len(), 6);
    // G28 from mid-travel takes 34 s of virtual time, which never runs
    // ahead of the wall clock (by more than the pacing's 1 ms): at 10×,
    // the `ok` came 3.4 s after the start.
    let homed = summary.endstops[5].2;
    let wall = start.elapsed().as_secs_f64();
    assert!(homed > 33.0, "{homed} s");
    assert!(wall > homed / 10.0 - 0.002, "{wall} s");
    assert_eq!(summary.shutdown, None);
    // The move after homing ran to its end once the port closed.
    let real = summary.real_position.expect("physics");
    for (real, commanded) in real.iter().zip([20.0, 30.0, 5.0]) {
        assert!((real - commanded).abs() < 0.01, "{real:?}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn told_to_end_the_simulator_stops_waiting_on_the_wall_clock_and_finishes_the_print() {
    let dir = sd("ending");
    let mut start = Instant::now();
    let summary = served(&dir, 1.0, |host, ending| {
        // Timed from here: the other tests may have held the simulator.
        start = Instant::now();
        // Homing from mid-travel: 34 s in real time.
        writeln!(host.port, "G28").expect("write");
        std::thread::sleep(Duration::from_millis(200));
        // The port goes with the simulator, maybe before the host has
        // read the `ok`.
        ending.store(true, Ordering::Relaxed);
    });
    assert!(
        start.elapsed() < Duration::from_secs(10),
        "{:?}",
        start.elapsed()
    );
    // Homing ran to its end, in virtual time.
    assert_eq!(summary.endstops.len(), 6);
    assert!(summary.print_time > 30.0, "{}", summary.print_time);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_print_through_the_port_steps_as_the_same_file_from_the_card() {
    let dir = sd("same-steps");
    // The shipped sample, heater waits included (the hot end must reach
    // min_extrude_temp before it extrudes).
    let program =
        std::fs::read_to_string(sd_folder::shipped_dir().join("first-layer-square.gcode"))
            .expect("sample");
    // At 10×, a host stalled for 0.2 s (a loaded CI machine) is 2 s late
    // in virtual time, as long as the lookahead holds (see the slow-host
    // test below).
    let summary = served(&dir, 10.0, |host, _| {
        for line in program.lines() {
            let reply = host.send(line);
            assert!(
                !reply
                    .iter()
                    .any(|r| r.starts_with("!!") || r.starts_with("//")),
                "{line}: {reply:?}"
            );
        }
    });
    std::fs::write(dir.join("job.gcode"), &program).expect("gcode");
    let batch = onechip_host::run(&dir, None).expect("batch run");
    for (served, batch) in summary.steppers.iter().zip(&batch.steppers) {
        assert_eq!(
            (served.steps, served.position),
            (batch.steps, batch.position),
            "{}",
            served.name
        );
    }
    assert_eq!(summary.final_position, batch.final_position);
    assert_eq!(summary.shutdown, None);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_host_slower_than_its_moves_does_not_starve_the_steppers() {
    let dir = sd("slow-host");
    let summary = served(&dir, 1.0, |host, _| {
        host.send("SET_KINEMATIC_POSITION X=100 Y=100 Z=10");
        host.send("G91");
        // 1 mm moves at 100 mm/s take about 20 ms; the host sends one every
        // 30 ms (OctoPrint on a busy Pi streaming short segments).
        for i in 0..60 {
            let reply = host.send(if i % 2 == 0 {
                "G1 X1 F6000"
            } else {
                "G1 X-1 F6000"
            });
            assert_eq!(reply, ["ok"], "move {i}");
            std::thread::sleep(Duration::from_millis(30));
        }
        assert_eq!(host.send("M400"), ["ok"]);
    });
    assert_eq!(summary.shutdown, None);
    assert_eq!(summary.steppers[0].steps, 60 * 80);
    std::fs::remove_dir_all(&dir).ok();
}

/// The release simulator the harnesses run, built once.
fn simulator() -> &'static Path {
    static BUILT: OnceLock<PathBuf> = OnceLock::new();
    BUILT.get_or_init(|| {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let status = Command::new(cargo)
            .current_dir(root())
            .args([
                "build",
                "--release",
                "-p",
                "onechip-host",
                "--bin",
                "onechip-sim",
            ])
            .status()
            .expect("cargo runs");
        assert!(status.success(), "building the release simulator failed");
        root().join("target/release/onechip-sim")
    })
}

/// The venv's python, or a failure saying how to make the venv.
fn python() -> PathBuf {
    let venv = std::env::var_os("ONECHIP_CLIENTS_VENV")
        .map_or_else(|| root().join("target/clients-venv"), PathBuf::from);
    let python = venv.join("bin/python");
    assert!(
        python.is_file(),
        "no client venv at {}: create it with `tests/clients/setup.sh {}` (what .ci/run does), \
         or point ONECHIP_CLIENTS_VENV at one",
        venv.display(),
        venv.display()
    );
    python
}

/// Runs the harness `script` with `args`; fails with its output unless it
/// passes.
fn harness(script: &str, args: &[&str]) {
    let python = python();
    let start = Instant::now();
    let out = Command::new(&python)
        .arg(root().join("tests/clients").join(script))
        .args(args)
        .env("ONECHIP_SIM", simulator())
        .output()
        .expect("python runs");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let run = format!("{script} {args:?} ({:.1} s)", start.elapsed().as_secs_f64());
    assert!(out.status.success(), "{run} failed:\n{text}");
    println!("{run}:\n{text}");
}

#[test]
#[ignore = "needs the client venv: tests/clients/setup.sh; run with --ignored"]
fn octoprint_prints_an_uploaded_file() {
    harness("octoprint_print.py", &["--source", "local"]);
}

#[test]
#[ignore = "needs the client venv: tests/clients/setup.sh; run with --ignored"]
fn octoprint_prints_from_the_sd_card() {
    harness("octoprint_print.py", &["--source", "sdcard"]);
}

#[test]
#[ignore = "needs the client venv: tests/clients/setup.sh; run with --ignored"]
fn printcore_streams_a_print() {
    harness("printcore_corrupt.py", &["--percent", "0"]);
}

#[test]
#[ignore = "needs the client venv: tests/clients/setup.sh; run with --ignored"]
fn printcore_runs_every_line_once_through_a_corrupting_line() {
    harness("printcore_corrupt.py", &[]);
}
