//! Z probes as Klipper has them: `[probe]` (a switch on a pin) and
//! `[bltouch]` (a sensor pin plus a servo-driven control pin), the
//! `probe:z_virtual_endstop` pin that lets a rail home on the probe, and
//! probing: a homing-style move of Z down to `position_min` that stops at
//! the probe's trigger (Klipper's `probing_move`), repeated and combined as
//! its `samples` options say.
//!
//! The BLTouch's servo commands ([`crate::bltouch`]) are timed in print
//! time around the probing moves and handed to the sink
//! ([`MoveSink::probe_pin`]).

use crate::bltouch::{self, Bltouch, BltouchConfig};
use crate::homing::HomingHooks;
use crate::homing::Rails;
use crate::move_sink::MoveSink;
use crate::reader::{Errors, Read, Reader};
use crate::toolhead::{Detail, HomingInfo, MoveError, Toolhead};
use onechip_config::decimal::Fixed;
use onechip_config::{Bounds, Config};

/// The endstop pin a rail names to home on the probe.
pub const VIRTUAL_ENDSTOP: &str = "probe:z_virtual_endstop";
/// Klipper's error when a probing move reaches its end untriggered.
pub const NO_TRIGGER: &str = "No trigger on probe after full movement";
/// Klipper's error when a communication timeout ends a probing move
/// (another MCU's trsync reports stopped).
pub const COMMS_TIMEOUT: &str = "Error during homing probe: Communication timeout during homing";
/// Klipper's error when probing before Z is homed.
pub const MUST_HOME: &str = "Must home before probe";
/// Klipper's error when samples spread more than samples_tolerance.
pub const EXCEED_TOLERANCE: &str = "Probe samples exceed samples_tolerance";

/// How several samples are combined (`samples_result`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SamplesResult {
    /// The mean of the samples.
    Average,
    /// The median sample (mean of the middle two for an even count).
    Median,
}

/// A probe as `[probe]` or `[bltouch]` describes it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeConfig<'a> {
    /// The section it comes from (`probe` or `bltouch`).
    pub section: &'a str,
    /// The input the probe triggers (`pin`, or the BLTouch's
    /// `sensor_pin`), as written.
    pub pin: &'a str,
    /// x_offset, y_offset, z_offset: where the probe is from the nozzle,
    /// mm; z_offset is the nozzle's height above the bed when it triggers.
    pub offsets: [f64; 3],
    /// speed: probing speed, mm/s.
    pub speed: f64,
    /// lift_speed: speed of the lifts between samples, mm/s.
    pub lift_speed: f64,
    /// samples: probes per result.
    pub samples: u32,
    /// sample_retract_dist: lift between samples, mm.
    pub sample_retract_dist: f64,
    /// samples_result.
    pub samples_result: SamplesResult,
    /// samples_tolerance: largest spread of one result's samples, mm.
    pub samples_tolerance: f64,
    /// samples_tolerance_retries: how often to start again past it.
    pub samples_tolerance_retries: u32,
    /// Where a probing move goes down to: stepper_z's position_min, mm.
    pub z_position: f64,
    /// The BLTouch's control pin and timings, for `[bltouch]`.
    pub bltouch: Option<BltouchConfig<'a>>,
}

