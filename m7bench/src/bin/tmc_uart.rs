//! Instructions per timer event of the TMC drivers' UART on a Cortex-M7
//! (the body of the board's TIM24 interrupt, `onechip_sched::tmc_uart`):
//! register reads as Klipper's periodic check makes them, each a 4-byte
//! request driven bit by bit, the line released, and an 8-byte reply
//! sampled 4 times per bit from a waveform standing in for the driver.
//! Region 2 runs the same loop around an empty function: region 1 less
//! region 2 is the events' own cost.
#![no_std]
#![no_main]

use cortex_m_rt::entry;
use onechip_m7bench::{exit, measure, report};
use onechip_sched::tmc_uart::{Pin, SoftUart, TURNAROUND_BITS, wire_level};

/// Klipper's 40 kbit/s at the board's 260 MHz timer clock, ticks.
const BIT: u32 = 6_500;
/// Reads measured.
const READS: u32 = 50;
/// The request: a read of IFCNT at address 0.
const REQUEST: [u8; 4] = [0xf5, 0x00, 0x02, 0x37];
/// The driver's reply, sent 8 bit times after the request.
const REPLY: [u8; 8] = [0x05, 0xff, 0x02, 0x00, 0x00, 0x00, 0x07, 0x2c];

/// The line's level `t` ticks after the release: the reply's bits.
fn line_at(t: u32) -> bool {
    t.checked_sub(8 * BIT)
        .is_none_or(|t| wire_level(&REPLY, (t / BIT) as usize))
}

/// The line's level at each event of one read exchange, recorded by
/// running it once with the driver's waveform.
fn recorded_lines(uart: &mut SoftUart) -> heapless::Vec<bool, 1024> {
    if uart.start(&REQUEST, REPLY.len(), BIT).is_err() {
        panic!("start")
    }
    let (mut lines, mut since_release) = (heapless::Vec::new(), None::<u32>);
    loop {
        let line = since_release.is_none_or(line_at);
        if lines.push(line).is_err() {
            panic!("events")
        }
        let Some(next) = uart.on_event(line, 0).next else {
            return lines;
        };
        since_release = match since_release {
            Some(t) => Some(t + next),
            // The release: the next wait is the turnaround.
            None if next == TURNAROUND_BITS * BIT => Some(next),
            None => None,
        };
    }
}

/// Runs `READS` exchanges, `event` called at each of their events with
/// the line's level recorded; the events run and the last reply's
/// checksum byte.
#[inline(never)]
fn exchanges(uart: &mut SoftUart, lines: &[bool], event: fn(&mut SoftUart, bool)) -> (u32, u8) {
    let mut reply = [0u8; 8];
    for _ in 0..READS {
        if uart.start(&REQUEST, REPLY.len(), BIT).is_err() {
            panic!("start")
        }
        for &line in lines {
            event(uart, line);
        }
        let _ = uart.reply(&mut reply);
    }
    (READS * lines.len() as u32, reply[7])
}

/// The interrupt's body: the event, and the pin action it asks for
/// (written to a stand-in for the GPIO registers).
#[inline(never)]
fn timer_event(uart: &mut SoftUart, line: bool) {
    let event = uart.on_event(line, 0);
    let word = match event.pin {
        Pin::Drive(true) => 1,
        Pin::Drive(false) => 1 << 16,
        Pin::Release | Pin::Keep => 0,
    };
    // SAFETY: a volatile write to a local, kept as a register write is.
    unsafe { core::ptr::write_volatile(&mut { 0u32 }, word) };
    // The next compare (a register write on the board).
    // SAFETY: as above.
    unsafe { core::ptr::write_volatile(&mut { 0u32 }, event.next.unwrap_or(0)) };
}

/// Nothing, called as the event is: the loop's own cost.
#[inline(never)]
fn no_event(uart: &mut SoftUart, line: bool) {
    // SAFETY: an empty asm block; it only keeps the call.
    unsafe {
        core::arch::asm!("/* {0} {1} */", in(reg) uart, in(reg) u32::from(line), options(nostack))
    }
}

#[entry]
fn main() -> ! {
    let mut uart = SoftUart::new();
    let lines = recorded_lines(&mut uart);
    measure(0, || 0u32);
    let (events, crc) = measure(1, || exchanges(&mut uart, &lines, timer_event));
    if crc != REPLY[7] {
        panic!("reply misread")
    }
    measure(2, || exchanges(&mut uart, &lines, no_event));
    report(format_args!(
        "tmc_uart: region 1 runs {events} events ({READS} register reads, reply checksum \
         {crc:#04x}); region 2 the same loop calling an empty function"
    ));
    exit()
}
