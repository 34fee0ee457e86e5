//! The micro-SD card: SDMMC1 in 4-bit mode, seen by the shared
//! [`onechip_app::sdcard`] code as an embedded-sdmmc [`BlockDevice`].
//!
//! embassy's SDMMC driver is async and embedded-sdmmc is blocking, so
//! [`SdBlocks`] completes each block transfer in thread code, asleep
//! (`wfe`) until the SDMMC interrupt that ends it; the stepper interrupt
//! preempts it as it preempts everything.

use core::cell::RefCell;
use embassy_stm32::sdmmc::sd::{Card, CmdBlock, DataBlock, StorageDevice};
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

/// Identifies the card in the slot and brings the bus to [`BUS_HZ`].
pub async fn open<'a, 'b>(sdmmc: &'a mut Sdmmc<'b>) -> Result<SdBlocks<'a, 'b>, SdmmcError> {
    let mut cmd = CmdBlock::new();
    let card = StorageDevice::new_sd_card(sdmmc, &mut cmd, Hertz(BUS_HZ))
        .await
        .map_err(SdmmcError::Card)?;
    Ok(SdBlocks(RefCell::new(card)))
}

/// Why a block transfer failed.
#[derive(Debug, defmt::Format)]
pub enum SdmmcError {
    /// The controller or the card reported an error.
    Card(sdmmc::Error),
}

impl core::fmt::Display for SdmmcError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Card(e) => write!(f, "SDMMC: {e:?}"),
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
pub struct SdBlocks<'a, 'b>(RefCell<StorageDevice<'a, 'b, Card>>);

impl BlockDevice for SdBlocks<'_, '_> {
    type Error = SdmmcError;

    fn read(&self, blocks: &mut [Block], start: BlockIdx) -> Result<(), SdmmcError> {
        let mut card = self.0.borrow_mut();
        let mut buffer = DataBlock::new();
        for (idx, block) in (start.0..).zip(blocks.iter_mut()) {
            finish(card.read_block(idx, &mut buffer)).map_err(SdmmcError::Card)?;
            block.contents.copy_from_slice(&buffer[..]);
        }
        Ok(())
    }

    fn write(&self, blocks: &[Block], start: BlockIdx) -> Result<(), SdmmcError> {
        let mut card = self.0.borrow_mut();
        let mut buffer = DataBlock::new();
        for (idx, block) in (start.0..).zip(blocks.iter()) {
            buffer.copy_from_slice(&block.contents);
            finish(card.write_block(idx, &buffer)).map_err(SdmmcError::Card)?;
        }
        Ok(())
    }

    fn num_blocks(&self) -> Result<BlockCount, SdmmcError> {
        // embedded-sdmmc counts blocks in u32 (2 TiB); larger cards saturate.
        let blocks = self.0.borrow().card().csd.block_count();
        Ok(BlockCount(u32::try_from(blocks).unwrap_or(u32::MAX)))
    }
}
