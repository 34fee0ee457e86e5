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
//! function the interrupt reaches (but the panic path and the memory move
//! of `itcm_exempt` in board/budget.toml) lies in ITCM, that the engine
//! lies in DTCM, and that [`load`] and the cache set-up are on the boot
//! path.
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
//! The interrupt's step path is about 36 instructions per step (QEMU's
//! count: `cargo m7`, `m7count ... stepper_isr`, with the pins as plain
//! stores). From ITCM, with the engine in DTCM, no fetch or load waits:
//! the Cortex-M7 issues up to two instructions a cycle; on this short,
//! branchy, load-dependent path count one a cycle, **about 36 cycles**.
//! Around it, per interrupt: exception entry and return, about 12 + 10
//! cycles (ARM's figures; the frame goes to the interrupted code's stack
//! lines, hot in the D-cache, and the vector is read from flash through
//! it); two reads of TIM5's count across the AXI/AHB/APB1 bridges (APB1 at
//! 130 MHz: about 10 cycles each); the status, compare and pin writes are
//! posted. So **about 80 cycles per step** (0.15 µs) when each step is an
//! interrupt of its own, the body's ~36 for further steps served in the
//! same wake, plus the step pulse the pins hold (`step_pulse_duration`:
//! 52 cycles for a TMC driver's 100 ns, 1,040 for Klipper's default 2 µs,
//! which then dominates).
//!
//! For comparison, the same path from flash: at 520 MHz flash needs 3
//! wait states at its 260 MHz AXI clock, so a 64-bit fetch (about three
//! instructions) takes 8 core cycles: ~100 cycles of fetch for the body
//! without the I-cache, ~250 per step with entry and registers. With the
//! caches but no TCM, the ITCM figure while the lines stay cached, plus a
//! line fill (32 bytes: ~12 cycles from flash, ~8 from AXI SRAM) for each
//! of the ~6 code and ~4 engine lines that thread code's planning and
//! step generation evicted in between: up to ~120 cycles more, and not
//! the same from one step to the next.

/// Proof that [`load`] ran: the ITCM holds its code and `.dtcm_bss` is
/// zero. Only [`load`] makes one; starting the stepper interrupt takes
/// one.
#[derive(Clone, Copy)]
pub struct Loaded(());

unsafe extern "C" {
    /// `.itcm_text` where it runs (ITCM) and where it is stored (flash);
    /// 8-byte aligned, a whole number of 8-byte words (board/memory.x
    /// asserts it).
    static mut __sitcm: u64;
    static mut __eitcm: u64;
    static __siitcm: u64;
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
/// boot-path check. With volatile accesses: no call out (memcpy, memset)
/// and no access merged or dropped. ITCM is written in aligned 64-bit
/// words, its ECC word (RM0468): a narrower write is a read-modify-write
/// of a word never written since power-on, whose check bits are random.
#[unsafe(no_mangle)]
#[inline(never)]
fn onechip_tcm_load() {
    // SAFETY: the linker script defines these as aligned bounds of
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
