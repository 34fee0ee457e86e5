//! What the board supplies to reach its secondary MCUs ([`Links`]): their
//! USART links ([`UsartLink`]), room for their data dictionaries, sleeps
//! on the stepper clock, and the static the host role for them lives in
//! ([`secondaries`]).
//!
//! The board has one USART for secondaries (USART2), so at most one
//! secondary is attached; it takes a dictionary buffer each time it is
//! connected: at start, and once more when it held another config and is
//! reset and connected anew (klippy's automated firmware restart). Hence
//! [`DICTIONARIES`] buffers of [`DICTIONARY_BYTES`], and as many slots for
//! the parsed dictionaries, handed out once each and never taken back
//! (the board restarts with a reset). Stock Klipper dictionaries inflate
//! to 10–12 KB (`../shared/golden/dicts`: an atmega2560's 10,172 bytes,
//! an STM32F446's 11,737; `../shared/peers/linux`: 11,987), so 24 KiB
//! leaves room for builds with every option.
//!
//! They live in DTCM, zeroed at boot with the stepper engine
//! (`.dtcm_bss`, [`onechip_board_rt::tcm`]), as does the host role
//! ([`BoardSecondaries`], about 28 KB): AXI SRAM holds the stack and the
//! session, and only the CPU touches these (no DMA, which could not reach
//! DTCM).

use core::cell::UnsafeCell;
use core::mem::MaybeUninit;
use core::sync::atomic::{AtomicUsize, Ordering};
use onechip_app::heaters::LinearConversion;
use onechip_app::secondary::attached::Secondaries;
use onechip_app::secondary::{LinkError, Links};
use onechip_board_rt::step_timer;
use onechip_board_rt::usart_link::UsartLink;
use onechip_protocol::dictionary::Dictionary;
use static_cell::StaticCell;

/// Secondary MCUs at most: USART2 is the one link.
pub const SECONDARIES: usize = 1;

/// The host role for the board's secondary MCUs.
pub type BoardSecondaries = Secondaries<UsartLink, SECONDARIES>;

/// The host role, empty, on the stepper clock (the board's internal
/// temperature sensor calibrated as `mcu_sensor`), in its static: once
/// (None after).
pub fn secondaries(mcu_sensor: LinearConversion) -> Option<&'static mut BoardSecondaries> {
    /// In DTCM, zeroed at boot: a cell not taken yet.
    #[unsafe(link_section = ".dtcm_bss.secondaries")]
    static CELL: StaticCell<BoardSecondaries> = StaticCell::new();
    let slot = CELL.try_uninit()?;
    Some(Secondaries::init_in(slot, step_timer::TIMER_HZ, mcu_sensor))
}

/// Dictionary buffers and parsed-dictionary slots.
pub const DICTIONARIES: usize = 2;
/// Bytes of one inflated data dictionary.
pub const DICTIONARY_BYTES: usize = 24 * 1024;

/// The buffers and slots, each handed out at most once
/// ([`NEXT_BUFFER`], [`NEXT_SLOT`]).
struct Pool {
    buffers: UnsafeCell<[[u8; DICTIONARY_BYTES]; DICTIONARIES]>,
    slots: UnsafeCell<[MaybeUninit<Dictionary<'static>>; DICTIONARIES]>,
}

// SAFETY: each buffer and slot is reached through the `&'static` handed
// out once for it (the counters below are taken by atomic increments), so
// no two references to one overlap.
unsafe impl Sync for Pool {}

/// In DTCM, zeroed at boot: empty buffers, and slots that are not read
/// before they are written.
#[unsafe(link_section = ".dtcm_bss.secondary_links")]
static POOL: Pool = Pool {
    buffers: UnsafeCell::new([[0; DICTIONARY_BYTES]; DICTIONARIES]),
    slots: UnsafeCell::new([const { MaybeUninit::uninit() }; DICTIONARIES]),
};
/// Buffers handed out.
static NEXT_BUFFER: AtomicUsize = AtomicUsize::new(0);
/// Slots handed out.
static NEXT_SLOT: AtomicUsize = AtomicUsize::new(0);

/// Takes index `counter` once, if below [`DICTIONARIES`].
fn take(counter: &AtomicUsize) -> Option<usize> {
    let i = counter.fetch_add(1, Ordering::AcqRel);
    if i < DICTIONARIES {
        Some(i)
    } else {
        // Stays past the end however often it is asked.
        counter.store(DICTIONARIES, Ordering::Release);
        None
    }
}

/// The board's [`Links`]: its USARTs.
pub struct BoardLinks;

impl Links for BoardLinks {
    type Link = UsartLink;

    fn open(&mut self, serial: &str, baud: u32) -> Result<UsartLink, LinkError> {
        UsartLink::open(serial, baud)
    }

    fn pause(&mut self, s: f64) {
        let until = step_timer::now64().saturating_add((s * step_timer::TIMER_HZ) as u64);
        while step_timer::now64() < until {
            // The I/O executor's tick wakes this at least every 10 ms.
            cortex_m::asm::wfe();
        }
    }

    fn dictionary_buffer(&mut self) -> Option<&'static mut [u8]> {
        let i = take(&NEXT_BUFFER)?;
        let first = POOL.buffers.get().cast::<[u8; DICTIONARY_BYTES]>();
        // SAFETY: `i` is below DICTIONARIES (`take`), so the pointer is in
        // the array; buffer `i` is handed out once, so this is its only
        // reference (none to the whole array is ever made).
        Some(unsafe { &mut *first.add(i) })
    }

    fn dictionary_slot(&mut self) -> Option<&'static mut MaybeUninit<Dictionary<'static>>> {
        let i = take(&NEXT_SLOT)?;
        let first = POOL.slots.get().cast::<MaybeUninit<Dictionary<'static>>>();
        // SAFETY: as for the buffers: in the array, and slot `i`'s only
        // reference.
        Some(unsafe { &mut *first.add(i) })
    }
}
