//! The Cortex-M7's tightly-coupled memories, which hold the stepper
//! interrupt: its code in the instruction TCM, its data (the stepper
//! engine) in the data TCM.
//!
//! Layout (RM0468 memory map, the reset-default TCM/AXI split; see
//! board/memory.x): ITCM at 0x0000_0000 (64 KiB), DTCM at 0x2000_0000
//! (128 KiB), both single-cycle (zero wait states) at the core clock and
//! never cached, so they cost the same whatever thread code did to the
//! caches in between. `.itcm_text` (the TIM5 handler and the engine
//! functions it calls out of line: onechip-sched's `itcm` feature) is
//! linked to run from ITCM and stored in flash after `.rodata`; [`load`]
//! copies it over and zeroes `.dtcm_bss` (the engine's cell) before
//! anything runs from or reads them. `cargo xtask image` checks that every
//! function the interrupt reaches (but the panic path and the memory
//! moves of `stepper_itcm_exempt`) lies in ITCM, that the engine lies in
//! DTCM, and that [`load`] and the cache set-up are on the boot path.
//!
//! Why the engine and not the stack goes to DTCM: the engine is the
//! interrupt's working set (13 KiB: eight steppers' move queues and
//! outboxes), read at a different stepper and queue slot on every step,
//! which thread code's planning (far more than the 32 KiB D-cache) would
//! evict between two interrupts; in DTCM no step ever misses. The stack
//! stays at the bottom of AXI SRAM, where an overflow runs into reserved
//! addresses and faults (checked by the image's `stack` rule), and the
//! interrupt's part of it (its exception frame and a few saved registers
//! at the interrupted SP, the lines thread code is using) is the hottest
//! data of the D-cache.
//!
//! # Expected cycles per step at 520 MHz
//!
//! The interrupt's path is about 36 instructions per step (QEMU's count:
//! `cargo m7`, `m7count ... stepper_isr`). From ITCM, with its data in
//! DTCM, nothing waits on memory: the Cortex-M7 issues up to two
//! instructions a cycle, call it one a cycle on this branchy, load-bound
//! path, so about **36 cycles**; exception entry and exit add 12 + 10
//! (vector fetch from flash through the cache), and the timer's and
//! GPIO's registers the rest: two reads of TIM5's count over the 130 MHz
//! APB1 (about 10 cycles each), the status, compare and pin writes
//! posted. About **80 cycles per step** (0.15 µs at 520 MHz) when every
//! step is an interrupt of its own, down to the 36 of the body for steps
//! served in the same wake. From flash without caches, each 64-bit fetch
//! takes 4 AXI cycles at 260 MHz with the 3 wait states 520 MHz needs
//! (8 core cycles for about three instructions), and each engine load an
//! AXI SRAM access: some 150 cycles for the body alone, 250 with entry
//! and registers; with the I-cache and D-cache but no TCM, the ITCM figure
//! when the lines are hot and that plus a 32-byte line fill (about 12
//! cycles from flash, 8 from AXI SRAM) for each of the ~6 code and ~4
//! data lines thread code evicted.

/// Proof that [`load`] ran: the ITCM holds its code and `.dtcm_bss` is
/// zero. Only [`load`] makes one; starting the stepper interrupt takes
/// one.
#[derive(Clone, Copy)]
pub struct Loaded(());

unsafe extern "C" {
    /// `.itcm_text` where it runs (ITCM) and where it is stored (flash);
    /// 4-byte aligned (board/memory.x asserts it).
    static mut __sitcm: u32;
    static mut __eitcm: u32;
    static __siitcm: u32;
    /// `.dtcm_bss` in DTCM, 4-byte aligned.
    static mut __sdtcm_bss: u32;
    static mut __edtcm_bss: u32;
}

/// Copies the interrupt's code to ITCM and zeroes the interrupt's data in
/// DTCM. Call once at boot, before anything in ITCM is called or the
/// stepper interrupt enabled (only start-up code runs then).
pub fn load() -> Loaded {
    onechip_tcm_load();
    Loaded(())
}

/// [`load`]'s work, out of line and by name for `cargo xtask image`'s
/// boot-path check. Word by word with volatile accesses: no call out
/// (memcpy, memset) and no access merged or dropped.
#[unsafe(no_mangle)]
#[inline(never)]
fn onechip_tcm_load() {
    // SAFETY: the linker script defines these as word-aligned bounds of
    // `.itcm_text` (in ITCM and its image in flash, of equal length) and
    // of `.dtcm_bss`; no code in ITCM runs and nothing reads `.dtcm_bss`
    // before this returns (start-up code only, interrupts not yet enabled).
    unsafe {
        let (start, end) = (&raw mut __sitcm, &raw mut __eitcm);
        let mut from = &raw const __siitcm;
        let mut to = start;
        while to < end {
            to.write_volatile(from.read_volatile());
            to = to.add(1);
            from = from.add(1);
        }
        let mut to = &raw mut __sdtcm_bss;
        while to < &raw mut __edtcm_bss {
            to.write_volatile(0);
            to = to.add(1);
        }
    }
    // The copied code is fetched only after the writes complete.
    cortex_m::asm::dsb();
    cortex_m::asm::isb();
}
