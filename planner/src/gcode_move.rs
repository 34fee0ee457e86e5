//! G-code semantics on top of the toolhead: coordinates, offsets, speed
//! and extrusion factors, and the motion commands, as Klipper's gcode_move
//! and toolhead interpret them.
//!
//! Positions are in mm; the G-code position of an axis is the toolhead
//! position minus the axis' base offset (G92, SET_GCODE_OFFSET); E is
//! additionally scaled by the extrusion factor (M221). Speeds from F are in
//! mm/min and scaled by M220.

use crate::gcode::{Command, Escaped, Extended, GcodeError, Line, Traditional};
use crate::move_sink::MoveSink;
use crate::planned_move::E;
use crate::toolhead::{MoveError, Toolhead};
use core::fmt::{self, Write};
use onechip_config::decimal::Fixed;

/// Why a command failed (the printer replies `!! <error>` and goes on).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CommandError<'a> {
    /// The line or a parameter could not be read.
    Gcode(GcodeError<'a>),
    /// The move was refused.
    Move(MoveError),
    /// A parameter is outside its allowed range.
    Invalid {
        /// The parameter.
        param: &'a str,
        /// The rule it breaks.
        rule: &'static str,
    },
    /// A command this firmware does not implement yet.
    NotSupported(&'static str),
    /// A mux command's key names nothing it serves (Klipper's "The value
    /// 'x' is not valid for KEY"; None: the key was not given).
    NotValidFor {
        /// The key (`EXTRUDER`).
        key: &'static str,
        /// Its value, if given.
        value: Option<&'a str>,
    },
    /// SYNC_EXTRUDER_MOTION's MOTION_QUEUE names no extruder.
    NotAnExtruder(&'a str),
    /// A refusal in Klipper's words.
    Refused(&'static str),
    /// SCREWS_TILT_CALCULATE found a screw beyond MAX_DEVIATION.
    BedLevel(crate::screws_tilt::Deviation),
}

impl<'a> From<GcodeError<'a>> for CommandError<'a> {
    fn from(e: GcodeError<'a>) -> Self {
        Self::Gcode(e)
    }
}

impl From<MoveError> for CommandError<'_> {
    fn from(e: MoveError) -> Self {
        Self::Move(e)
    }
}

impl CommandError<'_> {
    /// The line Klipper's message has under the error, if any (see
    /// [`MoveError::hint`]).
    pub fn hint(&self) -> Option<&'static str> {
        match self {
            Self::Move(e) => e.hint(),
            _ => None,
        }
    }
}

impl fmt::Display for CommandError<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Gcode(e) => write!(f, "{e}"),
            Self::Move(e) => write!(f, "{e}"),
            Self::Invalid { param, rule } => write!(f, "{} {rule}", Escaped(param)),
            Self::NotSupported(what) => write!(f, "{what} is not supported by onechip yet"),
            Self::NotValidFor { key, value } => write!(
                f,
                "The value '{}' is not valid for {key}",
                Escaped(value.unwrap_or("None"))
            ),
            Self::NotAnExtruder(name) => write!(f, "'{}' is not a valid extruder.", Escaped(name)),
            Self::Refused(message) => f.write_str(message),
            Self::BedLevel(deviation) => write!(f, "{deviation}"),
        }
    }
}

/// The G-code interpreter's state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GcodeMove {
    absolute_coord: bool,
    absolute_extrude: bool,
    base_position: [f64; 4],
    last_position: [f64; 4],
    homing_position: [f64; 4],
    /// Current speed, mm/s.
    speed: f64,
    /// Factor from F units (mm/min) to mm/s, including M220.
    speed_factor: f64,
    extrude_factor: f64,
}

impl Default for GcodeMove {
    fn default() -> Self {
        Self {
            absolute_coord: true,
            absolute_extrude: true,
            base_position: [0.0; 4],
            last_position: [0.0; 4],
            homing_position: [0.0; 4],
            speed: 25.0,
            speed_factor: 1.0 / 60.0,
            extrude_factor: 1.0,
        }
    }
}

