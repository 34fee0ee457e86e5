//! onechip firmware for the BTT Octopus Pro v1.1 (STM32H723ZG at 520 MHz).
//!
//! Boot: take control from the bootloader (caches on, the stepper
//! interrupt's code and data in the TCMs), start the watchdog, clocks,
//! interrupt priorities, the stepper timer and the I/O executor (USB); then
//! read `printer.cfg` and its includes from the SD card, configure the pins
//! it names for the stepper engine (TIM5's interrupt) and the heaters
//! (TIM2's), and build the shared printer session. Thread code then runs
//! the session on the console's lines, asleep whenever it waits for an
//! interrupt.
#![no_std]
#![no_main]

mod board_mcu;
mod boot;
mod cache;
mod octopus_pro_v1_1;
mod sd_card;
#[cfg(feature = "secondaries")]
mod secondary_links;
mod usb_console;

use core::mem::{ManuallyDrop, MaybeUninit};
use defmt_rtt as _;
use embassy_executor::{Executor, InterruptExecutor, SendSpawner, Spawner};
use embassy_stm32::interrupt;
use embassy_stm32::interrupt::InterruptExt;
use embassy_time::{Duration, Ticker};
use octopus_pro_v1_1::Board;
use onechip_app::config_files;
use onechip_app::console::Console;
use onechip_app::mcu_config::on_main;
use onechip_app::pin_check;
use onechip_app::sdcard::SdFiles;
use onechip_app::secondary::forwarded::ForwardedOutputs;
#[cfg(feature = "secondaries")]
use onechip_app::secondary::mcu::WithSecondaries;
#[cfg(feature = "secondaries")]
use onechip_app::secondary::{ConnectError, McuError};
use onechip_app::session::{BoardSession, Mcu, profile};
use onechip_app::setup::{Config, PrinterSetup};
use onechip_app::text::{ErrorText, error_text};
#[cfg(feature = "secondaries")]
use onechip_board_rt::usart_link;
use onechip_board_rt::{
    clocks, heater_io, priority, probe_servo, safety, spi_sensors, step_pins, step_timer, tcm,
    tmc_link,
};
use static_cell::{ConstStaticCell, StaticCell};

const _: () = assert!(
    safety::MAX_SAFE_PINS >= step_timer::STEPPERS + onechip_app::heaters::OUTPUTS,
    "room for every enable pin and every heater and fan output"
);

/// The MCU role the session drives: this board's, with the secondary MCUs
/// on its USART if printer.cfg has any (feature `secondaries`).
#[cfg(feature = "secondaries")]
type BoardRole =
    WithSecondaries<board_mcu::BoardMcu, usart_link::UsartLink, { secondary_links::SECONDARIES }>;
/// The MCU role the session drives: this board's (without the feature
/// `secondaries`, an `[mcu NAME]` is refused).
#[cfg(not(feature = "secondaries"))]
type BoardRole = board_mcu::BoardMcu;

/// The MCU role without a printer (no valid printer.cfg).
fn role_alone() -> BoardRole {
    #[cfg(feature = "secondaries")]
    return WithSecondaries::new(board_mcu::BoardMcu::default(), None, step_timer::TIMER_HZ);
    #[cfg(not(feature = "secondaries"))]
    board_mcu::BoardMcu::default()
}

/// Bytes of config text (printer.cfg and its includes, with their names).
const CONFIG_BUFFER: usize = 32 * 1024;

/// The I/O executor: USB, the watchdog and timers, on an otherwise unused
/// interrupt below the stepper and heater timers.
static IO: InterruptExecutor = InterruptExecutor::new();

#[interrupt]
unsafe fn SPI6() {
    // SAFETY: SPI6's interrupt is the I/O executor's alone.
    unsafe { IO.on_interrupt() }
}

/// Reset's `main`: takes control from the bootloader (caches, TCMs, bus
/// masters, clocks; directly called, so the image check sees it on the
/// boot path), then runs [`run`] on the thread-mode executor.
#[cortex_m_rt::entry]
fn main() -> ! {
    let tcm = boot::take_control();
    static EXECUTOR: StaticCell<Executor> = StaticCell::new();
    EXECUTOR
        .init(Executor::new())
        .run(|spawner| spawner.spawn(run(tcm).expect("spawned once")))
}

