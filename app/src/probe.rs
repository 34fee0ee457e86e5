//! The probe's G-code, as Klipper's `probe`, `bltouch`, `safe_z_home` and
//! `homing_override` modules answer it: PROBE, PROBE_ACCURACY,
//! PROBE_CALIBRATE (with TESTZ, ACCEPT, ABORT), BLTOUCH_DEBUG, and G28
//! through `[safe_z_home]` or `[homing_override]`. QUERY_PROBE reads the
//! probe's input, so the session answers it ([`query`]).

use crate::printer::{LineError, Printer};
use core::fmt::Write;
use onechip_config::decimal::Fixed;
use onechip_planner::bed_screws::{Adjusting, Answer, BedScrews};
use onechip_planner::bltouch::Command as BltCommand;
use onechip_planner::gcode::{self, Command, Extended, Line};
use onechip_planner::gcode_move::CommandError;
use onechip_planner::homing::NoHooks;
use onechip_planner::machine::Machine;
use onechip_planner::math::sqrt;
use onechip_planner::move_sink::MoveSink;
use onechip_planner::probe::{
    MAX_SAMPLES, ProbeConfig, ProbeHooks, ProbeState, SamplesResult, Sampling,
};
use onechip_planner::safe_home::{G28, requested};
use onechip_planner::screws_tilt::{self, ScrewsTilt};

/// The BLTouch's servo signal period, s (for the board's control pin).
pub use onechip_planner::bltouch::SIGNAL_PERIOD;

/// Lift before PROBE_CALIBRATE's manual probe, mm (Klipper's).
const CALIBRATE_LIFT: f64 = 5.0;
/// PROBE_ACCURACY's samples when not given (Klipper's).
const ACCURACY_SAMPLES: f64 = 10.0;

/// The probe and G28's variant, and what the commands remember.
#[derive(Debug, Clone, Copy)]
pub struct Probing<'a> {
    probe: Option<ProbeConfig<'a>>,
    /// `[screws_tilt_adjust]`, if present.
    screws: Option<ScrewsTilt<'a>>,
    /// `[bed_screws]`, if present.
    bed_screws: Option<BedScrews<'a>>,
    /// BED_SCREWS_ADJUST waits at a screw for ACCEPT, ADJUSTED or ABORT.
    adjusting: Option<Adjusting>,
    state: ProbeState,
    g28: G28<'a>,
    /// A `[homing_override]` script is running: its G28 homes plainly.
    in_override: bool,
    /// The MCU's print time when the line started, s.
    now: f64,
    /// PROBE_CALIBRATE's probed Z while its manual probe runs, mm.
    calibrating: Option<f64>,
    /// A BLTouch's start-up (output mode, pin up) has been sent.
    connected: bool,
}

impl<'a> Probing<'a> {
    /// The probe and G28 of `machine`.
    pub fn new(machine: &Machine<'a>) -> Self {
        Self {
            probe: machine.probe,
            screws: machine.screws_tilt,
            bed_screws: machine.bed_screws,
            adjusting: None,
            state: machine
                .probe
                .as_ref()
                .map(ProbeState::new)
                .unwrap_or_default(),
            g28: machine.g28,
            in_override: false,
            now: 0.0,
            calibrating: None,
            connected: false,
        }
    }

    /// The probe's z_offset now (PROBE_CALIBRATE's ACCEPT changes it), mm.
    pub fn z_offset(&self) -> Option<f64> {
        self.probe.map(|p| p.offsets[2])
    }
}

/// True if `pin` is `probe:z_virtual_endstop` (the rail homes on the
/// probe's input, not a pin of its own).
pub fn is_virtual_endstop(pin: &str) -> bool {
    pin.trim()
        .eq_ignore_ascii_case(onechip_planner::probe::VIRTUAL_ENDSTOP)
}

/// The probe's input to wire: its engine slot and pin (as written).
pub fn input<'a>(machine: &Machine<'a>) -> Option<(usize, &'a str)> {
    Some((machine.probe_slot()?, machine.probe.as_ref()?.pin))
}

/// The probe's pins for the pin check: its input, and a BLTouch's control
/// pin.
pub(crate) fn pin_uses<'m, 'a>(
    machine: &'m Machine<'a>,
) -> impl Iterator<Item = crate::pin_check::PinUse<'a>> + 'm {
    machine.probe.iter().flat_map(|p| {
        let input = if p.bltouch.is_some() {
            "sensor_pin"
        } else {
            "pin"
        };
        let control = p.bltouch.map(|b| b.control_pin);
        [(input, Some(p.pin)), ("control_pin", control)]
            .into_iter()
            .filter_map(move |(option, pin)| {
                pin.map(|pin| crate::pin_check::PinUse {
                    section: p.section,
                    option,
                    pin,
                })
            })
    })
}

