//! The board's TMC UART, bit by bit: the firmware's driver code
//! (`onechip_app::tmc::Tmc`) talks to simulated TMC2208/TMC2209 drivers
//! through the bit-banged single-wire UART the board runs from a timer
//! interrupt (`onechip_sched::tmc_uart::SoftUart`), in virtual time, each
//! timer event held off by a modelled interrupt latency.
//!
//! The drivers' side is modelled at the wire as the TMC22xx datasheet
//! describes its UART: it takes the bit rate from the request's sync
//! nibble (0x05: falling edges 0, 2 and 4 bit times after the first
//! start bit), reads each byte's bits in their middle after its start
//! bit's falling edge, ignores a request whose framing, sync or CRC is
//! wrong, and answers a read 8 bit times (SENDDELAY's default) after the
//! request's last stop bit, at the rate it measured. What a request means
//! is the simulated driver's (`onechip_host::tmc_sim`), the same as the
//! simulator's byte-level link uses; so a run over the wire must leave
//! every driver with the same register writes, in the same order, as the
//! byte-level run.

use onechip_app::tmc::{NoAnswer, Tmc, TmcLink};
use onechip_config::Config;
use onechip_host::tmc_sim::TmcSim;
use onechip_planner::machine::Machine;
use onechip_sched::tmc_uart::{FRAME_BITS, Failure, Pin, SoftUart, wire_level};
use std::path::PathBuf;

/// The board's timer clock, Hz, and Klipper's TMC UART bit rate.
const TIMER_HZ: f64 = 260e6;
const BAUD: f64 = 40_000.0;
/// Bit time, ticks.
const BIT: u32 = (TIMER_HZ / BAUD) as u32;

/// How late each timer event begins: a seeded pseudo-random latency of
/// up to `max` ticks, and with probability `p_long` one of `long` ticks
/// (another interrupt ran long).
struct Latency {
    state: u64,
    max: u32,
    p_long: f64,
    long: u32,
}

impl Latency {
    fn new(seed: u64, max: u32, p_long: f64, long: u32) -> Self {
        Self {
            state: seed | 1,
            max,
            p_long,
            long,
        }
    }

