//! Clock tree: 520 MHz core from the 25 MHz crystal.
//!
//! PLL1: 25 MHz / 5 = 5 MHz reference, x104 = 520 MHz VCO (wide range),
//! P / 1 = 520 MHz system clock, Q / 4 = 130 MHz for SDMMC1. AXI/AHB at
//! 260 MHz, APB buses at 130 MHz, timers at 260 MHz. 520 MHz needs voltage
//! scale 0. PLL2 and PLL3 stay off.
//!
//! USB runs from the internal 48 MHz oscillator (HSI48), which the clock
//! recovery system (CRS) trims continuously against the host's USB
//! start-of-frame packets (`sync_from_usb`), as USB's ±0.25 % needs.
//!
//! ADC3 (the thermistors) runs from the peripheral clock `per_ck` switched
//! to the crystal: 25 MHz, undivided by ADC3's prescaler, half the 50 MHz
//! limit embassy-stm32 applies to H7 ADCs (Klipper runs its H7 ADCs at
//! 25 MHz too). Its kernel-clock mux (`adcsel`) would otherwise stay at its
//! reset value, PLL2's P output, which is off. SPI1 (the SPI temperature
//! chips) runs from `per_ck` too: 25 MHz, divided by its baud-rate
//! divider (its reset mux, PLL1's Q output, would work too, but 130 MHz
//! divides to 4 MHz less closely).
//!
//! [`RCC`] is a constant so that the assertions below check the very
//! configuration `embassy_stm32::init` applies, at compile time: ADC3's
//! kernel clock must come from a running clock within its limit, USB must
//! run from a CRS-trimmed HSI48, and the core and timer clocks must be the
//! ones the rest of the firmware counts with.

use embassy_stm32::Config;
use embassy_stm32::rcc::{
    self, AHBPrescaler, APBPrescaler, Hse, HseMode, Hsi48Config, Pll, PllDiv, PllMul, PllPreDiv,
    PllSource, Sysclk, VoltageScale, mux,
};
use embassy_stm32::time::Hertz;

/// Core clock, in Hz.
pub const SYSCLK_HZ: u32 = 520_000_000;

/// ADC3's clock (its kernel clock after its prescaler), Hz.
pub const ADC3_HZ: u32 = 25_000_000;
/// ADC3_COMMON CCR.PRESC: the kernel clock divided by 1.
pub const ADC3_PRESC: u32 = 0b0000;
/// The divider [`ADC3_PRESC`] stands for.
const ADC3_PRESC_DIV: u32 = 1;
/// The fastest ADC clock embassy-stm32 0.6 accepts on the H7
/// (`MAX_ADC_CLK_FREQ`).
const ADC3_MAX_HZ: u32 = 50_000_000;

/// Frequency of the Octopus Pro's crystal (HSE).
pub const HSE: embassy_stm32::time::Hertz = embassy_stm32::time::Hertz(25_000_000);

/// The clock tree `embassy_stm32::init` sets up.
pub const RCC: rcc::Config = {
    let mut rcc = rcc::Config::new();
    rcc.hse = Some(Hse {
        freq: HSE,
        mode: HseMode::Oscillator,
    });
    rcc.hsi48 = Some(Hsi48Config {
        sync_from_usb: true,
    });
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
    rcc.mux.persel = mux::Persel::HSE;
    rcc.mux.adcsel = mux::Adcsel::PER;
    rcc.mux.spi123sel = mux::Saisel::PER;
    rcc
};

/// SPI1's kernel clock (`per_ck`, the crystal), Hz: the SPI temperature
/// chips' bus divides it.
pub const SPI1_KERNEL_HZ: u32 = 25_000_000;

// SPI1 runs from per_ck, the crystal.
const _: () = assert!(
    RCC.mux.spi123sel.to_bits() == mux::Saisel::PER.to_bits()
        && RCC.mux.persel.to_bits() == mux::Persel::HSE.to_bits()
        && is(hse_hz(&RCC), SPI1_KERNEL_HZ),
    "SPI1's kernel clock is not SPI1_KERNEL_HZ"
);