/// QUERY_PROBE's reply for an input reading `triggered`.
pub fn query(triggered: bool, out: &mut impl Write) {
    let state = if triggered { "TRIGGERED" } else { "open" };
    let _ = writeln!(out, "// probe: {state}");
}

fn invalid<'l>(param: &'l str, rule: &'static str) -> LineError<'l> {
    LineError::Command(CommandError::Invalid { param, rule })
}

/// `key`'s number, `default` if absent, checked by `ok` (else `rule`).
fn number<'l>(
    e: &Extended<'l>,
    key: &'l str,
    default: f64,
    ok: fn(f64) -> bool,
    rule: &'static str,
) -> Result<f64, LineError<'l>> {
    let v = e.float(key)?.unwrap_or(default);
    if ok(v) {
        Ok(v)
    } else {
        Err(invalid(key, rule))
    }
}

fn positive<'l>(e: &Extended<'l>, key: &'l str, default: f64) -> Result<f64, LineError<'l>> {
    number(e, key, default, |v| v > 0.0, "must be above 0")
}

/// `key`'s whole number of at least `min`.
fn count<'l>(e: &Extended<'l>, key: &'l str, default: u32, min: u32) -> Result<u32, LineError<'l>> {
    let v = e.float(key)?.unwrap_or(f64::from(default));
    if v != (v as u32) as f64 || v < f64::from(min) || v > MAX_SAMPLES as f64 {
        return Err(invalid(key, "must be a whole number within range"));
    }
    Ok(v as u32)
}

/// The probe's sampling with the command's overrides.
fn sampling<'l>(e: &Extended<'l>, base: Sampling) -> Result<Sampling, LineError<'l>> {
    Ok(Sampling {
        speed: positive(e, "PROBE_SPEED", base.speed)?,
        lift_speed: positive(e, "LIFT_SPEED", base.lift_speed)?,
        samples: count(e, "SAMPLES", base.samples, 1)?,
        retract_dist: positive(e, "SAMPLE_RETRACT_DIST", base.retract_dist)?,
        tolerance: number(
            e,
            "SAMPLES_TOLERANCE",
            base.tolerance,
            |v| v >= 0.0,
            "must not be negative",
        )?,
        retries: count(e, "SAMPLES_TOLERANCE_RETRIES", base.retries, 0)?,
        result: match e.get("SAMPLES_RESULT")? {
            Some(r) if r.eq_ignore_ascii_case("median") => SamplesResult::Median,
            Some(_) => SamplesResult::Average,
            None => base.result,
        },
    })
}

impl<'a, const N: usize> Printer<'a, N> {
    /// Sets the MCU's print time for the line about to run, s.
    pub fn set_probe_now(&mut self, now: f64) {
        self.probing.now = now;
    }

