//! Pin map and fixed resources of the BigTreeTech Octopus Pro v1.1 with the
//! STM32H723ZE (the only board supported so far; one such file per board).
//!
//! Facts of the board: 25 MHz crystal (`onechip_board_rt::clocks::HSE`); BTT's SD-card bootloader in the first
//! 128 KiB of flash (application at 0x0802_0000, see `memory.x`); USB-C on the
//! MCU's OTG_HS controller with its internal full-speed PHY (PA11/PA12); the
//! micro-SD slot on SDMMC1 in 4-bit mode (PC8..PC12, PD2).
//!
//! The stepper, heater and fan pins of Klipper's
//! `generic-bigtreetech-octopus-pro-v1.1.cfg` (for example stepper_x step PF13,
//! dir PF12, enable !PF14) are named in `printer.cfg` and resolved at run time.

use embassy_stm32::Peri;
use embassy_stm32::adc::{AdcChannel, AnyAdcChannel};
use embassy_stm32::peripherals::{
    ADC3, PA11, PA12, PC8, PC9, PC10, PC11, PC12, PD2, PF3, PF4, PF5, PF6, PF7, SDMMC1, USB_OTG_HS,
};

/// The USB-C connector.
pub struct UsbPins {
    /// The USB controller.
    pub otg: Peri<'static, USB_OTG_HS>,
    /// D+.
    pub dp: Peri<'static, PA12>,
    /// D-.
    pub dm: Peri<'static, PA11>,
}

/// The micro-SD slot.
pub struct SdPins {
    /// The SD/MMC controller.
    pub sdmmc: Peri<'static, SDMMC1>,
    /// Clock.
    pub clk: Peri<'static, PC12>,
    /// Command line.
    pub cmd: Peri<'static, PD2>,
    /// Data lines 0..3.
    pub data: (
        Peri<'static, PC8>,
        Peri<'static, PC9>,
        Peri<'static, PC10>,
        Peri<'static, PC11>,
    ),
}

/// The thermistor inputs TB, T0..T3 (PF3..PF7, on ADC3) and ADC3.
pub struct ThermistorPins {
    /// The ADC that reads them.
    pub adc: Peri<'static, ADC3>,
    tb: Option<Peri<'static, PF3>>,
    t0: Option<Peri<'static, PF4>>,
    t1: Option<Peri<'static, PF5>>,
    t2: Option<Peri<'static, PF6>>,
    t3: Option<Peri<'static, PF7>>,
}

impl ThermistorPins {
    /// The ADC channel of the thermistor input named `name` (`PF4`), once;
    /// None for any other pin.
    pub fn channel(&mut self, name: &str) -> Option<AnyAdcChannel<'static, ADC3>> {
        let is = |pin: &str| name.trim().eq_ignore_ascii_case(pin);
        if is("PF3") {
            self.tb.take().map(AdcChannel::degrade_adc)
        } else if is("PF4") {
            self.t0.take().map(AdcChannel::degrade_adc)
        } else if is("PF5") {
            self.t1.take().map(AdcChannel::degrade_adc)
        } else if is("PF6") {
            self.t2.take().map(AdcChannel::degrade_adc)
        } else if is("PF7") {
            self.t3.take().map(AdcChannel::degrade_adc)
        } else {
            None
        }
    }
}

/// The board's fixed connections, taken out of the chip's peripherals.
pub struct Board {
    /// USB console.
    pub usb: UsbPins,
    /// SD card.
    pub sd: SdPins,
    /// Thermistor inputs.
    pub thermistors: ThermistorPins,
}

impl Board {
    /// Splits the chip's peripherals into the board's named connections.
    pub fn take(p: embassy_stm32::Peripherals) -> Self {
        Self {
            usb: UsbPins {
                otg: p.USB_OTG_HS,
                dp: p.PA12,
                dm: p.PA11,
            },
            sd: SdPins {
                sdmmc: p.SDMMC1,
                clk: p.PC12,
                cmd: p.PD2,
                data: (p.PC8, p.PC9, p.PC10, p.PC11),
            },
            thermistors: ThermistorPins {
                adc: p.ADC3,
                tb: Some(p.PF3),
                t0: Some(p.PF4),
                t1: Some(p.PF5),
                t2: Some(p.PF6),
                t3: Some(p.PF7),
            },
        }
    }
}
