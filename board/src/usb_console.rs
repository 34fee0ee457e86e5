//! The USB CDC-ACM console: G-code lines in, replies out.
//!
//! USB runs on the I/O executor (an interrupt below the stepper and heater
//! timers), so it stays served however long thread code takes to plan,
//! generate steps or wait for a heater. Lines go to thread code through a
//! small channel (when it is full, reading stops and USB flow control
//! holds the host back: no line is lost); replies come back through a
//! pipe. Thread code never spins on either: it sleeps (`wfe`) until an
//! interrupt, and the I/O side signals (`sev`) whenever it moved data.

use embassy_stm32::usb::Driver;
use embassy_stm32::{bind_interrupts, peripherals, usb};
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::channel::Channel;
use embassy_sync::pipe::Pipe;
use embassy_usb::class::cdc_acm::{CdcAcmClass, Receiver, Sender, State};
use embassy_usb::{Builder, UsbDevice};
use onechip_app::emergency::EmergencyParser;
use onechip_app::line::{LineAssembler, LineEvent};
use onechip_app::session::profile::MAX_LINE;
use onechip_sched::shutdown::Shutdown;
use static_cell::StaticCell;

bind_interrupts!(struct Irqs {
    OTG_HS => usb::InterruptHandler<peripherals::USB_OTG_HS>;
});

/// USB full-speed bulk packet size, in bytes.
const PACKET: usize = 64;

type UsbDriver = Driver<'static, peripherals::USB_OTG_HS>;

/// One console line as thread code receives it.
pub struct Incoming {
    /// The line without its end (empty if it was too long).
    bytes: heapless::Vec<u8, MAX_LINE>,
    /// The length of a line longer than [`MAX_LINE`], which was dropped.
    too_long: Option<usize>,
}

impl Incoming {
    /// The line as the session takes it.
    pub fn event(&self) -> LineEvent<'_> {
        match self.too_long {
            Some(len) => LineEvent::TooLong { len },
            None => LineEvent::Complete(&self.bytes),
        }
    }
}

/// Lines from the host, waiting for thread code.
static LINES: Channel<CriticalSectionRawMutex, Incoming, 2> = Channel::new();
/// Replies from thread code, waiting for USB.
static REPLIES: Pipe<CriticalSectionRawMutex, 1024> = Pipe::new();

/// The next line from the host, if one has arrived (thread code).
pub fn try_line() -> Option<Incoming> {
    let line = LINES.try_receive().ok();
    if line.is_some() {
        // Room for the next line: the reader may go on.
        cortex_m::asm::sev();
    }
    line
}

/// Thread code's side of the replies: writing sleeps while the pipe is
/// full (the I/O executor empties it).
pub struct ConsoleOut;

impl core::fmt::Write for ConsoleOut {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        let mut bytes = s.as_bytes();
        while !bytes.is_empty() {
            match REPLIES.try_write(bytes) {
                Ok(n) => bytes = &bytes[n..],
                Err(_) => cortex_m::asm::wfe(),
            }
        }
        Ok(())
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

/// Runs the USB device (enumeration, control transfers) forever.
#[embassy_executor::task]
pub async fn device(mut device: UsbDevice<'static, UsbDriver>) -> ! {
    device.run().await
}

/// Reads packets and hands each completed line to thread code, one
/// connection after another.
#[embassy_executor::task]
pub async fn reader(mut rx: Receiver<'static, UsbDriver>) -> ! {
    let mut lines = LineAssembler::<MAX_LINE>::new();
    let mut emergency = EmergencyParser::new();
    let mut packet = [0u8; PACKET];
    loop {
        rx.wait_connection().await;
        defmt::info!("usb console connected");
        while let Ok(n) = rx.read_packet(&mut packet).await {
            for &byte in &packet[..n] {
                if emergency.push(byte) {
                    // Now, not when the line's turn comes.
                    crate::board_mcu::shutdown(Shutdown::EmergencyStop);
                }
                let incoming = match lines.push(byte) {
                    Some(LineEvent::Complete(bytes)) => Incoming {
                        // Fits: the assembler holds at most MAX_LINE bytes.
                        bytes: heapless::Vec::from_slice(bytes).unwrap_or_default(),
                        too_long: None,
                    },
                    Some(LineEvent::TooLong { len }) => Incoming {
                        bytes: heapless::Vec::new(),
                        too_long: Some(len),
                    },
                    None => continue,
                };
                LINES.send(incoming).await;
                cortex_m::asm::sev();
            }
        }
        defmt::info!("usb console disconnected");
    }
}

/// Sends the replies in packets; a reply that fills its last packet
/// exactly is closed with a zero-length packet so the host does not wait
/// for more. Without a host, replies are dropped (thread code never
/// blocks on a closed port).
#[embassy_executor::task]
pub async fn writer(mut tx: Sender<'static, UsbDriver>) -> ! {
    let mut buf = [0u8; PACKET];
    loop {
        let n = REPLIES.read(&mut buf).await;
        cortex_m::asm::sev();
        if tx.write_packet(&buf[..n]).await.is_ok() && n == PACKET && REPLIES.is_empty() {
            let _ = tx.write_packet(&[]).await;
        }
    }
}