/// The firmware after take-over: watchdog, clocks, interrupts, USB, the
/// card and the printer, then thread code's console loop.
#[embassy_executor::task]
async fn run(tcm: tcm::Loaded) -> ! {
    safety::start_watchdog();
    let p = init_hal();
    priority::apply();
    step_timer::start(tcm);
    defmt::info!("onechip: core at {} Hz", clocks::SYSCLK_HZ);
    let board = Board::take(p);
    interrupt::SPI6.set_priority(priority::IO_EXECUTOR);
    let io: SendSpawner = IO.start(interrupt::SPI6);
    io.spawn(start_io(board.usb).expect("spawned once"));
    let mut card = open_card(board.sd).await;
    let session = load_printer(&mut card, board.thermistors);
    if let Err(e) = &session {
        defmt::warn!("{}", e.as_str());
    }
    serve(card.ok(), session)
}

/// The HAL with this board's clocks. Not inlined: inlined into the `run`
/// task, the clock set-up's locals widened the task's frame past short
/// stack addressing.
#[inline(never)]
fn init_hal() -> embassy_stm32::Peripherals {
    embassy_stm32::init(clocks::config())
}

/// The card in the slot, as the session reads and writes it.
type BoardCard = SdFiles<sd_card::SdBlocks<'static, 'static>>;

/// Opens the SD card, or says why there is none.
async fn open_card(sd: octopus_pro_v1_1::SdPins) -> Result<BoardCard, ErrorText> {
    static SDMMC: StaticCell<embassy_stm32::sdmmc::Sdmmc<'static>> = StaticCell::new();
    let sdmmc = SDMMC.init(sd_card::controller(sd));
    let blocks = sd_card::open(sdmmc)
        .await
        .map_err(|e| error_text(&format_args!("no SD card: {e}")))?;
    Ok(SdFiles::new(blocks))
}

/// The I/O executor's first task: starts the watchdog's, USB's and the
/// tick that wakes thread code at least every 10 ms (built here, as they
/// stay on this executor).
#[embassy_executor::task]
async fn start_io(usb: octopus_pro_v1_1::UsbPins) {
    // SAFETY: awaited in a task of the I/O executor, with the context the
    // executor made (the one way to reach an interrupt executor's spawner).
    let spawner = unsafe { Spawner::for_current_executor() }.await;
    let console = usb_console::build(usb);
    let (tx, rx) = console.class.split();
    spawner.spawn(safety::watchdog().expect("spawned once"));
    spawner.spawn(usb_console::device(console.device).expect("spawned once"));
    spawner.spawn(usb_console::reader(rx).expect("spawned once"));
    spawner.spawn(usb_console::writer(tx).expect("spawned once"));
    spawner.spawn(tick().expect("spawned once"));
}

/// Thread code: answers console lines through the session forever, and
/// between them prints from the card (`auto0.g`, ... at boot, as Marlin);
/// asleep whenever there is nothing to do (the console's timers look at
/// the clock whenever woken). Without a printer (no valid printer.cfg),
/// every command that needs one is answered with the reason; the card
/// still lists and takes uploads (M20, M28), so a fixed printer.cfg can be
/// sent and the board restarted with M999.
fn serve(
    mut card: Option<BoardCard>,
    session: Result<(&'static mut BoardSession<'static>, BoardRole), ErrorText>,
) -> ! {
    let (mut session, mut mcu, no_printer) = match session {
        Ok((session, mcu)) => (Some(session), mcu, ErrorText::new()),
        Err(e) => (None, role_alone(), e),
    };
    let mut out = usb_console::ConsoleOut;
    let mut console = Console::new(step_timer::TIMER_HZ);
    console.autostart();
    loop {
        if let Some(incoming) = usb_console::try_line() {
            let event = incoming.event();
            let _ = console.line(
                session.as_deref_mut().map(BoardSession::console),
                &no_printer,
                &event,
                &mut card,
                &mut mcu,
                &mut out,
            );
            if console.take_restart() {
                restart();
            }
            continue;
        }
        let _ = console.poll(
            session.as_deref_mut().map(BoardSession::console),
            &mut card,
            &mut mcu,
            &mut out,
        );
        if !console.is_printing() {
            mcu.wait(u64::MAX);
        }
    }
}

/// FIRMWARE_RESTART, M999: a reset once the reply has had time to leave,
/// which reads printer.cfg again (as Klipper's restart reloads it); the
/// USB host sees the console reconnect.
fn restart() -> ! {
    let until = step_timer::now64() + (RESTART_DELAY * step_timer::TIMER_HZ) as u64;
    while step_timer::now64() < until {
        cortex_m::asm::wfe();
    }
    cortex_m::peripheral::SCB::sys_reset()
}

