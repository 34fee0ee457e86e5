//! The pins printer.cfg uses, checked before any is configured: a pin
//! named by two options is refused (Klipper: "pin … used multiple times in
//! config"), and so is a pin the board itself uses (USB, the SD card, the
//! crystal, the debug port).
//!
//! Pins are compared without their modifiers (`!` inverted, `^` pull-up,
//! `~` pull-down) and ignoring case; `PF13` and `mcu:PF13` are the same
//! pin, `probe:z_virtual_endstop` is on another chip (and so is a TMC
//! driver's `tmc2209_stepper_x:virtual_endstop`, whose DIAG pin is checked
//! as its section's `diag_pin`). As in Klipper, two
//! options may share a pin only when
//! - both are steppers' `enable_pin` (one driver enable line for several
//!   drivers), or
//! - both are `endstop_pin` of one rail's steppers (`stepper_z` and
//!   `stepper_z1`);
//!
//! and then only written with the same modifiers. Klipper's
//! `[duplicate_pin_override]` is not supported.

use core::fmt;
use onechip_planner::board_pins::{BoardPins, ReservedPin};
use onechip_planner::machine::Machine;
use onechip_planner::sensor_section::SensorInput;
use onechip_planner::spi_temperature::SpiBusPins;
use onechip_planner::tmc::config::Bus;
use onechip_planner::tmc::sensorless;

/// The board's hardware SPI bus for SPI sensors (Klipper's name for SPI1
/// on PA5, PA6 and PA7 on the STM32H7).
pub const BOARD_SPI_BUS: &str = "spi1";

/// The pins the BigTreeTech Octopus Pro (STM32H723) build uses itself, as
/// `board/` wires them: USB on OTG_HS's internal full-speed PHY (PA11,
/// PA12), the micro-SD slot on SDMMC1 in 4-bit mode (PC8 to PC12, PD2),
/// the 25 MHz crystal on the HSE oscillator pins (PH0, PH1) and the SWD
/// debug port (PA13 SWDIO, PA14 SWCLK, kept for the probe). For [`check`];
/// another board has its own list.
pub const BOARD_RESERVED: &[(&str, &str)] = &[
    ("PA11", "USB D-"),
    ("PA12", "USB D+"),
    ("PA13", "SWD"),
    ("PA14", "SWD"),
    ("PH0", "crystal"),
    ("PH1", "crystal"),
    ("PC8", "SD card D0"),
    ("PC9", "SD card D1"),
    ("PC10", "SD card D2"),
    ("PC11", "SD card D3"),
    ("PC12", "SD card CLK"),
    ("PD2", "SD card CMD"),
];

/// One option of printer.cfg naming a pin.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PinUse<'a> {
    /// The section (`stepper_x`, `extruder`, `fan`).
    pub section: &'a str,
    /// The option (`step_pin`, `heater_pin`, `pin`).
    pub option: &'static str,
    /// The pin as written (`!PF14`, `^PG6`, `probe:z_virtual_endstop`).
    pub pin: &'a str,
}

impl<'a> PinUse<'a> {
    /// The pin without its modifiers (`PF14`).
    pub fn bare_pin(&self) -> &'a str {
        Pin::parse(self.pin).bare
    }
}

impl fmt::Display for PinUse<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "[{}] {}", self.section, self.option)
    }
}

/// Why the pins of printer.cfg cannot be used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PinConflict<'a> {
    /// Two options name the same pin.
    Duplicate {
        /// The option naming it first.
        first: PinUse<'a>,
        /// The option naming it again.
        second: PinUse<'a>,
    },
    /// Two options that may share a pin write it with different
    /// modifiers.
    Modifiers {
        /// The option naming it first.
        first: PinUse<'a>,
        /// The option naming it again.
        second: PinUse<'a>,
    },
    /// The board uses the pin itself.
    Reserved {
        /// The option naming it.
        used: PinUse<'a>,
        /// What the board uses it for (`USB D-`).
        by: &'a str,
    },
    /// An SPI sensor names a hardware bus the board does not have (only
    /// checked with the board's pins).
    NoSuchBus {
        /// The `spi_bus` option (its `pin`: the bus name).
        used: PinUse<'a>,
    },
    /// The option names a `[board_pins]` alias reserved with `<NAME>`.
    ReservedAlias {
        /// The option naming it.
        used: PinUse<'a>,
        /// The alias and what it is reserved for.
        reserved: ReservedPin<'a>,
    },
}

