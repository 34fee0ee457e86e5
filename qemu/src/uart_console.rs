//! The console on CMSDK UART 0: G-code lines in, replies out, the board's
//! USB console protocol on a serial line (QEMU `-serial`).
//!
//! The UART's receive interrupt (below the heaters') assembles lines and
//! hands them to thread code through a queue of two, as the board's USB
//! reader does; M112 is acted on by the byte. While the queue is full the
//! interrupt stops taking bytes: the UART's one-byte buffer stays full and
//! QEMU holds the host back, so no byte is lost. Replies are written by
//! thread code, byte by byte, waiting (`wfe`) while the transmitter is
//! full.

use crate::cmsdk_uart as reg;
use crate::handler_cell::HandlerCell;
use crate::machine::{Irq, UART0, priority, read, write};
use crate::probe::{self, Context};
use onechip_app::emergency::EmergencyParser;
use onechip_app::line::{LineAssembler, LineEvent};
use onechip_app::session::profile::MAX_LINE;
use onechip_sched::shutdown::Shutdown;

/// One console line as thread code receives it.
pub struct Incoming {
    /// The line without its end (empty if it was too long).
    bytes: heapless::Vec<u8, MAX_LINE>,
    /// The length of a line longer than [`MAX_LINE`], which was dropped.
    too_long: Option<usize>,
}

impl Incoming {
    /// The line as the session takes it.
    pub fn event(&self) -> LineEvent<'_> {
        match self.too_long {
            Some(len) => LineEvent::TooLong { len },
            None => LineEvent::Complete(&self.bytes),
        }
    }
}

/// The receive side, owned by the UART's interrupt.
struct Rx {
    lines: LineAssembler<MAX_LINE>,
    emergency: EmergencyParser,
    /// Lines waiting for thread code (two, as the board).
    queue: heapless::Deque<Incoming, 2>,
}

static RX: HandlerCell<Rx> = HandlerCell::new(priority::CONSOLE);

/// Starts the UART with its receive interrupt.
pub fn start() {
    RX.install(Rx {
        lines: LineAssembler::new(),
        emergency: EmergencyParser::new(),
        queue: heapless::Deque::new(),
    });
    write(UART0 + reg::BAUDDIV, 16);
    write(UART0 + reg::CTRL, reg::ON | reg::RX_IRQ);
    crate::machine::enable(Irq::Uart0Rx, priority::CONSOLE);
}

/// The next line from the host, if one has arrived (thread code).
pub fn try_line() -> Option<Incoming> {
    let line = RX.with(|rx| rx.queue.pop_front()).flatten();
    if line.is_some() {
        // Room again: take the bytes held back.
        write(UART0 + reg::CTRL, reg::ON | reg::RX_IRQ);
        crate::machine::pend(Irq::Uart0Rx);
    }
    line
}

/// Thread code's side of the replies.
pub struct ConsoleOut;

impl core::fmt::Write for ConsoleOut {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        for &byte in s.as_bytes() {
            if read(UART0 + reg::STATE) & reg::TX_FULL != 0 {
                probe::within(Context::Idle, || {
                    while read(UART0 + reg::STATE) & reg::TX_FULL != 0 {}
                });
            }
            write(UART0 + reg::DATA, u32::from(byte));
        }
        Ok(())
    }
}

/// The UART's receive interrupt: every byte waiting, while the queue has
/// room.
pub extern "C" fn uart0_rx() {
    probe::within(Context::Console, || {
        write(UART0 + reg::INTCLEAR, reg::INT_RX);
        // SAFETY: this is the UART's receive handler, which owns `RX`.
        let Some(rx) = (unsafe { RX.in_handler() }) else {
            return;
        };
        while read(UART0 + reg::STATE) & reg::RX_FULL != 0 {
            if rx.queue.is_full() {
                // Thread code re-enables it when it takes a line.
                write(UART0 + reg::CTRL, reg::ON);
                return;
            }
            let byte = read(UART0 + reg::DATA) as u8;
            if rx.emergency.push(byte) {
                crate::mcu::shutdown(Shutdown::EmergencyStop);
            }
            let incoming = match rx.lines.push(byte) {
                Some(LineEvent::Complete(bytes)) => Incoming {
                    // Fits: the assembler holds at most MAX_LINE bytes.
                    bytes: heapless::Vec::from_slice(bytes).unwrap_or_default(),
                    too_long: None,
                },
                Some(LineEvent::TooLong { len }) => Incoming {
                    bytes: heapless::Vec::new(),
                    too_long: Some(len),
                },
                None => continue,
            };
            // Room checked above.
            let _ = rx.queue.push_back(incoming);
        }
    });
}