/// Reads `[probe]` or `[bltouch]`, if present (both: an error, as in
/// Klipper where each registers the `probe` object).
// Out of line: see `Machine::from_config_in`.
#[inline(never)]
pub(crate) fn read<'c, 'a>(
    config: &'c Config<'a>,
    errors: &Errors<'c>,
) -> Read<Option<ProbeConfig<'a>>> {
    let section = |name| config.section(name).map(|s| Reader::new(s, errors));
    let (section, bltouch) = match (section("probe"), section("bltouch")) {
        (Some(_), Some(b)) => {
            return Err(b.error_for("control_pin", "[probe] is already defined"));
        }
        (Some(p), None) => (p, None),
        (None, Some(b)) => {
            let blt = bltouch::read(&b)?;
            (b, Some(blt))
        }
        (None, None) => return Ok(None),
    };
    let pin = section.get(if bltouch.is_some() {
        "sensor_pin"
    } else {
        "pin"
    })?;
    let z_offset_bounds = if bltouch.is_some() {
        Bounds::NON_NEGATIVE
    } else {
        Bounds::NONE
    };
    let offsets = [
        section.float("x_offset", 0.0, Bounds::NONE)?,
        section.float("y_offset", 0.0, Bounds::NONE)?,
        section.required_float("z_offset", z_offset_bounds)?,
    ];
    let speed = section.float("speed", 5.0, Bounds::POSITIVE)?;
    let lift_speed = section.float("lift_speed", speed, Bounds::POSITIVE)?;
    let samples = count(&section, "samples", 1, 1)?;
    let sample_retract_dist = section.float("sample_retract_dist", 2.0, Bounds::POSITIVE)?;
    let samples_result =
        match section.get_choice("samples_result", &["average", "median"], Some("average"))? {
            "median" => SamplesResult::Median,
            _ => SamplesResult::Average,
        };
    let samples_tolerance = section.float("samples_tolerance", 0.100, Bounds::NON_NEGATIVE)?;
    let samples_tolerance_retries = count(&section, "samples_tolerance_retries", 0, 0)?;
    if bltouch.is_none() {
        // Run around each probing move by Klipper; onechip takes them as
        // written but has no G-code to run them with yet (templates are
        // refused, as everywhere).
        for option in ["activate_gcode", "deactivate_gcode"] {
            if section.get_opt(option).is_some_and(|g| g.contains('{')) {
                return Err(section.error_for(
                    option,
                    "uses a template ({ }), which onechip does not support yet",
                ));
            }
        }
        section.get_bool("deactivate_on_each_sample", true)?;
    }
    let z_position = match config.section("stepper_z").map(|s| Reader::new(s, errors)) {
        Some(z) => z.float("position_min", 0.0, Bounds::NONE)?,
        None => 0.0,
    };
    Ok(Some(ProbeConfig {
        section: section.name_in_file(),
        pin,
        offsets,
        speed,
        lift_speed,
        samples,
        sample_retract_dist,
        samples_result,
        samples_tolerance,
        samples_tolerance_retries,
        z_position,
        bltouch,
    }))
}

/// An integer option of at least `min`.
fn count<'c>(section: &Reader<'_, 'c, '_>, option: &'c str, default: i64, min: i64) -> Read<u32> {
    let n = section.get_int(option, Some(default), Some(min))?;
    u32::try_from(n).map_err(|_| section.error_for(option, "is too large"))
}

/// How a probe command runs its samples (the probe's options, each of which
/// the command may override: `PROBE_SPEED=`, `SAMPLES=`, ...).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sampling {
    /// Probing speed, mm/s.
    pub speed: f64,
    /// Lift speed between samples, mm/s.
    pub lift_speed: f64,
    /// Samples per result.
    pub samples: u32,
    /// Lift between samples, mm.
    pub retract_dist: f64,
    /// Largest spread of the samples, mm.
    pub tolerance: f64,
    /// Retries past the tolerance.
    pub retries: u32,
    /// How the samples are combined.
    pub result: SamplesResult,
}

impl ProbeConfig<'_> {
    /// The sampling the probe's options ask for.
    pub fn sampling(&self) -> Sampling {
        Sampling {
            speed: self.speed,
            lift_speed: self.lift_speed,
            samples: self.samples,
            retract_dist: self.sample_retract_dist,
            tolerance: self.samples_tolerance,
            retries: self.samples_tolerance_retries,
            result: self.samples_result,
        }
    }
}

/// Most samples one probe command takes (SAMPLES= above is refused).
pub const MAX_SAMPLES: usize = 64;

/// Probe samples (toolhead positions at the trigger, mm).
pub type Samples = heapless::Vec<[f64; 3], MAX_SAMPLES>;

/// The mean of `samples`.
pub fn mean(samples: &[[f64; 3]]) -> [f64; 3] {
    let n = samples.len().max(1) as f64;
    core::array::from_fn(|i| samples.iter().map(|p| p[i]).sum::<f64>() / n)
}

/// The median of `samples` by Z (Klipper's: the mean of the middle two for
/// an even count).
pub fn median(samples: &[[f64; 3]]) -> [f64; 3] {
    // An insertion sort by Z: at most MAX_SAMPLES samples, and far less
    // code than the library's sort.
    let mut sorted = Samples::new();
    for &p in samples {
        let at = sorted
            .iter()
            .position(|q| q[2] > p[2])
            .unwrap_or(sorted.len());
        let _ = sorted.insert(at, p);
    }
    let middle = sorted.len() / 2;
    if sorted.len() % 2 == 1 {
        sorted[middle]
    } else if middle > 0 {
        mean(&sorted[middle - 1..=middle])
    } else {
        [0.0; 3]
    }
}

/// Where the probe is during a command: stowed between commands unless
/// the BLTouch keeps it down for all of one command's samples.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ProbeState {
    /// The BLTouch's timing and pin state.
    pub bltouch: Option<Bltouch>,
    /// A multi-sample command is running (the probe stays down between
    /// samples if it may).
    multi: bool,
    /// The probe is down for the running multi-sample command.
    down: bool,
}

