//! What one stepper did, in memory that does not grow with the print: the
//! running figures the summary needs, every step streamed to its
//! `steps-<stepper>.txt` file as it happens, and only the steps inside a
//! plot's window kept.

use std::collections::VecDeque;
use std::fs::File;
use std::io::{self, BufWriter, Write as _};
use std::ops::RangeInclusive;
use std::path::{Path, PathBuf};

/// Buffer of each steps file, bytes.
const FILE_BUFFER: usize = 64 * 1024;

/// A steps file that could not be written: its path, and why.
pub type FileError = (PathBuf, io::Error);

/// The steps one stepper made.
#[derive(Debug, Default)]
pub struct StepLog {
    /// Steps made.
    pub count: usize,
    /// Position in steps (+1 per positive step).
    pub position: i64,
    /// Shortest time between two steps, ticks.
    pub min_interval: Option<u64>,
    /// 64-bit MCU clock of the last step, ticks.
    pub last: Option<u64>,
    /// Where every step is written, if anywhere.
    file: Option<StepFile>,
    /// The clocks kept (ticks), and the clocks of the steps kept there.
    window: Option<(RangeInclusive<u64>, Vec<u64>)>,
    /// The last [`RECENT`] steps: clock (ticks) and direction (true:
    /// positive), oldest first.
    recent: VecDeque<(u64, bool)>,
}

/// Steps [`StepLog::moved_since`] looks back over (at 100,000 steps/s,
/// 40 ms: beyond any relay latency between MCUs).
const RECENT: usize = 4096;

/// A `steps-*.txt` file being written: one `<clock> <dir>` line per step.
#[derive(Debug)]
struct StepFile {
    path: PathBuf,
    out: BufWriter<File>,
    /// The first write that failed (nothing is written after it).
    error: Option<io::Error>,
}

impl StepLog {
    /// Records a step at 64-bit MCU clock `clock` (ticks), positive or not.
    pub fn record(&mut self, clock: u64, positive: bool) {
        if let Some(last) = self.last {
            let gap = clock - last;
            self.min_interval = Some(self.min_interval.map_or(gap, |m| m.min(gap)));
        }
        self.count += 1;
        self.last = Some(clock);
        if self.recent.len() == RECENT {
            self.recent.pop_front();
        }
        self.recent.push_back((clock, positive));
        self.position += if positive { 1 } else { -1 };
        if let Some(file) = &mut self.file
            && file.error.is_none()
            && let Err(e) = writeln!(file.out, "{clock} {}", u8::from(positive))
        {
            file.error = Some(e);
        }
        if let Some((clocks, steps)) = &mut self.window
            && clocks.contains(&clock)
        {
            steps.push(clock);
        }
    }

    /// Where the steps made after 64-bit clock `clock` (ticks) moved it,
    /// in steps (+1 per positive step), among the last [`RECENT`].
    pub fn moved_since(&self, clock: u64) -> i64 {
        let after = self.recent.iter().rev().take_while(|s| s.0 > clock);
        after
            .map(|&(_, positive)| if positive { 1 } else { -1 })
            .sum()
    }

    /// Writes every step from now on to `dir/steps-<name>.txt` (created,
    /// as is `dir`).
    pub fn write_to(&mut self, dir: &Path, name: &str) -> Result<(), FileError> {
        let path = dir.join(format!("steps-{name}.txt"));
        let file = std::fs::create_dir_all(dir).and_then(|()| File::create(&path));
        match file {
            Ok(file) => {
                self.file = Some(StepFile {
                    path,
                    out: BufWriter::with_capacity(FILE_BUFFER, file),
                    error: None,
                });
                Ok(())
            }
            Err(e) => Err((path, e)),
        }
    }

    /// Keeps the clocks of the steps made within `clocks` (ticks).
    pub fn keep_window(&mut self, clocks: RangeInclusive<u64>) {
        self.window = Some((clocks, Vec::new()));
    }

    /// The clocks of the steps kept by [`Self::keep_window`], ticks.
    pub fn window_steps(&self) -> &[u64] {
        self.window.as_ref().map_or(&[], |(_, steps)| steps)
    }

    /// Writes out what the steps file still buffers; the first error of
    /// any write to it, if one failed.
    pub fn flush(&mut self) -> Result<(), FileError> {
        let Some(file) = &mut self.file else {
            return Ok(());
        };
        match file.error.take().map_or_else(|| file.out.flush(), Err) {
            Ok(()) => Ok(()),
            Err(e) => Err((file.path.clone(), e)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn running_figures_follow_the_steps() {
        let mut log = StepLog::default();
        for (clock, positive) in [(100, true), (130, true), (140, false), (200, true)] {
            log.record(clock, positive);
        }
        assert_eq!(
            (log.count, log.position, log.min_interval, log.last),
            (4, 2, Some(10), Some(200))
        );
        assert!(log.window_steps().is_empty());
        // Past 130: back one, forward one.
        assert_eq!(log.moved_since(130), 0);
        assert_eq!(log.moved_since(135), 0);
        assert_eq!(log.moved_since(99), 2);
        assert_eq!(log.moved_since(140), 1);
        assert_eq!(log.moved_since(200), 0);
    }

    #[test]
    fn only_the_last_steps_are_looked_back_over() {
        let mut log = StepLog::default();
        for clock in 0..RECENT as u64 + 10 {
            log.record(clock, true);
        }
        assert_eq!(log.moved_since(0), RECENT as i64);
    }

    #[test]
    fn only_the_window_is_kept_and_every_step_is_written() {
        let dir = std::env::temp_dir().join(format!("onechip-step-log-{}", std::process::id()));
        let mut log = StepLog::default();
        log.write_to(&dir, "stepper_x").expect("creates the file");
        log.keep_window(120..=140);
        for (clock, positive) in [(100, true), (120, false), (140, true), (141, true)] {
            log.record(clock, positive);
        }
        log.flush().expect("writes");
        assert_eq!(log.window_steps(), [120, 140]);
        let text = std::fs::read_to_string(dir.join("steps-stepper_x.txt")).expect("reads");
        assert_eq!(text, "100 1\n120 0\n140 1\n141 1\n");
        std::fs::remove_dir_all(&dir).ok();
    }
}
