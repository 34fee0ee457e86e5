//! The SPI temperature chips' bus (MAX6675, MAX31855, MAX31856,
//! MAX31865): hardware SPI1, the Octopus Pro's SPI on PA5 (SCK), PA6
//! (MISO) and PA7 (MOSI), brought out on EXP2 and shared with the
//! drivers' SPI header (`spi_bus: spi1`, Klipper's name for those pins on
//! the STM32H7), or a software bus on any three GPIOs
//! (`spi_software_sclk_pin`, `…_mosi_pin`, `…_miso_pin`); the chip select
//! (`sensor_pin`) is a GPIO, driven low for a transfer.
//!
//! Transfers are blocking, from TIM2's interrupt, as Klipper reads the
//! chips from its timer task: 4 bytes at 3.125 MHz take about 11 µs.
//! Every wait on SPI1 is bounded; a transfer that does not finish reads
//! as zeros, which the MCU's range check turns into a shutdown.

use crate::step_pins::{InPin, OutPin};
use embassy_stm32::pac;
use onechip_app::heaters::{SpiBus, SpiBusPins};
use onechip_app::pins::BadPin;
use onechip_app::setup::PrinterSetup;
use onechip_app::text::{ErrorText, error_text};

use crate::clocks::SPI1_KERNEL_HZ;

/// SPI1's register fields (RM0468, "SPI registers").
mod reg {
    /// CR1: enable.
    pub const CR1_SPE: u32 = 1 << 0;
    /// CR1: start the transfer (master).
    pub const CR1_CSTART: u32 = 1 << 9;
    /// CR1: internal slave select level (high: no mode fault with SSM).
    pub const CR1_SSI: u32 = 1 << 12;
    /// CFG1: frames of 8 bits (DSIZE = bits − 1).
    pub const CFG1_DSIZE_8: u32 = 7;
    /// CFG1: CRCSIZE at its reset value, 8 bits (CRC off; the field is
    /// to be at least DSIZE).
    pub const CFG1_CRCSIZE_8: u32 = 7 << 16;
    /// CFG1: the baud-rate divider's position (MBR: kernel / 2^(MBR+1)).
    pub const CFG1_MBR_SHIFT: u32 = 28;
    /// CFG2: clock phase.
    pub const CFG2_CPHA: u32 = 1 << 24;
    /// CFG2: clock polarity.
    pub const CFG2_CPOL: u32 = 1 << 25;
    /// CFG2: master.
    pub const CFG2_MASTER: u32 = 1 << 22;
    /// CFG2: slave select managed by software (SSI).
    pub const CFG2_SSM: u32 = 1 << 26;
    /// CFG2: keep driving the pins while disabled.
    pub const CFG2_AFCNTR: u32 = 1 << 31;
    /// SR: a byte received.
    pub const SR_RXP: u32 = 1 << 0;
    /// SR: room for a byte to send.
    pub const SR_TXP: u32 = 1 << 1;
    /// SR: end of transfer.
    pub const SR_EOT: u32 = 1 << 3;
    /// IFCR: clears EOT and TXTF.
    pub const IFCR_EOT_TXTF: u32 = 1 << 3 | 1 << 4;
    /// GPIO alternate function of SPI1 on PA5..PA7.
    pub const AF_SPI1: u8 = 5;
}

/// Polls of an SPI1 status bit before giving up (far beyond the 2.6 µs a
/// byte takes at the slowest divider this uses).
const SPI1_POLLS: u32 = 20_000;

/// One chip: its chip select and bus.
pub struct SpiDevice {
    cs: OutPin,
    bus: Bus,
}

enum Bus {
    /// SPI1, with its CFG1 and CFG2 for this chip.
    Spi1 { cfg1: u32, cfg2: u32 },
    /// Bit-banged, `half` CPU cycles per half clock period.
    Software {
        sclk: OutPin,
        mosi: OutPin,
        miso: InPin,
        mode: u8,
        half: u32,
    },
}

/// Why a chip's bus cannot be set up.
#[derive(Debug)]
pub enum SpiError<'a> {
    /// A pin that is not a GPIO of this board.
    Pin(BadPin<'a>),
    /// A hardware bus other than SPI1.
    Bus(&'a str),
}

impl core::fmt::Display for SpiError<'_> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Pin(e) => write!(f, "{e}"),
            Self::Bus(bus) => write!(
                f,
                "spi_bus {bus} is not on this board (spi1: PA5 SCK, PA6 MISO, PA7 MOSI)"
            ),
        }
    }
}

