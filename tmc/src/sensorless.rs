//! Sensorless homing as Klipper's `tmc.py` sets it up: a rail's
//! `endstop_pin: tmc2209_stepper_x:virtual_endstop` names the driver's
//! virtual pin chip (`<driver type>_<stepper>`), which stands for the
//! driver's DIAG output wired to an MCU input (`diag_pin`, or `diag0_pin` /
//! `diag1_pin`). Only the drivers with StallGuard have that chip (TMC2130,
//! TMC2209, TMC2240, TMC5160; not the TMC2208 or TMC2660).
//!
//! Around each homing move on such a rail the driver's registers are
//! changed so that a stall reaches DIAG ([`begin`]), then put back
//! ([`end`]), with the writes Klipper makes:
//! - StallGuard4 drivers (TMC2209, no `en_pwm_mode` field) need
//!   stealthChop: TPWMTHRS 0, then GCONF with `en_spreadcycle` clear;
//! - StallGuard2 drivers (TMC2130, TMC2240, TMC5160) need spreadCycle:
//!   GCONF with `en_pwm_mode` clear and the stall routed to the DIAG pin
//!   used (`diag0_stall` or `diag1_stall`);
//! - TCOOLTHRS 0xfffff if it was 0 (stall detection at every speed);
//! - THIGH 0 where the driver has it.

use crate::config::{TSTEP_MAX, TmcDriver};
use crate::{DriverKind, RegisterFile};
use core::fmt;

/// The pin name of a driver's virtual endstop.
pub const VIRTUAL_ENDSTOP: &str = "virtual_endstop";

/// Why an endstop pin naming a TMC driver's chip cannot be used, in
/// Klipper's words.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VirtualPinError<'p> {
    /// No driver section with a virtual pin chip of that name.
    UnknownChip(&'p str),
    /// A pin of the chip other than `virtual_endstop`.
    NotEndstop,
    /// Written with `!`, `^` or `~`.
    Modifiers,
    /// The driver's section has no DIAG pin.
    NoDiagPin,
}

impl<'p> VirtualPinError<'p> {
    /// Klipper's message, and the name it quotes (if any).
    pub fn message(&self) -> (&'static str, Option<&'p str>) {
        match *self {
            Self::UnknownChip(chip) => ("Unknown pin chip name", Some(chip)),
            Self::NotEndstop => ("tmc virtual endstop only useful as endstop", None),
            Self::Modifiers => ("Can not pullup/invert tmc virtual pin", None),
            Self::NoDiagPin => ("tmc virtual endstop requires diag pin config", None),
        }
    }
}

impl fmt::Display for VirtualPinError<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.message() {
            (message, Some(name)) => write!(f, "{message} '{name}'"),
            (message, None) => f.write_str(message),
        }
    }
}

/// The driver among `drivers` (its index) whose virtual endstop `pin` (an
/// endstop pin as written) names: `None` if `pin` names no TMC driver's
/// chip (an MCU pin, the probe's); an error, in Klipper's words, if it
/// cannot be used.
pub fn virtual_endstop<'p>(
    drivers: &[TmcDriver<'_>],
    pin: &'p str,
) -> Result<Option<u8>, VirtualPinError<'p>> {
    let written = pin.trim();
    let bare = written.trim_start_matches(['^', '~', '!', ' ']);
    let Some((chip, name)) = bare.split_once(':').map(|(c, n)| (c.trim(), n.trim())) else {
        return Ok(None);
    };
    // Only a chip named like a driver's (`tmc2209_…`) is a driver's.
    let Some((prefix, stepper)) = chip.split_once('_') else {
        return Ok(None);
    };
    let Some(&(_, kind)) = crate::DRIVERS
        .iter()
        .find(|(p, _)| p.eq_ignore_ascii_case(prefix))
    else {
        return Ok(None);
    };
    let (index, driver) = (drivers.iter().enumerate())
        .filter(|(_, d)| has_virtual_pin(d.kind))
        .find(|(_, d)| d.kind == kind && d.stepper.eq_ignore_ascii_case(stepper))
        .ok_or(VirtualPinError::UnknownChip(chip))?;
    if name != VIRTUAL_ENDSTOP {
        return Err(VirtualPinError::NotEndstop);
    }
    if bare.len() != written.len() {
        return Err(VirtualPinError::Modifiers);
    }
    if driver.diag.is_none() {
        return Err(VirtualPinError::NoDiagPin);
    }
    Ok(u8::try_from(index).ok())
}

/// True if drivers of `kind` have a virtual endstop (StallGuard and a
/// DIAG output).
fn has_virtual_pin(kind: DriverKind) -> bool {
    !matches!(kind, DriverKind::Tmc2208 | DriverKind::Tmc2660)
}

/// The option naming a driver's DIAG pin, by the GCONF field routing the
/// stall to it (`None`: the TMC2209's single DIAG output).
pub fn diag_option(field: Option<&str>) -> &'static str {
    match field {
        None => "diag_pin",
        Some("diag0_stall") => "diag0_pin",
        Some(_) => "diag1_pin",
    }
}

/// What [`begin`] changed, for [`end`] to put back.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Saved {
    /// stealthChop was on (`en_pwm_mode` set, or `en_spreadcycle` clear).
    stealth: bool,
    /// TPWMTHRS, TSTEP units (driver clocks per 1/256 microstep).
    tpwmthrs: u32,
    /// TCOOLTHRS, TSTEP units.
    tcoolthrs: u32,
    /// THIGH, TSTEP units (0 where the driver has none).
    thigh: u32,
}

