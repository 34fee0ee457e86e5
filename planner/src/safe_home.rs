//! G28 as `[safe_z_home]` and `[homing_override]` change it, with
//! Klipper's options and defaults.
//!
//! - `[safe_z_home]`: Z may first be lifted by `z_hop`; X and Y home, then
//!   the toolhead goes to `home_xy_position` (so that a probe homing Z is
//!   over the bed) and Z homes; Z is lifted again and, with
//!   `move_to_previous`, XY go back.
//! - `[homing_override]`: a G28 of one of its `axes` runs its `gcode`
//!   instead (after forcing the `set_position_*` positions); a G28 inside
//!   that gcode homes as usual. The lines are run by the caller (they may
//!   be any command); this module reads the section.

use crate::homing::HomingHooks;
use crate::move_sink::MoveSink;
use crate::reader::{Errors, Read, Reader};
use crate::toolhead::{Detail, MoveError, Toolhead};
use onechip_config::{Bounds, Config, decimal};

/// Klipper's error when Z would home before X and Y.
pub const HOME_XY_FIRST: &str = "Must home X and Y axes first";

/// `[safe_z_home]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SafeZHome {
    /// home_xy_position: where Z homes, mm.
    pub home_xy: [f64; 2],
    /// speed: of the moves to and from it, mm/s.
    pub speed: f64,
    /// z_hop: lift before and after homing Z, mm (0: none).
    pub z_hop: f64,
    /// z_hop_speed, mm/s.
    pub z_hop_speed: f64,
    /// move_to_previous: XY go back to where they were.
    pub move_to_previous: bool,
}

/// `[homing_override]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HomingOverride<'a> {
    /// gcode: the lines run instead of G28.
    pub gcode: &'a str,
    /// axes: a G28 naming one of them (or none) is overridden (X, Y, Z).
    pub axes: [bool; 3],
    /// set_position_x/y/z: positions forced (and axes marked homed)
    /// before the gcode runs, mm.
    pub set_position: [Option<f64>; 3],
}

/// How G28 homes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum G28<'a> {
    /// Axis by axis (Klipper's plain G28).
    Plain,
    /// With `[safe_z_home]`.
    SafeZ(SafeZHome),
    /// With `[homing_override]`.
    Override(HomingOverride<'a>),
}

/// Reads `[safe_z_home]` and `[homing_override]` (not both: Klipper's
/// error).
// Out of line: see `Machine::from_config_in`.
#[inline(never)]
pub(crate) fn read<'c, 'a>(config: &'c Config<'a>, errors: &Errors<'c>) -> Read<G28<'a>> {
    let section = |name| config.section(name).map(|s| Reader::new(s, errors));
    match (section("safe_z_home"), section("homing_override")) {
        (Some(s), Some(_)) => Err(s.error_for(
            "home_xy_position",
            "homing_override and safe_z_homing cannot be used simultaneously",
        )),
        (Some(s), None) => read_safe_z_home(&s).map(G28::SafeZ),
        (None, Some(s)) => read_override(&s).map(G28::Override),
        (None, None) => Ok(G28::Plain),
    }
}

fn read_safe_z_home(s: &Reader<'_, '_, '_>) -> Read<SafeZHome> {
    let text = s.get("home_xy_position")?;
    let mut parts = text.split(',').map(|p| decimal::parse(p.trim()));
    let home_xy = match (parts.next(), parts.next(), parts.next()) {
        (Some(Some(x)), Some(Some(y)), None) if x.is_finite() && y.is_finite() => [x, y],
        _ => {
            return Err(s.error_for("home_xy_position", "must be two numbers: x, y"));
        }
    };
    Ok(SafeZHome {
        home_xy,
        speed: s.float("speed", 50.0, Bounds::POSITIVE)?,
        z_hop: s.float("z_hop", 0.0, Bounds::NONE)?,
        z_hop_speed: s.float("z_hop_speed", 15.0, Bounds::POSITIVE)?,
        move_to_previous: s.get_bool("move_to_previous", false)?,
    })
}

fn read_override<'a>(s: &Reader<'_, '_, 'a>) -> Read<HomingOverride<'a>> {
    let gcode = s.get("gcode")?;
    if gcode.contains('{') {
        return Err(s.error_for(
            "gcode",
            "uses a template ({ }), which onechip does not support yet",
        ));
    }
    let axes_text = s.get_opt("axes").unwrap_or("xyz");
    let axes = core::array::from_fn(|i| {
        axes_text
            .bytes()
            .any(|b| b.eq_ignore_ascii_case(&b"xyz"[i]))
    });
    let set_position = [
        s.get_float_opt("set_position_x", Bounds::NONE)?,
        s.get_float_opt("set_position_y", Bounds::NONE)?,
        s.get_float_opt("set_position_z", Bounds::NONE)?,
    ];
    Ok(HomingOverride {
        gcode,
        axes,
        set_position,
    })
}

