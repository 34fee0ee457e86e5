//! The board's serial link to secondary MCUs (printer.cfg's `[mcu NAME]`
//! with `serial: usart2`): a USART as a [`SecondaryLink`], driven from
//! its interrupt with bounded rings, straight on its registers
//! (embassy-stm32's `BufferedUart` would do as much, but wakes an async
//! task; thread code here sleeps in `wfe` and polls, and the rings'
//! accounting is [`onechip_sched::serial`]'s, tested on the host).
//!
//! - Receive: the USART's receive FIFO (16 bytes, RM0468's USART chapter,
//!   "USART FIFOs and thresholds") raises the interrupt while it holds a
//!   byte (RXFNEIE); the handler moves every byte held into a
//!   [`RX_RING`]-byte ring, in order. A byte with a framing or noise error
//!   is kept (Klipper's transport checks every block's CRC and has a bad
//!   one sent again) and counted; an overrun (the FIFO full when a byte
//!   came) and a byte the ring had no room for are lost and counted, the
//!   bytes around them kept in order; nothing panics.
//! - Transmit: `write_all` stores into a [`TX_RING`]-byte ring (asleep in
//!   `wfe` while it is full) and enables the "transmit FIFO not full"
//!   interrupt (TXFNFIE), whose handler fills the FIFO from the ring and
//!   disables itself once the ring is empty.
//! - Waiting: `wait_readable` sleeps (`wfe`) until a byte is in the ring
//!   or its timeout passes on the stepper clock
//!   ([`crate::step_timer::now64`]); any interrupt wakes it (the receive
//!   interrupt, the I/O executor's 10 ms tick at the latest), so a wait
//!   may end up to 10 ms after its timeout when nothing else runs.
//! - `pulse_reset` is an error: the header has no DTR or RTS line
//!   (`restart_method: command` resets a secondary through its `reset`
//!   command).
//!
//! USART2 on the Octopus Pro v1.1's Raspberry Pi UART header ("USART2":
//! TX2 on PD5, RX2 on PD6, alternate function 7, 3.3 V levels; BTT's
//! Klipper build for a Pi on that header is "Serial (on USART2
//! PD6/PD5)"), 8 data bits, no parity, 1 stop bit, 16× oversampling,
//! from its 130 MHz kernel clock ([`crate::clocks::USART2_KERNEL_HZ`]):
//! 250,000 bit/s exactly. The procedure is RM0468's ("USART character
//! transmission/reception procedure", "USART baud rate generation",
//! "USART interrupts"): FIFOEN and OVER8 written while UE is 0, then BRR,
//! then TE, RE, UE.

// Errors carry their words in bounded buffers (no heap to box them in);
// they come once per connection, not per byte.
#![allow(clippy::result_large_err)]

use crate::clocks::USART2_KERNEL_HZ;
use crate::handler_cell::{mask_of, masked};
use crate::priority;
use crate::step_timer;
use core::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use embassy_stm32::interrupt;
use embassy_stm32::interrupt::InterruptExt;
use embassy_stm32::pac;
use embassy_stm32::pac::gpio::vals;
use onechip_app::secondary::{LinkError, SecondaryLink, text};
use onechip_sched::serial::{BaudError, ByteRing, RxRing, divisor};

/// Bytes the receive ring holds: 82 ms of a 250,000 bit/s line, longer
/// than thread code goes between two reads of the link (it serves the
/// link every 1 ms while it waits).
pub const RX_RING: usize = 2048;
/// Bytes the transmit ring holds (several of Klipper's 64-byte blocks).
pub const TX_RING: usize = 1024;
/// Longest `write_all` waits for room before it calls the link broken,
/// s (the ring drains in 41 ms at 250,000 bit/s).
const WRITE_TIMEOUT: f64 = 1.0;
/// The alternate function of USART1/2/3 on their pins (RM0468 and the
/// STM32H723 datasheet's alternate function table: AF7).
const AF_USART2: u8 = 7;

