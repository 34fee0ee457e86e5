//! What keeps the printer safe when the firmware is not: the independent
//! watchdog, and the panic and fault handlers that turn every heater and
//! stepper driver off before resetting.
//!
//! - The independent watchdog (IWDG1, on the 32 kHz LSI) resets the chip
//!   512 ms after its last feed, as Klipper's (src/stm32/watchdog.c). Only
//!   the [`watchdog`] task feeds it, so a thread that stops yielding (a
//!   busy-wait, a deadlock) or a heater interrupt that stops running resets
//!   the chip; a reset leaves every GPIO floating (analog input), so the
//!   board's gate pull-downs turn the heater MOSFETs off. The watchdog also
//!   resets a core locked up by a fault during a fault (a stack overflow
//!   into unmapped memory, see `memory.x`) and a core halted by a debugger
//!   (it is not frozen in debug, so a halted core never leaves a heater on).
//! - The panic handler, the HardFault handler and the default handler (any
//!   other exception, any interrupt without a handler) mask interrupts,
//!   drive every registered pin to its safe level through the GPIO
//!   registers ([`onechip_safe_off`]: no embassy object, no lock), log what
//!   happened over defmt, and reset.
//!
//! The safe pins are registered at run time, as printer.cfg names them:
//! the heater and fan outputs by `heater_io::install`, the stepper enable
//! pins by `step_pins::OutPin::new_safe_off`. The table is static and
//! bounded ([`MAX_SAFE_PINS`]); handlers read it without a lock.
//!
//! `cargo xtask image` checks that the handlers reach [`onechip_safe_off`],
//! that the watchdog is started and fed, and that panic-probe is gone.

use core::sync::atomic::{AtomicBool, AtomicU32, AtomicUsize, Ordering};
use embassy_stm32::pac;
use embassy_stm32::pac::iwdg::vals::{Key, Pr};
use embassy_time::{Duration, Ticker};

/// Pins the handlers can drive safe: every stepper's enable pin and every
/// heater, fan and pin output fit.
pub const MAX_SAFE_PINS: usize = 40;

/// An entry is in use.
const VALID: u32 = 1 << 31;
/// Where an entry keeps its port (0 = GPIOA).
const PORT_SHIFT: u32 = 16;

/// The safe pins: `VALID`, the port, and the bit of the port's BSRR that
/// drives the pin to its safe level (the pin number for high, plus 16 for
/// low).
static SAFE_PINS: [AtomicU32; MAX_SAFE_PINS] = [const { AtomicU32::new(0) }; MAX_SAFE_PINS];
/// Entries of [`SAFE_PINS`] in use.
static SAFE_PIN_COUNT: AtomicUsize = AtomicUsize::new(0);
/// A fatal handler has started logging (the log is skipped if another
/// fault or panic happens meanwhile, e.g. inside the logger).
static ENDING: AtomicBool = AtomicBool::new(false);

/// Why a pin could not be registered.
#[derive(Debug, Clone, Copy, PartialEq, Eq, defmt::Format)]
pub enum SafePinError {
    /// No such GPIO (port beyond GPIOH, or number above 15).
    NotAPin,
    /// [`MAX_SAFE_PINS`] pins are registered already.
    Full,
}

/// Registers GPIO `number` (0..=15) of port `port` (0 = A) to be driven to
/// `high` (true) or low by the panic and fault handlers. Registering a
/// pin again replaces its level.
pub fn register_safe_pin(port: u8, number: u8, high: bool) -> Result<(), SafePinError> {
    if crate::gpio::port(port).is_none() || number > 15 {
        return Err(SafePinError::NotAPin);
    }
    let bit = u32::from(number) + if high { 0 } else { 16 };
    let entry = VALID | u32::from(port) << PORT_SHIFT | bit;
    let same_pin = |e: u32| e >> PORT_SHIFT == entry >> PORT_SHIFT && e % 16 == bit % 16;
    critical_section::with(|_| {
        let count = SAFE_PIN_COUNT.load(Ordering::Relaxed);
        let used = &SAFE_PINS[..count.min(MAX_SAFE_PINS)];
        if let Some(slot) = used.iter().find(|e| same_pin(e.load(Ordering::Relaxed))) {
            slot.store(entry, Ordering::Release);
            return Ok(());
        }
        let slot = SAFE_PINS.get(count).ok_or(SafePinError::Full)?;
        slot.store(entry, Ordering::Release);
        SAFE_PIN_COUNT.store(count + 1, Ordering::Release);
        Ok(())
    })
}

/// Masks interrupts and drives every registered pin to its safe level:
/// heaters and fan off, stepper drivers disabled. Writes each pin's port
/// set/reset register directly; safe from any handler, at any time.
#[unsafe(no_mangle)]
#[inline(never)]
pub extern "C" fn onechip_safe_off() {
    // No interrupt may drive a pin again (the heaters' timer would).
    cortex_m::interrupt::disable();
    let count = SAFE_PIN_COUNT.load(Ordering::Acquire).min(MAX_SAFE_PINS);
    for entry in &SAFE_PINS[..count] {
        let entry = entry.load(Ordering::Acquire);
        let port = ((entry >> PORT_SHIFT) & 0xf) as u8;
        if entry & VALID != 0
            && let Some(gpio) = crate::gpio::port(port)
        {
            gpio.bsrr()
                .write_value(pac::gpio::regs::Bsrr(1 << (entry & 31)));
        }
    }
}