/// Time given to the last reply before a restart, s.
const RESTART_DELAY: f64 = 0.05;

/// Reads printer.cfg and its includes from the SD card, configures the
/// pins it names and builds the session (in place, in a static).
// Not inlined: its locals (the engine, the heaters, before they move
// into their statics) stay out of the caller's frame.
#[inline(never)]
fn load_printer(
    card: &mut Result<BoardCard, ErrorText>,
    thermistors: octopus_pro_v1_1::ThermistorPins,
) -> Result<(&'static mut BoardSession<'static>, BoardRole), ErrorText> {
    static AREA: StaticCell<LoadArea> = StaticCell::new();
    let area = AREA.uninit();
    let setup = read_setup(card, area)?;
    install_engine(setup)?;
    install_heaters(setup, thermistors)?;
    let mcu = install_board_mcu(setup)?;
    #[cfg(feature = "secondaries")]
    let mcu = WithSecondaries::new(mcu, connect_secondaries(setup)?, step_timer::TIMER_HZ);
    let session = BoardSession::init_board_in(
        LoadArea::session(area),
        setup.machine(),
        step_timer::TIMER_HZ,
        profile::MAX_STEP_ERROR,
        step_timer::now64(),
    );
    Ok((session, mcu))
}

/// Reads printer.cfg and its includes from the card and the printer from
/// them, indexing the text in `area`; checks what this build cannot drive.
// Not inlined (nor is `install_board_mcu`): their locals stay out of
// `load_printer`'s frame, which they made too large for short stack
// addressing.
#[inline(never)]
fn read_setup(
    card: &mut Result<BoardCard, ErrorText>,
    area: &mut MaybeUninit<LoadArea>,
) -> Result<&'static mut PrinterSetup<'static>, ErrorText> {
    static TEXT: ConstStaticCell<[u8; CONFIG_BUFFER]> = ConstStaticCell::new([0; CONFIG_BUFFER]);
    // The printer read from it (several KB: kept out of the stack).
    static SETUP: StaticCell<PrinterSetup<'static>> = StaticCell::new();
    let files = card.as_mut().map_err(|e| e.clone())?;
    let texts = config_files::load(files, TEXT.take()).map_err(|e| error_text(&e))?;
    let setup = PrinterSetup::load_in(
        SETUP.uninit(),
        &texts,
        pin_check::BOARD_RESERVED,
        LoadArea::scratch(area),
    )
    .map_err(|e| error_text(&e))?;
    #[cfg(not(feature = "secondaries"))]
    setup.without_secondaries().map_err(|e| error_text(&e))?;
    #[cfg(feature = "secondaries")]
    check_links(setup)?;
    for section in setup.unsupported() {
        defmt::info!("[{}] is not supported yet, ignored", section);
    }
    Ok(setup)
}

/// Configures the BLTouch's control pin, the TMC drivers' wires and the
/// filament sensors' inputs: this board's MCU role.
// Not inlined: see `read_setup`.
#[inline(never)]
fn install_board_mcu(setup: &PrinterSetup<'_>) -> Result<board_mcu::BoardMcu, ErrorText> {
    if let Some(pin) = setup
        .machine()
        .probe
        .and_then(|p| p.bltouch)
        .map(|b| b.control_pin)
    {
        let pin = setup.resolve_pin(pin).map_err(|e| error_text(&e))?;
        let pin = step_pins::OutPin::new_safe_off(&pin)
            .map_err(|e| error_text(&format_args!("[bltouch] {e}")))?;
        probe_servo::install(pin);
    }
    let mut mcu = board_mcu::BoardMcu {
        tmc: tmc_link::BoardTmc::install(setup)?,
        ..Default::default()
    };
    for sensor in &setup.machine().accessories.filament_sensors {
        let pin = setup
            .resolve_pin(sensor.switch_pin)
            .map_err(|e| error_text(&e))?;
        let input = step_pins::InPin::new(&pin)
            .map_err(|e| error_text(&format_args!("[{}] {e}", sensor.section)))?;
        let _ = mcu.filament.push(input);
    }
    Ok(mcu)
}