impl<'a> PinConflict<'a> {
    /// The option at fault: the one naming the pin again, or the one
    /// naming the board's pin.
    pub fn at(&self) -> PinUse<'a> {
        match *self {
            Self::Duplicate { second, .. } | Self::Modifiers { second, .. } => second,
            Self::Reserved { used, .. }
            | Self::ReservedAlias { used, .. }
            | Self::NoSuchBus { used } => used,
        }
    }
}

impl fmt::Display for PinConflict<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Duplicate { first, second } => {
                write!(
                    f,
                    "pin {} used by both {first} and {second}",
                    first.bare_pin()
                )
            }
            Self::Modifiers { first, second } => write!(
                f,
                "pin {} shared by {first} and {second} must have the same polarity ({} vs {})",
                first.bare_pin(),
                first.pin.trim(),
                second.pin.trim()
            ),
            Self::Reserved { used, by } => {
                write!(
                    f,
                    "pin {} of {used} is used by the board ({by})",
                    used.bare_pin()
                )
            }
            Self::ReservedAlias { used, reserved } => write!(f, "{reserved} ({used})"),
            Self::NoSuchBus { used } => write!(
                f,
                "{used} {} is not on this board (its SPI is {BOARD_SPI_BUS}: PA5 SCK, PA6 MISO, PA7 MOSI)",
                used.pin.trim()
            ),
        }
    }
}

/// Checks the pins `machine` uses against each other and against the pins
/// the board reserves, `(pin, what for)`; the first conflict found, going
/// through the steppers (in [`Machine::steppers`] order), heaters and fan.
pub fn check<'a>(
    machine: &Machine<'a>,
    reserved: &[(&'a str, &'a str)],
) -> Result<(), PinConflict<'a>> {
    let aliases = &machine.accessories.board_pins;
    let resolve = |used: PinUse<'a>| {
        Pin::resolve(aliases, used.pin)
            .map_err(|reserved| PinConflict::ReservedAlias { used, reserved })
    };
    for (i, used) in uses(machine).enumerate() {
        let pin = resolve(used)?;
        if let Some(&(_, by)) = reserved
            .iter()
            .find(|(name, _)| Pin::parse(name).same_as(&pin))
        {
            return Err(PinConflict::Reserved { used, by });
        }
        for first in uses(machine).take(i) {
            let earlier = resolve(first)?;
            if !earlier.same_as(&pin) {
                continue;
            }
            let second = used;
            if !may_share(&first, &second) {
                return Err(PinConflict::Duplicate { first, second });
            }
            if earlier.modifiers != pin.modifiers {
                return Err(PinConflict::Modifiers { first, second });
            }
        }
    }
    if reserved.is_empty() {
        return Ok(());
    }
    // With the board's pins: its one hardware SPI bus (a chip on a
    // secondary MCU is on that MCU's buses).
    let heater_buses = machine.heaters.iter().map(|h| (h.name, h.spi));
    let sensor_buses = machine.sensors.iter().map(|s| match s.input {
        SensorInput::Spi { bus, .. } => (s.section, Some(bus)),
        _ => (s.section, None),
    });
    for (section, bus) in heater_buses.chain(sensor_buses) {
        let bus = bus.filter(|b| crate::mcu_config::on_main(b.cs_pin));
        if let Some(SpiBusPins::Hardware(Some(name))) = bus.map(|b| b.pins)
            && !name.trim().eq_ignore_ascii_case(BOARD_SPI_BUS)
        {
            let used = PinUse {
                section,
                option: "spi_bus",
                pin: name,
            };
            return Err(PinConflict::NoSuchBus { used });
        }
    }
    Ok(())
}

