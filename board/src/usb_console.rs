//! The USB CDC-ACM console: G-code lines in, replies out.
//!
//! Packets are split into lines by the shared [`LineAssembler`]; each line is
//! answered by [`onechip_app::console::answer`], which runs it on the
//! printer, and the reply is sent back in packets of at most the endpoint's
//! size.

use core::fmt;
use embassy_futures::select::{Either, select};
use embassy_stm32::usb::Driver;
use embassy_stm32::{bind_interrupts, peripherals, usb};
use embassy_time::{Duration, Timer};
use embassy_usb::class::cdc_acm::{CdcAcmClass, State};
use embassy_usb::driver::EndpointError;
use embassy_usb::{Builder, UsbDevice};
use onechip_app::console::error_text;
use onechip_app::heaters::ThermalCommand;
use onechip_app::line::{Line, LineAssembler};
use onechip_app::printer::LineError;
use onechip_app::printer::{PRIMING_TIME, Printer};
use onechip_planner::homing::HomingMove;
use onechip_planner::machine::MAX_STEPPERS;
use onechip_sched::endstop::Endstop;
use onechip_sched::engine::Command;
use onechip_stepgen::compress::StepCommand;
use onechip_stepgen::motion::{Motion, StepSink};
use static_cell::StaticCell;

bind_interrupts!(struct Irqs {
    OTG_HS => usb::InterruptHandler<peripherals::USB_OTG_HS>;
});

/// USB full-speed bulk packet size, in bytes.
const PACKET: usize = 64;
/// Longest accepted G-code line, in bytes.
const MAX_LINE: usize = 256;
/// Longest reply to one line, in bytes.
const MAX_REPLY: usize = 256;

type UsbDriver = Driver<'static, peripherals::USB_OTG_HS>;

/// Lookahead capacity of the board's printer, in moves: more than the
/// 0.25 s lazy-flush window of 1 ms segments, so long runs of tiny moves
/// are released lazily (about 117 KB of RAM).
pub const LOOKAHEAD: usize = 384;

/// Motion queue of the board, in segments.
pub const MOTION_QUEUE: usize = 128;
/// Steps each stepper's compressor holds.
pub const COMPRESS_QUEUE: usize = 256;

/// The board's step generation.
pub type BoardMotion = Motion<MOTION_QUEUE, COMPRESS_QUEUE>;

/// The printer and its step generation (both live in statics).
pub struct Machinery {
    /// G-code to planned moves.
    pub printer: &'static mut Printer<'static, LOOKAHEAD>,
    /// Planned moves to step commands for the engine.
    pub motion: &'static mut BoardMotion,
    /// What homing needs.
    pub homing: HomingSetup,
}

/// What homing needs on this board.
#[derive(Debug, Clone, Copy)]
pub struct HomingSetup {
    /// Axes (0 = X) whose stepper has an endstop on a GPIO input.
    pub endstops: [bool; 3],
    /// The motion steppers (bit `i`: stepper `i`): a trigger stops them all.
    pub rails: u32,
    /// The finest of their step distances, mm.
    pub finest_step: f64,
}

/// The printer the console drives (None if printer.cfg did not load).
pub type BoardPrinter = Option<Machinery>;

/// Hands step commands to the stepper engine, waiting while its outbox
/// for that stepper is full (its interrupt makes room), and runs homing
/// moves against the endstops.
struct EngineSteps<'h> {
    homing: &'h HomingSetup,
    /// The start clock of the homing move whose endstop is watched.
    watching: Option<u64>,
}

impl<'h> EngineSteps<'h> {
    fn new(homing: &'h HomingSetup) -> Self {
        Self {
            homing,
            watching: None,
        }
    }
}