    /// 0..1, uniform (xorshift64*).
    fn uniform(&mut self) -> f64 {
        self.state ^= self.state >> 12;
        self.state ^= self.state << 25;
        self.state ^= self.state >> 27;
        (self.state.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
    }

    fn next(&mut self) -> u32 {
        if self.uniform() < self.p_long {
            return self.long;
        }
        (self.uniform() * f64::from(self.max)) as u32
    }
}

/// The simulated drivers behind the bit-banged UART.
struct Wire {
    drivers: TmcSim,
    latency: Latency,
    /// Exchanges run, and how many failed, by why.
    exchanges: usize,
    late: usize,
    no_reply: usize,
    /// Times the firmware drove the line while the driver was sending.
    contention: usize,
}

impl Wire {
    fn new(drivers: TmcSim, latency: Latency) -> Self {
        Self {
            drivers,
            latency,
            exchanges: 0,
            late: 0,
            no_reply: 0,
            contention: 0,
        }
    }
}

/// The request as a driver reads it from the levels the firmware drove
/// (`edges`: time in ticks and level, in order; high before the first):
/// its bytes, the bit time it measured (ticks) and when its last stop bit
/// ended. None if the line carried no well-formed request.
fn driver_reads(edges: &[(f64, bool)]) -> Option<(Vec<u8>, f64, f64)> {
    let level_at = |t: f64| {
        edges
            .iter()
            .rev()
            .find(|(at, _)| *at <= t)
            .is_none_or(|(_, level)| *level)
    };
    let falls: Vec<f64> = edges
        .iter()
        .enumerate()
        .filter(|&(i, &(_, level))| !level && (i == 0 || edges[i - 1].1))
        .map(|(_, &(t, _))| t)
        .collect();
    let first = *falls.first()?;
    let bit = (falls.get(2)? - first) / 4.0;
    let (mut bytes, mut start) = (Vec::new(), Some(first));
    let mut end = first;
    while let Some(s) = start {
        let at = |k: usize| s + (k as f64 + 0.5) * bit;
        if level_at(at(0)) || !level_at(at(FRAME_BITS - 1)) {
            return None;
        }
        bytes.push((0..8).fold(0u8, |b, k| b | u8::from(level_at(at(k + 1))) << k));
        end = s + FRAME_BITS as f64 * bit;
        start = falls.iter().copied().find(|&t| t > at(FRAME_BITS - 1));
    }
    (bytes.first().is_some_and(|b| b & 0x0f == 0x05)).then_some((bytes, bit, end))
}

/// The line's level at `t` while a driver sends `reply` from `start`,
/// `bit` ticks per bit (high outside it: the pull-up).
fn reply_level(reply: &[u8], start: f64, bit: f64, t: f64) -> bool {
    let k = (t - start) / bit;
    k < 0.0 || wire_level(reply, k as usize)
}

impl TmcLink for Wire {
    fn uart(&mut self, port: u8, tx: &[u8], rx: &mut [u8]) -> Result<(), NoAnswer> {
        self.exchanges += 1;
        let mut uart = SoftUart::new();
        uart.start(tx, rx.len(), BIT).map_err(|_| NoAnswer)?;
        // What the firmware drove, and the driver's reply once it has
        // read the request (its bytes, start, bit time).
        let mut edges: Vec<(f64, bool)> = Vec::new();
        let mut reply: Option<(Vec<u8>, f64, f64)> = None;
        let mut released = false;
        let mut due = 0u64;
        loop {
            let late = self.latency.next();
            let t = (due + u64::from(late)) as f64;
            let line = match (&reply, released) {
                (Some((bytes, start, bit)), true) => reply_level(bytes, *start, *bit, t),
                (None, true) => true,
                (_, false) => edges.last().is_none_or(|e| e.1),
            };
            let event = uart.on_event(line, late);
            match event.pin {
                Pin::Drive(level) => {
                    // The driver's output is on from its reply's start
                    // to 4 bit times after its last stop bit, high for
                    // those 4: driving the line while it sends its
                    // frames, or low after them, fights it.
                    if let Some((bytes, start, bit)) = &reply {
                        let frames_end = start + (bytes.len() * FRAME_BITS) as f64 * bit;
                        let off = frames_end + 4.0 * bit;
                        if (*start..frames_end).contains(&t)
                            || (!level && (frames_end..off).contains(&t))
                        {
                            self.contention += 1;
                        }
                    }
                    edges.push((t, level));
                    released = false;
                }
                Pin::Release => released = true,
                Pin::Keep => {}
            }
            // The driver acts on a request once its last stop bit ends
            // (a write: at the end of the exchange).
            if (event.pin == Pin::Release || event.next.is_none())
                && reply.is_none()
                && let Some((bytes, bit, end)) = driver_reads(&edges)
            {
                let mut answer = [0u8; 8];
                let len = if bytes.len() == 4 { answer.len() } else { 0 };
                if self.drivers.uart(port, &bytes, &mut answer[..len]).is_ok() {
                    reply = Some((answer[..len].to_vec(), end + 8.0 * bit, bit));
                }
            }
            match event.next {
                Some(d) => due += u64::from(d),
                None => break,
            }
        }
        let outcome = uart.reply(rx);
        match outcome {
            Err(Failure::Late) => self.late += 1,
            Err(_) => self.no_reply += 1,
            Ok(()) => {}
        }
        outcome.map_err(|_| NoAnswer)
    }

    fn spi(&mut self, port: u8, data: &mut [u8]) -> Result<(), NoAnswer> {
        self.drivers.spi(port, data)
    }
}

/// Stock config `file`'s machine (leaked: the test's lifetime).
fn machine(file: &str) -> Machine<'static> {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/klipper-configs")
        .join(file);
    let text = std::fs::read_to_string(&path).expect("stock config");
    let text: &'static str = Box::leak(text.into_boxed_str());
    let name: &'static str = Box::leak(file.to_string().into_boxed_str());
    let config: &'static Config<'static> =
        Box::leak(Box::new(Config::parse(name, text).expect("parses")));
    Machine::from_config(config).unwrap_or_else(|e| panic!("{file}: {e}"))
}