/// The axes a G28 asks for (none named: all).
pub fn requested(named: [bool; 3]) -> [bool; 3] {
    if named.iter().any(|&n| n) {
        named
    } else {
        [true; 3]
    }
}

impl<const N: usize> Toolhead<N> {
    /// Lifts Z to `z` at `speed` (mm, mm/s), XY where they are.
    fn lift_to(&mut self, z: f64, speed: f64, sink: &mut impl MoveSink) -> Result<(), MoveError> {
        let mut pos = self.position();
        pos[2] = z;
        self.move_to(pos, speed, sink)
    }

    /// G28 of the `named` axes (none: all) with `[safe_z_home]`.
    pub fn home_safe_z(
        &mut self,
        cfg: &SafeZHome,
        named: [bool; 3],
        sink: &mut impl MoveSink,
        hooks: &mut impl HomingHooks<N>,
    ) -> Result<(), MoveError> {
        let need = requested(named);
        if cfg.z_hop != 0.0 {
            let mut pos = self.position();
            if !self.kinematics.axis_homed(2) {
                // Z is taken to be at 0 for the lift, then unhomed again.
                pos[2] = 0.0;
                self.set_position(pos, sink);
                self.kinematics.set_axis_homed(2);
                let lifted = self.lift_to(cfg.z_hop, cfg.z_hop_speed, sink);
                self.kinematics.clear_axis_homed(2);
                lifted?;
            } else if pos[2] < cfg.z_hop {
                self.lift_to(cfg.z_hop, cfg.z_hop_speed, sink)?;
            }
        }
        let xy: heapless::Vec<usize, 2> = (0..2).filter(|&a| need[a]).collect();
        if !xy.is_empty() {
            self.home_with(&xy, sink, hooks)?;
        }
        if !need[2] {
            return Ok(());
        }
        if !(self.kinematics.axis_homed(0) && self.kinematics.axis_homed(1)) {
            return Err(MoveError {
                reason: HOME_XY_FIRST,
                end: self.position(),
                detail: Detail::Nothing,
            });
        }
        let previous = self.position();
        let mut over = previous;
        over[0] = cfg.home_xy[0];
        over[1] = cfg.home_xy[1];
        self.move_to(over, cfg.speed, sink)?;
        self.home_with(&[2], sink, hooks)?;
        if cfg.z_hop != 0.0 && self.position()[2] < cfg.z_hop {
            self.lift_to(cfg.z_hop, cfg.z_hop_speed, sink)?;
        }
        if cfg.move_to_previous {
            let mut back = self.position();
            back[0] = previous[0];
            back[1] = previous[1];
            self.move_to(back, cfg.speed, sink)?;
        }
        Ok(())
    }

    /// `[homing_override]`'s forced positions: each set axis takes its
    /// position and counts as homed.
    pub fn force_override_position(&mut self, cfg: &HomingOverride<'_>, sink: &mut impl MoveSink) {
        let mut pos = self.position();
        for (axis, at) in cfg.set_position.iter().enumerate() {
            if let Some(at) = at {
                pos[axis] = *at;
            }
        }
        self.set_position(pos, sink);
        for (axis, at) in cfg.set_position.iter().enumerate() {
            if at.is_some() {
                self.kinematics.set_axis_homed(axis);
            }
        }
    }
}
