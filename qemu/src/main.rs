//! onechip firmware for QEMU's emulated Cortex-M7 (`mps2-an500`): the
//! same printer session as the Octopus Pro firmware (board/), on this
//! machine's hardware. Only the HAL layer differs:
//!
//! | | board (STM32H723) | here (mps2-an500) |
//! |---|---|---|
//! | console | USB CDC on an interrupt executor | CMSDK UART 0, its RX interrupt ([`uart_console`]) |
//! | stepper engine | TIM5 compare, top priority | CMSDK timer 0, top priority, on timer 1's clock ([`step_timer`]) |
//! | heaters | TIM2 compare, next priority, ADC3 | dual timer, next priority, thermistors at 25 °C ([`heater_io`]) |
//! | pins | GPIO BSRR stores | address-coded stores the TCG plugin logs ([`pins`]) |
//! | printer.cfg | SD card | built into the image ([`card`]) |
//!
//! Thread code runs the session on the console's lines and waits with
//! `wfe` (see [`machine`] for time: `-icount shift=1`, 500 M instructions
//! per virtual second, about a 520 MHz H723).
#![no_std]
#![no_main]

mod card;
mod cmsdk_uart;
mod handler_cell;
mod heater_io;
mod links;
mod machine;
mod mcu;
mod pins;
mod probe;
mod stats;
mod step_timer;
mod uart_console;
mod uart_link;
mod vectors;

use cortex_m_rt::{ExceptionFrame, entry, exception};
use cortex_m_semihosting::debug;
use onechip_app::config_files;
use onechip_app::console::Console;
use onechip_app::heaters::{
    FIRST_REPORT, Heaters, LinearConversion, McuSetup, TYPICAL_STM32H7_CAL,
};
use onechip_app::mcu_config::on_main;
use onechip_app::pin_check;
use onechip_app::secondary::attached::Secondaries;
use onechip_app::secondary::forwarded::ForwardedOutputs;
use onechip_app::secondary::mcu::WithSecondaries;
use onechip_app::session::{BoardSession, profile};
use onechip_app::setup::{Config, PrinterSetup};
use onechip_app::text::{ErrorText, error_text};
use onechip_sched::shutdown::Shutdown;
use static_cell::{ConstStaticCell, StaticCell};

/// Bytes of config text (printer.cfg with its name), as the board.
const CONFIG_BUFFER: usize = 32 * 1024;

/// Secondary MCUs at most: UART 1 is the one link, as the board has one.
const SECONDARIES: usize = 1;

/// The MCU role the session drives: this machine's, with the secondary
/// MCU on UART 1 if printer.cfg has one.
type QemuRole = WithSecondaries<mcu::QemuMcu, uart_link::Uart1Link, SECONDARIES>;