// ADC3's kernel clock is a running clock, and ADC3 runs at ADC3_HZ, within
// its limit.
const _: () = match adc_kernel_hz(&RCC) {
    Some(hz) => assert!(
        hz / ADC3_PRESC_DIV == ADC3_HZ && ADC3_HZ <= ADC3_MAX_HZ,
        "ADC3's clock is not ADC3_HZ, or above its limit"
    ),
    None => panic!("mux.adcsel selects a clock that is off"),
};

// USB runs from HSI48, trimmed by the CRS against USB start-of-frame.
const _: () = match RCC.hsi48 {
    Some(hsi48) => assert!(
        hsi48.sync_from_usb && RCC.mux.usbsel.to_bits() == mux::Usbsel::HSI48.to_bits(),
        "USB must run from HSI48 with CRS sync from USB SOF"
    ),
    None => panic!("HSI48 is off"),
};

// The core runs at the rate the firmware counts with.
const _: () = assert!(is(sysclk_hz(&RCC), SYSCLK_HZ), "SYSCLK_HZ is wrong");

/// The clock of the APB1 timers (TIM2, TIM5), Hz, as the tree above
/// makes it.
pub const APB1_TIMER_HZ: u32 = apb1_timer_hz(&RCC);

/// USART2's kernel clock, Hz: `rcc_pclk1` (RM0468, RCC_D2CCIP2R's
/// USART234578SEL at its reset value 0, which embassy's zeroed mux keeps),
/// 520 MHz / 2 (HPRE) / 2 (D2PPRE1) = 130 MHz. The link to the secondary
/// MCUs divides it (`onechip_sched::serial::divisor`): 250,000 bit/s is
/// BRR 520 at 16× oversampling, exact.
pub const USART2_KERNEL_HZ: u32 = apb1_hz(&RCC);

// USART2 runs from PCLK1, at the rate the link divides.
const _: () = assert!(
    RCC.mux.usart234578sel.to_bits() == mux::Usart234578sel::PCLK1.to_bits()
        && USART2_KERNEL_HZ == 130_000_000,
    "USART2's kernel clock is not PCLK1 at 130 MHz"
);

/// The embassy configuration for this board: clocks, and every DMA interrupt
/// below the stepper timer's priority.
pub fn config() -> Config {
    let mut config = Config::default();
    config.rcc = RCC;
    config.bdma_interrupt_priority = crate::priority::PERIPHERALS;
    config.dma_interrupt_priority = crate::priority::PERIPHERALS;
    config.mdma_interrupt_priority = crate::priority::PERIPHERALS;
    config
}

/// True if `hz` is `Some(expected)` (`==` on options is not const).
const fn is(hz: Option<u32>, expected: u32) -> bool {
    matches!(hz, Some(hz) if hz == expected)
}

/// HSI's frequency (after its divider), if on.
const fn hsi_hz(rcc: &rcc::Config) -> Option<u32> {
    match rcc.hsi {
        // HSIDIV: 0 = /1, 1 = /2, 2 = /4, 3 = /8.
        Some(div) => Some(rcc::HSI_FREQ.0 >> div.to_bits()),
        None => None,
    }
}

/// HSE's frequency, if on.
const fn hse_hz(rcc: &rcc::Config) -> Option<u32> {
    match rcc.hse {
        Some(Hse {
            freq: Hertz(hz), ..
        }) => Some(hz),
        None => None,
    }
}

/// CSI's frequency, if on.
const fn csi_hz(rcc: &rcc::Config) -> Option<u32> {
    if rcc.csi { Some(rcc::CSI_FREQ.0) } else { None }
}