/// One USART's state shared between its interrupt (producer of the
/// receive ring, consumer of the transmit ring) and thread code (the
/// other ends).
struct Port {
    rx: RxRing<RX_RING>,
    tx: ByteRing<TX_RING>,
    /// Receive FIFO overruns (bytes lost in the USART), wrapping.
    overruns: AtomicU32,
    /// Bytes received with a framing error (kept), wrapping.
    framing: AtomicU32,
    /// Bytes received with noise (kept), wrapping.
    noise: AtomicU32,
    /// A [`UsartLink`] owns the USART.
    open: AtomicBool,
}

impl Port {
    const fn new() -> Self {
        Self {
            rx: RxRing::new(),
            tx: ByteRing::new(),
            overruns: AtomicU32::new(0),
            framing: AtomicU32::new(0),
            noise: AtomicU32::new(0),
            open: AtomicBool::new(false),
        }
    }
}

/// Adds one to a counter only its interrupt writes.
#[inline(always)]
fn count(counter: &AtomicU32) {
    counter.store(
        counter.load(Ordering::Relaxed).wrapping_add(1),
        Ordering::Relaxed,
    );
}

/// A USART of the board that can reach a secondary, and its wiring.
#[derive(Clone, Copy)]
struct Usart {
    /// Its name in printer.cfg's `serial` option (any case).
    name: &'static str,
    regs: pac::usart::Usart,
    irq: interrupt::Interrupt,
    port: &'static Port,
    /// Clocks and resets the USART (RCC).
    enable: fn(),
    /// Transmit and receive pins by name, and what for, for the pin check.
    pins: [(&'static str, &'static str); 2],
    /// Transmit and receive pins: GPIO port index (0 = A) and number.
    tx: (u8, usize),
    rx: (u8, usize),
}

static USART2_PORT: Port = Port::new();

/// The USARTs `serial` may name. Only USART2 so far: of the Octopus Pro's
/// other USART pins, PA9/PA10 (USART1) and PD8/PD9 (USART3) are on the
/// TFT and ESP-01 headers, not yet tried.
const USARTS: [Usart; 1] = [Usart {
    name: "usart2",
    regs: pac::USART2,
    irq: interrupt::Interrupt::USART2,
    port: &USART2_PORT,
    enable: embassy_stm32::rcc::enable_and_reset::<embassy_stm32::peripherals::USART2>,
    pins: [
        ("PD5", "USART2 TX, the link to a secondary MCU"),
        ("PD6", "USART2 RX, the link to a secondary MCU"),
    ],
    tx: (3, 5),
    rx: (3, 6),
}];

/// What printer.cfg's `serial` may be on this board, for messages.
pub const SUPPORTED: &str = "usart2 (PD5 TX, PD6 RX: the Raspberry Pi UART header)";

/// The USART `serial` names, if this board has it.
fn find(serial: &str) -> Option<Usart> {
    let name = serial.trim();
    USARTS
        .iter()
        .find(|u| u.name.eq_ignore_ascii_case(name))
        .copied()
}

/// Checks that `serial` is a USART of this board and that `baud` bit/s
/// can be made from its kernel clock within 1 %: the BRR value, else the
/// reason (naming the value and what is supported).
pub fn check(serial: &str, baud: u32) -> Result<u16, LinkError> {
    let Some(usart) = find(serial) else {
        return Err(LinkError(text(format_args!(
            "'{}' is not a serial link of this board; supported: {SUPPORTED}",
            serial.trim()
        ))));
    };
    match divisor(USART2_KERNEL_HZ, baud) {
        Ok(d) if !d.over8 => Ok(d.brr),
        Ok(_) | Err(BaudError::OutOfRange) => Err(LinkError(text(format_args!(
            "{}: baud {baud} is out of its range ({} to {})",
            usart.name,
            USART2_KERNEL_HZ / 0xffff + 1,
            USART2_KERNEL_HZ / 16
        )))),
        Err(BaudError::TooFar(actual)) => Err(LinkError(text(format_args!(
            "{}: baud {baud} cannot be made within 1 % from its {} Hz clock \
             (nearest: {actual})",
            usart.name, USART2_KERNEL_HZ
        )))),
    }
}

/// The pins (transmit, receive) of the USART `serial` names, each with
/// what it is for, if this board has that USART: printer.cfg may not use
/// them for anything else.
pub fn pins(serial: &str) -> Option<[(&'static str, &'static str); 2]> {
    find(serial).map(|u| u.pins)
}

