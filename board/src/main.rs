//! onechip firmware for the BTT Octopus Pro v1.1 (STM32H723ZG at 520 MHz).
//!
//! Boot: clocks, interrupt priorities, the stepper timer; then read
//! `printer.cfg` from the SD card, build the printer and its step
//! generation from it, configure the stepper pins it names and hand them
//! to the stepper engine in TIM5's interrupt, and serve the USB console,
//! whose G-code lines are planned, turned into steps and executed.
#![no_std]
#![no_main]

mod clocks;
mod octopus_pro_v1_1;
mod priority;
mod sd_card;
mod step_pins;
mod step_timer;
mod usb_console;

use defmt_rtt as _;
use embassy_executor::Spawner;
use embassy_time::{Duration, Ticker};
use embassy_usb::UsbDevice;
use octopus_pro_v1_1::Board;
use onechip_app::printer::Printer;
use onechip_planner::config::Config;
use onechip_planner::machine::Machine;
use onechip_stepgen::motion::Motion;
use panic_probe as _;
use static_cell::{ConstStaticCell, StaticCell};

/// Largest printer.cfg accepted, in bytes.
const MAX_PRINTER_CFG: usize = 32 * 1024;

#[embassy_executor::main]
async fn main(spawner: Spawner) -> ! {
    let p = embassy_stm32::init(clocks::config());
    priority::apply();
    step_timer::start();
    defmt::info!("onechip: core at {} Hz", clocks::SYSCLK_HZ);
    let board = Board::take(p);

    let printer = match load_printer_cfg(board.sd).await {
        Some(text) => build_printer(text),
        None => None,
    };

    let console = usb_console::build(board.usb);
    spawner.spawn(usb_device(console.device).expect("spawned once"));
    spawner.spawn(heartbeat().expect("spawned once"));
    let mut class = console.class;
    usb_console::serve(&mut class, printer).await
}

/// Reads printer.cfg from the SD card; None (logged) if there is none.
async fn load_printer_cfg(pins: octopus_pro_v1_1::SdPins) -> Option<&'static str> {
    static CFG: StaticCell<[u8; MAX_PRINTER_CFG]> = StaticCell::new();
    let cfg = CFG.init([0; MAX_PRINTER_CFG]);
    let mut sdmmc = sd_card::controller(pins);
    let card = match sd_card::open(&mut sdmmc).await {
        Ok(card) => card,
        Err(e) => {
            defmt::warn!("no SD card: {}", e);
            return None;
        }
    };
    match onechip_app::sdcard::read_root_file(card, onechip_app::sdcard::PRINTER_CFG, cfg) {
        Ok(n) => match core::str::from_utf8(&cfg[..n]) {
            Ok(text) => {
                defmt::info!("printer.cfg: {} bytes", n);
                Some(text)
            }
            Err(_) => {
                defmt::warn!("printer.cfg is not UTF-8 text");
                None
            }
        },
        Err(e) => {
            defmt::warn!("printer.cfg: {}", defmt::Display2Format(&e));
            None
        }
    }
}

/// Builds the printer described by printer.cfg; None (logged) if invalid.
fn build_printer(text: &'static str) -> usb_console::BoardPrinter {
    static CONFIG: StaticCell<Config<'static>> = StaticCell::new();
    static PRINTER: StaticCell<Printer<{ usb_console::LOOKAHEAD }>> = StaticCell::new();
    // Built in place: too large to pass through the stack.
    static MOTION: ConstStaticCell<usb_console::BoardMotion> =
        ConstStaticCell::new(Motion::empty());
    let config = match Config::parse("printer.cfg", text) {
        Ok(config) => CONFIG.init(config),
        Err(e) => {
            defmt::warn!("{}", defmt::Display2Format(&e));
            return None;
        }
    };
    match Machine::from_config(config) {
        Ok(machine) => {
            for section in &machine.unsupported {
                defmt::info!("[{}] is not supported yet, ignored", section);
            }
            let homing = install_engine(&machine)?;
            // Steps within Klipper's 25 µs, on the stepper timer's clock.
            let max_error = (0.000_025 * step_timer::TIMER_HZ) as u32;
            let motion = MOTION.take();
            motion.setup(&machine, step_timer::TIMER_HZ, max_error, [0.0; 3]);
            Some(usb_console::Machinery {
                printer: PRINTER.init_with(|| Printer::new(&machine)),
                motion,
                homing,
            })
        }
        Err(e) => {
            defmt::warn!("{}", defmt::Display2Format(&e));
            None
        }
    }
}

/// Configures every stepper's step, direction and enable pins (drivers
/// enabled) and its endstop input, and hands them to the stepper engine;
/// returns what homing needs, or None (logged) if a step, direction or
/// enable pin is not a GPIO.
fn install_engine(machine: &Machine<'_>) -> Option<usb_console::HomingSetup> {
    let mut slots = [step_pins::StepperPins::default(); step_timer::STEPPERS];
    let rails = machine.stepper_kinematics.len().min(3);
    let mut homing = usb_console::HomingSetup {
        endstops: [false; 3],
        rails: (1 << rails) - 1,
        finest_step: f64::INFINITY,
    };
    for (i, (slot, stepper)) in slots.iter_mut().zip(&machine.steppers).enumerate() {
        let pins = step_pins::StepperPins::new(stepper.step_pin, stepper.dir_pin);
        let enable = stepper.enable_pin.map(step_pins::OutPin::new).transpose();
        match (pins, enable) {
            (Ok(pins), Ok(enable)) => {
                if let Some(enable) = enable {
                    enable.set(true);
                }
                *slot = pins;
            }
            (Err(e), _) | (_, Err(e)) => {
                defmt::warn!("[{}]: {}", stepper.name, defmt::Display2Format(&e));
                return None;
            }
        }
        if i < rails {
            homing.finest_step = homing.finest_step.min(stepper.step_dist);
            match stepper.endstop_pin.map(step_pins::InPin::new) {
                Some(Ok(endstop)) => {
                    *slot = slot.with_endstop(endstop);
                    homing.endstops[i] = true;
                }
                Some(Err(e)) => defmt::warn!(
                    "[{}]: endstop {} (G28 refused)",
                    stepper.name,
                    defmt::Display2Format(&e)
                ),
                None => {}
            }
        }
    }
    step_timer::install(step_timer::BoardEngine::new(slots));
    Some(homing)
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

/// Logs the stepper clock once a second (a liveness check over RTT).
#[embassy_executor::task]
async fn heartbeat() -> ! {
    let mut ticker = Ticker::every(Duration::from_secs(1));
    loop {
        ticker.next().await;
        defmt::info!("stepper clock at {} ticks", step_timer::now64());
    }
}
