//! onechip firmware for the BTT Octopus Pro v1.1 (STM32H723ZG at 520 MHz).
//!
//! Boot: clocks, interrupt priorities, the stepper timer; then read
//! `printer.cfg` from the SD card and serve the USB console. The motion
//! pipeline (planner, stepgen, sched) plugs in behind the console and the
//! stepper timer as it lands.
#![no_std]
#![no_main]

mod clocks;
mod octopus_pro_v1_1;
mod priority;
mod sd_card;
mod step_timer;
mod usb_console;

use defmt_rtt as _;
use embassy_executor::Spawner;
use embassy_time::{Duration, Ticker};
use embassy_usb::UsbDevice;
use octopus_pro_v1_1::Board;
use panic_probe as _;
use static_cell::StaticCell;

/// Largest printer.cfg accepted, in bytes.
const MAX_PRINTER_CFG: usize = 32 * 1024;

#[embassy_executor::main]
async fn main(spawner: Spawner) -> ! {
    let p = embassy_stm32::init(clocks::config());
    priority::apply();
    step_timer::start();
    defmt::info!("onechip: core at {} Hz", clocks::SYSCLK_HZ);
    let board = Board::take(p);

    load_printer_cfg(board.sd).await;

    let console = usb_console::build(board.usb);
    spawner.spawn(usb_device(console.device).expect("spawned once"));
    spawner.spawn(heartbeat().expect("spawned once"));
    let mut class = console.class;
    usb_console::serve(&mut class).await
}

/// Reads printer.cfg from the SD card and reports what was found.
async fn load_printer_cfg(pins: octopus_pro_v1_1::SdPins) {
    static CFG: StaticCell<[u8; MAX_PRINTER_CFG]> = StaticCell::new();
    let cfg = CFG.init([0; MAX_PRINTER_CFG]);
    let mut sdmmc = sd_card::controller(pins);
    let card = match sd_card::open(&mut sdmmc).await {
        Ok(card) => card,
        Err(e) => return defmt::warn!("no SD card: {}", e),
    };
    match onechip_app::sdcard::read_root_file(card, onechip_app::sdcard::PRINTER_CFG, cfg) {
        Ok(n) => defmt::info!("printer.cfg: {} bytes", n),
        Err(e) => defmt::warn!("printer.cfg: {}", defmt::Display2Format(&e)),
    }
}

#[embassy_executor::task]
async fn usb_device(
    mut device: UsbDevice<
        'static,
        embassy_stm32::usb::Driver<'static, embassy_stm32::peripherals::USB_OTG_HS>,
    >,
) -> ! {
    device.run().await
}

/// Logs the stepper timer's progress once a second (a liveness check over RTT).
#[embassy_executor::task]
async fn heartbeat() -> ! {
    let mut ticker = Ticker::every(Duration::from_secs(1));
    loop {
        ticker.next().await;
        defmt::info!(
            "stepper timer at {}, {} interrupts",
            step_timer::now(),
            step_timer::irq_count()
        );
    }
}