/// Runs the firmware's start-up writes and `checks` periodic checks
/// through `link`; the messages it printed.
fn run(tmc: &mut Tmc<'_>, link: &mut dyn TmcLink, checks: usize) -> Result<String, String> {
    let mut out = String::new();
    tmc.poll(link, 0.0, &mut out).map_err(|e| e.to_string())?;
    for k in 1..=checks {
        tmc.poll(link, k as f64, &mut out)
            .map_err(|e| e.to_string())?;
    }
    Ok(out)
}

/// Every driver's register writes, in order, by stepper.
fn writes(sim: &TmcSim) -> Vec<(String, Vec<(u8, u32)>)> {
    sim.drivers
        .iter()
        .map(|d| (d.stepper.clone(), d.written.clone()))
        .collect()
}

/// Stock configs whose drivers are all on a UART: one pin each, one pin
/// shared by four addresses with its own transmit pin, a TMC2208.
const UART_CONFIGS: [&str; 4] = [
    "printer-sovol-sv06-2022.cfg",
    "generic-bigtreetech-skr-mini-e3-v2.0.cfg",
    "generic-bigtreetech-skr-pico-v1.0.cfg",
    "printer-biqu-b1-se-plus-2022.cfg",
];

#[test]
fn stock_uart_drivers_get_the_same_writes_over_the_wire_as_over_datagrams() {
    for file in UART_CONFIGS {
        let machine = machine(file);
        assert!(!machine.tmc.is_empty(), "{file}: no TMC driver");
        let mut direct = TmcSim::new(&machine);
        run(&mut Tmc::new(&machine), &mut direct, 3).unwrap_or_else(|e| panic!("{file}: {e}"));
        // Latency up to a tenth of a bit on every event.
        let mut wire = Wire::new(TmcSim::new(&machine), Latency::new(7, BIT / 10, 0.0, 0));
        let mut tmc = Tmc::new(&machine);
        run(&mut tmc, &mut wire, 3).unwrap_or_else(|e| panic!("{file}: {e}"));
        assert_eq!(writes(&wire.drivers), writes(&direct), "{file}");
        for d in &machine.tmc {
            let regs = tmc.registers(d.stepper).expect("driver");
            let sim = wire.drivers.driver(d.stepper).expect("simulated");
            for (addr, value) in regs.iter() {
                assert_eq!(sim.register(addr), value, "{file}: {} {addr:#x}", d.stepper);
            }
        }
        assert_eq!(
            (wire.late, wire.no_reply, wire.contention),
            (0, 0, 0),
            "{file}"
        );
        eprintln!("{file}: {} exchanges over the wire", wire.exchanges);
    }
}

#[test]
fn an_exchange_held_off_by_another_interrupt_is_retried_never_misread() {
    let machine = machine("printer-sovol-sv06-2022.cfg");
    let mut direct = TmcSim::new(&machine);
    run(&mut Tmc::new(&machine), &mut direct, 3).expect("direct");
    // One event in 2,000 begins a whole bit late: a read (about 400
    // events) fails now and then, and is tried again.
    let mut wire = Wire::new(
        TmcSim::new(&machine),
        Latency::new(11, BIT / 10, 0.0005, BIT),
    );
    run(&mut Tmc::new(&machine), &mut wire, 3).expect("over the wire");
    assert!(
        wire.late > 0,
        "no exchange was late: the test shows nothing"
    );
    assert_eq!(writes(&wire.drivers), writes(&direct));
    // A late exchange still leaves the line to the driver for its reply.
    assert_eq!(wire.contention, 0, "the line driven during a reply");
    eprintln!(
        "{} exchanges, {} retried after a late event",
        wire.exchanges, wire.late
    );
}