/// The memory printer.cfg is indexed in while the machine is read from it
/// (the scratch, 30 KB), then the session's (156 KB): the machine keeps
/// nothing of the index, which is dead before the session is built, so
/// they share it.
union LoadArea {
    _scratch: ManuallyDrop<Config<'static>>,
    _session: ManuallyDrop<BoardSession<'static>>,
}

impl LoadArea {
    /// The area as the config's index, for as long as `area` is lent.
    fn scratch(area: &mut MaybeUninit<Self>) -> &mut MaybeUninit<Config<'static>> {
        // SAFETY: a member of the union: at its start, no larger than it,
        // and a `MaybeUninit` asks nothing of the bytes there.
        unsafe { &mut *area.as_mut_ptr().cast() }
    }

    /// The area as the session's slot, once the index is no longer lent.
    fn session(area: &mut MaybeUninit<Self>) -> &mut MaybeUninit<BoardSession<'static>> {
        // SAFETY: as in `scratch`.
        unsafe { &mut *area.as_mut_ptr().cast() }
    }
}

/// Configures every stepper's step, direction and enable pins (drivers
/// enabled, off again on a fault) and its endstop input, and hands them to
/// the stepper engine; a pin that is not a GPIO of this board is an error.
// Not inlined: its locals (the engine, the heaters, before they move
// into their statics) stay out of the caller's frame.
#[inline(never)]
fn install_engine(setup: &PrinterSetup<'_>) -> Result<(), ErrorText> {
    let mut slots = [step_pins::StepperPins::default(); step_timer::STEPPERS];
    for (slot, stepper) in slots.iter_mut().zip(setup.steppers()) {
        let fail = |e: &dyn core::fmt::Display| error_text(&format_args!("[{}] {e}", stepper.name));
        let pin = |written| setup.resolve_pin(written).map_err(|e| fail(&e));
        // An enable pin here is on, whichever MCU steps its stepper.
        if let Some(enable) = stepper.enable_pin.filter(|p| on_main(p)) {
            step_pins::OutPin::new_safe_off(&pin(enable)?)
                .map_err(|e| fail(&e))?
                .set(true);
        }
        // A stepper on a secondary runs there (its slot here stays
        // empty); so do an enable pin or endstop written `NAME:PIN`.
        if !on_main(stepper.step_pin) {
            continue;
        }
        let (step, dir) = (pin(stepper.step_pin)?, pin(stepper.dir_pin)?);
        let pins = step_pins::StepperPins::new(&step, &dir).map_err(|e| fail(&e))?;
        *slot = pins.with_step_pulse(stepper.step_pulse);
        if let Some(endstop) = stepper.endstop_pin.filter(|p| on_main(p)) {
            let endstop = step_pins::InPin::new(&pin(endstop)?).map_err(|e| fail(&e))?;
            *slot = slot.with_endstop(endstop);
        }
    }
    // The probe's input: an endstop on the slot after the steppers.
    if let Some((i, pin)) = onechip_app::probe::input(setup.machine())
        && let Some(slot) = slots.get_mut(i)
    {
        let endstop =
            step_pins::InPin::new(pin).map_err(|e| error_text(&format_args!("[probe] {e}")))?;
        *slot = slot.with_endstop(endstop);
    }
    step_timer::install(step_timer::BoardEngine::new(slots));
    Ok(())
}

#[cfg(feature = "secondaries")]
/// Checks, before any secondary is connected, that each `[mcu NAME]`'s
/// `serial` is a USART of this board with a `baud` it can make, and that
/// printer.cfg uses that USART's pins for nothing else: an error names the
/// option (as a connect failure does).
fn check_links(setup: &PrinterSetup<'static>) -> Result<(), ErrorText> {
    let machine = setup.machine();
    for mcu in &machine.secondaries {
        let fail = |error| {
            error_text(&McuError::new(
                mcu.name,
                mcu.serial_at,
                ConnectError::Link(error),
            ))
        };
        usart_link::check(mcu.serial, mcu.baud).map_err(fail)?;
        if let Some(link_pins) = usart_link::pins(mcu.serial) {
            onechip_app::pin_check::check(machine, &link_pins).map_err(|e| error_text(&e))?;
        }
    }
    Ok(())
}

