//! The link to a secondary MCU (`[mcu NAME]` with `serial: uart1`): CMSDK
//! UART 1, which the harness attaches to the peer's serial device (QEMU's
//! second `-serial`).
//!
//! Its receive interrupt moves every byte into a ring of [`RX_RING`]
//! bytes; thread code reads them from there. Unlike the console's, this
//! UART does not hold bytes back while the ring is full: as on a board's
//! USART, a byte that finds no room is lost and counted
//! ([`overruns`]), and Klipper's transport retransmits. Thread code writes
//! byte by byte; while the transmitter is full it sleeps until the
//! transmit interrupt (or the real-time tick) wakes it.
//!
//! A board's UART always empties at its baud rate; QEMU's holds a byte
//! while nothing on the host takes it (the peer's pseudo-terminal closed:
//! the MCU is gone). A byte held [`TX_STALL`] s breaks the link: this
//! write and every later one until the next [`open`] are errors, which
//! the host role takes as lost communication.

use crate::cmsdk_uart as reg;
use crate::handler_cell::HandlerCell;
use crate::machine::{Irq, UART1, interrupt_ran, priority, read, write};
use crate::step_timer;
use core::sync::atomic::{AtomicBool, Ordering::Relaxed};
use onechip_app::secondary::{LinkError, SecondaryLink, text};

/// Bytes the receive ring holds: 4 ms of a 250 kbaud link, far more than
/// one of Klipper's message blocks (64 bytes) times its receive window.
pub const RX_RING: usize = 2048;

/// Longest the transmitter may stay full before the link counts as
/// broken, s (a byte takes 40 µs at 250 kbaud).
pub const TX_STALL: f64 = 0.25;

/// The transmitter stalled ([`TX_STALL`]) since the last [`open`].
static BROKEN: AtomicBool = AtomicBool::new(false);

/// The receive side, owned by UART 1's receive interrupt.
struct Rx {
    ring: heapless::Deque<u8, RX_RING>,
    /// Bytes lost to a full ring.
    overruns: u32,
}

static RX: HandlerCell<Rx> = HandlerCell::new(priority::LINK);

/// UART 1 as a [`SecondaryLink`]: a handle, as many as opened (there is
/// one UART: each open empties the ring of what the last one left).
pub struct Uart1Link;

/// Starts UART 1 with its interrupts and an empty ring.
pub fn open() -> Uart1Link {
    RX.install(Rx {
        ring: heapless::Deque::new(),
        overruns: 0,
    });
    write(UART1 + reg::BAUDDIV, 16);
    write(UART1 + reg::CTRL, reg::ON | reg::RX_IRQ | reg::TX_IRQ);
    crate::machine::enable(Irq::Uart1Rx, priority::LINK);
    crate::machine::enable(Irq::Uart1Tx, priority::LINK);
    // Bytes that came before the ring was there.
    crate::machine::pend(Irq::Uart1Rx);
    BROKEN.store(false, Relaxed);
    Uart1Link
}

/// Bytes lost so far to a full receive ring.
pub fn overruns() -> u32 {
    RX.with(|rx| rx.overruns).unwrap_or(0)
}

impl SecondaryLink for Uart1Link {
    fn write_all(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        let stall = (TX_STALL * step_timer::CLOCK_HZ) as u64;
        for &byte in bytes {
            if read(UART1 + reg::STATE) & reg::TX_FULL != 0 {
                let give_up = step_timer::now64().saturating_add(stall);
                while read(UART1 + reg::STATE) & reg::TX_FULL != 0 {
                    if BROKEN.load(Relaxed) || step_timer::now64() > give_up {
                        BROKEN.store(true, Relaxed);
                        return Err(LinkError(text(format_args!(
                            "uart1: nothing took a byte for {TX_STALL} s"
                        ))));
                    }
                    crate::machine::sleep();
                }
            }
            write(UART1 + reg::DATA, u32::from(byte));
        }
        Ok(())
    }

    /// What has arrived; never an error (a UART cannot tell that the other
    /// side is gone: silence is for the transport to notice).
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, LinkError> {
        let n = RX.with(|rx| {
            let mut n = 0;
            for (slot, byte) in buf
                .iter_mut()
                .zip(core::iter::from_fn(|| rx.ring.pop_front()))
            {
                *slot = byte;
                n += 1;
            }
            n
        });
        Ok(n.unwrap_or(0))
    }

    /// Sleeps until a byte is in the ring or `timeout` s (the step clock)
    /// have passed.
    fn wait_readable(&mut self, timeout: f64) -> Result<(), LinkError> {
        let ticks = (timeout.max(0.0) * step_timer::CLOCK_HZ) as u64;
        let deadline = step_timer::now64().saturating_add(ticks);
        while RX.with(|rx| rx.ring.is_empty()).unwrap_or(true) && step_timer::now64() < deadline {
            crate::machine::sleep();
        }
        Ok(())
    }

    fn pulse_reset(&mut self, _cheetah: bool) -> Result<(), LinkError> {
        Err(LinkError(text(format_args!(
            "uart1 has no modem lines (DTR, RTS) to reset the MCU by: use restart_method: command"
        ))))
    }
}

/// UART 1's receive interrupt: every byte waiting, into the ring.
pub extern "C" fn uart1_rx() {
    write(UART1 + reg::INTCLEAR, reg::INT_RX);
    // SAFETY: this is UART 1's receive handler, which owns `RX`.
    if let Some(rx) = unsafe { RX.in_handler() } {
        while read(UART1 + reg::STATE) & reg::RX_FULL != 0 {
            let byte = read(UART1 + reg::DATA) as u8;
            if rx.ring.push_back(byte).is_err() {
                rx.overruns = rx.overruns.wrapping_add(1);
            }
        }
    }
    interrupt_ran();
}

/// UART 1's transmit interrupt: the transmitter has room; wakes thread
/// code.
pub extern "C" fn uart1_tx() {
    write(UART1 + reg::INTCLEAR, reg::INT_TX);
    interrupt_ran();
}