/// Counts of a link's line errors since boot (wrapping).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LineErrors {
    /// Bytes lost to a receive FIFO overrun.
    pub overruns: u32,
    /// Bytes lost for want of room in the receive ring.
    pub dropped: u32,
    /// Bytes received with a framing error.
    pub framing: u32,
    /// Bytes received with noise.
    pub noise: u32,
}

/// A USART opened as a link to one secondary MCU; closed (the USART off,
/// its pins released) when dropped.
pub struct UsartLink {
    usart: Usart,
    /// Its rate, bit/s.
    baud: u32,
}

impl UsartLink {
    /// Opens `serial` (`usart2`) at `baud` bit/s, 8N1: an error naming the
    /// value if this board has no such USART, the rate cannot be made, or
    /// the USART is already another secondary's link.
    pub fn open(serial: &str, baud: u32) -> Result<Self, LinkError> {
        let brr = check(serial, baud)?;
        let Some(usart) = find(serial) else {
            return Err(LinkError(text(format_args!("no USART '{serial}'"))));
        };
        if usart.port.open.swap(true, Ordering::AcqRel) {
            return Err(LinkError(text(format_args!(
                "{} is already the link of another [mcu]",
                usart.name
            ))));
        }
        start(&usart, brr);
        Ok(Self { usart, baud })
    }

    /// The line errors counted on this link's USART since boot.
    pub fn errors(&self) -> LineErrors {
        let port = self.usart.port;
        LineErrors {
            overruns: port.overruns.load(Ordering::Relaxed),
            dropped: port.rx.dropped(),
            framing: port.framing.load(Ordering::Relaxed),
            noise: port.noise.load(Ordering::Relaxed),
        }
    }

    /// Lets the transmit interrupt run (it stops itself once the ring
    /// is empty). CR1 is read, modified and written with the link's
    /// interrupt masked, so the handler's own change is never lost.
    fn kick(&self) {
        let regs = self.usart.regs;
        masked(mask_of(priority::SECONDARY_LINK), || {
            regs.cr1().modify(|w| w.set_txeie(true));
        });
    }
}

/// The stepper clock `s` seconds from now, ticks (saturating; a negative
/// or NaN `s` is now).
fn ticks_from_now(s: f64) -> u64 {
    let ticks = (s * step_timer::TIMER_HZ) as u64;
    step_timer::now64().saturating_add(ticks)
}

impl SecondaryLink for UsartLink {
    fn write_all(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        let port = self.usart.port;
        let mut rest = bytes;
        let deadline = ticks_from_now(WRITE_TIMEOUT);
        while !rest.is_empty() {
            let n = port.tx.push_slice(rest);
            rest = rest.get(n..).unwrap_or_default();
            self.kick();
            if rest.is_empty() {
                break;
            }
            if step_timer::now64() > deadline {
                return Err(LinkError(text(format_args!(
                    "{}: transmit stalled",
                    self.usart.name
                ))));
            }
            // The transmit interrupt makes room and wakes this.
            cortex_m::asm::wfe();
        }
        Ok(())
    }

    fn read(&mut self, buf: &mut [u8]) -> Result<usize, LinkError> {
        Ok(self.usart.port.rx.read(buf))
    }

    fn wait_readable(&mut self, timeout: f64) -> Result<(), LinkError> {
        let port = self.usart.port;
        let deadline = ticks_from_now(timeout);
        while !port.rx.has_data() && step_timer::now64() < deadline {
            // Woken by any interrupt's return (the receive interrupt's
            // included), so a byte arriving between the test and here is
            // not slept through.
            cortex_m::asm::wfe();
        }
        Ok(())
    }

    fn pulse_reset(&mut self, _cheetah: bool) -> Result<(), LinkError> {
        Err(LinkError(text(format_args!(
            "{} has no DTR or RTS line (set restart_method: command)",
            self.usart.name
        ))))
    }
}

impl Drop for UsartLink {
    /// Lets what was written go out (at most the ring's time on the line
    /// and 10 ms more), then turns the USART off and releases its pins.
    fn drop(&mut self) {
        let usart = self.usart;
        // 10 bits a byte, the ring and the FIFO.
        let line = (TX_RING + 16) as f64 * 10.0 / f64::from(self.baud.max(1));
        let deadline = ticks_from_now(0.010 + line);
        while (!usart.port.tx.is_empty() || !usart.regs.isr().read().tc())
            && step_timer::now64() < deadline
        {
            cortex_m::asm::wfe();
        }
        stop(&usart);
        usart.port.open.store(false, Ordering::Release);
    }
}