impl ProbeState {
    /// The state of `probe` at start-up.
    pub fn new(probe: &ProbeConfig<'_>) -> Self {
        Self {
            bltouch: probe.bltouch.map(|_| Bltouch::default()),
            multi: false,
            down: false,
        }
    }

    /// A command of several samples starts: a BLTouch may stay down
    /// between them (see [`Toolhead::end_multi_probe`]).
    pub fn begin_multi(&mut self) {
        self.multi = true;
    }
}

impl crate::machine::Machine<'_> {
    /// The engine slot whose endstop input is the probe's: the one after
    /// the steppers (None without a probe, or with every slot taken).
    pub fn probe_slot(&self) -> Option<usize> {
        let slot = self.steppers.len();
        (self.probe.is_some() && slot < crate::machine::MAX_STEPPERS).then_some(slot)
    }

    /// True if rail `axis` homes on the probe (`probe:z_virtual_endstop`).
    pub fn homes_on_probe(&self, axis: usize) -> bool {
        self.travel.homing_info(axis).is_some_and(|h| h.probe)
    }
}

/// The probe's part of homing and probing moves: a BLTouch's pin goes
/// down before each move on the probe and up after it, or (with
/// stow_on_each_sample off) stays down for all the moves of one command.
pub struct ProbeHooks<'p, 'c> {
    /// The probe.
    pub probe: &'p ProbeConfig<'c>,
    /// Its state.
    pub state: &'p mut ProbeState,
    /// The MCU's print time when the command started, s.
    pub now: f64,
    /// Where notes go (a BLTouch raised again).
    pub out: &'p mut dyn core::fmt::Write,
}

impl<const N: usize> HomingHooks<N> for ProbeHooks<'_, '_> {
    fn rails_begin(&mut self) {
        self.state.begin_multi();
    }

    fn rails_end(
        &mut self,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
    ) -> Result<(), MoveError> {
        toolhead.end_multi_probe(self.probe, self.state, self.now, sink, self.out)
    }

    fn move_begin(
        &mut self,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
    ) -> Result<(), MoveError> {
        let state = &mut *self.state;
        if let (Some(blt), Some(cfg)) = (&mut state.bltouch, &self.probe.bltouch)
            && !state.down
        {
            blt.lower(cfg, toolhead, sink)
                .map_err(|reason| error(reason, toolhead.position()))?;
            state.down = state.multi && !cfg.stow_on_each_sample;
        }
        Ok(())
    }

    fn move_end(
        &mut self,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
    ) -> Result<(), MoveError> {
        let state = &mut *self.state;
        match (&mut state.bltouch, &self.probe.bltouch) {
            (Some(blt), Some(cfg)) if !state.down => blt
                .raise(cfg, self.now, toolhead, sink, self.out)
                .map_err(|reason| error(reason, toolhead.position())),
            _ => Ok(()),
        }
    }
}

fn error(reason: &'static str, end: [f64; 4]) -> MoveError {
    MoveError {
        reason,
        end,
        detail: Detail::Nothing,
    }
}

impl<const N: usize> Toolhead<N> {
    /// Klipper's `probing_move`: Z goes down to the probe's z_position at
    /// `speed` (mm/s) and stops at the probe's trigger; returns where the
    /// toolhead stopped (mm). The BLTouch's pin goes down before and up
    /// after, as its options say. Reports `probe at X,Y is z=Z` to `out`.
    pub fn probe_once(
        &mut self,
        probe: &ProbeConfig<'_>,
        state: &mut ProbeState,
        speed: f64,
        now: f64,
        sink: &mut impl MoveSink,
        out: &mut impl core::fmt::Write,
    ) -> Result<[f64; 3], MoveError> {
        let start = self.position();
        if !self.kinematics.axis_homed(2) {
            return Err(error(MUST_HOME, start));
        }
        let mut target = start;
        target[2] = probe.z_position;
        let (min, max) = (probe.z_position, start[2].max(probe.z_position));
        let info = HomingInfo {
            position_endstop: probe.z_position,
            positive_dir: false,
            speed,
            second_speed: speed,
            retract_dist: 0.0,
            retract_speed: speed,
            range: (min, max),
            probe: true,
        };
        let mut hooks = ProbeHooks {
            probe,
            state,
            now,
            out,
        };
        let end = self.homing_move(Rails::Axis(2), &info, target, speed, sink, &mut hooks)?;
        if end.comms_timeout {
            return Err(error(COMMS_TIMEOUT, self.position()));
        }
        let trigger = end.stopped_at;
        // Klipper's probe_pos: where the toolhead was at the trigger, not
        // the move's target.
        if let Some(mut at) = trigger.and_then(|t| self.released_position_at(t)) {
            at[crate::planned_move::E] = self.position()[crate::planned_move::E];
            self.set_position(at, sink);
        }
        if trigger.is_none() {
            return Err(error(NO_TRIGGER, self.position()));
        }
        let p = self.position();
        let _ = writeln!(
            out,
            "// probe at {},{} is z={}",
            Fixed(p[0], 3),
            Fixed(p[1], 3),
            Fixed(p[2], 6)
        );
        Ok([p[0], p[1], p[2]])
    }

