//! QEMU's `mps2-an500` machine as this firmware uses it: a Cortex-M7
//! with CMSDK peripherals (ARM AN500; QEMU `hw/arm/mps2.c`).
//!
//! # Time
//! QEMU runs with `-icount shift=1`: every guest instruction advances the
//! virtual clock by 2^1 = 2 ns, so the CPU runs at 500 M instructions per
//! virtual second. A 520 MHz STM32H723 retires about one instruction per
//! cycle on this code (more when it dual-issues, fewer on flash wait
//! states), so one virtual second here is about one second of the H723
//! at 520 MHz, 4 % slower. The firmware never executes `wfi` (thread code
//! waits with `wfe`, which QEMU runs as a hint without sleeping), so the
//! virtual clock is exactly the instruction count times 2 ns: the pin log
//! of the TCG plugin (`plugin/pinlog.c`) stamps each write with it.
//!
//! The CMSDK timers count at the machine's 25 MHz peripheral clock
//! ([`TIMER_HZ`]), derived from that virtual clock: 20 instructions per
//! tick.

/// The CMSDK timers' clock (the machine's `SYSCLK`), Hz.
pub const TIMER_HZ: u32 = 25_000_000;
/// Guest instructions per virtual second with `-icount shift=1`: the CPU
/// clock the delays are computed for, Hz.
pub const CPU_HZ: u32 = 500_000_000;

/// CMSDK APB timer 0: the stepper engine's compare (IRQ 8).
pub const TIMER0: usize = 0x4000_0000;
/// CMSDK APB timer 1: the free-running step clock (its interrupt unused).
pub const TIMER1: usize = 0x4000_1000;
/// CMSDK APB dual timer, timer 1: the heaters' wake (IRQ 10).
pub const DUALTIMER: usize = 0x4000_2000;
/// CMSDK APB UART 0: the console (RX IRQ 0).
pub const UART0: usize = 0x4000_4000;
/// CMSDK APB UART 1: the link to a secondary MCU (RX IRQ 2, TX IRQ 3).
pub const UART1: usize = 0x4000_5000;

/// Where this machine's pin ports start: QEMU models no GPIO here (the
/// CMSDK AHB GPIO and peripheral region at 0x4001_0000 is an
/// unimplemented device: reads 0, writes ignored), so the pins are
/// defined by their writes alone, which the TCG plugin logs
/// ([`crate::pins`]).
pub const PINS: usize = 0x4001_0000;
/// Bytes between two pin ports (port A at [`PINS`], B after it, ...).
pub const PORT_STRIDE: usize = 0x1000;
/// Pin ports (A to K, as the STM32H723's).
pub const PORTS: u8 = 11;
/// Where the firmware marks entering and leaving its interrupts and its
/// waits for the plugin's CPU-time accounting ([`crate::probe`]): past
/// the pin ports, in the same unimplemented region.
pub const PROBE: usize = 0x4001_F000;

/// The interrupts this firmware uses, by their NVIC number.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u16)]
pub enum Irq {
    /// UART 0 received a byte.
    Uart0Rx = 0,
    /// UART 1 received a byte.
    Uart1Rx = 2,
    /// UART 1's transmitter emptied.
    Uart1Tx = 3,
    /// Timer 0 reached 0: the stepper engine's wake.
    Timer0 = 8,
    /// The dual timer: the heaters' wake.
    DualTimer = 10,
}

// SAFETY: the numbers are the machine's interrupt lines (mps2.c).
unsafe impl cortex_m::interrupt::InterruptNumber for Irq {
    fn number(self) -> u16 {
        self as u16
    }
}

/// Interrupt priorities as the NVIC's priority byte (lower is more
/// urgent), in the board's order: the stepper engine alone at the top,
/// the heaters next, then the console.
pub mod priority {
    /// The stepper engine's timer.
    pub const STEPPER: u8 = 0x00;
    /// The heaters' and fan's timer.
    pub const HEATERS: u8 = 0x20;
    /// The secondary MCU's UART (its bytes are not held back as the
    /// console's: a full ring drops them).
    pub const LINK: u8 = 0x30;
    /// The console's UART.
    pub const CONSOLE: u8 = 0x40;
}