/// Register writes of one [`begin`] or [`end`], in Klipper's order:
/// (address, value).
pub type Writes = [Option<(u8, u32)>; 3];

/// The register changes at the start of a homing move on the virtual
/// endstop of a driver whose stall is routed by GCONF field `diag_field`
/// (`None` on the TMC2209): `regs` changed, the writes to make, and what
/// to restore at the end.
pub fn begin(regs: &mut RegisterFile, diag_field: Option<&str>) -> (Writes, Saved) {
    let field = |regs: &RegisterFile, name| regs.get(name) as u32;
    let mut saved = Saved {
        tpwmthrs: field(regs, "tpwmthrs"),
        tcoolthrs: field(regs, "tcoolthrs"),
        ..Saved::default()
    };
    let mut writes: Writes = [None; 3];
    if stallguard4(regs) {
        // StallGuard4 reports in stealthChop only.
        saved.stealth = regs.get("en_spreadcycle") == 0;
        push(&mut writes, set(regs, "tpwmthrs", 0));
        push(&mut writes, set(regs, "en_spreadcycle", 0));
    } else {
        // StallGuard2 reports in spreadCycle only; GCONF also routes the
        // stall to the DIAG pin used.
        saved.stealth = regs.get("en_pwm_mode") != 0;
        if let Some(f) = diag_field {
            set(regs, f, 1);
        }
        push(&mut writes, set(regs, "en_pwm_mode", 0));
    }
    if saved.tcoolthrs == 0 {
        push(&mut writes, set(regs, "tcoolthrs", i64::from(TSTEP_MAX)));
    }
    if regs.kind().field("thigh").is_some() {
        saved.thigh = field(regs, "thigh");
        push(&mut writes, set(regs, "thigh", 0));
    }
    (writes, saved)
}

/// The register changes at the end of that homing move: what [`begin`]
/// changed put back as `saved` says; `regs` changed, the writes to make.
pub fn end(regs: &mut RegisterFile, diag_field: Option<&str>, saved: Saved) -> Writes {
    let mut writes: Writes = [None; 3];
    if stallguard4(regs) {
        push(
            &mut writes,
            set(regs, "tpwmthrs", i64::from(saved.tpwmthrs)),
        );
        let spreadcycle = i64::from(!saved.stealth);
        push(&mut writes, set(regs, "en_spreadcycle", spreadcycle));
    } else {
        if let Some(f) = diag_field {
            set(regs, f, 0);
        }
        push(
            &mut writes,
            set(regs, "en_pwm_mode", i64::from(saved.stealth)),
        );
    }
    push(
        &mut writes,
        set(regs, "tcoolthrs", i64::from(saved.tcoolthrs)),
    );
    if regs.kind().field("thigh").is_some() {
        push(&mut writes, set(regs, "thigh", i64::from(saved.thigh)));
    }
    writes
}

/// True for a StallGuard4 driver (the TMC2209: no `en_pwm_mode` field).
fn stallguard4(regs: &RegisterFile) -> bool {
    regs.kind().field("en_pwm_mode").is_none()
}

/// Adds `write` (if any) after those in `writes`.
fn push(writes: &mut Writes, write: Option<(u8, u32)>) {
    if let Some(slot) = writes.iter_mut().find(|w| w.is_none()) {
        *slot = write;
    }
}

/// Sets field `name`; its register's address and new value (`None` if
/// the driver has no such field or its table is full).
fn set(regs: &mut RegisterFile, name: &str, value: i64) -> Option<(u8, u32)> {
    regs.set(name, value).ok().flatten()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn regs(kind: DriverKind, fields: &[(&str, i64)]) -> RegisterFile {
        let mut r = RegisterFile::new(kind);
        for &(name, value) in fields {
            r.set(name, value).expect("room").expect("field");
        }
        r
    }

    #[test]
    fn a_tmc2209_homes_in_stealthchop_with_tcoolthrs_set_and_gets_its_registers_back() {
        let mut r = regs(
            DriverKind::Tmc2209,
            &[
                ("en_spreadcycle", 1),
                ("tpwmthrs", 0xfffff),
                ("tcoolthrs", 0),
            ],
        );
        let before = r.clone();
        let (writes, saved) = begin(&mut r, None);
        // TPWMTHRS 0x13, GCONF 0x00, TCOOLTHRS 0x14.
        assert_eq!(
            writes,
            [Some((0x13, 0)), Some((0x00, 0)), Some((0x14, 0xfffff))]
        );
        let back = end(&mut r, None, saved);
        assert_eq!(
            back,
            [Some((0x13, 0xfffff)), Some((0x00, 1 << 2)), Some((0x14, 0))]
        );
        assert_eq!(r, before);
    }

    #[test]
    fn a_tmc2130_homes_in_spreadcycle_with_the_stall_on_its_diag1_pin() {
        let mut r = regs(
            DriverKind::Tmc2130,
            &[
                ("en_pwm_mode", 1),
                ("tpwmthrs", 100),
                ("tcoolthrs", 50),
                ("thigh", 7),
            ],
        );
        let before = r.clone();
        let (writes, saved) = begin(&mut r, Some("diag1_stall"));
        // GCONF (en_pwm_mode bit 2 clear, diag1_stall bit 8), TCOOLTHRS
        // kept (not 0: not written), THIGH 0.
        assert_eq!(writes, [Some((0x00, 1 << 8)), Some((0x15, 0)), None]);
        let back = end(&mut r, Some("diag1_stall"), saved);
        assert_eq!(
            back,
            [Some((0x00, 1 << 2)), Some((0x14, 50)), Some((0x15, 7))]
        );
        assert_eq!(r, before);
    }
}
