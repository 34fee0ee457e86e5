//! Trinamic stepper drivers configured over UART or SPI, as Klipper
//! configures them (`[tmc2130 …]`, `[tmc2208 …]`, `[tmc2209 …]`,
//! `[tmc2240 …]`, `[tmc2660 …]`, `[tmc5160 …]`).
//!
//! - [`registers`]: each driver's registers and fields, by Klipper's names;
//! - [`RegisterFile`]: the values to write, in the order Klipper first sets
//!   them (its `FieldHelper`);
//! - [`current`]: run and hold current to register bits (vsense,
//!   globalscaler, current_range);
//! - [`config`]: a section to a [`config::TmcDriver`] with every register
//!   value computed as Klipper computes it;
//! - [`sensorless`]: a rail homing on a driver's virtual endstop (its
//!   DIAG pin) and the register changes around such a homing move;
//! - [`wire`]: the UART and SPI datagrams, shared by the firmware and the
//!   simulated drivers.
//!
//! Config reading, off every real-time path, is built for size (its own
//! crate, so its release opt-level can be `s`); the planner re-exports it
//! as `onechip_planner::tmc` and its machine holds the drivers.
#![cfg_attr(not(test), no_std)]

pub mod config;
pub mod current;
pub mod registers;
pub mod sensorless;
pub mod wire;

use registers::{FieldDef, RegDef};

/// Most registers one driver's [`RegisterFile`] holds.
pub const MAX_REGISTERS: usize = 28;

/// A driver type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DriverKind {
    /// TMC2130 (SPI).
    Tmc2130,
    /// TMC2208 (single-wire UART, address 0 only).
    Tmc2208,
    /// TMC2209 (single-wire UART, addresses 0 to 3).
    Tmc2209,
    /// TMC2240 (SPI).
    Tmc2240,
    /// TMC2660 (SPI, 20-bit datagrams).
    Tmc2660,
    /// TMC5160 (SPI).
    Tmc5160,
}

/// Every driver type, by section prefix.
pub const DRIVERS: [(&str, DriverKind); 6] = [
    ("tmc2130", DriverKind::Tmc2130),
    ("tmc2208", DriverKind::Tmc2208),
    ("tmc2209", DriverKind::Tmc2209),
    ("tmc2240", DriverKind::Tmc2240),
    ("tmc2660", DriverKind::Tmc2660),
    ("tmc5160", DriverKind::Tmc5160),
];

impl DriverKind {
    /// The driver type and stepper of a section name (`tmc2209 stepper_x`,
    /// `tmc2209 extruder_stepper e1`: a stepper section's name of one
    /// word, or an extruder stepper's).
    pub fn of_section(section: &str) -> Option<(Self, &str)> {
        let (prefix, stepper) = section.trim().split_once(char::is_whitespace)?;
        let stepper = stepper.trim_start();
        let words = stepper.split_whitespace().count();
        if !(words == 1 || words == 2 && stepper.starts_with("extruder_stepper ")) {
            return None;
        }
        let kind = DRIVERS.iter().find(|(p, _)| *p == prefix)?.1;
        Some((kind, stepper))
    }

    /// The section prefix (`tmc2209`).
    pub fn name(self) -> &'static str {
        DRIVERS
            .iter()
            .find(|(_, k)| *k == self)
            .map_or("tmc", |(p, _)| p)
    }

    /// Its registers that the config sets.
    pub fn registers(self) -> &'static [RegDef] {
        match self {
            Self::Tmc2130 => registers::TMC2130,
            Self::Tmc2208 => registers::TMC2208,
            Self::Tmc2209 => registers::TMC2209,
            Self::Tmc2240 => registers::TMC2240,
            Self::Tmc2660 => registers::TMC2660,
            Self::Tmc5160 => registers::TMC5160,
        }
    }

    /// Its other registers (status, counters; kept apart so that a build
    /// that never talks to drivers does not carry their tables).
    pub fn status_registers(self) -> &'static [RegDef] {
        match self {
            Self::Tmc2130 => registers::TMC2130_STATUS,
            Self::Tmc2208 => registers::TMC2208_STATUS,
            Self::Tmc2209 => registers::TMC2209_STATUS,
            Self::Tmc2240 => registers::TMC2240_STATUS,
            Self::Tmc2660 => registers::TMC2660_STATUS,
            Self::Tmc5160 => registers::TMC5160_STATUS,
        }
    }

    /// Every register: those the config sets, then the others.
    pub fn all_registers(self) -> impl Iterator<Item = &'static RegDef> {
        self.registers().iter().chain(self.status_registers())
    }

    /// The registers Klipper reads back (DUMP_TMC's "queried registers").
    pub fn read_registers(self) -> &'static [&'static str] {
        match self {
            Self::Tmc2130 => registers::TMC2130_READ,
            Self::Tmc2208 => registers::TMC2208_READ,
            Self::Tmc2209 => registers::TMC2209_READ,
            Self::Tmc2240 => registers::TMC2240_READ,
            Self::Tmc2660 => registers::TMC2660_READ,
            Self::Tmc5160 => registers::TMC5160_READ,
        }
    }

    /// The driver's clock, Hz, which TSTEP-based thresholds count (none
    /// for the TMC2660, which has no such thresholds).
    pub fn clock_hz(self) -> Option<f64> {
        match self {
            Self::Tmc2130 => Some(13_200_000.0),
            Self::Tmc2208 | Self::Tmc2209 | Self::Tmc5160 => Some(12_000_000.0),
            Self::Tmc2240 => Some(12_500_000.0),
            Self::Tmc2660 => None,
        }
    }

    /// True for the single-wire UART drivers.
    pub fn is_uart(self) -> bool {
        matches!(self, Self::Tmc2208 | Self::Tmc2209)
    }

    /// The register the config sets named `name` (any case).
    pub fn register(self, name: &str) -> Option<&'static RegDef> {
        find_register(self.registers().iter(), name)
    }

    /// The register the config sets at `addr`.
    pub fn register_at(self, addr: u8) -> Option<&'static RegDef> {
        self.registers().iter().find(|r| r.addr == addr)
    }

    /// The field named `name` (any case) of a register the config sets,
    /// and its register.
    pub fn field(self, name: &str) -> Option<(&'static RegDef, &'static FieldDef)> {
        find_field(self.registers().iter(), name)
    }

    /// Any register named `name` (any case).
    pub fn register_any(self, name: &str) -> Option<&'static RegDef> {
        find_register(self.all_registers(), name)
    }

    /// Any register at `addr`.
    pub fn register_at_any(self, addr: u8) -> Option<&'static RegDef> {
        self.all_registers().find(|r| r.addr == addr)
    }

    /// Any field named `name` (any case), and its register.
    pub fn field_any(self, name: &str) -> Option<(&'static RegDef, &'static FieldDef)> {
        find_field(self.all_registers(), name)
    }

    /// True if Klipper reads register `name` back.
    pub fn is_read(self, name: &str) -> bool {
        self.read_registers().contains(&name)
    }
}