/// The printer's session and its MCU role.
type Loaded = (&'static mut BoardSession<'static>, &'static mut QemuRole);

#[entry]
fn main() -> ! {
    stats::paint_stack();
    step_timer::start();
    uart_console::start();
    let session = load_printer();
    serve(session)
}

/// Thread code: answers console lines through the session forever,
/// waiting for an interrupt whenever there is nothing to do (as the
/// board's `serve`, with its figures reported once a second).
fn serve(loaded: Result<Loaded, ErrorText>) -> ! {
    static NO_PRINTER: StaticCell<QemuRole> = StaticCell::new();
    let mut reporter = stats::Reporter::new();
    let (mut session, mcu, no_printer) = match loaded {
        Ok((session, mcu)) => (Some(session), mcu, ErrorText::new()),
        Err(e) => {
            reporter.print(format_args!("onechip-qemu: no printer: {}", e.as_str()));
            let bare = WithSecondaries::new(mcu::QemuMcu, None, step_timer::CLOCK_HZ);
            (None, NO_PRINTER.init(bare), e)
        }
    };
    let mut card = Some(card::BuiltIn);
    let mut out = uart_console::ConsoleOut;
    let mut console = Console::new(step_timer::CLOCK_HZ);
    loop {
        reporter.poll(step_timer::now64());
        if let Some(incoming) = uart_console::try_line() {
            let event = incoming.event();
            let _ = console.line(
                session.as_deref_mut().map(BoardSession::console),
                &no_printer,
                &event,
                &mut card,
                mcu,
                &mut out,
            );
            if console.take_restart() {
                cortex_m::peripheral::SCB::sys_reset();
            }
            continue;
        }
        let _ = console.poll(
            session.as_deref_mut().map(BoardSession::console),
            &mut card,
            mcu,
            &mut out,
        );
        if !console.is_printing() {
            onechip_app::session::Mcu::wait(mcu, u64::MAX);
        }
    }
}

/// Reads the built-in printer.cfg, configures the pins it names,
/// connects the secondary MCUs and builds the session (in place, in a
/// static) with its MCU role.
fn load_printer() -> Result<Loaded, ErrorText> {
    static TEXT: ConstStaticCell<[u8; CONFIG_BUFFER]> = ConstStaticCell::new([0; CONFIG_BUFFER]);
    static SESSION: StaticCell<BoardSession<'static>> = StaticCell::new();
    static SCRATCH: StaticCell<Config<'static>> = StaticCell::new();
    static ROLE: StaticCell<QemuRole> = StaticCell::new();
    let texts = config_files::load(&mut card::BuiltIn, TEXT.take()).map_err(|e| error_text(&e))?;
    let mut setup = PrinterSetup::load(&texts, pin_check::BOARD_RESERVED, SCRATCH.uninit())
        .map_err(|e| error_text(&e))?;
    install_engine(&setup)?;
    install_heaters(&mut setup)?;
    let secondaries = connect_secondaries(&setup)?;
    let role = WithSecondaries::new(mcu::QemuMcu, secondaries, step_timer::CLOCK_HZ);
    let session = BoardSession::init_in(
        SESSION.uninit(),
        setup.machine(),
        step_timer::CLOCK_HZ,
        profile::MAX_STEP_ERROR,
        step_timer::now64(),
    );
    Ok((session, ROLE.init(role)))
}

/// The printer's secondary MCU on UART 1, identified and configured
/// (None without one), in a static; from then on the machine runs in real
/// time ([`machine::start_real_time`]), as it does.
fn connect_secondaries(
    setup: &PrinterSetup<'static>,
) -> Result<Option<&'static mut Secondaries<uart_link::Uart1Link, SECONDARIES>>, ErrorText> {
    static CONNECTED: StaticCell<Secondaries<uart_link::Uart1Link, SECONDARIES>> =
        StaticCell::new();
    let machine = setup.machine();
    if machine.secondaries.is_empty() {
        return Ok(None);
    }
    machine::start_real_time();
    let mcu_sensor = LinearConversion::stm32h7(TYPICAL_STM32H7_CAL);
    let now = || step_timer::now64() as f64 / step_timer::CLOCK_HZ;
    let secondaries = Secondaries::init_in(CONNECTED.uninit(), step_timer::CLOCK_HZ, mcu_sensor);
    (secondaries.connect(setup, &|name| name, &mut links::UartLinks, &now))
        .map_err(|e| error_text(&e))?;
    Ok(Some(secondaries))
}

/// Every stepper's step, direction and enable pins (drivers enabled) and
/// endstop, handed to the stepper engine; a stepper, enable pin or
/// endstop on a secondary MCU is left to it (its slot stays idle).
fn install_engine(setup: &PrinterSetup<'_>) -> Result<(), ErrorText> {
    let mut slots = [pins::StepperPins::default(); step_timer::STEPPERS];
    for (slot, stepper) in slots.iter_mut().zip(setup.steppers()) {
        let fail = |e: &dyn core::fmt::Display| error_text(&format_args!("[{}] {e}", stepper.name));
        // An enable pin here is on, whichever MCU steps its stepper.
        if let Some(pin) = stepper.enable_pin.filter(|p| on_main(p)) {
            pins::OutPin::new(pin).map_err(|e| fail(&e))?.set(true);
        }
        if !on_main(stepper.step_pin) {
            continue;
        }
        *slot = pins::StepperPins::new(stepper.step_pin, stepper.dir_pin, stepper.step_pulse)
            .map_err(|e| fail(&e))?;
        if let Some(pin) = stepper.endstop_pin.filter(|p| on_main(p)) {
            *slot = slot.with_endstop(pins::InPin::new(pin).map_err(|e| fail(&e))?);
        }
    }
    step_timer::install(step_timer::QemuEngine::new(slots));
    Ok(())
}

