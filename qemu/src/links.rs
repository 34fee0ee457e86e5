//! What this machine supplies to reach its secondary MCUs
//! ([`onechip_app::secondary::Links`]): `serial: uart1` (the one link, see
//! [`crate::uart_link`]), and static room for the data dictionaries.
//!
//! There are two dictionary buffers and two parsed dictionaries: one for
//! the MCU's first connection and one for klippy's reset-and-reconnect
//! at start (an MCU holding another config is reset and identified
//! again). A third connection (FIRMWARE_RESTART's) finds no room: its
//! error says so.

use crate::uart_link::{self, Uart1Link};
use core::mem::MaybeUninit;
use onechip_app::secondary::{LinkError, Links, text};
use onechip_protocol::dictionary::Dictionary;
use static_cell::{ConstStaticCell, StaticCell};

/// Bytes of one inflated data dictionary (Klipper's are 10–15 KB).
pub const DICTIONARY_MAX: usize = 32 * 1024;
/// The `serial` option's value naming UART 1.
pub const UART1: &str = "uart1";

static BUFFERS: [ConstStaticCell<[u8; DICTIONARY_MAX]>; 2] = [
    ConstStaticCell::new([0; DICTIONARY_MAX]),
    ConstStaticCell::new([0; DICTIONARY_MAX]),
];
static DICTIONARIES: [StaticCell<Dictionary<'static>>; 2] = [StaticCell::new(), StaticCell::new()];

/// This machine's links: UART 1.
pub struct UartLinks;

impl Links for UartLinks {
    type Link = Uart1Link;

    /// UART 1 for `serial: uart1`; the baud rate is QEMU's (none: bytes
    /// pass as fast as both sides take them).
    fn open(&mut self, serial: &str, _baud: u32) -> Result<Uart1Link, LinkError> {
        if serial != UART1 {
            return Err(LinkError(text(format_args!(
                "'{serial}': only {UART1} here"
            ))));
        }
        Ok(uart_link::open())
    }

    /// Sleeps `s` seconds of the step clock.
    fn pause(&mut self, s: f64) {
        let ticks = (s.max(0.0) * crate::step_timer::CLOCK_HZ) as u64;
        let until = crate::step_timer::now64().saturating_add(ticks);
        while crate::step_timer::now64() < until {
            crate::machine::sleep();
        }
    }

    fn dictionary_buffer(&mut self) -> Option<&'static mut [u8]> {
        let buffer = BUFFERS.iter().find_map(ConstStaticCell::try_take)?;
        Some(buffer.as_mut_slice())
    }

    fn dictionary_slot(&mut self) -> Option<&'static mut MaybeUninit<Dictionary<'static>>> {
        DICTIONARIES.iter().find_map(StaticCell::try_uninit)
    }
}