impl SpiDevice {
    /// The chip on `bus`, its pins already resolved (`cs` and, for a
    /// software bus, `sclk`, `mosi`, `miso`); SPI1 is set up on first use.
    pub fn new<'a>(
        bus: &SpiBus<'a>,
        cs: &'a str,
        software: Option<[&'a str; 3]>,
    ) -> Result<Self, SpiError<'a>> {
        let cs = OutPin::new(cs).map_err(SpiError::Pin)?;
        // Idle: high (not selected).
        cs.set(true);
        let bus = match (bus.pins, software) {
            (SpiBusPins::Software { .. }, Some([sclk, mosi, miso])) => {
                let sclk = OutPin::new(sclk).map_err(SpiError::Pin)?;
                sclk.set(bus.mode & 2 != 0);
                Bus::Software {
                    sclk,
                    mosi: OutPin::new(mosi).map_err(SpiError::Pin)?,
                    miso: InPin::new(miso).map_err(SpiError::Pin)?,
                    mode: bus.mode,
                    half: (crate::clocks::SYSCLK_HZ / 2 / bus.speed.max(1)).max(1),
                }
            }
            (SpiBusPins::Hardware(name), _) => {
                if let Some(name) = name.filter(|n| {
                    !n.trim()
                        .eq_ignore_ascii_case(onechip_app::pin_check::BOARD_SPI_BUS)
                }) {
                    return Err(SpiError::Bus(name));
                }
                spi1_setup();
                Bus::Spi1 {
                    cfg1: reg::CFG1_DSIZE_8
                        | reg::CFG1_CRCSIZE_8
                        | mbr(bus.speed) << reg::CFG1_MBR_SHIFT,
                    cfg2: reg::CFG2_MASTER
                        | reg::CFG2_SSM
                        | reg::CFG2_AFCNTR
                        | if bus.mode & 1 != 0 { reg::CFG2_CPHA } else { 0 }
                        | if bus.mode & 2 != 0 { reg::CFG2_CPOL } else { 0 },
                }
            }
            (SpiBusPins::Software { sclk, .. }, None) => return Err(SpiError::Pin(BadPin(sclk))),
        };
        Ok(Self { cs, bus })
    }

    /// The chip on `bus` (a temperature chip, a TMC driver; `owner` in
    /// errors) of `setup`: its chip select and (software bus) clock and
    /// data pins resolved through `[board_pins]`.
    pub fn configured(
        setup: &PrinterSetup<'_>,
        bus: &SpiBus<'_>,
        owner: &dyn core::fmt::Display,
    ) -> Result<Self, ErrorText> {
        let fail = |e: &dyn core::fmt::Display| error_text(&format_args!("{owner}: {e}"));
        let pin = |written| setup.resolve_pin(written).map_err(|e| fail(&e));
        let cs = pin(bus.cs_pin)?;
        let software = match bus.pins {
            SpiBusPins::Software { sclk, mosi, miso } => Some([pin(sclk)?, pin(mosi)?, pin(miso)?]),
            SpiBusPins::Hardware(_) => None,
        };
        let names = software
            .as_ref()
            .map(|[a, b, c]| [a.as_str(), b.as_str(), c.as_str()]);
        Self::new(bus, &cs, names).map_err(|e| fail(&e))
    }

    /// One transfer, chip selected throughout: `data` out, replies in.
    /// The bus takes the chip's mode (clock polarity) before the chip is
    /// selected.
    pub fn transfer(&mut self, data: &mut [u8]) {
        let done = match &self.bus {
            Bus::Spi1 { cfg1, cfg2 } => {
                spi1_configure(*cfg1, *cfg2);
                self.cs.set(false);
                let done = spi1_transfer(data);
                self.cs.set(true);
                done
            }
            Bus::Software {
                sclk,
                mosi,
                miso,
                mode,
                half,
            } => {
                sclk.set(mode & 2 != 0);
                self.cs.set(false);
                software_transfer(sclk, mosi, miso, *mode, *half, data);
                self.cs.set(true);
                true
            }
        };
        if !done {
            data.fill(0);
        }
    }
}

