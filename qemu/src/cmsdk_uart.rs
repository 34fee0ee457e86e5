//! CMSDK APB UART registers (byte offsets from a UART's base) and bits,
//! as QEMU's `hw/char/cmsdk-apb-uart.c` models them: one byte each way,
//! no FIFO, no modem lines.

/// A byte in or out.
pub const DATA: usize = 0x00;
/// Bit 0: transmitter full; bit 1: a byte received.
pub const STATE: usize = 0x04;
/// Bit 0 TX on, bit 1 RX on, bit 2 TX interrupt, bit 3 RX interrupt.
pub const CTRL: usize = 0x08;
/// Write 1s to clear interrupts (bit 0: TX, bit 1: RX).
pub const INTCLEAR: usize = 0x0c;
/// Clock divider (QEMU needs at least 16).
pub const BAUDDIV: usize = 0x10;
/// STATE: transmitter full.
pub const TX_FULL: u32 = 1 << 0;
/// STATE: a byte is waiting.
pub const RX_FULL: u32 = 1 << 1;
/// CTRL: transmitter and receiver on.
pub const ON: u32 = 1 << 0 | 1 << 1;
/// CTRL: transmit interrupt (raised as the transmitter empties).
pub const TX_IRQ: u32 = 1 << 2;
/// CTRL: receive interrupt.
pub const RX_IRQ: u32 = 1 << 3;
/// INTCLEAR: the transmit interrupt.
pub const INT_TX: u32 = 1 << 0;
/// INTCLEAR: the receive interrupt.
pub const INT_RX: u32 = 1 << 1;
