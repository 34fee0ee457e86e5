//! `cargo xtask sim-memory`: the host build's memory must not grow with
//! the print. Builds the release simulator, runs it on a 1-hour and a
//! 4-hour benchmark print ([`crate::bench_print`]), and reports each run's
//! peak resident set size, CPU and wall time; fails if the 1-hour peak is
//! above [`PEAK_LIMIT_MIB`] or the 4-hour peak more than
//! [`GROWTH_LIMIT`] above it. Linux only (it reads the peak with `wait4`).

use std::io::Read as _;
use std::os::unix::process::ExitStatusExt as _;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Highest peak RSS allowed for the 1-hour print, MiB.
const PEAK_LIMIT_MIB: f64 = 64.0;
/// Highest ratio of the 4-hour peak RSS to the 1-hour one.
const GROWTH_LIMIT: f64 = 1.1;
/// The prints' lengths, h.
const HOURS: [f64; 2] = [1.0, 4.0];
/// The simulator under the target directory.
const SIM_IN_TARGET: &str = "release/onechip-sim";

/// What one run of the simulator used.
struct Usage {
    /// Peak resident set size, KiB.
    peak_kib: u64,
    /// User and system CPU time.
    cpu: Duration,
    /// Wall time.
    wall: Duration,
    /// The print time the summary gives.
    print_time: String,
}

/// Builds the simulator, measures it on each print, checks the limits.
pub fn run(root: &Path, target: &Path) -> Result<(), String> {
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let built = Command::new(cargo)
        .args([
            "build",
            "--release",
            "-p",
            "onechip-host",
            "--bin",
            "onechip-sim",
        ])
        .arg("--manifest-path")
        .arg(root.join("Cargo.toml"))
        .status()
        .map_err(|e| format!("cargo build: {e}"))?;
    if !built.success() {
        return Err(format!("cargo build: {built}"));
    }
    let sim = target.join(SIM_IN_TARGET);
    let work = std::env::temp_dir().join(format!("onechip-sim-memory-{}", std::process::id()));
    let mut peaks = Vec::new();
    println!("print  peak RSS    CPU       wall      print time");
    for hours in HOURS {
        let dir = work.join(format!("{hours}h"));
        crate::bench_print::write(root, &dir, hours)?;
        let usage = measure(&sim, &dir)?;
        println!(
            "{hours} h    {:>5.1} MiB  {:>6.2} s  {:>6.2} s  {}",
            mib(usage.peak_kib),
            usage.cpu.as_secs_f64(),
            usage.wall.as_secs_f64(),
            usage.print_time
        );
        peaks.push(mib(usage.peak_kib));
    }
    std::fs::remove_dir_all(&work).ok();
    let (first, last) = (peaks[0], peaks[peaks.len() - 1]);
    let mut problems = Vec::new();
    if first > PEAK_LIMIT_MIB {
        problems.push(format!(
            "the 1-hour print peaks at {first:.1} MiB, above {PEAK_LIMIT_MIB} MiB"
        ));
    }
    if last > first * GROWTH_LIMIT {
        problems.push(format!(
            "the 4-hour print peaks at {last:.1} MiB, more than {:.0} % above the 1-hour print's {first:.1} MiB",
            (GROWTH_LIMIT - 1.0) * 100.0
        ));
    }
    if problems.is_empty() {
        println!("sim-memory: ok");
        Ok(())
    } else {
        Err(problems.join("; "))
    }
}

fn mib(kib: u64) -> f64 {
    kib as f64 / 1024.0
}

/// Runs `sim` on the SD folder `dir` and waits for it, reading what it
/// used from the kernel.
fn measure(sim: &Path, dir: &Path) -> Result<Usage, String> {
    let what = format!("{} {}", sim.display(), dir.display());
    let start = Instant::now();
    let mut child = Command::new(sim)
        .arg(dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| format!("{what}: {e}"))?;
    let mut summary = String::new();
    if let Some(out) = &mut child.stdout {
        out.read_to_string(&mut summary)
            .map_err(|e| format!("{what}: {e}"))?;
    }
    let pid = libc::pid_t::try_from(child.id()).map_err(|e| format!("{what}: {e}"))?;
    let mut status = 0;
    // SAFETY: rusage is plain integers, for which all zeros is a value.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    loop {
        // SAFETY: `pid` is this process's child, not yet waited for (std
        // only reaps it in `wait`, never called on it); `status` and
        // `usage` are valid for writes.
        if unsafe { libc::wait4(pid, &mut status, 0, &mut usage) } == pid {
            break;
        }
        let e = std::io::Error::last_os_error();
        if e.kind() != std::io::ErrorKind::Interrupted {
            return Err(format!("{what}: wait4: {e}"));
        }
    }
    let wall = start.elapsed();
    let status = std::process::ExitStatus::from_raw(status);
    if !status.success() {
        return Err(format!(
            "{what}: {status} (`cargo sim {}` shows why)",
            dir.display()
        ));
    }
    let time = |t: libc::timeval| {
        Duration::from_secs(t.tv_sec.unsigned_abs())
            + Duration::from_micros(t.tv_usec.unsigned_abs())
    };
    Ok(Usage {
        peak_kib: usage.ru_maxrss.unsigned_abs(),
        cpu: time(usage.ru_utime) + time(usage.ru_stime),
        wall,
        print_time: summary
            .lines()
            .find_map(|l| l.strip_prefix("print time:"))
            .unwrap_or("?")
            .trim()
            .to_string(),
    })
}