/// Every pin option of `machine`, in printer.cfg's order.
pub(crate) fn uses<'m, 'a>(machine: &'m Machine<'a>) -> impl Iterator<Item = PinUse<'a>> + 'm {
    let steppers = machine.steppers.iter().flat_map(|s| {
        let pins = [
            ("step_pin", Some(s.step_pin)),
            ("dir_pin", Some(s.dir_pin)),
            ("enable_pin", s.enable_pin),
            ("endstop_pin", s.endstop_pin),
        ];
        pins.into_iter().filter_map(move |(option, pin)| {
            pin.map(|pin| PinUse {
                section: s.name,
                option,
                pin,
            })
        })
    });
    let heaters = machine.heaters.iter().flat_map(|h| {
        [("heater_pin", h.heater_pin), ("sensor_pin", h.sensor_pin)].map(|(option, pin)| PinUse {
            section: h.name,
            option,
            pin,
        })
    });
    let sensors = machine.sensors.iter().filter_map(|s| match s.input {
        SensorInput::Adc { pin, .. } => Some(PinUse {
            section: s.section,
            option: "sensor_pin",
            pin,
        }),
        // The chip select; a bus's clock and data pins are shared by its
        // chips, as Klipper allows.
        SensorInput::Spi { bus, .. } => Some(PinUse {
            section: s.section,
            option: "sensor_pin",
            pin: bus.cs_pin,
        }),
        SensorInput::Mcu(_) => None,
    });
    // A software SPI bus's pins, which the bus's chips share.
    let heater_buses = machine.heaters.iter().map(|h| (h.name, h.spi));
    let sensor_buses = machine.sensors.iter().map(|s| match s.input {
        SensorInput::Spi { bus, .. } => (s.section, Some(bus)),
        _ => (s.section, None),
    });
    let spi = heater_buses.chain(sensor_buses).flat_map(|(section, bus)| {
        let pins = match bus.map(|b| b.pins) {
            Some(SpiBusPins::Software { sclk, mosi, miso }) => Some([
                ("spi_software_sclk_pin", sclk),
                ("spi_software_mosi_pin", mosi),
                ("spi_software_miso_pin", miso),
            ]),
            _ => None,
        };
        pins.into_iter().flatten().map(move |(option, pin)| PinUse {
            section,
            option,
            pin,
        })
    });
    let fan = machine.fan.iter().map(|f| PinUse {
        section: "fan",
        option: "pin",
        pin: f.pin,
    });
    let accessories = machine
        .accessories
        .pins()
        .map(|(section, option, pin)| PinUse {
            section,
            option,
            pin,
        });
    steppers
        .chain(diag_uses(machine))
        .chain(tmc_bus_uses(machine))
        .chain(heaters)
        .chain(sensors)
        .chain(spi)
        .chain(fan)
        .chain(crate::probe::pin_uses(machine))
        .chain(accessories)
}

/// The DIAG pins of the TMC drivers whose virtual endstop a rail homes on
/// (Klipper claims a driver's DIAG pin only then).
fn diag_uses<'m, 'a>(machine: &'m Machine<'a>) -> impl Iterator<Item = PinUse<'a>> + 'm {
    (machine.tmc.iter().enumerate())
        .filter(|&(k, _)| {
            machine
                .stall_homing
                .iter()
                .flatten()
                .any(|&d| usize::from(d) == k)
        })
        .filter_map(|(_, d)| {
            d.diag.map(|(pin, field)| PinUse {
                section: d.section,
                option: sensorless::diag_option(field),
                pin,
            })
        })
}

