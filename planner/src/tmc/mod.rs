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
//! - [`wire`]: the UART and SPI datagrams, shared by the firmware and the
//!   simulated drivers.

pub mod config;
pub mod current;
pub mod registers;
pub mod wire;

use registers::{FieldDef, RegDef};

/// Most registers one driver's [`RegisterFile`] holds.
pub const MAX_REGISTERS: usize = 32;

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
    /// The driver type and stepper of a section name (`tmc2209 stepper_x`).
    pub fn of_section(section: &str) -> Option<(Self, &str)> {
        let mut words = section.split_whitespace();
        let (prefix, stepper) = (words.next()?, words.next()?);
        if words.next().is_some() {
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

    /// Its registers.
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

    /// The register named `name` (any case).
    pub fn register(self, name: &str) -> Option<&'static RegDef> {
        self.registers()
            .iter()
            .find(|r| r.name.eq_ignore_ascii_case(name))
    }

    /// The register at `addr`.
    pub fn register_at(self, addr: u8) -> Option<&'static RegDef> {
        self.registers().iter().find(|r| r.addr == addr)
    }

    /// The field named `name` (any case) and its register.
    pub fn field(self, name: &str) -> Option<(&'static RegDef, &'static FieldDef)> {
        self.registers().iter().find_map(|r| {
            r.fields
                .iter()
                .find(|f| f.name.eq_ignore_ascii_case(name))
                .map(|f| (r, f))
        })
    }

    /// True if Klipper reads register `name` back.
    pub fn is_read(self, name: &str) -> bool {
        self.read_registers().contains(&name)
    }
}

/// The table of a driver's register values was full.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RegistersFull;

/// A driver's register values as Klipper's `FieldHelper` keeps them: each
/// register in the order a field of it was first set, unset bits 0.
#[derive(Debug, Clone, PartialEq)]
pub struct RegisterFile {
    kind: DriverKind,
    values: heapless::Vec<(u8, u32), MAX_REGISTERS>,
}

impl RegisterFile {
    /// No register set yet.
    pub fn new(kind: DriverKind) -> Self {
        Self {
            kind,
            values: heapless::Vec::new(),
        }
    }

    /// The driver type.
    pub fn kind(&self) -> DriverKind {
        self.kind
    }

    /// Register `addr`'s value (0 if never set).
    pub fn value(&self, addr: u8) -> u32 {
        self.values
            .iter()
            .find(|(a, _)| *a == addr)
            .map_or(0, |&(_, v)| v)
    }

    /// Register `name`'s value (0 if never set or unknown).
    pub fn value_of(&self, name: &str) -> u32 {
        self.kind.register(name).map_or(0, |r| self.value(r.addr))
    }

    /// The registers set, in the order they were first set: (address,
    /// value).
    pub fn iter(&self) -> impl Iterator<Item = (u8, u32)> + '_ {
        self.values.iter().copied()
    }

    /// Field `name`'s value (0 for an unknown field).
    pub fn get(&self, name: &str) -> i64 {
        self.kind
            .field(name)
            .map_or(0, |(r, f)| f.get(self.value(r.addr)))
    }

    /// Sets register `addr` to `value` (appended if new).
    pub fn set_register(&mut self, addr: u8, value: u32) -> Result<(), RegistersFull> {
        if let Some(slot) = self.values.iter_mut().find(|(a, _)| *a == addr) {
            slot.1 = value;
            Ok(())
        } else {
            self.values.push((addr, value)).map_err(|_| RegistersFull)
        }
    }

    /// Sets field `name` to `value`; returns its register's address and
    /// new value. An unknown field name is a bug of the caller's table:
    /// `None`, nothing changed.
    pub fn set(&mut self, name: &str, value: i64) -> Result<Option<(u8, u32)>, RegistersFull> {
        let Some((reg, field)) = self.kind.field(name) else {
            return Ok(None);
        };
        let new = field.set(self.value(reg.addr), value);
        self.set_register(reg.addr, new)?;
        Ok(Some((reg.addr, new)))
    }
}