#[test]
fn a_driver_reset_is_seen_over_the_wire_and_its_registers_written_again() {
    let machine = machine("printer-sovol-sv06-2022.cfg");
    let mut wire = Wire::new(TmcSim::new(&machine), Latency::new(3, BIT / 10, 0.0, 0));
    let mut tmc = Tmc::new(&machine);
    run(&mut tmc, &mut wire, 1).expect("start");
    let before = writes(&wire.drivers);
    wire.drivers
        .driver("stepper_y")
        .expect("stepper_y")
        .power_cycle();
    let out = run(&mut tmc, &mut wire, 2).expect("checks");
    assert!(
        out.contains("TMC 'stepper_y' was reset"),
        "no reset reported: {out}"
    );
    let after = writes(&wire.drivers);
    for ((name, was), (_, now)) in before.iter().zip(&after) {
        let added = now.len() - was.len();
        if name == "stepper_y" {
            assert!(added >= 4, "{name}: {added} writes after the reset");
        } else {
            assert_eq!(added, 0, "{name} written again: {:?}", &now[was.len()..]);
        }
    }
    let regs = tmc.registers("stepper_y").expect("stepper_y");
    let sim = wire.drivers.driver("stepper_y").expect("stepper_y");
    for (addr, value) in regs.iter() {
        assert_eq!(sim.register(addr), value, "{addr:#x}");
    }
}

#[test]
fn a_driver_that_never_answers_is_klippers_error_after_its_tries() {
    let machine = machine("printer-sovol-sv06-2022.cfg");
    let mut sim = TmcSim::new(&machine);
    // The driver answers at another address: nothing answers ours.
    sim.drivers.retain(|d| d.stepper != "stepper_x");
    let mut wire = Wire::new(sim, Latency::new(5, BIT / 10, 0.0, 0));
    let error = run(&mut Tmc::new(&machine), &mut wire, 0).expect_err("no driver");
    // Klipper's: the interface counter is read before the first write,
    // 5 tries.
    assert_eq!(error, "Unable to read tmc uart 'stepper_x' register IFCNT");
    assert_eq!((wire.no_reply, wire.late), (5, 0), "Klipper's 5 tries");
}

#[test]
fn a_periodic_check_tries_a_silent_uart_driver_three_times_50_ms_apart() {
    let machine = machine("printer-sovol-sv06-2022.cfg");
    let mut wire = Wire::new(TmcSim::new(&machine), Latency::new(9, BIT / 10, 0.0, 0));
    let mut tmc = Tmc::new(&machine);
    run(&mut tmc, &mut wire, 0).expect("start");
    let mut out = String::new();
    // stepper_x, the first checked, stops answering.
    let at = wire
        .drivers
        .drivers
        .iter()
        .position(|d| d.stepper == "stepper_x");
    wire.drivers.drivers.remove(at.expect("stepper_x"));
    let mut poll =
        |wire: &mut Wire, now: f64| tmc.poll(wire, now, &mut out).map_err(|e| e.to_string());
    // Not due yet: nothing is read.
    let before = wire.exchanges;
    assert_eq!(poll(&mut wire, 0.5), Ok(()));
    assert_eq!(wire.exchanges, before);
    // Due: the read fails (5 exchanges), the check is tried again 50 ms
    // later, not sooner.
    assert_eq!(poll(&mut wire, 1.0), Ok(()));
    assert_eq!(wire.no_reply, 5);
    assert_eq!(poll(&mut wire, 1.04), Ok(()));
    assert_eq!(wire.no_reply, 5);
    assert_eq!(poll(&mut wire, 1.05), Ok(()));
    assert_eq!(wire.no_reply, 10);
    // The third try fails: Klipper's error.
    assert_eq!(
        poll(&mut wire, 1.10),
        Err("Unable to read tmc uart 'stepper_x' register DRV_STATUS".into())
    );
    assert_eq!(wire.no_reply, 15);

    // A driver back before its third try: no error, and the checks go on.
    let mut tmc = Tmc::new(&machine);
    let mut wire = Wire::new(TmcSim::new(&machine), Latency::new(9, BIT / 10, 0.0, 0));
    run(&mut tmc, &mut wire, 0).expect("start");
    let mut out = String::new();
    let at = wire
        .drivers
        .drivers
        .iter()
        .position(|d| d.stepper == "stepper_x");
    let unplugged = wire.drivers.drivers.remove(at.expect("stepper_x"));
    assert!(tmc.poll(&mut wire, 1.0, &mut out).is_ok());
    wire.drivers.drivers.push(unplugged);
    for k in 1..=40 {
        let now = 1.0 + 0.05 * f64::from(k);
        tmc.poll(&mut wire, now, &mut out)
            .unwrap_or_else(|e| panic!("at {now} s: {e}"));
    }
    assert_eq!(
        wire.no_reply, 5,
        "one failed read, then every check answered"
    );
}