/// The heaters' and fan's outputs and thermistor readings, handed with
/// the heater control to the dual timer's interrupt.
fn install_heaters(setup: &mut PrinterSetup<'_>) -> Result<(), ErrorText> {
    if !setup.has_thermal() {
        return Ok(());
    }
    // Software PWM for a hard_pwm fan, as the board.
    let _ = setup.without_hard_pwm();
    let machine = setup.machine();
    let freq = step_timer::CLOCK_HZ;
    let start = step_timer::now().wrapping_add((FIRST_REPORT * freq) as u32);
    // The machine models no die temperature: a typical chip at room
    // temperature.
    let mcu_sensor = LinearConversion::stm32h7(TYPICAL_STM32H7_CAL);
    let mcu_setup = McuSetup::new(machine, freq, heater_io::ADC_MAX, mcu_sensor, start);
    let mut hw = heater_io::QemuPeripherals {
        outputs: heapless::Vec::new(),
        forwarded: ForwardedOutputs::new(&mcu_setup),
        readings: heapless::Vec::new(),
        chips: onechip_app::heaters::input_chips(machine)
            .take(onechip_app::heaters::INPUTS)
            .collect(),
    };
    for (pin, _) in &mcu_setup.outputs {
        // One on a secondary MCU is driven there (its updates forwarded).
        let out = if on_main(pin) {
            Some(pins::OutPin::new(pin).map_err(|e| error_text(&e))?)
        } else {
            None
        };
        let _ = hw.outputs.push(out);
    }
    let heaters = machine
        .heaters
        .iter()
        .map(|h| h.sensor.adc(heater_io::ROOM));
    let sensors = machine.sensors.iter().map(|s| {
        let conversion = s.conversion(mcu_sensor);
        conversion.reading(heater_io::ROOM)
    });
    for fraction in heaters.chain(sensors) {
        let _ = hw
            .readings
            .push((fraction * f64::from(heater_io::ADC_MAX)) as u16);
    }
    let heaters = Heaters::new(
        machine,
        freq,
        heater_io::ADC_MAX,
        mcu_sensor,
        start,
        &mut hw,
    );
    heater_io::install(heaters, hw);
    Ok(())
}

/// Steppers and heaters off, the reason on QEMU's standard output, and
/// QEMU told to exit with a failure.
fn fail(args: core::fmt::Arguments<'_>) -> ! {
    mcu::shutdown(Shutdown::EmergencyStop);
    if let Ok(mut out) = cortex_m_semihosting::hio::hstdout() {
        let _ = core::fmt::Write::write_fmt(&mut HostWriter(&mut out), args);
    }
    debug::exit(debug::EXIT_FAILURE);
    loop {
        cortex_m::asm::wfe();
    }
}

/// `core::fmt::Write` on a semihosting stream.
struct HostWriter<'a>(&'a mut cortex_m_semihosting::hio::HostStream);

impl core::fmt::Write for HostWriter<'_> {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        self.0.write_all(s.as_bytes()).map_err(|_| core::fmt::Error)
    }
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo<'_>) -> ! {
    fail(format_args!("onechip-qemu: panic: {info}\n"))
}

#[exception]
unsafe fn HardFault(frame: &ExceptionFrame) -> ! {
    fail(format_args!(
        "onechip-qemu: hard fault at pc {:#010x}\n",
        frame.pc()
    ))
}