/// Requires `value` (if given) to be above zero.
fn positive<'a>(param: &'a str, value: Option<f64>) -> Result<Option<f64>, CommandError<'a>> {
    match value {
        Some(v) if v <= 0.0 => Err(CommandError::Invalid {
            param,
            rule: "must be above 0",
        }),
        other => Ok(other),
    }
}

impl GcodeMove {
    /// The G-code position (X, Y, Z, E) as M114 reports it, mm.
    pub fn gcode_position(&self) -> [f64; 4] {
        let mut p = [0.0; 4];
        for (i, v) in p.iter_mut().enumerate() {
            *v = self.last_position[i] - self.base_position[i];
        }
        p[E] /= self.extrude_factor;
        p
    }

    /// Takes the toolhead's position as the last one after the toolhead
    /// moved on its own (probing, homing), as Klipper's
    /// `reset_last_position`.
    pub fn reset_last_position<const N: usize>(&mut self, toolhead: &Toolhead<N>) {
        self.last_position = toolhead.position();
    }

    /// Runs one parsed line; text replies (M114, SET_VELOCITY_LIMIT) go to
    /// `out`. Unknown commands get Klipper's `Unknown command` reply. An
    /// error whose message has a hint line (see [`CommandError::hint`])
    /// writes both lines to `out` as `// ` information, as Klipper does,
    /// before the caller reports the error itself (`!! <first line>`).
    pub fn execute<'a, const N: usize>(
        &mut self,
        line: &Line<'a>,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
        out: &mut impl Write,
    ) -> Result<(), CommandError<'a>> {
        let result = match line.command {
            Command::Empty => Ok(()),
            Command::Traditional(t) => self.traditional(&t, toolhead, sink, out),
            Command::Extended(e) => self.extended(&e, toolhead, sink, out),
        };
        if let Err(e) = &result
            && let Some(hint) = e.hint()
        {
            // Klipper's reply to an error of several lines: all of them as
            // information, then the first as the error.
            let _ = writeln!(out, "// {e}\n// {hint}");
        }
        result
    }

    // Not inlined (nor is `extended`): the printer's `execute` would
    // carry both frames at once.
    #[inline(never)]
    fn traditional<'a, const N: usize>(
        &mut self,
        t: &Traditional<'a>,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
        out: &mut impl Write,
    ) -> Result<(), CommandError<'a>> {
        match (t.letter, t.number, t.sub) {
            (b'G', 0 | 1, None) => self.g1(t, toolhead, sink),
            (b'G', 4, None) => {
                let ms = t.float("P")?.unwrap_or(0.0);
                if ms < 0.0 {
                    return Err(CommandError::Invalid {
                        param: "P",
                        rule: "must not be negative",
                    });
                }
                toolhead.dwell(ms / 1000.0, sink);
                Ok(())
            }
            (b'G', 28, None) => {
                let mut axes = heapless::Vec::<usize, 3>::new();
                for (i, axis) in ["X", "Y", "Z"].iter().enumerate() {
                    if t.param(axis).is_some() {
                        let _ = axes.push(i);
                    }
                }
                if axes.is_empty() {
                    axes.extend([0, 1, 2]);
                }
                toolhead.home(&axes, sink)?;
                self.last_position = toolhead.position();
                Ok(())
            }
            (b'G', 90, None) => {
                self.absolute_coord = true;
                Ok(())
            }
            (b'G', 91, None) => {
                self.absolute_coord = false;
                Ok(())
            }
            (b'G', 92, None) => self.g92(t),
            (b'M', 82, None) => {
                self.absolute_extrude = true;
                Ok(())
            }
            (b'M', 83, None) => {
                self.absolute_extrude = false;
                Ok(())
            }
            (b'M', 114, None) => {
                let p = self.gcode_position();
                let _ = writeln!(
                    out,
                    "X:{} Y:{} Z:{} E:{}",
                    Fixed(p[0], 3),
                    Fixed(p[1], 3),
                    Fixed(p[2], 3),
                    Fixed(p[3], 3)
                );
                Ok(())
            }
            (b'M', 204, None) => self.m204(t, toolhead, out),
            (b'M', 220, None) => {
                let value = positive("S", t.float("S")?)?.unwrap_or(100.0) / (60.0 * 100.0);
                self.speed = self.speed / self.speed_factor * value;
                self.speed_factor = value;
                Ok(())
            }
            (b'M', 221, None) => {
                let factor = positive("S", t.float("S")?)?.unwrap_or(100.0) / 100.0;
                let last_e = self.last_position[E];
                let e_value = (last_e - self.base_position[E]) / self.extrude_factor;
                self.base_position[E] = last_e - e_value * factor;
                self.extrude_factor = factor;
                Ok(())
            }
            (b'M', 400, None) => {
                toolhead.wait_moves(sink);
                Ok(())
            }
            // Drivers stay enabled on this firmware (their enable pins are
            // set at start-up): M17 has nothing to do, and M18/M84 let the
            // moves finish and forget homing, as Klipper's motor off.
            (b'M', 17, None) => Ok(()),
            (b'M', 18 | 84, None) => {
                toolhead.wait_moves(sink);
                toolhead.kinematics.clear_homed();
                Ok(())
            }
            _ => {
                let _ = writeln!(out, "Unknown command:\"{}{}\"", t.letter as char, t.number);
                Ok(())
            }
        }
    }

    fn g1<'a, const N: usize>(
        &mut self,
        t: &Traditional<'a>,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
    ) -> Result<(), CommandError<'a>> {
        // Read everything first so a bad parameter changes nothing.
        let [x, y, z, e, f] = t.floats(["X", "Y", "Z", "E", "F"])?;
        let axes = [x, y, z];
        if f.is_some_and(|f| f <= 0.0) {
            return Err(CommandError::Invalid {
                param: "F",
                rule: "must be above 0",
            });
        }
        let mut target = self.last_position;
        for (i, v) in axes.iter().enumerate() {
            if let Some(v) = v {
                target[i] = if self.absolute_coord {
                    v + self.base_position[i]
                } else {
                    target[i] + v
                };
            }
        }
        if let Some(v) = e {
            let v = v * self.extrude_factor;
            target[E] = if self.absolute_coord && self.absolute_extrude {
                v + self.base_position[E]
            } else {
                target[E] + v
            };
        }
        let speed = f.map_or(self.speed, |f| f * self.speed_factor);
        toolhead.move_to(target, speed, sink)?;
        self.last_position = target;
        self.speed = speed;
        Ok(())
    }

    fn g92<'a>(&mut self, t: &Traditional<'a>) -> Result<(), CommandError<'a>> {
        let offsets = [t.float("X")?, t.float("Y")?, t.float("Z")?, t.float("E")?];
        if offsets.iter().all(Option::is_none) {
            self.base_position = self.last_position;
            return Ok(());
        }
        for (i, offset) in offsets.iter().enumerate() {
            if let Some(mut offset) = *offset {
                if i == E {
                    offset *= self.extrude_factor;
                }
                self.base_position[i] = self.last_position[i] - offset;
            }
        }
        Ok(())
    }

    fn m204<'a, const N: usize>(
        &mut self,
        t: &Traditional<'a>,
        toolhead: &mut Toolhead<N>,
        out: &mut impl Write,
    ) -> Result<(), CommandError<'a>> {
        let accel = match positive("S", t.float("S")?)? {
            Some(s) => s,
            None => match (positive("P", t.float("P")?)?, positive("T", t.float("T")?)?) {
                (Some(p), Some(t)) => p.min(t),
                _ => {
                    let params = Escaped(t.raw_params());
                    let _ = writeln!(out, "Invalid M204 command \"M204 {params}\"");
                    return Ok(());
                }
            },
        };
        toolhead.limits.max_accel = accel;
        toolhead.limits.update_derived();
        Ok(())
    }

    // Not inlined: see `traditional`.
    #[inline(never)]
    fn extended<'a, const N: usize>(
        &mut self,
        e: &Extended<'a>,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
        out: &mut impl Write,
    ) -> Result<(), CommandError<'a>> {
        let name = e.name;
        if name.eq_ignore_ascii_case("SET_VELOCITY_LIMIT") {
            self.set_velocity_limit(e, toolhead, out)
        } else if name.eq_ignore_ascii_case("SET_KINEMATIC_POSITION") {
            toolhead.last_move_time(sink);
            let cur = toolhead.position();
            let pos = [
                e.float("X")?.unwrap_or(cur[0]),
                e.float("Y")?.unwrap_or(cur[1]),
                e.float("Z")?.unwrap_or(cur[2]),
                cur[E],
            ];
            toolhead.set_position(pos, sink);
            toolhead.kinematics.set_homed();
            self.last_position = pos;
            Ok(())
        } else if name.eq_ignore_ascii_case("SET_GCODE_OFFSET") {
            self.set_gcode_offset(e, toolhead, sink)
        } else {
            let _ = writeln!(
                out,
                "Unknown command:\"{}\"",
                name.to_ascii_uppercase_display()
            );
            Ok(())
        }
    }

    fn set_velocity_limit<'a, const N: usize>(
        &mut self,
        e: &Extended<'a>,
        toolhead: &mut Toolhead<N>,
        out: &mut impl Write,
    ) -> Result<(), CommandError<'a>> {
        let velocity = positive("VELOCITY", e.float("VELOCITY")?)?;
        let accel = positive("ACCEL", e.float("ACCEL")?)?;
        let scv = e.float("SQUARE_CORNER_VELOCITY")?;
        if scv.is_some_and(|v| v < 0.0) {
            return Err(CommandError::Invalid {
                param: "SQUARE_CORNER_VELOCITY",
                rule: "must not be negative",
            });
        }
        let mut mcr = e.float("MINIMUM_CRUISE_RATIO")?;
        if mcr.is_some_and(|v| !(0.0..1.0).contains(&v)) {
            return Err(CommandError::Invalid {
                param: "MINIMUM_CRUISE_RATIO",
                rule: "must be at least 0 and below 1",
            });
        }
        if mcr.is_none()
            && let Some(a2d) = positive("ACCEL_TO_DECEL", e.float("ACCEL_TO_DECEL")?)?
        {
            let max_accel = accel.unwrap_or(toolhead.limits.max_accel);
            mcr = Some(1.0 - (a2d / max_accel).min(1.0));
        }
        let limits = &mut toolhead.limits;
        if let Some(v) = velocity {
            limits.max_velocity = v;
        }
        if let Some(a) = accel {
            limits.max_accel = a;
        }
        if let Some(v) = scv {
            limits.square_corner_velocity = v;
        }
        if let Some(r) = mcr {
            limits.min_cruise_ratio = r;
        }
        limits.update_derived();
        if velocity.is_none() && accel.is_none() && scv.is_none() && mcr.is_none() {
            let _ = writeln!(
                out,
                "// max_velocity: {}\n// max_accel: {}\n// minimum_cruise_ratio: {}\n// square_corner_velocity: {}",
                Fixed(limits.max_velocity, 6),
                Fixed(limits.max_accel, 6),
                Fixed(limits.min_cruise_ratio, 6),
                Fixed(limits.square_corner_velocity, 6)
            );
        }
        Ok(())
    }

    fn set_gcode_offset<'a, const N: usize>(
        &mut self,
        e: &Extended<'a>,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
    ) -> Result<(), CommandError<'a>> {
        const AXES: [(&str, &str); 4] = [
            ("X", "X_ADJUST"),
            ("Y", "Y_ADJUST"),
            ("Z", "Z_ADJUST"),
            ("E", "E_ADJUST"),
        ];
        let mut offsets = [None; 4];
        for (i, (axis, adjust)) in AXES.iter().enumerate() {
            offsets[i] = match e.float(axis)? {
                Some(v) => Some(v),
                None => e.float(adjust)?.map(|adj| adj + self.homing_position[i]),
            };
        }
        let do_move = e
            .get("MOVE")?
            .map(|v| v.parse::<i64>())
            .transpose()
            .map_err(|_| CommandError::Invalid {
                param: "MOVE",
                rule: "must be an integer",
            })?;
        let move_speed = positive("MOVE_SPEED", e.float("MOVE_SPEED")?)?;
        let mut move_delta = [0.0; 4];
        for (i, offset) in offsets.iter().enumerate() {
            if let Some(offset) = *offset {
                let delta = offset - self.homing_position[i];
                move_delta[i] = delta;
                self.base_position[i] += delta;
                self.homing_position[i] = offset;
            }
        }
        if do_move.unwrap_or(0) != 0 {
            let mut target = self.last_position;
            for (t, d) in target.iter_mut().zip(move_delta) {
                *t += d;
            }
            toolhead.move_to(target, move_speed.unwrap_or(self.speed), sink)?;
            self.last_position = target;
        }
        Ok(())
    }

    /// What klippy does at the end of a G-code file: a 0.5 s dwell, then
    /// waiting for every move.
    pub fn finish<const N: usize>(&mut self, toolhead: &mut Toolhead<N>, sink: &mut impl MoveSink) {
        toolhead.dwell(0.5, sink);
        toolhead.wait_moves(sink);
    }
}