    /// Klipper's `run_probe`: `sampling.samples` probes at this XY, lifting
    /// `retract_dist` between them, started again (up to `retries` times)
    /// if they spread more than `tolerance`; their average or median
    /// (mm). With `keep`, every sample taken is also pushed there.
    #[allow(clippy::too_many_arguments)]
    pub fn run_probe(
        &mut self,
        probe: &ProbeConfig<'_>,
        state: &mut ProbeState,
        sampling: &Sampling,
        now: f64,
        sink: &mut impl MoveSink,
        out: &mut impl core::fmt::Write,
    ) -> Result<[f64; 3], MoveError> {
        state.begin_multi();
        let result = self.probe_samples(probe, state, sampling, now, sink, out);
        let raised = self.end_multi_probe(probe, state, now, sink, out);
        let pos = result?;
        raised?;
        Ok(pos)
    }

    /// [`Self::run_probe`]'s samples, within a multi-sample command the
    /// caller began ([`ProbeState::begin_multi`]) and ends
    /// ([`Self::end_multi_probe`]).
    pub fn probe_samples(
        &mut self,
        probe: &ProbeConfig<'_>,
        state: &mut ProbeState,
        sampling: &Sampling,
        now: f64,
        sink: &mut impl MoveSink,
        out: &mut impl core::fmt::Write,
    ) -> Result<[f64; 3], MoveError> {
        let xy = self.position();
        let mut samples = Samples::new();
        let mut retries = 0;
        let wanted = (sampling.samples as usize).min(MAX_SAMPLES);
        while samples.len() < wanted {
            let pos = self.probe_once(probe, state, sampling.speed, now, sink, out)?;
            let _ = samples.push(pos);
            let (lo, hi) = samples.iter().fold((f64::MAX, f64::MIN), |(lo, hi), p| {
                (lo.min(p[2]), hi.max(p[2]))
            });
            if hi - lo > sampling.tolerance {
                if retries >= sampling.retries {
                    return Err(error(EXCEED_TOLERANCE, self.position()));
                }
                let _ = writeln!(out, "// Probe samples exceed tolerance. Retrying...");
                retries += 1;
                samples.clear();
            }
            if samples.len() < wanted {
                let mut lift = self.position();
                lift[0] = xy[0];
                lift[1] = xy[1];
                lift[2] = pos[2] + sampling.retract_dist;
                self.move_to(lift, sampling.lift_speed, sink)?;
            }
        }
        Ok(match sampling.result {
            SamplesResult::Median => median(&samples),
            SamplesResult::Average => mean(&samples),
        })
    }

    /// Ends a multi-sample command: a BLTouch kept down goes up (see
    /// [`Bltouch::raise`]; notes to `out`).
    pub fn end_multi_probe(
        &mut self,
        probe: &ProbeConfig<'_>,
        state: &mut ProbeState,
        now: f64,
        sink: &mut impl MoveSink,
        out: &mut dyn core::fmt::Write,
    ) -> Result<(), MoveError> {
        let raised = match (&mut state.bltouch, &probe.bltouch, state.down) {
            (Some(blt), Some(cfg), true) => blt.raise(cfg, now, self, sink, out),
            _ => Ok(()),
        };
        state.multi = false;
        state.down = false;
        raised.map_err(|reason| error(reason, self.position()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_and_mean_are_klippers() {
        let s = [[0.0, 0.0, 1.0], [0.0, 0.0, 3.0], [0.0, 0.0, 2.0]];
        assert_eq!(median(&s)[2], 2.0);
        assert_eq!(mean(&s)[2], 2.0);
        let s = [
            [0.0, 0.0, 1.0],
            [0.0, 0.0, 4.0],
            [0.0, 0.0, 2.0],
            [0.0, 0.0, 10.0],
        ];
        assert_eq!(median(&s)[2], 3.0);
        assert_eq!(mean(&s)[2], 4.25);
    }
}
