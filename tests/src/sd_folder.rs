//! SD folders for the tests: what the firmware reads from its card, a
//! `printer.cfg` and the G-code it runs (`job.gcode`), written to a
//! throw-away folder in the system's temp dir, most often from the
//! shipped printer.cfg with a few sections added or lines changed.

use std::path::{Path, PathBuf};

/// The shipped SD folder, `sdcard-configs/octopus-pro-h723`, as it goes
/// on the card: the BTT Octopus Pro (STM32H723) printer.cfg and its
/// sample job.
pub fn shipped_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../sdcard-configs/octopus-pro-h723")
}

/// The text of the shipped printer.cfg ([`shipped_dir`]).
///
/// # Panics
///
/// If it cannot be read.
pub fn shipped_cfg() -> String {
    std::fs::read_to_string(shipped_dir().join("printer.cfg")).expect("shipped printer.cfg")
}

/// An empty folder `onechip-<name>-<pid>` in the system's temp dir, with
/// whatever an earlier run left there removed. The tests of one file run
/// as threads of one process: give each of them its own `name`.
///
/// # Panics
///
/// If the folder cannot be made.
pub fn empty(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("onechip-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("SD folder");
    dir
}

/// Writes `cfg` as `dir/printer.cfg` and, if there is one, `job` (G-code)
/// as `dir/job.gcode`, making `dir` if it is not there.
///
/// # Panics
///
/// If the folder or a file cannot be written.
pub fn write(dir: &Path, cfg: &str, job: Option<&str>) {
    std::fs::create_dir_all(dir).expect("SD folder");
    std::fs::write(dir.join("printer.cfg"), cfg).expect("printer.cfg");
    if let Some(job) = job {
        std::fs::write(dir.join("job.gcode"), job).expect("job.gcode");
    }
}

/// An [`empty`] folder named after `name` holding `cfg` as printer.cfg and
/// `job`, if any, as job.gcode ([`write`]).
///
/// # Panics
///
/// As [`empty`] and [`write`].
pub fn new(name: &str, cfg: &str, job: Option<&str>) -> PathBuf {
    let dir = empty(name);
    write(&dir, cfg, job);
    dir
}
