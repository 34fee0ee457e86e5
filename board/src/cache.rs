//! The Cortex-M7's instruction and data caches (32 KiB each on the
//! STM32H723), on from boot, and the MPU region that keeps DMA coherent.
//!
//! The D-cache is write-back, write-allocate on the SRAMs (the default
//! memory map, which the MPU keeps as the background for privileged code):
//! a bus master other than the core would read stale RAM or have its
//! writes hidden by cached lines. The firmware's only such masters:
//!
//! - SDMMC1's internal DMA (IDMA), which embassy-stm32 points straight at
//!   the buffers it is given and does no cache maintenance on: its buffers
//!   live in `.dma_buffers` ([`crate::sd_card`]), a 1 KiB block at the top
//!   of AXI SRAM that MPU region 0 ([`enable`]) makes normal, shareable,
//!   non-cacheable memory before the D-cache goes on (so no line of it is
//!   ever cached);
//! - USB OTG_HS: embassy's driver moves packets through the core's FIFO
//!   registers (its internal DMA stays off), so USB needs nothing.
//!
//! TCM (the stepper interrupt's code and data, [`onechip_board_rt::tcm`]) is never
//! cached. Once loaded, the ITCM is made read-only (MPU region 1): a
//! stray write there (a pointer near null) faults, and the fault handler
//! turns everything off, instead of corrupting the stepper interrupt.
//! Code in flash never changes while the firmware runs, so the I-cache
//! needs no maintenance after it is invalidated and enabled.
//!
//! Klipper's H7 start-up (src/stm32/stm32h7.c) has no cache calls of its
//! own; the sequence here is ARM's (as CMSIS's `SCB_EnableICache` and
//! `SCB_EnableDCache`: invalidate, enable, barriers), as the cortex-m
//! crate implements it, after the MPU.

unsafe extern "C" {
    /// The `DMA` memory region of board/memory.x (its bounds): a power of
    /// two of at least 32 bytes, aligned to its size (asserted there), as
    /// one MPU region needs.
    static __dma_region_start: u8;
    static __dma_region_end: u8;
}

/// MPU_RASR fields (ARMv7-M): execute never, full access, read-only,
/// normal memory non-cacheable (TEX 0b001, C 0, B 0), shareable, region
/// enabled.
const RASR_XN: u32 = 1 << 28;
const RASR_AP_FULL: u32 = 0b011 << 24;
const RASR_AP_READ_ONLY: u32 = 0b110 << 24;
const RASR_TEX_NORMAL_NONCACHEABLE: u32 = 0b001 << 19;
const RASR_SHAREABLE: u32 = 1 << 18;
const RASR_ENABLE: u32 = 1;
/// MPU_RBAR: the REGION field holds the region number.
const RBAR_VALID: u32 = 1 << 4;
/// MPU_CTRL: enabled, with the default memory map as background for
/// privileged code (the whole firmware).
const CTRL_ENABLE: u32 = 1;
const CTRL_PRIVDEFENA: u32 = 1 << 2;

/// The DMA buffers' MPU region number.
const DMA_REGION: u32 = 0;
/// The ITCM's MPU region number, its base and size (RM0468's reset
/// default; board/budget.toml's `itcm_base` and `itcm_kib`).
const ITCM_REGION: u32 = 1;
const ITCM_BASE: u32 = 0x0000_0000;
const ITCM_BYTES: u32 = 64 * 1024;

/// MPU_RASR of a region of `size` bytes (a power of two of at least 32)
/// with the attribute bits `attributes`, enabled: the SIZE field (bits
/// 5:1) makes the region 2^(SIZE + 1) bytes.
const fn rasr(size: u32, attributes: u32) -> u32 {
    let size_field = size.trailing_zeros().saturating_sub(1);
    attributes | size_field << 1 | RASR_ENABLE
}

/// The DMA region's attributes: normal, shareable, non-cacheable,
/// read-write, execute never.
const DMA_ATTRIBUTES: u32 = RASR_XN | RASR_AP_FULL | RASR_TEX_NORMAL_NONCACHEABLE | RASR_SHAREABLE;
/// The ITCM's once loaded: read-only, executable (TCM is never cached
/// whatever the type says).
const ITCM_ATTRIBUTES: u32 = RASR_AP_READ_ONLY | RASR_TEX_NORMAL_NONCACHEABLE;

// The encoding against the ARMv7-M Architecture Reference Manual's
// MPU_RASR, worked by hand. DMA, 1 KiB: XN 0x1000_0000, AP 0b011
// 0x0300_0000, TEX 0b001 0x0008_0000, S 0x0004_0000, SIZE 9 0x12, ENABLE
// (32 bytes: SIZE 4). ITCM, 64 KiB: AP 0b110 0x0600_0000, TEX 0b001,
// SIZE 15 0x1E, ENABLE.
const _: () = assert!(rasr(1024, DMA_ATTRIBUTES) == 0x130C_0013);
const _: () = assert!(rasr(32, DMA_ATTRIBUTES) == 0x130C_0009);
const _: () = assert!(rasr(ITCM_BYTES, ITCM_ATTRIBUTES) == 0x0608_001F);
const _: () = assert!(
    ITCM_BASE.is_multiple_of(ITCM_BYTES),
    "an MPU region is aligned to its size"
);

/// Makes the DMA region non-cacheable and the ITCM read-only, then
/// invalidates and enables the I-cache and the D-cache. Call once at
/// boot, with the D-cache off, no DMA running and the ITCM loaded (which
/// the proof `_tcm` shows; [`crate::boot::take_control`]).
pub fn enable(_tcm: &onechip_board_rt::tcm::Loaded) {
    onechip_caches_enable();
}

/// [`enable`]'s work, out of line and by name for `cargo xtask image`'s
/// boot-path check.
#[unsafe(no_mangle)]
#[inline(never)]
fn onechip_caches_enable() {
    let base = (&raw const __dma_region_start) as u32;
    let size = ((&raw const __dma_region_end) as u32).wrapping_sub(base);
    // SAFETY: start-up code owns the core peripherals (nothing else runs).
    let mut core = unsafe { cortex_m::Peripherals::steal() };
    // SAFETY: the MPU is reprogrammed while disabled, and only the DMA
    // region's attributes differ from the default map, which the rest of
    // the firmware runs on (MPU_TYPE's DREGION field, bits 15:8, counts
    // the regions).
    unsafe {
        cortex_m::asm::dmb();
        core.MPU.ctrl.write(0);
        // Every region off first: the bootloader may have left some on.
        for region in 0..(core.MPU._type.read() >> 8 & 0xff) {
            core.MPU.rnr.write(region);
            core.MPU.rasr.write(0);
        }
        core.MPU.rbar.write(base | RBAR_VALID | DMA_REGION);
        core.MPU.rasr.write(rasr(size, DMA_ATTRIBUTES));
        core.MPU.rbar.write(ITCM_BASE | RBAR_VALID | ITCM_REGION);
        core.MPU.rasr.write(rasr(ITCM_BYTES, ITCM_ATTRIBUTES));
        core.MPU.ctrl.write(CTRL_PRIVDEFENA | CTRL_ENABLE);
    }
    cortex_m::asm::dsb();
    cortex_m::asm::isb();
    core.SCB.enable_icache();
    core.SCB.enable_dcache(&mut core.CPUID);
}
