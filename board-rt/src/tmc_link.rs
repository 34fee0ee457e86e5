//! The wires to the TMC drivers ([`onechip_app::tmc::TmcLink`]): each
//! driver section's UART pin or SPI chip select, resolved at start.
//!
//! - UART (TMC2208, TMC2209; `uart_pin`, and `tx_pin` if separate): the
//!   single-wire UART bit-banged at Klipper's 40,000 bits/s from TIM24's
//!   compare interrupt, just below the stepper's
//!   ([`onechip_sched::tmc_uart`], which measures each event's latency
//!   and fails an exchange held off too long, to be tried again after
//!   1 ms of idle line). On the Octopus Pro each driver socket has its
//!   own pin (PC4, PD11, PC6, PC7, PF2, PE4, PE1, PD3 in Klipper's board
//!   config), so TIM24 serves one exchange at a time. Thread code sleeps
//!   (`wfe`) until the exchange is over: a register write takes 2.0 ms
//!   (80 bits), a read about 3.3 ms (40 bits out, the driver's 8-bit
//!   pause, 84 bits sampled).
//! - SPI (TMC2130, TMC2240, TMC2660, TMC5160; `cs_pin`, `spi_bus: spi1`
//!   or a software bus): [`crate::spi_sensors::SpiDevice`], as the
//!   temperature chips use; a transfer holds the heaters' interrupt off,
//!   as SPI1 is theirs too (5 bytes at 4 MHz: about 12 µs).

use crate::handler_cell::{HandlerCell, mask_of, masked};
use crate::priority;
use crate::spi_sensors::SpiDevice;
use crate::step_pins::{InPin, gpio_pin};
use core::sync::atomic::{AtomicBool, Ordering};
use embassy_stm32::interrupt;
use embassy_stm32::interrupt::InterruptExt;
use embassy_stm32::pac;
use embassy_stm32::pac::gpio::vals;
use onechip_app::heaters::{SpiBus, SpiBusPins};
use onechip_app::pins::BadPin;
use onechip_app::setup::PrinterSetup;
use onechip_app::text::{ErrorText, error_text};
use onechip_app::tmc::{NoAnswer, TmcLink, port_numbers};
use onechip_sched::tmc_uart::{Pin, SoftUart};
use onechip_tmc::DriverKind;
use onechip_tmc::config::{Bus, MAX_DRIVERS};

/// Klipper's TMC UART bit rate, bits/s.
const BAUD: u32 = 40_000;
/// One bit, TIM24 ticks (TIM24 counts at the APB1 timer clock).
const BIT_TICKS: u32 = crate::clocks::APB1_TIMER_HZ / BAUD;
const _: () = assert!(
    BIT_TICKS.is_multiple_of(onechip_sched::tmc_uart::OVERSAMPLE),
    "samples fall on whole ticks"
);
/// The first event of an exchange, ticks after it is armed (20 µs).
const LEAD: u32 = BIT_TICKS * 4 / 5;
/// How long the line stays idle after a failed exchange, TIM24 ticks
/// (1 ms: the I/O executor's 10 ms tick wakes the wait at the latest).
const IDLE_AFTER_FAILURE: u32 = 260_000;
/// Time allowed beyond an exchange's longest before thread code gives
/// up on it, TIM24 ticks (1 ms; an exchange is at most about 6 ms, far
/// below the counter's 16.5 s wrap).
const GRACE: u32 = 260_000;

/// A driver's single-wire UART: its receive pin, and the pin driven (the
/// transmit pin if separate, else the receive pin itself).
#[derive(Clone, Copy)]
pub struct UartLine {
    rx: InPin,
    /// The pin driven: its port and number.
    wire: (pac::gpio::Gpio, usize),
    /// The wire is the receive pin: released as an input.
    single: bool,
}