impl StepSink for EngineSteps<'_> {
    fn command(&mut self, index: usize, cmd: StepCommand, clock: u64) {
        let cmd = Command::from(cmd);
        while crate::step_timer::push(index, cmd, clock).is_err() {
            if crate::step_timer::shutdown_reason().is_some() {
                return;
            }
            cortex_m::asm::nop();
        }
    }

    /// Watches the homed axis' endstop from the move's start and waits
    /// until the steps sent so far have run or the endstop triggered
    /// (which stopped every motion stepper at once). The wait holds the
    /// console (a homing move's slices are 50 ms apart).
    fn home(
        &mut self,
        homing: &HomingMove,
        start_clock: u64,
        until_clock: u64,
    ) -> Option<[i64; MAX_STEPPERS]> {
        use crate::step_timer;
        if self.watching != Some(start_clock) {
            let endstop = Endstop::for_homing(
                start_clock as u32,
                step_timer::TIMER_HZ,
                homing.speed,
                self.homing.finest_step,
            );
            step_timer::watch_endstop(homing.axis, endstop, self.homing.rails);
            self.watching = Some(start_clock);
        }
        while step_timer::now64() < until_clock && step_timer::shutdown_reason().is_none() {
            if step_timer::take_trigger().is_some() {
                self.watching = None;
                // Stopped at once: no step past the trigger.
                return Some([0; MAX_STEPPERS]);
            }
        }
        if until_clock as f64 >= homing.end_time * step_timer::TIMER_HZ {
            // The whole move ran without a trigger.
            step_timer::stop_watching();
            self.watching = None;
        }
        None
    }
}

/// Why a line could not run.
enum RunError<'l> {
    /// No valid printer.cfg, so no printer.
    NoConfig,
    /// Homing needs every axis' endstop on a GPIO input: without one, a
    /// homing move would run its whole length into the endstop.
    NoEndstops,
    /// The printer refused the command.
    Command(LineError<'l>),
}

impl fmt::Display for RunError<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::NoConfig => f.write_str("no valid printer.cfg on the SD card"),
            Self::NoEndstops => f.write_str(
                "G28: an axis has no endstop_pin on a GPIO of this board; set the position with SET_KINEMATIC_POSITION",
            ),
            Self::Command(e) => write!(f, "{e}"),
        }
    }
}

/// The USB device and its CDC-ACM function, ready to run.
pub struct Console {
    /// Runs enumeration and control transfers; must be polled forever.
    pub device: UsbDevice<'static, UsbDriver>,
    /// The serial port.
    pub class: CdcAcmClass<'static, UsbDriver>,
}

/// Builds the USB device (full speed on the internal PHY).
pub fn build(pins: crate::octopus_pro_v1_1::UsbPins) -> Console {
    static EP_OUT: StaticCell<[u8; 256]> = StaticCell::new();
    static CONFIG_DESC: StaticCell<[u8; 256]> = StaticCell::new();
    static BOS_DESC: StaticCell<[u8; 256]> = StaticCell::new();
    static CONTROL: StaticCell<[u8; 64]> = StaticCell::new();
    static STATE: StaticCell<State> = StaticCell::new();

    let mut usb_config = usb::Config::default();
    usb_config.vbus_detection = false;
    let driver = Driver::new_fs(
        pins.otg,
        Irqs,
        pins.dp,
        pins.dm,
        EP_OUT.init([0; 256]),
        usb_config,
    );

    let mut config = embassy_usb::Config::new(0x1d50, 0x614e);
    config.manufacturer = Some("onechip");
    config.product = Some("onechip Octopus Pro H723");
    config.serial_number = Some("onechip-0");
    config.max_power = 100;
    config.max_packet_size_0 = 64;

    let mut builder = Builder::new(
        driver,
        config,
        CONFIG_DESC.init([0; 256]),
        BOS_DESC.init([0; 256]),
        &mut [],
        CONTROL.init([0; 64]),
    );
    let class = CdcAcmClass::new(&mut builder, STATE.init(State::new()), PACKET as u16);
    Console {
        device: builder.build(),
        class,
    }
}

/// Serves the console forever: one connection after another.
pub async fn serve(class: &mut CdcAcmClass<'static, UsbDriver>, mut printer: BoardPrinter) -> ! {
    let mut lines = LineAssembler::<MAX_LINE>::new();
    loop {
        class.wait_connection().await;
        defmt::info!("usb console connected");
        match answer_lines(class, &mut lines, &mut printer).await {
            Ok(never) => match never {},
            Err(EndpointError::Disabled) => defmt::info!("usb console disconnected"),
            Err(EndpointError::BufferOverflow) => defmt::warn!("usb packet overflow"),
        }
    }
}