/// SPI1's divider for at most `speed` Hz: kernel / 2^(MBR+1), MBR 0..=7
/// (the fastest not above the request, as Klipper picks; the slowest if
/// none is).
fn mbr(speed: u32) -> u32 {
    (0..8)
        .find(|&m| SPI1_KERNEL_HZ >> (m + 1) <= speed)
        .unwrap_or(7)
}

/// Clocks SPI1 and gives it PA5 (SCK), PA6 (MISO) and PA7 (MOSI), AF5.
fn spi1_setup() {
    use pac::gpio::vals;
    embassy_stm32::rcc::enable_and_reset::<embassy_stm32::peripherals::SPI1>();
    let port = pac::GPIOA;
    for pin in 5..=7 {
        port.afr(0).modify(|w| w.set_afr(pin, reg::AF_SPI1));
        port.ospeedr()
            .modify(|w| w.set_ospeedr(pin, vals::Ospeedr::HIGH_SPEED));
        port.moder()
            .modify(|w| w.set_moder(pin, vals::Moder::ALTERNATE));
    }
}

/// Polls `done` up to [`SPI1_POLLS`] times; true once it is.
fn poll(mut done: impl FnMut() -> bool) -> bool {
    (0..SPI1_POLLS).any(|_| done())
}

/// SPI1 disabled and configured for a chip (RM0468: CFG1 and CFG2 are
/// written while SPE is 0; with AFCNTR the clock pin then idles at the
/// new polarity).
fn spi1_configure(cfg1: u32, cfg2: u32) {
    use pac::spi::regs::{Cfg1, Cfg2, Cr1};
    let spi = pac::SPI1;
    spi.cr1().write_value(Cr1(reg::CR1_SSI));
    spi.cfg1().write_value(Cfg1(cfg1));
    spi.cfg2().write_value(Cfg2(cfg2));
}

/// One full-duplex transfer on SPI1, configured (RM0468's master
/// sequence: TSIZE bytes, enable, start, a byte in for each out, wait for
/// the end, clear it, disable); false if a wait timed out.
fn spi1_transfer(data: &mut [u8]) -> bool {
    use pac::spi::regs::{Cr1, Cr2, Ifcr};
    let spi = pac::SPI1;
    spi.cr2().write_value(Cr2(data.len() as u32 & 0xffff));
    spi.cr1().write_value(Cr1(reg::CR1_SSI | reg::CR1_SPE));
    spi.cr1()
        .write_value(Cr1(reg::CR1_SSI | reg::CR1_SPE | reg::CR1_CSTART));
    let mut ok = true;
    for byte in data.iter_mut() {
        ok = ok && poll(|| spi.sr().read().0 & reg::SR_TXP != 0);
        if !ok {
            break;
        }
        spi.txdr8().write_value(*byte);
        ok = poll(|| spi.sr().read().0 & reg::SR_RXP != 0);
        if !ok {
            break;
        }
        *byte = spi.rxdr8().read();
    }
    ok = ok && poll(|| spi.sr().read().0 & reg::SR_EOT != 0);
    spi.ifcr().write_value(Ifcr(reg::IFCR_EOT_TXTF));
    spi.cr1().write_value(Cr1(reg::CR1_SSI));
    ok
}

/// One transfer bit-banged, most significant bit first, in SPI `mode`
/// (CPOL bit 1, CPHA bit 0), `half` CPU cycles per half period.
fn software_transfer(
    sclk: &OutPin,
    mosi: &OutPin,
    miso: &InPin,
    mode: u8,
    half: u32,
    data: &mut [u8],
) {
    let idle = mode & 2 != 0;
    let late = mode & 1 != 0;
    for byte in data.iter_mut() {
        let mut received = 0u8;
        for bit in (0..8).rev() {
            let out = *byte & (1 << bit) != 0;
            if late {
                sclk.set(!idle);
            }
            mosi.set(out);
            cortex_m::asm::delay(half);
            sclk.set(if late { idle } else { !idle });
            received = received << 1 | u8::from(miso.is_active());
            cortex_m::asm::delay(half);
            if !late {
                sclk.set(idle);
            }
        }
        *byte = received;
    }
}