/// Writes the 32-bit register at `address`.
#[inline(always)]
pub fn write(address: usize, value: u32) {
    // SAFETY: `address` is one of this machine's device registers (the
    // constants above), where a volatile store has no effect on memory.
    unsafe { core::ptr::write_volatile(address as *mut u32, value) }
}

/// Reads the 32-bit register at `address`.
#[inline(always)]
pub fn read(address: usize) -> u32 {
    // SAFETY: as in `write`.
    unsafe { core::ptr::read_volatile(address as *const u32) }
}

/// Sets interrupt `irq`'s priority and enables it.
pub fn enable(irq: Irq, priority: u8) {
    // SAFETY: called at start-up, before the handler's state is used by
    // anything else; the handlers take no lock they could deadlock on.
    unsafe {
        let mut p = cortex_m::Peripherals::steal();
        p.NVIC.set_priority(irq, priority);
        cortex_m::peripheral::NVIC::unmask(irq);
    }
}

/// Makes interrupt `irq` pending (it runs as soon as its priority
/// allows).
pub fn pend(irq: Irq) {
    cortex_m::peripheral::NVIC::pend(irq);
}

/// Interrupt handler runs so far (wrapping): what [`sleep`] waits for.
static EVENTS: core::sync::atomic::AtomicU32 = core::sync::atomic::AtomicU32::new(0);

/// Counts a run of an interrupt handler (each handler calls it once).
#[inline(always)]
pub fn interrupt_ran() {
    EVENTS.fetch_add(1, core::sync::atomic::Ordering::Relaxed);
}

/// Thread code's wait, as the board's `wfe`: returns once an interrupt
/// handler has run. QEMU runs `wfe` as a hint without sleeping (and
/// leaves its translated code at each one, which is slow), so the wait
/// spins on the count of handler runs, marked idle for the plugin; its
/// instructions are the time the board would sleep. In real time
/// ([`start_real_time`]) it halts the CPU with `wfi` instead.
pub fn sleep() {
    use core::sync::atomic::Ordering::Relaxed;
    crate::probe::within(crate::probe::Context::Idle, || {
        let before = EVENTS.load(Relaxed);
        if REAL_TIME.load(Relaxed) {
            // An interrupt between the load and the `wfi` is waited out
            // by the next one: the tick's 1 ms at most.
            if EVENTS.load(Relaxed) == before {
                cortex_m::asm::wfi();
            }
        } else {
            while EVENTS.load(Relaxed) == before {}
        }
    });
}

/// Thread code sleeps with `wfi` ([`sleep`]).
static REAL_TIME: core::sync::atomic::AtomicBool = core::sync::atomic::AtomicBool::new(false);

/// SysTick's reload for its tick: 1 ms of the processor clock
/// ([`TIMER_HZ`] on this machine), ticks.
const TICK_RELOAD: u32 = TIMER_HZ / 1000 - 1;

/// Real-time mode, for a printer with secondary MCUs (they keep the wall
/// clock's time, and the harness runs QEMU without `-icount`, the
/// virtual clock following the host's): thread code sleeps with `wfi`
/// (QEMU halts the CPU and its host thread) instead of spinning, and
/// SysTick wakes it every millisecond, so that a wait with a deadline
/// (a link's [`SecondaryLink::wait_readable`]) ends on time without a
/// timer of its own.
///
/// [`SecondaryLink::wait_readable`]: onechip_app::secondary::SecondaryLink::wait_readable
pub fn start_real_time() {
    // SAFETY: SysTick is used by nothing else; its handler only counts.
    let mut p = unsafe { cortex_m::Peripherals::steal() };
    // SAFETY: the lowest priority; its handler touches no shared state.
    unsafe {
        p.SCB
            .set_priority(cortex_m::peripheral::scb::SystemHandler::SysTick, 0xe0);
    }
    p.SYST
        .set_clock_source(cortex_m::peripheral::syst::SystClkSource::Core);
    p.SYST.set_reload(TICK_RELOAD);
    p.SYST.clear_current();
    p.SYST.enable_interrupt();
    p.SYST.enable_counter();
    REAL_TIME.store(true, core::sync::atomic::Ordering::Relaxed);
}

/// SysTick's tick: wakes thread code ([`start_real_time`]).
#[cortex_m_rt::exception]
fn SysTick() {
    interrupt_ran();
}