    /// The probe's state (for QUERY_PROBE and tests).
    pub fn probing(&self) -> &Probing<'a> {
        &self.probing
    }

    /// Runs `line` if it is a probe command or a G28 that `[safe_z_home]`
    /// or `[homing_override]` changes; false otherwise.
    // Not inlined: see `Printer::thermal`.
    #[inline(never)]
    pub(crate) fn probe_command<'l>(
        &mut self,
        line: &Line<'l>,
        sink: &mut impl MoveSink,
        out: &mut impl Write,
    ) -> Result<bool, LineError<'l>>
    where
        'a: 'l,
    {
        let p = &mut self.probing;
        if !p.connected
            && let (Some(cfg), Some(blt)) = (p.probe.and_then(|p| p.bltouch), &mut p.state.bltouch)
        {
            // Klipper's start-up: the output mode if set, then the pin up
            // (here with the first line that is not a heater command).
            blt.connect(&cfg, p.now, sink);
            p.connected = true;
        }
        match line.command {
            Command::Traditional(t) if t.is(b'G', 28) && t.sub.is_none() => {
                let named = ["X", "Y", "Z"].map(|a| t.param(a).is_some());
                self.g28(named, sink, out)
            }
            Command::Extended(e)
                if self.probing.probe.is_some()
                    || self.probing.screws.is_some()
                    || self.probing.bed_screws.is_some() =>
            {
                let result = self.probe_extended(&e, sink, out);
                if result.as_ref().is_ok_and(|&handled| handled) || result.is_err() {
                    // The toolhead moved on its own: G-code follows it.
                    self.gcode.reset_last_position(&self.toolhead);
                }
                result
            }
            _ => Ok(false),
        }
    }

    fn g28<'l>(
        &mut self,
        named: [bool; 3],
        sink: &mut impl MoveSink,
        out: &mut impl Write,
    ) -> Result<bool, LineError<'l>>
    where
        'a: 'l,
    {
        let Probing {
            probe,
            state,
            now,
            g28,
            in_override,
            ..
        } = &mut self.probing;
        // Inside `[homing_override]`'s gcode, G28 homes plainly.
        let g28 = if *in_override { G28::Plain } else { *g28 };
        let homed = match (&g28, probe.as_ref()) {
            (G28::SafeZ(cfg), Some(probe)) => {
                let mut hooks = ProbeHooks {
                    probe,
                    state,
                    now: *now,
                    out: &mut *out,
                };
                self.toolhead.home_safe_z(cfg, named, sink, &mut hooks)
            }
            (G28::SafeZ(cfg), None) => self.toolhead.home_safe_z(cfg, named, sink, &mut NoHooks),
            (G28::Plain, Some(probe)) => {
                // As gcode_move's G28, with the probe deployed around its
                // homing moves.
                let need = requested(named);
                let axes: heapless::Vec<usize, 3> = (0..3).filter(|&a| need[a]).collect();
                let mut hooks = ProbeHooks {
                    probe,
                    state,
                    now: *now,
                    out: &mut *out,
                };
                self.toolhead.home_with(&axes, sink, &mut hooks)
            }
            (G28::Plain, None) => return Ok(false),
            (G28::Override(_), _) => return self.g28_override(named, sink, out),
        };
        self.gcode.reset_last_position(&self.toolhead);
        homed.map_err(CommandError::Move)?;
        Ok(true)
    }

    /// G28 through `[homing_override]`.
    fn g28_override<'l>(
        &mut self,
        named: [bool; 3],
        sink: &mut impl MoveSink,
        out: &mut impl Write,
    ) -> Result<bool, LineError<'l>>
    where
        'a: 'l,
    {
        let G28::Override(cfg) = self.probing.g28 else {
            return Ok(false);
        };
        let need = requested(named);
        if !(0..3).any(|a| need[a] && cfg.axes[a]) {
            // Not overridden: G28 as without the section.
            self.probing.in_override = true;
            let homed = self.g28(named, sink, out);
            self.probing.in_override = false;
            return homed;
        }
        self.toolhead.force_override_position(&cfg, sink);
        self.gcode.reset_last_position(&self.toolhead);
        self.probing.in_override = true;
        let ran = cfg.gcode.lines().try_for_each(|text| {
            let line = gcode::parse(text)?;
            self.execute(&line, sink, out)
        });
        self.probing.in_override = false;
        ran.map(|()| true)
    }

    // Not inlined: see `Printer::thermal`.
    #[inline(never)]
    fn probe_extended<'l>(
        &mut self,
        e: &Extended<'l>,
        sink: &mut impl MoveSink,
        out: &mut impl Write,
    ) -> Result<bool, LineError<'l>> {
        let name = e.name;
        let is = |n: &str| name.eq_ignore_ascii_case(n);
        if self.bed_screws_command(e, sink, out)? {
            return Ok(true);
        }
        let Some(probe) = self.probing.probe else {
            if is("SCREWS_TILT_CALCULATE") && self.probing.screws.is_some() {
                const MANUAL: &str = "SCREWS_TILT_CALCULATE without a [probe] (manual probing)";
                return Err(CommandError::NotSupported(MANUAL).into());
            }
            return Ok(false);
        };
        let now = self.probing.now;
        if let Some(screws) = self.probing.screws.filter(|_| is("SCREWS_TILT_CALCULATE")) {
            self.screws_tilt_calculate(e, &screws, &probe, sink, out)?;
        } else if is("PROBE") {
            let s = sampling(e, probe.sampling())?;
            let pos = (self.toolhead)
                .run_probe(&probe, &mut self.probing.state, &s, now, sink, out)
                .map_err(CommandError::Move)?;
            let _ = writeln!(out, "// Result is z={}", Fixed(pos[2], 6));
        } else if is("PROBE_ACCURACY") {
            self.probe_accuracy(e, &probe, sink, out)?;
        } else if is("PROBE_CALIBRATE") {
            let s = sampling(e, probe.sampling())?;
            let th = &mut self.toolhead;
            let pos = th
                .run_probe(&probe, &mut self.probing.state, &s, now, sink, out)
                .map_err(CommandError::Move)?;
            let mut at = th.position();
            at[2] = pos[2] + CALIBRATE_LIFT;
            th.move_to(at, s.lift_speed, sink)
                .map_err(CommandError::Move)?;
            at[0] += probe.offsets[0];
            at[1] += probe.offsets[1];
            th.move_to(at, probe.speed, sink)
                .map_err(CommandError::Move)?;
            self.probing.calibrating = Some(pos[2]);
            let _ = writeln!(
                out,
                "// Starting manual Z probe. Use TESTZ to adjust position.\n\
                 // Finish with ACCEPT or ABORT command."
            );
        } else if is("TESTZ") && self.probing.calibrating.is_some() {
            let dz = e.float("Z")?.ok_or(invalid("Z", "is required"))?;
            let mut at = self.toolhead.position();
            at[2] += dz;
            (self.toolhead)
                .move_to(at, probe.speed, sink)
                .map_err(CommandError::Move)?;
            let _ = writeln!(out, "// Z position: {}", Fixed(at[2], 3));
        } else if is("ACCEPT")
            && let Some(probed) = self.probing.calibrating.take()
        {
            let z_offset = probed - self.toolhead.position()[2];
            if let Some(p) = &mut self.probing.probe {
                p.offsets[2] = z_offset;
            }
            let _ = writeln!(
                out,
                "// {}: z_offset: {}\n\
                 // The SAVE_CONFIG command will update the printer config file\n\
                 // with the above and restart the printer.",
                probe.section,
                Fixed(z_offset, 3)
            );
        } else if is("ABORT") && self.probing.calibrating.take().is_some() {
            let _ = writeln!(out, "// Manual probe aborted");
        } else if is("BLTOUCH_DEBUG")
            && let (Some(cfg), Some(blt)) = (probe.bltouch, &mut self.probing.state.bltouch)
        {
            match e.get("COMMAND")?.and_then(BltCommand::from_name) {
                Some(cmd) => {
                    let _ = writeln!(out, "// Sending BLTOUCH_DEBUG COMMAND={}", cmd.name());
                    blt.debug(&cfg, cmd, &mut self.toolhead, sink);
                }
                None => {
                    let _ = write!(out, "// BLTouch commands:");
                    for (i, cmd) in BltCommand::ALL.iter().enumerate() {
                        let sep = if i == 0 { " " } else { ", " };
                        let _ = write!(out, "{sep}{}", cmd.name());
                    }
                    let _ = writeln!(out);
                }
            }
        } else {
            return Ok(false);
        }
        Ok(true)
    }

    /// BED_SCREWS_ADJUST and, while it waits at a screw, ACCEPT, ADJUSTED
    /// and ABORT, as Klipper's `bed_screws` tool; false for any other
    /// line. A move that fails ends the tool.
    fn bed_screws_command<'l>(
        &mut self,
        e: &Extended<'l>,
        sink: &mut impl MoveSink,
        out: &mut impl Write,
    ) -> Result<bool, LineError<'l>> {
        let Some(tool) = self.probing.bed_screws else {
            return Ok(false);
        };
        let is = |n: &str| e.name.eq_ignore_ascii_case(n);
        // What was answered at which screw; None: the tool starts.
        let answer = match self.probing.adjusting {
            Some(_) if is("BED_SCREWS_ADJUST") => {
                const BUSY: &str = "Already in bed_screws helper; use ABORT to exit";
                return Err(CommandError::Refused(BUSY).into());
            }
            None if is("BED_SCREWS_ADJUST") => None,
            Some(state) if is("ACCEPT") => Some((state, Answer::Accept)),
            Some(state) if is("ADJUSTED") => Some((state, Answer::Adjusted)),
            Some(_) if is("ABORT") => {
                self.probing.adjusting = None;
                return Ok(true);
            }
            _ => return Ok(false),
        };
        self.probing.adjusting = None;
        let th = &mut self.toolhead;
        let next = match answer {
            None => tool.start(th, sink).map(Some),
            Some((state, answer)) => tool.answer(state, answer, th, sink),
        };
        match next.map_err(CommandError::Move)? {
            Some((state, screw)) => {
                self.probing.adjusting = Some(state);
                let _ = writeln!(
                    out,
                    "// Adjust {screw}. Then run ACCEPT, ADJUSTED, or ABORT\n\
                     // Use ADJUSTED if a significant screw adjustment is made"
                );
            }
            None => {
                let _ = writeln!(out, "// Bed screws tool completed successfully");
            }
        }
        Ok(true)
    }

    /// SCREWS_TILT_CALCULATE, as Klipper's `screws_tilt_adjust`: every
    /// screw probed (the probe's own parameters, HORIZONTAL_MOVE_Z), then
    /// each one's turn against the base; an error past MAX_DEVIATION.
    fn screws_tilt_calculate<'l>(
        &mut self,
        e: &Extended<'l>,
        screws: &ScrewsTilt<'_>,
        probe: &ProbeConfig<'_>,
        sink: &mut impl MoveSink,
        out: &mut impl Write,
    ) -> Result<(), LineError<'l>> {
        let (max_deviation, direction) = screws_tilt::parameters(e)?;
        let s = sampling(e, probe.sampling())?;
        let move_z = e.float("HORIZONTAL_MOVE_Z")?;
        let move_z = move_z.unwrap_or(screws.horizontal_move_z);
        if move_z < probe.offsets[2] {
            return Err(CommandError::Refused(
                "horizontal_move_z can't be less than probe's z_offset",
            )
            .into());
        }
        let points: heapless::Vec<[f64; 2], { screws_tilt::MAX_SCREWS }> =
            screws.screws().iter().map(|screw| screw.at).collect();
        let mut zs = [0.0; screws_tilt::MAX_SCREWS];
        (self.toolhead)
            .probe_points(
                probe,
                &mut self.probing.state,
                &s,
                &points,
                (move_z, screws.speed),
                self.probing.now,
                sink,
                out,
                &mut |i, z| zs[i] = z,
            )
            .map_err(CommandError::Move)?;
        screws
            .report(&zs[..points.len()], direction, max_deviation, out)
            .map_err(|d| CommandError::BedLevel(d).into())
    }

    /// PROBE_ACCURACY: SAMPLES probes (10) with a lift after each, then
    /// their spread as Klipper reports it.
    fn probe_accuracy<'l>(
        &mut self,
        e: &Extended<'l>,
        probe: &ProbeConfig<'_>,
        sink: &mut impl MoveSink,
        out: &mut impl Write,
    ) -> Result<(), LineError<'l>> {
        let speed = positive(e, "PROBE_SPEED", probe.speed)?;
        let lift_speed = positive(e, "LIFT_SPEED", probe.lift_speed)?;
        let samples = count(e, "SAMPLES", ACCURACY_SAMPLES as u32, 1)?;
        let retract = positive(e, "SAMPLE_RETRACT_DIST", probe.sample_retract_dist)?;
        let th = &mut self.toolhead;
        let at = th.position();
        let _ = writeln!(
            out,
            "// PROBE_ACCURACY at X:{} Y:{} Z:{} (samples={samples} \
             retract={} speed={} lift_speed={})",
            Fixed(at[0], 3),
            Fixed(at[1], 3),
            Fixed(at[2], 3),
            Fixed(retract, 3),
            Fixed(speed, 1),
            Fixed(lift_speed, 1)
        );
        let state = &mut self.probing.state;
        let now = self.probing.now;
        state.begin_multi();
        let mut zs = heapless::Vec::<[f64; 3], MAX_SAMPLES>::new();
        let taken = (|| {
            while zs.len() < samples as usize {
                let pos = th.probe_once(probe, state, speed, now, sink, out)?;
                let _ = zs.push(pos);
                let mut lift = th.position();
                lift[2] = pos[2] + retract;
                th.move_to(lift, lift_speed, sink)?;
            }
            Ok(())
        })();
        let raised = th.end_multi_probe(probe, state, now, sink, out);
        taken.and(raised).map_err(CommandError::Move)?;
        let (max, min) = zs.iter().fold((f64::MIN, f64::MAX), |(hi, lo), p| {
            (hi.max(p[2]), lo.min(p[2]))
        });
        let avg = onechip_planner::probe::mean(&zs)[2];
        let median = onechip_planner::probe::median(&zs)[2];
        let n = zs.len().max(1) as f64;
        let sigma = sqrt(zs.iter().map(|p| (p[2] - avg) * (p[2] - avg)).sum::<f64>() / n);
        let _ = writeln!(
            out,
            "// probe accuracy results: maximum {}, minimum {}, range {}, \
             average {}, median {}, standard deviation {}",
            Fixed(max, 6),
            Fixed(min, 6),
            Fixed(max - min, 6),
            Fixed(avg, 6),
            Fixed(median, 6),
            Fixed(sigma, 6)
        );
        Ok(())
    }
}