/// The VCO frequency of `pll`, if it and its source are on.
const fn vco_hz(rcc: &rcc::Config, pll: Option<Pll>) -> Option<u32> {
    let Some(pll) = pll else {
        return None;
    };
    let source = match pll.source.to_bits() {
        s if s == PllSource::HSI.to_bits() => hsi_hz(rcc),
        s if s == PllSource::HSE.to_bits() => hse_hz(rcc),
        s if s == PllSource::CSI.to_bits() => csi_hz(rcc),
        _ => None,
    };
    match source {
        // DIVM is the divider; DIVN is the multiplier less one.
        Some(hz) => Some(hz / pll.prediv.to_bits() as u32 * (pll.mul.to_bits() as u32 + 1)),
        None => None,
    }
}

/// A PLL output: the VCO over `div` (DIVx is the divider less one), if
/// both are on.
const fn pll_out(vco: Option<u32>, div: Option<PllDiv>) -> Option<u32> {
    match (vco, div) {
        (Some(hz), Some(div)) => Some(hz / (div.to_bits() as u32 + 1)),
        _ => None,
    }
}

/// The system clock, if its source is on.
const fn sysclk_hz(rcc: &rcc::Config) -> Option<u32> {
    match rcc.sys.to_bits() {
        s if s == Sysclk::HSI.to_bits() => hsi_hz(rcc),
        s if s == Sysclk::HSE.to_bits() => hse_hz(rcc),
        s if s == Sysclk::CSI.to_bits() => csi_hz(rcc),
        s if s == Sysclk::PLL1_P.to_bits() => match rcc.pll1 {
            Some(pll) => pll_out(vco_hz(rcc, rcc.pll1), pll.divp),
            None => None,
        },
        _ => None,
    }
}

/// The divider an AHB prescaler stands for (HPRE: 0..=7 /1, then /2../512
/// skipping /32).
const fn ahb_div(pre: AHBPrescaler) -> u32 {
    match pre.to_bits() {
        0..=7 => 1,
        bits @ 8..=11 => 1 << (bits - 7),
        bits => 1 << (bits - 6),
    }
}

/// The divider an APB prescaler stands for (PPRE: 0..=3 /1, then /2../16).
const fn apb_div(pre: APBPrescaler) -> u32 {
    match pre.to_bits() {
        0..=3 => 1,
        bits => 1 << (bits - 3),
    }
}

/// The APB1 clock (`rcc_pclk1`), Hz; 0 if the system clock is off.
const fn apb1_hz(rcc: &rcc::Config) -> u32 {
    let Some(sys) = sysclk_hz(rcc) else {
        return 0;
    };
    sys / ahb_div(rcc.d1c_pre) / ahb_div(rcc.ahb_pre) / apb_div(rcc.apb1_pre)
}

/// The APB1 timers' clock (TIM2..TIM7): twice the APB1 clock, at most the
/// AHB clock (TIMPRE = 0).
const fn apb1_timer_hz(rcc: &rcc::Config) -> u32 {
    let Some(sys) = sysclk_hz(rcc) else {
        return 0;
    };
    let hclk = sys / ahb_div(rcc.d1c_pre) / ahb_div(rcc.ahb_pre);
    match apb_div(rcc.apb1_pre) {
        1 => hclk,
        div => hclk / div * 2,
    }
}

/// ADC1/2/3's kernel clock, as `mux.adcsel` selects it, if that clock is
/// on.
const fn adc_kernel_hz(rcc: &rcc::Config) -> Option<u32> {
    match rcc.mux.adcsel.to_bits() {
        s if s == mux::Adcsel::PLL2_P.to_bits() => match rcc.pll2 {
            Some(pll) => pll_out(vco_hz(rcc, rcc.pll2), pll.divp),
            None => None,
        },
        s if s == mux::Adcsel::PLL3_R.to_bits() => match rcc.pll3 {
            Some(pll) => pll_out(vco_hz(rcc, rcc.pll3), pll.divr),
            None => None,
        },
        s if s == mux::Adcsel::PER.to_bits() => match rcc.mux.persel.to_bits() {
            p if p == mux::Persel::HSI.to_bits() => hsi_hz(rcc),
            p if p == mux::Persel::CSI.to_bits() => csi_hz(rcc),
            p if p == mux::Persel::HSE.to_bits() => hse_hz(rcc),
            _ => None,
        },
        _ => None,
    }
}