#[cfg(feature = "secondaries")]
/// Connects printer.cfg's secondary MCU over its USART and configures
/// its steppers (up to 15 s, as klippy's connect), in a static: None if
/// there is none; a failure is reported as a config error is.
#[inline(never)]
fn connect_secondaries(
    setup: &PrinterSetup<'static>,
) -> Result<Option<&'static mut secondary_links::BoardSecondaries>, ErrorText> {
    let machine = setup.machine();
    if machine.secondaries.is_empty() {
        return Ok(None);
    }
    let now = || step_timer::now64() as f64 / step_timer::TIMER_HZ;
    for mcu in &machine.secondaries {
        defmt::info!("connecting MCU '{}'", mcu.name);
    }
    let secondaries = secondary_links::secondaries(heater_io::mcu_sensor())
        .ok_or_else(|| error_text(&"secondary MCUs connected once already"))?;
    let links = &mut secondary_links::BoardLinks;
    (secondaries.connect(setup, &|name| name, links, &now)).map_err(|e| error_text(&e))?;
    Ok(Some(secondaries))
}

/// Configures the heaters' and fan's output pins and the thermistors'
/// ADC channels, and hands them with the heater control to TIM2's
/// interrupt; a pin that is not usable is an error.
// Not inlined: its locals (the engine, the heaters, before they move
// into their statics) stay out of the caller's frame.
#[inline(never)]
fn install_heaters(
    setup: &mut PrinterSetup<'_>,
    mut thermistors: octopus_pro_v1_1::ThermistorPins,
) -> Result<(), ErrorText> {
    if !setup.has_thermal() {
        return Ok(());
    }
    if setup.without_hard_pwm() {
        defmt::warn!("hardware_pwm is not supported on this board yet: software PWM");
    }
    let machine = setup.machine();
    let start = step_timer::now()
        .wrapping_add((onechip_app::heaters::FIRST_REPORT * step_timer::TIMER_HZ) as u32);
    let mcu_sensor = heater_io::mcu_sensor();
    let mcu_setup = onechip_app::heaters::McuSetup::new(
        machine,
        step_timer::TIMER_HZ,
        heater_io::ADC_MAX,
        mcu_sensor,
        start,
    );
    let (mut outputs, mut inputs) = (heapless::Vec::new(), heapless::Vec::new());
    for (pin, _) in &mcu_setup.outputs {
        // One on a secondary MCU is driven there (its updates forwarded).
        let out = if on_main(pin) {
            let pin = setup.resolve_pin(pin).map_err(|e| error_text(&e))?;
            Some(step_pins::OutPin::new(&pin).map_err(|e| error_text(&e))?)
        } else {
            None
        };
        let _ = outputs.push(out);
    }
    let buses = onechip_app::heaters::input_buses(machine);
    for ((pin, _), bus) in mcu_setup.inputs.iter().zip(buses) {
        let input = if !on_main(pin) {
            heater_io::AdcInput::Elsewhere
        } else if let Some(bus) = bus {
            let owner = format_args!("SPI sensor on {}", bus.cs_pin);
            heater_io::AdcInput::Spi(spi_sensors::SpiDevice::configured(setup, &bus, &owner)?)
        } else if *pin == onechip_app::heaters::MCU_TEMPERATURE_PIN {
            heater_io::AdcInput::Temperature
        } else {
            heater_io::AdcInput::Pin(thermistors.channel(pin).ok_or_else(|| {
                error_text(&format_args!(
                    "sensor_pin {pin} is not a thermistor input of this board (PF3..PF7)"
                ))
            })?)
        };
        let _ = inputs.push(input);
    }
    let mut hw = heater_io::BoardPeripherals {
        outputs,
        forwarded: ForwardedOutputs::new(&mcu_setup),
        adc: heater_io::Adc3::new(thermistors.adc),
        inputs,
    };
    let heaters = onechip_app::heaters::Heaters::new(
        machine,
        step_timer::TIMER_HZ,
        heater_io::ADC_MAX,
        mcu_sensor,
        start,
        &mut hw,
    );
    heater_io::install(heaters, hw);
    Ok(())
}

/// Wakes thread code at least every 10 ms (its priming timeout and
/// heater waits look at the clock when woken), and logs the stepper clock
/// once a second over RTT.
#[embassy_executor::task]
async fn tick() -> ! {
    let mut ticker = Ticker::every(Duration::from_millis(10));
    let mut ticks = 0u32;
    loop {
        ticker.next().await;
        cortex_m::asm::sev();
        ticks = ticks.wrapping_add(1);
        if ticks.is_multiple_of(100) {
            defmt::info!("stepper clock at {} ticks", step_timer::now64());
        }
    }
}
