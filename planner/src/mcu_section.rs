//! `[mcu NAME]` sections: secondary boards running stock Klipper
//! firmware, with Klipper's options. The main MCU's `[mcu]` is the board
//! onechip runs on; its options are accepted and need nothing.

use crate::reader::{Errors, Read, Reader};
use onechip_config::Config;

/// Most secondary MCUs.
pub const MAX_SECONDARIES: usize = 4;

/// How a secondary is reset (`restart_method`, Klipper's choices).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RestartMethod {
    /// Toggle the serial line's DTR (`arduino`, the default).
    Arduino,
    /// As `arduino`, for the Cheetah boards (`cheetah`).
    Cheetah,
    /// The `reset` or `config_reset` command (`command`).
    Command,
    /// Power-cycle the USB port (`rpi_usb`).
    RpiUsb,
}

/// One `[mcu NAME]` section.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SecondaryMcu<'a> {
    /// The name pins use (`NAME:PA4`).
    pub name: &'a str,
    /// Its serial device (`/dev/serial/by-id/…`, or a USART of the board).
    pub serial: &'a str,
    /// Where `serial` is set: file name and 1-based line, for messages.
    pub serial_at: (&'a str, usize),
    /// Serial speed, baud (Klipper's default 250000).
    pub baud: u32,
    /// How it is reset.
    pub restart_method: RestartMethod,
}

/// Reads every `[mcu NAME]` section of `config`, and accepts `[mcu]`.
// Out of line: see `Machine::from_config_in`.
#[inline(never)]
pub(crate) fn read_all<'c, 'a>(
    config: &'c Config<'a>,
    errors: &Errors<'c>,
) -> Read<heapless::Vec<SecondaryMcu<'a>, MAX_SECONDARIES>> {
    config.accept_section("mcu");
    let mut all = heapless::Vec::new();
    for name in config.section_names() {
        if name.strip_prefix("mcu ").is_none() {
            continue;
        }
        let Some(section) = config.section(name) else {
            continue;
        };
        let section = Reader::new(section, errors);
        let mcu = read(&section)?;
        if all.push(mcu).is_err() {
            return Err(
                section.error_for("serial", "is one [mcu NAME] more than onechip drives (4)")
            );
        }
    }
    Ok(all)
}

fn read<'a>(section: &Reader<'_, '_, 'a>) -> Read<SecondaryMcu<'a>> {
    if section.get_opt("canbus_uuid").is_some() {
        return Err(section.error_for("canbus_uuid", "CAN bus MCUs are not supported yet"));
    }
    let serial = section.get("serial")?;
    let baud = section.get_int("baud", Some(250_000), Some(1))?;
    let restart_method = match section.get_choice(
        "restart_method",
        &["arduino", "cheetah", "command", "rpi_usb"],
        Some("arduino"),
    )? {
        "cheetah" => RestartMethod::Cheetah,
        "command" => RestartMethod::Command,
        "rpi_usb" => RestartMethod::RpiUsb,
        _ => RestartMethod::Arduino,
    };
    section.accept(&["canbus_interface", "is_non_critical"]);
    let name = section.name_in_file();
    Ok(SecondaryMcu {
        name: name.strip_prefix("mcu ").unwrap_or(name).trim(),
        serial,
        serial_at: section.locate("serial"),
        baud: u32::try_from(baud).unwrap_or(u32::MAX),
        restart_method,
    })
}
