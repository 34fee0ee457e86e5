//! Taking control from the bootloader, as Klipper's start-up does
//! (src/generic/armcm_boot.c, src/stm32/stm32h7.c).
//!
//! BTT's SD-card bootloader jumps to the application at 0x0802_0000 with
//! whatever it set up still in place: interrupts possibly enabled and
//! pending, its vector table in VTOR, SysTick running, PLL1 driving the
//! core, DMA streams and caches in any state. Two steps undo that:
//!
//! - `__pre_init` (assembly, run by cortex-m-rt's reset handler before RAM
//!   is initialised): interrupts off, CONTROL and BASEPRI cleared, the stack
//!   pointer set to `_stack_start` and VTOR to this image's vector table,
//!   every NVIC interrupt disabled and un-pended with its priority reset,
//!   SysTick stopped and its and PendSV's pending bits cleared, system
//!   handler priorities reset; then interrupts back on (nothing can fire:
//!   every source is disabled).
//! - [`take_control`] (first thing in `main`): both caches off (the
//!   D-cache cleaned first: cortex-m-rt initialised RAM through it if the
//!   bootloader left it on), the bus masters the bootloader may have left
//!   running (DMA1/2, MDMA, BDMA, SDMMC1/2's IDMA, USB, Ethernet, DMA2D)
//!   reset, the peripheral clocks Klipper turns off turned off, the
//!   stepper interrupt's code and data loaded into the TCMs
//!   ([`onechip_board_rt::tcm`]), the clock tree back to its reset state (HSI, every
//!   PLL off, kernel clock muxes at reset), because PLL registers are
//!   write-protected while the PLL runs and embassy-stm32 0.6's
//!   `rcc::init` switches the core to HSI but reprograms PLL1 without
//!   stopping it; then the MPU's regions (the DMA buffers non-cacheable,
//!   the loaded ITCM read-only) and both caches on ([`crate::cache`]),
//!   with no DMA running.
//!
//! `cargo xtask image` checks that the reset handler calls this
//! `__pre_init` and that it begins with `cpsid i` and writes SP and VTOR,
//! and that `Reset` reaches the TCM load and the cache set-up.

use core::arch::global_asm;
use embassy_stm32::pac;
use embassy_stm32::pac::rcc::regs;
use embassy_stm32::pac::rcc::vals::Sw;

// Registers (Cortex-M7): VTOR 0xE000ED08; NVIC ICER0..7 0xE000E180,
// ICPR0..7 0xE000E280, IPR0..59 0xE000E400; SYST_CSR 0xE000E010; ICSR
// 0xE000ED04 (PENDSVCLR bit 27, PENDSTCLR bit 25); SHPR1..3 0xE000ED18.
// Uses r0-r3 only and no stack: it runs before the stack pointer is ours.
global_asm!(
    ".section .text.__pre_init,\"ax\",%progbits",
    ".global __pre_init",
    ".type __pre_init,%function",
    ".thumb_func",
    "__pre_init:",
    "cpsid i",
    "movs r0, #0",
    "msr basepri, r0",
    "msr control, r0",
    "isb",
    "ldr r0, =_stack_start",
    "msr msp, r0",
    "ldr r0, =0xE000ED08",
    "ldr r1, =__vector_table",
    "str r1, [r0]",
    "dsb",
    "isb",
    "ldr r0, =0xE000E180",
    "ldr r1, =0xE000E280",
    "movs r2, #0",
    "mvns r3, r2",
    "3:",
    "str r3, [r0, r2, lsl #2]",
    "str r3, [r1, r2, lsl #2]",
    "adds r2, #1",
    "cmp r2, #8",
    "bne 3b",
    "dsb",
    "isb",
    "ldr r0, =0xE000E400",
    "movs r2, #0",
    "movs r3, #0",
    "4:",
    "str r3, [r0, r2, lsl #2]",
    "adds r2, #1",
    "cmp r2, #60",
    "bne 4b",
    "ldr r0, =0xE000E010",
    "str r3, [r0]",
    "ldr r0, =0xE000ED04",
    "ldr r1, =0x0A000000",
    "str r1, [r0]",
    "ldr r0, =0xE000ED18",
    "str r3, [r0]",
    "str r3, [r0, #4]",
    "str r3, [r0, #8]",
    "dsb",
    "isb",
    "cpsie f",
    "cpsie i",
    "bx lr",
    ".ltorg",
    ".size __pre_init, . - __pre_init",
);