impl UartLine {
    /// The UART on `uart_pin` (with its pull-up if written `^`) and
    /// `tx_pin` if any, driven idle high. An inverted pin is refused, as
    /// Klipper refuses one.
    pub fn new<'a>(uart_pin: &'a str, tx_pin: Option<&'a str>) -> Result<Self, BadPin<'a>> {
        let not_inverted = |name: &'a str| match gpio_pin(name)? {
            (_, _, parsed) if parsed.inverted => Err(BadPin(name)),
            (port, number, _) => Ok((port, number)),
        };
        let rx_wire = not_inverted(uart_pin)?;
        let line = Self {
            rx: InPin::new(uart_pin)?,
            wire: tx_pin.map_or(Ok(rx_wire), not_inverted)?,
            single: tx_pin.is_none(),
        };
        line.apply(Pin::Drive(true));
        Ok(line)
    }

    /// The line's level now.
    #[inline(always)]
    fn read(&self) -> bool {
        self.rx.is_active()
    }

    /// Does what an event asks of the pin: drive it (a single wire
    /// becomes an output), or let it go (a single wire becomes an input
    /// again; a separate transmit pin goes back to idle high).
    #[inline(always)]
    fn apply(&self, pin: Pin) {
        let (port, number) = self.wire;
        let mode = |mode| port.moder().modify(|w| w.set_moder(number, mode));
        let drive = |level: bool| {
            let bit = if level { number } else { number + 16 };
            port.bsrr().write_value(pac::gpio::regs::Bsrr(1 << bit));
            mode(vals::Moder::OUTPUT);
        };
        match pin {
            Pin::Drive(level) => drive(level),
            Pin::Release if self.single => mode(vals::Moder::INPUT),
            Pin::Release => drive(true),
            Pin::Keep => {}
        }
    }
}

/// One exchange on TIM24's interrupt: its state and its line.
struct Exchange {
    uart: SoftUart,
    line: Option<UartLine>,
}

/// The exchange; it belongs to TIM24's handler, thread code reaches it
/// with TIM24's priority masked.
static EXCHANGE: HandlerCell<Exchange, { mask_of(priority::TMC_UART) }> = HandlerCell::new();
/// Set by the handler when an exchange is over.
static DONE: AtomicBool = AtomicBool::new(false);

/// Starts TIM24 counting, its interrupt enabled at [`priority::TMC_UART`]
/// with no compare armed.
fn start_timer() {
    EXCHANGE.install(Exchange {
        uart: SoftUart::new(),
        line: None,
    });
    embassy_stm32::rcc::enable_and_reset::<embassy_stm32::peripherals::TIM24>();
    crate::timer32::start(pac::TIM24, None);
    interrupt::TIM24.set_priority(priority::TMC_UART);
    // SAFETY: the handler below touches TIM24 and the exchange, as the
    // exchange's `HandlerCell` allows.
    unsafe { interrupt::TIM24.enable() };
}

/// One exchange on `line`: `tx` out, `rx` filled from the reply (none if
/// empty). Thread code sleeps until TIM24's handler ends it, or gives up
/// a millisecond past its longest.
fn exchange(line: UartLine, tx: &[u8], rx: &mut [u8]) -> Result<(), NoAnswer> {
    let started = EXCHANGE.with(|x| {
        x.line = Some(line);
        x.uart.start(tx, rx.len(), BIT_TICKS)
    });
    if !matches!(started, Some(Ok(()))) {
        return Err(NoAnswer);
    }
    DONE.store(false, Ordering::Release);
    let longest = SoftUart::longest_bits(tx.len(), rx.len()) * BIT_TICKS;
    let limit = LEAD + longest + GRACE;
    let tim = pac::TIM24;
    // Armed with TIM24's interrupt held off, so that its first run sees
    // the compare it is armed for: the compare before the flags are
    // cleared and the interrupt enabled (no stale match starts the
    // exchange early), and a first event passed meanwhile raised now (it
    // fails as late: the exchange is tried again).
    let start = masked(mask_of(priority::TMC_UART), || {
        let start = tim.cnt().read();
        let first = start.wrapping_add(LEAD);
        tim.ccr(0).write_value(first);
        tim.sr().write_value(Default::default());
        tim.dier().write(|w| w.set_ccie(0, true));
        crate::timer32::raise_if_passed(tim, first);
        start
    });
    while !DONE.load(Ordering::Acquire) {
        if tim.cnt().read().wrapping_sub(start) > limit {
            tim.dier().write(|w| w.set_ccie(0, false));
            EXCHANGE.with(|x| {
                x.uart.abort();
                line.apply(Pin::Drive(true));
            });
            break;
        }
        cortex_m::asm::wfe();
    }
    let reply = EXCHANGE
        .with(|x| x.uart.reply(rx))
        .map_or(Err(NoAnswer), |r| r.map_err(|_| NoAnswer));
    if reply.is_err() {
        // The line idle a while before the next try, so that a driver
        // that took part of it sees its datagram end (Klipper's retries
        // are a host round trip apart).
        let end = tim.cnt().read();
        while tim.cnt().read().wrapping_sub(end) < IDLE_AFTER_FAILURE {
            cortex_m::asm::wfe();
        }
    }
    reply
}