/// Clocks, configures and starts `usart` with BRR `brr` (16× oversampling),
/// its pins on their alternate function, its interrupt enabled.
fn start(usart: &Usart, brr: u16) {
    usart.irq.disable();
    (usart.enable)();
    let regs = usart.regs;
    // After the RCC reset every register is at its reset value: UE = 0,
    // 8 data bits, no parity, 1 stop bit, prescaler 1.
    regs.cr1().write(|w| {
        w.set_fifoen(true);
        w.set_over8(pac::usart::vals::Over8::OVERSAMPLING16);
    });
    regs.brr().write(|w| w.set_brr(brr));
    usart.port.rx.clear();
    usart.port.tx.clear();
    regs.cr1().modify(|w| {
        w.set_te(true);
        w.set_re(true);
        w.set_rxneie(true);
        w.set_ue(true);
    });
    set_pin(usart.tx, vals::Moder::ALTERNATE, vals::Pupdr::FLOATING);
    // Pulled up: an unplugged header reads idle, not a stream of breaks.
    set_pin(usart.rx, vals::Moder::ALTERNATE, vals::Pupdr::PULL_UP);
    usart.irq.set_priority(priority::SECONDARY_LINK);
    // SAFETY: the handler below touches only this USART's registers and
    // its port's interrupt ends, as `Port` documents.
    unsafe { usart.irq.enable() };
}

/// Stops `usart`: its interrupt off, the USART disabled and unclocked
/// state left to the next open's reset, its pins inputs with pull-ups
/// (the line idles high).
fn stop(usart: &Usart) {
    usart.irq.disable();
    usart.regs.cr1().write(|_| {});
    set_pin(usart.tx, vals::Moder::INPUT, vals::Pupdr::PULL_UP);
    set_pin(usart.rx, vals::Moder::INPUT, vals::Pupdr::PULL_UP);
    usart.port.tx.clear();
}

/// Puts pin `(port, number)` in `mode` (alternate function 7 when
/// alternate) with `pull`.
fn set_pin((port, number): (u8, usize), mode: vals::Moder, pull: vals::Pupdr) {
    let Some(gpio) = crate::gpio::port(port) else {
        return;
    };
    gpio.afr(number / 8)
        .modify(|w| w.set_afr(number % 8, AF_USART2));
    gpio.ospeedr()
        .modify(|w| w.set_ospeedr(number, vals::Ospeedr::MEDIUM_SPEED));
    gpio.pupdr().modify(|w| w.set_pupdr(number, pull));
    gpio.moder().modify(|w| w.set_moder(number, mode));
}

/// The handler's work for `usart`: every byte in the receive FIFO into
/// the ring (error flags read first: in FIFO mode they belong to the byte
/// at the FIFO's head, RDR), then the transmit FIFO filled from the ring.
#[inline(always)]
fn serve(usart: &Usart) {
    let (regs, port) = (usart.regs, usart.port);
    loop {
        let isr = regs.isr().read();
        if isr.ore() {
            count(&port.overruns);
        }
        if isr.fe() {
            count(&port.framing);
        }
        if isr.ne() {
            count(&port.noise);
        }
        if isr.ore() || isr.fe() || isr.ne() || isr.pe() {
            regs.icr().write(|w| {
                w.set_ore(true);
                w.set_fe(true);
                w.set_ne(true);
                w.set_pe(true);
            });
        }
        if !isr.rxne() {
            break;
        }
        port.rx.receive(regs.rdr().read().dr() as u8);
    }
    if regs.cr1().read().txeie() {
        // At most the FIFO's 16 bytes: TXFNF clears when it is full.
        while regs.isr().read().txe() {
            match port.tx.pop() {
                Some(byte) => regs.tdr().write(|w| w.set_dr(u16::from(byte))),
                None => {
                    regs.cr1().modify(|w| w.set_txeie(false));
                    break;
                }
            }
        }
    }
}

#[interrupt]
fn USART2() {
    serve(&USARTS[0]);
}