/// Brings caches, bus masters, the TCMs and the clock tree to a known
/// state before `embassy_stm32::init` configures them, and turns the
/// caches on. Call first thing in `main`; the proof that the TCMs are
/// loaded starts the stepper interrupt.
pub fn take_control() -> onechip_board_rt::tcm::Loaded {
    caches_off();
    stop_bus_masters();
    let loaded = onechip_board_rt::tcm::load();
    reset_clock_tree();
    crate::cache::enable(&loaded);
    loaded
}

/// Both caches off and invalidated, the D-cache cleaned first (RAM
/// initialisation may have gone through it), so that the MPU can be set
/// up before they go on again.
fn caches_off() {
    // SAFETY: only this start-up code uses the core peripherals here, before
    // anything else runs.
    let mut core = unsafe { cortex_m::Peripherals::steal() };
    core.SCB.disable_dcache(&mut core.CPUID);
    core.SCB.disable_icache();
}

/// Resets every peripheral that can write memory on its own (a stream the
/// bootloader left running would keep writing into this image's RAM), and
/// turns off the peripheral clocks Klipper turns off at start-up; embassy
/// enables (and resets) what it uses.
fn stop_bus_masters() {
    let rcc = pac::RCC;
    let ahb1 = |on: bool| {
        rcc.ahb1rstr().modify(|w| {
            w.set_dma1rst(on);
            w.set_dma2rst(on);
            w.set_ethrst(on);
            w.set_usb_otg_hsrst(on);
        })
    };
    let ahb2 = |on: bool| rcc.ahb2rstr().modify(|w| w.set_sdmmc2rst(on));
    let ahb3 = |on: bool| {
        rcc.ahb3rstr().modify(|w| {
            w.set_mdmarst(on);
            w.set_dma2drst(on);
            w.set_sdmmc1rst(on);
        })
    };
    let ahb4 = |on: bool| rcc.ahb4rstr().modify(|w| w.set_bdmarst(on));
    for on in [true, false] {
        ahb1(on);
        ahb2(on);
        ahb3(on);
        ahb4(on);
    }
    rcc.ahb1enr().write_value(regs::Ahb1enr(0));
    rcc.apb1lenr().write_value(regs::Apb1lenr(0));
    rcc.apb1henr().write_value(regs::Apb1henr(0));
    rcc.apb2enr().write_value(regs::Apb2enr(0));
    rcc.apb3enr().write_value(regs::Apb3enr(0));
    rcc.apb4enr().write_value(regs::Apb4enr(0));
}

/// The clock tree as after reset: the core on HSI (64 MHz, within every
/// bus's limit at any voltage scale and flash latency the bootloader may
/// have left), bus prescalers at /1, HSE, CSI, HSI48 and every PLL off,
/// clock interrupts off and the kernel clock muxes at their reset values.
fn reset_clock_tree() {
    let rcc = pac::RCC;
    rcc.cr().modify(|w| w.set_hsion(true));
    while !rcc.cr().read().hsirdy() {}
    // SW = HSI; MCO, TIMPRE and the rest at reset.
    rcc.cfgr().write_value(regs::Cfgr(0));
    while rcc.cfgr().read().sws() != Sw::HSI {}
    rcc.d1cfgr().write_value(regs::D1cfgr(0));
    rcc.d2cfgr().write_value(regs::D2cfgr(0));
    rcc.d3cfgr().write_value(regs::D3cfgr(0));
    rcc.cr().modify(|w| {
        for pll in 0..3 {
            w.set_pllon(pll, false);
        }
        w.set_hseon(false);
        w.set_csion(false);
        w.set_hsi48on(false);
    });
    while (0..3).any(|pll| rcc.cr().read().pllrdy(pll)) || rcc.cr().read().hserdy() {}
    rcc.cier().write_value(regs::Cier(0));
    rcc.d1ccipr().write_value(regs::D1ccipr(0));
    rcc.d2ccip1r().write_value(regs::D2ccip1r(0));
    rcc.d2ccip2r().write_value(regs::D2ccip2r(0));
    rcc.d3ccipr().write_value(regs::D3ccipr(0));
}
