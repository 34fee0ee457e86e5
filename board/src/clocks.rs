//! Clock tree: 520 MHz core from the 25 MHz crystal.
//!
//! PLL1: 25 MHz / 5 = 5 MHz reference, x104 = 520 MHz VCO (wide range),
//! P / 1 = 520 MHz system clock, Q / 4 = 130 MHz for SDMMC1. AXI/AHB at
//! 260 MHz, APB buses at 130 MHz, timers at 260 MHz. 520 MHz needs voltage
//! scale 0. USB runs from the internal 48 MHz oscillator (HSI48, trimmed by
//! the clock recovery system on USB start-of-frame).

use embassy_stm32::Config;
use embassy_stm32::rcc::{
    AHBPrescaler, APBPrescaler, Hse, HseMode, Pll, PllDiv, PllMul, PllPreDiv, PllSource, Sysclk,
    VoltageScale, mux,
};

/// Core clock, in Hz.
pub const SYSCLK_HZ: u32 = 520_000_000;

/// The embassy configuration for this board: clocks, and every DMA interrupt
/// below the stepper timer's priority.
pub fn config() -> Config {
    let mut config = Config::default();
    let rcc = &mut config.rcc;
    rcc.hse = Some(Hse {
        freq: crate::octopus_pro_v1_1::HSE,
        mode: HseMode::Oscillator,
    });
    rcc.hsi48 = Some(Default::default());
    rcc.pll1 = Some(Pll {
        source: PllSource::HSE,
        prediv: PllPreDiv::DIV5,
        mul: PllMul::MUL104,
        divp: Some(PllDiv::DIV1),
        divq: Some(PllDiv::DIV4),
        divr: None,
    });
    rcc.sys = Sysclk::PLL1_P;
    rcc.d1c_pre = AHBPrescaler::DIV1;
    rcc.ahb_pre = AHBPrescaler::DIV2;
    rcc.apb1_pre = APBPrescaler::DIV2;
    rcc.apb2_pre = APBPrescaler::DIV2;
    rcc.apb3_pre = APBPrescaler::DIV2;
    rcc.apb4_pre = APBPrescaler::DIV2;
    rcc.voltage_scale = VoltageScale::Scale0;
    rcc.mux.usbsel = mux::Usbsel::HSI48;
    rcc.mux.sdmmcsel = mux::Sdmmcsel::PLL1_Q;
    config.bdma_interrupt_priority = crate::priority::PERIPHERALS;
    config.dma_interrupt_priority = crate::priority::PERIPHERALS;
    config.mdma_interrupt_priority = crate::priority::PERIPHERALS;
    config
}