/// Starts the independent watchdog with Klipper's timeout: LSI (32 kHz) /
/// 4, reload 4095: 512 ms (482 to 555 ms over LSI's tolerance). If the
/// bootloader left it running, this sets that timeout. Once started it
/// cannot be stopped; [`watchdog`] must be running to feed it.
#[unsafe(export_name = "onechip_watchdog_start")]
#[inline(never)]
pub fn start_watchdog() {
    let iwdg = pac::IWDG1;
    iwdg.kr().write(|w| w.set_key(Key::START));
    iwdg.kr().write(|w| w.set_key(Key::ENABLE));
    iwdg.pr().write(|w| w.set_pr(Pr::DIVIDE_BY4));
    iwdg.rlr().write(|w| w.set_rl(0xfff));
    // The new values reach the LSI domain within a few LSI cycles; the
    // watchdog keeps running (and must be fed) meanwhile.
    while iwdg.sr().read().0 != 0 {}
    feed();
}

/// Feeds the independent watchdog (reloads it to 512 ms).
#[unsafe(export_name = "onechip_watchdog_feed")]
#[inline(never)]
pub fn feed() {
    pac::IWDG1.kr().write(|w| w.set_key(Key::RESET));
}

/// How often [`watchdog`] feeds: a fifth of the timeout.
const FEED_PERIOD: Duration = Duration::from_millis(100);

/// Runs of the heaters' timer interrupt so far (see [`heaters_ran`]).
static HEATER_RUNS: AtomicU32 = AtomicU32::new(0);
/// The heaters' timer interrupt is running and must keep running.
static HEATERS_WATCHED: AtomicBool = AtomicBool::new(false);

/// Called by the heaters' timer interrupt on every run.
#[inline(always)]
pub fn heaters_ran() {
    HEATER_RUNS.fetch_add(1, Ordering::Relaxed);
}

/// From now on the heaters' timer interrupt must run (at least every
/// 10 ms, it does) or the watchdog resets the chip.
pub fn watch_heaters() {
    HEATERS_WATCHED.store(true, Ordering::Relaxed);
}

/// Feeds the independent watchdog every 100 ms while the executor runs
/// this task and, once [`watch_heaters`] was called, while the heaters'
/// interrupt runs: two periods in a row without a heater run stop the
/// feeding, and the chip resets 512 ms later.
#[embassy_executor::task]
pub async fn watchdog() -> ! {
    let mut ticker = Ticker::every(FEED_PERIOD);
    let mut last_runs = HEATER_RUNS.load(Ordering::Relaxed);
    let mut stale = 0u32;
    loop {
        let runs = HEATER_RUNS.load(Ordering::Relaxed);
        if HEATERS_WATCHED.load(Ordering::Relaxed) && runs == last_runs {
            stale += 1;
        } else {
            stale = 0;
        }
        last_runs = runs;
        if stale < 2 {
            feed();
        } else if stale == 2 {
            defmt::error!("the heaters' interrupt stopped: the watchdog will reset");
        }
        ticker.next().await;
    }
}

/// The end of every fatal path (pins already safe): give a debugger the
/// chance to show where it happened, give a host reading the defmt log
/// over RTT time to fetch it, and reset.
fn end() -> ! {
    if cortex_m::peripheral::DCB::is_debugger_attached() {
        // probe-rs stops here and prints the backtrace; the watchdog (not
        // frozen in debug) resets the chip if nothing resumes it.
        cortex_m::asm::bkpt();
    }
    // About 50 ms (the loop takes at least a cycle per iteration), well
    // within the watchdog's timeout.
    cortex_m::asm::delay(crate::clocks::SYSCLK_HZ / 20);
    cortex_m::peripheral::SCB::sys_reset()
}

/// True the first time a fatal path asks: that one logs.
fn first_to_log() -> bool {
    !ENDING.swap(true, Ordering::Relaxed)
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    onechip_safe_off();
    if first_to_log() {
        defmt::error!("panic: {}", defmt::Display2Format(info));
    }
    end()
}

#[cortex_m_rt::exception]
unsafe fn HardFault(frame: &cortex_m_rt::ExceptionFrame) -> ! {
    onechip_safe_off();
    if first_to_log() {
        defmt::error!(
            "HardFault at pc {=u32:#010x} (lr {=u32:#010x})",
            frame.pc(),
            frame.lr()
        );
    }
    end()
}

#[cortex_m_rt::exception]
unsafe fn DefaultHandler(irqn: i16) -> ! {
    onechip_safe_off();
    if first_to_log() {
        defmt::error!("unexpected exception or interrupt {=i16}", irqn);
    }
    end()
}