/// Reads packets, answers every completed line; when no input arrives for
/// the priming time, releases the moves still waiting in the lookahead.
/// Returns only on USB errors.
async fn answer_lines(
    class: &mut CdcAcmClass<'static, UsbDriver>,
    lines: &mut LineAssembler<MAX_LINE>,
    printer: &mut BoardPrinter,
) -> Result<core::convert::Infallible, EndpointError> {
    let mut packet = [0u8; PACKET];
    let idle = Duration::from_micros((PRIMING_TIME * 1e6) as u64);
    loop {
        let n = match select(class.read_packet(&mut packet), Timer::after(idle)).await {
            Either::First(read) => read?,
            Either::Second(()) => {
                if let Some(m) = printer.as_mut() {
                    m.printer
                        .priming_timeout(&mut m.motion.sink(&mut EngineSteps::new(&m.homing)));
                    m.motion
                        .generate(f64::INFINITY, &mut EngineSteps::new(&m.homing));
                }
                continue;
            }
        };
        for &byte in &packet[..n] {
            if let Some(event) = lines.push(byte) {
                let mut reply = heapless::String::<MAX_REPLY>::new();
                // A heater to wait for (M109, M190) before answering.
                let mut wait = None;
                let run = |text: &str, out: &mut heapless::String<MAX_REPLY>| match printer.as_mut()
                {
                    Some(m)
                        if !m.homing.endstops.iter().all(|&e| e)
                            && onechip_app::console::command_word(text.as_bytes())
                                .eq_ignore_ascii_case(b"G28") =>
                    {
                        Err(error_text(&RunError::NoEndstops))
                    }
                    Some(m) => {
                        // An idle printer starts its next move from now.
                        let now = crate::step_timer::now64() as f64 / crate::step_timer::TIMER_HZ;
                        m.printer.set_time_origin(now);
                        let mut steps = EngineSteps::new(&m.homing);
                        let result = m
                            .printer
                            .execute(text, &mut m.motion.sink(&mut steps), out)
                            .map_err(|e| error_text(&RunError::Command(e)));
                        m.motion.generate(f64::INFINITY, &mut steps);
                        while let Some(command) = m.printer.take_thermal() {
                            match command {
                                ThermalCommand::Report => crate::heater_io::report(out),
                                ThermalCommand::Target {
                                    heater, wait: true, ..
                                } => {
                                    crate::heater_io::command(command);
                                    wait = Some(heater);
                                }
                                _ => crate::heater_io::command(command),
                            }
                        }
                        result
                    }
                    None => Err(error_text(&RunError::NoConfig)),
                };
                if onechip_app::console::answer(&event, &mut reply, run).is_err() {
                    reply.clear();
                    // Fits: the fallback is far shorter than MAX_REPLY.
                    let _ = reply.push_str("!! reply too long\nok\n");
                }
                if let Line::TooLong { len } = event {
                    defmt::warn!("dropped a {} byte line", len);
                }
                if let Some(heater) = wait {
                    wait_for_heater(class, heater).await?;
                }
                send(class, reply.as_bytes()).await?;
            }
        }
    }
}

/// Waits until `heater` has reached its target (or everything shut
/// down), reporting temperatures once a second as Klipper does.
async fn wait_for_heater(
    class: &mut CdcAcmClass<'static, UsbDriver>,
    heater: usize,
) -> Result<(), EndpointError> {
    while crate::heater_io::busy(heater) {
        Timer::after(Duration::from_secs(1)).await;
        let mut line = heapless::String::<64>::new();
        crate::heater_io::report(&mut line);
        // Fits: two heaters' report is about 30 bytes.
        let _ = line.push('\n');
        send(class, line.as_bytes()).await?;
    }
    Ok(())
}

/// Sends `data` in packets; a reply that fills its last packet exactly is
/// closed with a zero-length packet so the host does not wait for more.
async fn send(
    class: &mut CdcAcmClass<'static, UsbDriver>,
    data: &[u8],
) -> Result<(), EndpointError> {
    for chunk in data.chunks(PACKET) {
        class.write_packet(chunk).await?;
    }
    if data.len().is_multiple_of(PACKET) {
        class.write_packet(&[]).await?;
    }
    Ok(())
}