/// Writes a command name in upper case without allocating.
trait UpperDisplay {
    fn to_ascii_uppercase_display(&self) -> Upper<'_>;
}

struct Upper<'a>(&'a str);

impl UpperDisplay for str {
    fn to_ascii_uppercase_display(&self) -> Upper<'_> {
        Upper(self)
    }
}

impl fmt::Display for Upper<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.0
            .chars()
            .try_for_each(|c| f.write_char(c.to_ascii_uppercase()))
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::gcode;
    use crate::machine::Machine;
    use crate::move_sink::TrapqMove;
    use std::boxed::Box;
    use std::string::{String, ToString};

    /// A cartesian printer with a heated extruder (Klipper's extruder
    /// defaults: min_extrude_temp 170 °C, max_extrude_only_distance 50
    /// mm, max_extrude_cross_section 4 × nozzle² = 0.64 mm²).
    const CFG: &str = concat!(
        cartesian_printer!(),
        "heater_pin: PA0\nsensor_pin: PF4\n\
        sensor_type: EPCOS 100K B57560G104F\ncontrol: watermark\nmin_temp: 0\nmax_temp: 250\n"
    );

    /// Counts the moves planned.
    #[derive(Default)]
    struct Count {
        toolhead: usize,
        extruder: usize,
    }

    impl MoveSink for Count {
        fn toolhead(&mut self, _: &TrapqMove) {
            self.toolhead += 1;
        }
        fn extruder(&mut self, _: &TrapqMove) {
            self.extruder += 1;
        }
    }

    /// A homed printer at X10 Y10 Z0 E0, with the extruder hot or cold.
    struct Bench {
        gcode: GcodeMove,
        toolhead: Box<Toolhead<16>>,
        sink: Count,
    }

    impl Bench {
        fn new(can_extrude: bool) -> Self {
            let config = onechip_config::Config::parse("printer.cfg", CFG).expect("config");
            let machine = Machine::from_config(&config).expect("machine");
            assert!(!machine.can_extrude_cold());
            let mut toolhead = Box::new(machine.toolhead::<16>());
            toolhead.set_can_extrude(can_extrude);
            let mut bench = Self {
                gcode: GcodeMove::default(),
                toolhead,
                sink: Count::default(),
            };
            bench
                .run("SET_KINEMATIC_POSITION X=10 Y=10 Z=0")
                .expect("homed");
            bench
        }

        /// Runs `line`; its replies, or the error (as `!! ` would show it)
        /// after them.
        fn run(&mut self, line: &str) -> Result<String, (String, String)> {
            let parsed = gcode::parse(line).expect("parses");
            let mut out = String::new();
            match self
                .gcode
                .execute(&parsed, &mut self.toolhead, &mut self.sink, &mut out)
            {
                Ok(()) => Ok(out),
                Err(e) => Err((out, e.to_string())),
            }
        }
    }

    #[test]
    fn cold_extrusion_is_refused_with_klippers_message_and_the_move_not_made() {
        let mut b = Bench::new(false);
        // Klipper's reply: the whole message as information, then the
        // error's first line.
        let refused = Err((
            "// Extrude below minimum temp\n\
             // See the 'min_extrude_temp' config option for details\n"
                .to_string(),
            "Extrude below minimum temp".to_string(),
        ));
        // An extrusion, an extrude-only move, and a retraction.
        for line in ["G1 X20 E1 F1200", "G1 E5", "G1 E-1"] {
            assert_eq!(b.run(line), refused, "{line}");
            assert_eq!(b.gcode.gcode_position(), [10.0, 10.0, 0.0, 0.0]);
        }
        // Moves without E still run, and are planned.
        assert_eq!(b.run("G1 X30 F6000"), Ok(String::new()));
        b.toolhead.wait_moves(&mut b.sink);
        assert_eq!((b.sink.toolhead, b.sink.extruder), (1, 0));
        // Hot: the same extrusion runs.
        b.toolhead.set_can_extrude(true);
        assert_eq!(b.run("G1 X40 E1 F1200"), Ok(String::new()));
        b.toolhead.wait_moves(&mut b.sink);
        assert_eq!((b.sink.toolhead, b.sink.extruder), (2, 1));
        assert_eq!(b.gcode.gcode_position(), [40.0, 10.0, 0.0, 1.0]);
    }

    #[test]
    fn an_extrude_only_move_longer_than_max_extrude_only_distance_is_refused() {
        let mut b = Bench::new(true);
        assert_eq!(
            b.run("G1 E50.5 F300"),
            Err((
                "// Extrude only move too long (50.500mm vs 50.000mm)\n\
                 // See the 'max_extrude_only_distance' config option for details\n"
                    .to_string(),
                "Extrude only move too long (50.500mm vs 50.000mm)".to_string()
            ))
        );
        // A retraction too, also with XY motion.
        let long_retract = b.run("G1 X20 E-51 F300").expect_err("too long");
        assert_eq!(
            long_retract.1,
            "Extrude only move too long (-51.000mm vs 50.000mm)"
        );
        assert_eq!(b.gcode.gcode_position(), [10.0, 10.0, 0.0, 0.0]);
        // Exactly the limit is allowed.
        assert_eq!(b.run("G1 E50 F300"), Ok(String::new()));
    }

    #[test]
    fn an_extrusion_wider_than_max_extrude_cross_section_is_refused() {
        let mut b = Bench::new(true);
        // 10 mm of filament over 1 mm of travel: 24.053 mm² against 0.64.
        let (out, error) = b.run("G1 X11 E10 F600").expect_err("too wide");
        assert_eq!(
            error,
            "Move exceeds maximum extrusion (24.053mm^2 vs 0.640mm^2)"
        );
        assert!(
            out.ends_with("// See the 'max_extrude_cross_section' config option for details\n"),
            "{out}"
        );
        // A tiny amount is let through (Klipper's nozzle-sized allowance).
        assert_eq!(b.run("G1 X10.1 E0.05 F600"), Ok(String::new()));
    }
}
