//! The micro-SD card: SDMMC1 in 4-bit mode, seen by the shared
//! [`onechip_app::sdcard`] code as an embedded-sdmmc [`BlockDevice`].
//!
//! embassy's SDMMC driver is async and embedded-sdmmc is blocking, so
//! [`SdBlocks`] completes each block transfer in thread code, asleep
//! (`wfe`) until the SDMMC interrupt that ends it; the stepper interrupt
//! preempts it as it preempts everything.
//!
//! SDMMC1's internal DMA reads and writes the transfer buffers behind the
//! D-cache's back, so they are statics in `.dma_buffers`, which the MPU
//! makes non-cacheable ([`crate::cache`]), never on the (cached) stack.

use core::cell::{RefCell, UnsafeCell};
use core::sync::atomic::{AtomicBool, Ordering};
use embassy_stm32::sdmmc::sd::{CmdBlock, DataBlock, StorageDevice};
use embassy_stm32::sdmmc::{self, Sdmmc};
use embassy_stm32::time::Hertz;
use embassy_stm32::{bind_interrupts, peripherals};
use embedded_sdmmc::{Block, BlockCount, BlockDevice, BlockIdx};

bind_interrupts!(struct Irqs {
    SDMMC1 => sdmmc::InterruptHandler<peripherals::SDMMC1>;
});

/// Bus clock after card identification, in Hz (SD default speed).
const BUS_HZ: u32 = 25_000_000;

/// Opens the SDMMC1 controller on the board's SD pins.
pub fn controller(pins: crate::octopus_pro_v1_1::SdPins) -> Sdmmc<'static> {
    let (d0, d1, d2, d3) = pins.data;
    Sdmmc::new_4bit(
        pins.sdmmc,
        Irqs,
        pins.clk,
        pins.cmd,
        d0,
        d1,
        d2,
        d3,
        Default::default(),
    )
}

/// The buffers SDMMC1's DMA transfers through: a data block and the
/// command block (card registers read at identification).
///
/// Invariant: in `.dma_buffers` (board/memory.x), which the MPU keeps out
/// of the D-cache and start-up leaves as it finds it: every byte pattern
/// is a valid value of these `u32` arrays. Taken once ([`DmaBuffers::take`]).
#[repr(C)]
struct DmaBuffers {
    data: UnsafeCell<DataBlock>,
    cmd: UnsafeCell<CmdBlock>,
}

// SAFETY: the buffers are handed out once, as `&mut` ([`DmaBuffers::take`]).
unsafe impl Sync for DmaBuffers {}

#[unsafe(link_section = ".dma_buffers.sd_card")]
static DMA_BUFFERS: DmaBuffers = DmaBuffers {
    data: UnsafeCell::new(DataBlock::new()),
    cmd: UnsafeCell::new(CmdBlock::new()),
};

/// True once [`DMA_BUFFERS`] is handed out.
static DMA_TAKEN: AtomicBool = AtomicBool::new(false);

impl DmaBuffers {
    /// The buffers, the first time only.
    #[allow(clippy::mut_from_ref)]
    fn take(&'static self) -> Option<(&'static mut DataBlock, &'static mut CmdBlock)> {
        if DMA_TAKEN.swap(true, Ordering::AcqRel) {
            return None;
        }
        // SAFETY: the first and only call gets them (flag above).
        Some(unsafe { (&mut *self.data.get(), &mut *self.cmd.get()) })
    }
}

/// Identifies the card in the slot and brings the bus to [`BUS_HZ`].
pub async fn open<'a, 'b>(sdmmc: &'a mut Sdmmc<'b>) -> Result<SdBlocks<'a, 'b>, SdmmcError> {
    let (data, cmd) = DMA_BUFFERS.take().ok_or(SdmmcError::Busy)?;
    let card = StorageDevice::new_sd_card(sdmmc, cmd, Hertz(BUS_HZ))
        .await
        .map_err(SdmmcError::Card)?;
    Ok(SdBlocks(RefCell::new(Card { device: card, data })))
}

/// Why a block transfer failed.
#[derive(Debug, defmt::Format)]
pub enum SdmmcError {
    /// The controller or the card reported an error.
    Card(sdmmc::Error),
    /// The card was opened already (its DMA buffers are in use).
    Busy,
}

impl core::fmt::Display for SdmmcError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Card(e) => write!(f, "SDMMC: {e:?}"),
            Self::Busy => f.write_str("SDMMC: the card is open already"),
        }
    }
}

/// Runs `transfer` to its end, asleep (`wfe`) between polls: the SDMMC
/// interrupt that moves it on wakes the core, as does every other
/// interrupt (the 10 ms tick at the latest).
fn finish<F: core::future::Future>(transfer: F) -> F::Output {
    let mut transfer = core::pin::pin!(transfer);
    let mut cx = core::task::Context::from_waker(core::task::Waker::noop());
    loop {
        if let core::task::Poll::Ready(done) = transfer.as_mut().poll(&mut cx) {
            return done;
        }
        cortex_m::asm::wfe();
    }
}

impl core::error::Error for SdmmcError {}

/// An identified card, read and written block by block.
pub struct SdBlocks<'a, 'b>(RefCell<Card<'a, 'b>>);

/// The card and the block buffer its transfers go through.
struct Card<'a, 'b> {
    device: StorageDevice<'a, 'b, sdmmc::sd::Card>,
    /// In `.dma_buffers` (non-cacheable).
    data: &'static mut DataBlock,
}

impl BlockDevice for SdBlocks<'_, '_> {
    type Error = SdmmcError;

    fn read(&self, blocks: &mut [Block], start: BlockIdx) -> Result<(), SdmmcError> {
        let mut card = self.0.borrow_mut();
        let Card { device, data } = &mut *card;
        for (idx, block) in (start.0..).zip(blocks.iter_mut()) {
            finish(device.read_block(idx, data)).map_err(SdmmcError::Card)?;
            block.contents.copy_from_slice(&data[..]);
        }
        Ok(())
    }

    fn write(&self, blocks: &[Block], start: BlockIdx) -> Result<(), SdmmcError> {
        let mut card = self.0.borrow_mut();
        let Card { device, data } = &mut *card;
        for (idx, block) in (start.0..).zip(blocks.iter()) {
            data.copy_from_slice(&block.contents);
            finish(device.write_block(idx, data)).map_err(SdmmcError::Card)?;
        }
        Ok(())
    }

    fn num_blocks(&self) -> Result<BlockCount, SdmmcError> {
        // embedded-sdmmc counts blocks in u32 (2 TiB); larger cards saturate.
        let blocks = self.0.borrow().device.card().csd.block_count();
        Ok(BlockCount(u32::try_from(blocks).unwrap_or(u32::MAX)))
    }
}