/// The TMC drivers' wires: UART pins (`uart_pin`, `tx_pin`), SPI chip
/// selects (`cs_pin`) and software SPI pins.
fn tmc_bus_uses<'m, 'a>(machine: &'m Machine<'a>) -> impl Iterator<Item = PinUse<'a>> + 'm {
    machine.tmc.iter().flat_map(|d| {
        let pins: [(&'static str, Option<&'a str>); 4] = match d.bus {
            Bus::Uart {
                uart_pin, tx_pin, ..
            } => [
                ("uart_pin", Some(uart_pin)),
                ("tx_pin", tx_pin),
                ("", None),
                ("", None),
            ],
            Bus::Spi {
                cs_pin, software, ..
            } => {
                let [miso, mosi, sclk] = software.map_or([None; 3], |p| p.map(Some));
                [
                    ("cs_pin", Some(cs_pin)),
                    ("spi_software_miso_pin", miso),
                    ("spi_software_mosi_pin", mosi),
                    ("spi_software_sclk_pin", sclk),
                ]
            }
        };
        pins.into_iter().filter_map(move |(option, pin)| {
            pin.map(|pin| PinUse {
                section: d.section,
                option,
                pin,
            })
        })
    })
}

/// True if Klipper lets `a` and `b` name one pin: steppers' enable pins,
/// the endstop pins of one rail's steppers, chips on one SPI bus, TMC
/// drivers on one UART (told apart by address) or one SPI chip select (a
/// daisy chain).
fn may_share(a: &PinUse<'_>, b: &PinUse<'_>) -> bool {
    a.option == b.option
        && match a.option {
            "enable_pin" => true,
            // Chips on one software SPI bus.
            "spi_software_sclk_pin" | "spi_software_mosi_pin" | "spi_software_miso_pin" => true,
            "uart_pin" | "tx_pin" | "cs_pin" => true,
            "endstop_pin" => rail(a.section).eq_ignore_ascii_case(rail(b.section)),
            _ => false,
        }
}

/// The rail a stepper section belongs to: `stepper_z1` is `stepper_z`'s.
fn rail(section: &str) -> &str {
    section.trim_end_matches(|c: char| c.is_ascii_digit())
}

/// True if `a` and `b` name one pin (modifiers aside).
pub fn same_pin(a: &str, b: &str) -> bool {
    Pin::parse(a).same_as(&Pin::parse(b))
}

/// A pin as written: chip, name and modifiers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Pin<'a> {
    /// The chip (`mcu` unless written `chip:pin`).
    chip: &'a str,
    /// The pin's name on its chip.
    name: &'a str,
    /// The pin as written without its modifiers (`PF14`, `probe:z_virtual_endstop`).
    bare: &'a str,
    /// Inverted (`!`), and pulled up (`^`) or down (`~`).
    modifiers: (bool, Option<char>),
}

impl<'a> Pin<'a> {
    fn parse(text: &'a str) -> Self {
        let mut rest = text.trim();
        let (mut inverted, mut pull) = (false, None);
        while let Some(c) = rest.chars().next().filter(|c| matches!(c, '!' | '^' | '~')) {
            if c == '!' {
                inverted = true;
            } else {
                pull = Some(c);
            }
            rest = rest[1..].trim_start();
        }
        let (chip, name) = rest
            .split_once(':')
            .map_or(("mcu", rest), |(chip, name)| (chip.trim(), name.trim()));
        Self {
            chip,
            name,
            bare: rest,
            modifiers: (inverted, pull),
        }
    }

    /// `text` with its `[board_pins]` alias resolved.
    fn resolve(aliases: &BoardPins<'a>, text: &'a str) -> Result<Self, ReservedPin<'a>> {
        let resolved = aliases.resolve(text)?;
        let written = Self::parse(text);
        Ok(Self {
            chip: resolved.chip.unwrap_or("mcu"),
            name: resolved.name,
            ..written
        })
    }

    /// True if `self` and `other` are one pin of one chip.
    fn same_as(&self, other: &Self) -> bool {
        self.chip.eq_ignore_ascii_case(other.chip) && self.name.eq_ignore_ascii_case(other.name)
    }
}