#[interrupt]
fn TIM24() {
    let tim = pac::TIM24;
    tim.sr().write_value(Default::default());
    let late = tim.cnt().read().wrapping_sub(tim.ccr(0).read());
    // SAFETY: this is TIM24's handler, which owns the exchange.
    let Some(x) = (unsafe { EXCHANGE.in_handler() }) else {
        return;
    };
    let Some(line) = x.line else {
        tim.dier().write(|w| w.set_ccie(0, false));
        return;
    };
    let event = x.uart.on_event(line.read(), late);
    line.apply(event.pin);
    match event.next {
        // Already passed: it runs at once (and the exchange fails as late).
        Some(ticks) => crate::timer32::arm(tim, tim.ccr(0).read().wrapping_add(ticks)),
        None => {
            tim.dier().write(|w| w.set_ccie(0, false));
            DONE.store(true, Ordering::Release);
            cortex_m::asm::sev();
        }
    }
}

/// One wire to one or more drivers.
enum Port {
    Uart(UartLine),
    Spi(SpiDevice),
}

/// The board's wires to the drivers, by port number
/// ([`onechip_app::tmc::port_numbers`]).
#[derive(Default)]
pub struct BoardTmc {
    ports: heapless::Vec<Port, MAX_DRIVERS>,
}

impl BoardTmc {
    /// The wires of `setup`'s drivers, their pins resolved through
    /// `[board_pins]`; None without a driver. TIM24 starts if a driver is
    /// on a UART.
    pub fn install(setup: &PrinterSetup<'_>) -> Result<Option<Self>, ErrorText> {
        let drivers = &setup.machine().tmc;
        if drivers.is_empty() {
            return Ok(None);
        }
        let mut tmc = Self::default();
        for (port, driver) in port_numbers(drivers).zip(drivers) {
            if usize::from(port) < tmc.ports.len() {
                // A wire already set up (drivers sharing a UART pin).
                continue;
            }
            let fail =
                |e: &dyn core::fmt::Display| error_text(&format_args!("[{}] {e}", driver.section));
            let pin = |written| setup.resolve_pin(written).map_err(|e| fail(&e));
            let port = match driver.bus {
                Bus::Uart {
                    select_pins: Some(_),
                    ..
                } => return Err(fail(&"select_pins: this board has no UART mux")),
                Bus::Uart {
                    uart_pin, tx_pin, ..
                } => {
                    let rx = pin(uart_pin)?;
                    let tx = tx_pin.map(pin).transpose()?;
                    let line = UartLine::new(&rx, tx.as_deref()).map_err(|e| fail(&e))?;
                    if !tmc.ports.iter().any(|p| matches!(p, Port::Uart(_))) {
                        start_timer();
                    }
                    Port::Uart(line)
                }
                Bus::Spi {
                    cs_pin,
                    spi_bus,
                    software,
                    speed,
                    ..
                } => {
                    let bus = SpiBus {
                        cs_pin,
                        pins: match software {
                            Some([miso, mosi, sclk]) => SpiBusPins::Software { sclk, mosi, miso },
                            None => SpiBusPins::Hardware(spi_bus),
                        },
                        speed,
                        // Klipper's: mode 3, the TMC2660's mode 0.
                        mode: if driver.kind == DriverKind::Tmc2660 {
                            0
                        } else {
                            3
                        },
                    };
                    Port::Spi(SpiDevice::configured(
                        setup,
                        &bus,
                        &format_args!("[{}]", driver.section),
                    )?)
                }
            };
            // One port per driver at most: there is room.
            let _ = tmc.ports.push(port);
        }
        Ok(Some(tmc))
    }
}

impl TmcLink for BoardTmc {
    fn uart(&mut self, port: u8, tx: &[u8], rx: &mut [u8]) -> Result<(), NoAnswer> {
        match self.ports.get(usize::from(port)) {
            Some(&Port::Uart(line)) => exchange(line, tx, rx),
            _ => Err(NoAnswer),
        }
    }

    fn spi(&mut self, port: u8, data: &mut [u8]) -> Result<(), NoAnswer> {
        match self.ports.get_mut(usize::from(port)) {
            Some(Port::Spi(device)) => {
                masked(mask_of(priority::HEATERS), || device.transfer(data));
                Ok(())
            }
            _ => Err(NoAnswer),
        }
    }
}