fn find_register(
    mut regs: impl Iterator<Item = &'static RegDef>,
    name: &str,
) -> Option<&'static RegDef> {
    regs.find(|r| r.name.eq_ignore_ascii_case(name))
}

fn find_field(
    mut regs: impl Iterator<Item = &'static RegDef>,
    name: &str,
) -> Option<(&'static RegDef, &'static FieldDef)> {
    regs.find_map(|r| {
        r.fields
            .iter()
            .find(|f| f.name.eq_ignore_ascii_case(name))
            .map(|f| (r, f))
    })
}

/// The table of a driver's register values was full.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RegistersFull;

/// A driver's register values as Klipper's `FieldHelper` keeps them: each
/// register in the order a field of it was first set, unset bits 0.
#[derive(Debug, Clone, PartialEq)]
pub struct RegisterFile {
    kind: DriverKind,
    /// Registers set so far.
    len: u8,
    /// Their addresses, in the order first set.
    addrs: [u8; MAX_REGISTERS],
    /// Their values.
    values: [u32; MAX_REGISTERS],
}

impl RegisterFile {
    /// No register set yet.
    pub fn new(kind: DriverKind) -> Self {
        Self {
            kind,
            len: 0,
            addrs: [0; MAX_REGISTERS],
            values: [0; MAX_REGISTERS],
        }
    }

    /// The driver type.
    pub fn kind(&self) -> DriverKind {
        self.kind
    }

    fn slot(&self, addr: u8) -> Option<usize> {
        self.addrs[..usize::from(self.len)]
            .iter()
            .position(|&a| a == addr)
    }

    /// Register `addr`'s value (0 if never set).
    pub fn value(&self, addr: u8) -> u32 {
        self.slot(addr).map_or(0, |i| self.values[i])
    }

    /// Register `name`'s value (0 if never set or unknown).
    pub fn value_of(&self, name: &str) -> u32 {
        self.kind.register(name).map_or(0, |r| self.value(r.addr))
    }

    /// The registers set, in the order they were first set: (address,
    /// value).
    pub fn iter(&self) -> impl Iterator<Item = (u8, u32)> + '_ {
        let n = usize::from(self.len);
        self.addrs[..n]
            .iter()
            .copied()
            .zip(self.values[..n].iter().copied())
    }

    /// Field `name`'s value (0 for an unknown field).
    pub fn get(&self, name: &str) -> i64 {
        self.kind
            .field(name)
            .map_or(0, |(r, f)| f.get(self.value(r.addr)))
    }

    /// Sets register `addr` to `value` (appended if new).
    pub fn set_register(&mut self, addr: u8, value: u32) -> Result<(), RegistersFull> {
        let i = match self.slot(addr) {
            Some(i) => i,
            None if usize::from(self.len) < MAX_REGISTERS => {
                self.len += 1;
                usize::from(self.len - 1)
            }
            None => return Err(RegistersFull),
        };
        self.addrs[i] = addr;
        self.values[i] = value;
        Ok(())
    }

    /// Sets field `name` (of a register the config sets) to `value`;
    /// returns its register's address and new value. An unknown field
    /// name is a bug of the caller's table: `None`, nothing changed.
    pub fn set(&mut self, name: &str, value: i64) -> Result<Option<(u8, u32)>, RegistersFull> {
        match self.kind.field(name) {
            Some((reg, field)) => self.set_in(reg, field, value).map(Some),
            None => Ok(None),
        }
    }

    /// Sets `field` of `reg` to `value`; returns the register's address
    /// and new value.
    pub fn set_in(
        &mut self,
        reg: &RegDef,
        field: &FieldDef,
        value: i64,
    ) -> Result<(u8, u32), RegistersFull> {
        let new = field.set(self.value(reg.addr), value);
        self.set_register(reg.addr, new)?;
        Ok((reg.addr, new))
    }
}
