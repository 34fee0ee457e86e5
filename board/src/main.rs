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
mod handler_cell;
mod heater_io;
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
        Some(text) => build_printer(text, board.thermistors),
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
fn build_printer(
    text: &'static str,
    thermistors: octopus_pro_v1_1::ThermistorPins,
) -> usb_console::BoardPrinter {
    static CONFIG: StaticCell<Config<'static>> = StaticCell::new();
    static PRINTER: StaticCell<Printer<'static, { usb_console::LOOKAHEAD }>> = StaticCell::new();
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
            install_heaters(&machine, thermistors);
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

/// Configures the heaters' and fan's output pins and the thermistors'
/// ADC channels, and hands them with the heater control to TIM2's
/// interrupt. A pin that is not usable is logged; a heater whose output or
/// thermistor is missing stays off (its range check shuts the printer
/// down rather than heat blind).
fn install_heaters(machine: &Machine<'_>, mut thermistors: octopus_pro_v1_1::ThermistorPins) {
    if machine.heaters.is_empty() && machine.fan.is_none() {
        return;
    }
    let mut machine = machine.clone();
    if let Some(fan) = machine.fan.as_mut().filter(|f| f.hard_pwm) {
        defmt::warn!("[fan] hard_pwm is not supported on this board yet: software PWM");
        fan.hard_pwm = false;
    }
    let start = step_timer::now()
        .wrapping_add((onechip_app::heaters::FIRST_REPORT * step_timer::TIMER_HZ) as u32);
    let setup = onechip_app::heaters::McuSetup::new(
        &machine,
        step_timer::TIMER_HZ,
        heater_io::ADC_MAX,
        start,
    );
    let (mut outputs, mut channels) = (heapless::Vec::new(), heapless::Vec::new());
    for (pin, _) in &setup.outputs {
        match step_pins::OutPin::new(pin) {
            Ok(out) => {
                let _ = outputs.push(out);
            }
            Err(e) => {
                defmt::warn!("heater/fan pin: {}", defmt::Display2Format(&e));
                return;
            }
        }
    }
    for (pin, _) in &setup.inputs {
        match thermistors.channel(pin) {
            Some(channel) => {
                let _ = channels.push(channel);
            }
            None => {
                defmt::warn!("sensor_pin {} is not a thermistor input (PF3..PF7)", pin);
                return;
            }
        }
    }
    let mut hw = heater_io::BoardPeripherals {
        outputs,
        adc: embassy_stm32::adc::Adc::new(thermistors.adc),
        channels,
    };
    let heaters = onechip_app::heaters::Heaters::new(
        &machine,
        step_timer::TIMER_HZ,
        heater_io::ADC_MAX,
        start,
        &mut hw,
    );
    heater_io::install(heaters, hw);
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
