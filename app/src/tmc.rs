//! TMC drivers at run time, as Klipper's `tmc.py` drives them: every
//! register written at start, the drivers checked once a second (a reset
//! or power loss is seen in GSTAT's `reset` flag, or a TMC2660's zero
//! current scale, and the registers are written again), and the G-code
//! commands SET_TMC_CURRENT, SET_TMC_FIELD, DUMP_TMC and INIT_TMC. A rail
//! homing on a driver's virtual endstop (sensorless homing) gets Klipper's
//! register changes around each homing move
//! (`onechip_planner::tmc::sensorless`).
//!
//! The bytes go through a [`TmcLink`] that the board or the simulator
//! provides; the datagrams are `onechip_planner::tmc::wire`'s.
//!
//! A command that writes registers waits, as Klipper's does, until the
//! queued moves have run (Klipper sends the writes for the last move's
//! time and waits for their answer). Differences from Klipper, by design
//! of this firmware: drivers stay enabled, so a reset is repaired when the periodic
//! check sees it (Klipper rewrites the registers at the next enable and
//! reports a reset seen while enabled as an error).

use crate::text::{ErrorText, cut_text};
use core::fmt::{self, Write};
use onechip_config::decimal::{self, Fixed};
use onechip_planner::gcode::{Command, Extended, Line};
use onechip_planner::machine::Machine;
use onechip_planner::tmc::config::{Bus, MAX_DRIVERS, TmcDriver};
use onechip_planner::tmc::registers::{RegDef, TMC2660_READRSP};
use onechip_planner::tmc::sensorless::{self, Saved};
use onechip_planner::tmc::{DriverKind, RegisterFile, wire};

/// The bus did not answer (no reply, or a reply that failed its check).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NoAnswer;

/// The wires to the drivers, as the board or the simulator provides them.
/// A port is one UART pin or one SPI chip select (drivers sharing it are
/// told apart by UART address or chain position).
pub trait TmcLink {
    /// Sends `tx` on UART port `port`, then receives `rx.len()` bytes
    /// (none after a write request).
    fn uart(&mut self, port: u8, tx: &[u8], rx: &mut [u8]) -> Result<(), NoAnswer>;
    /// One SPI transfer on port `port` with its chip select held: `data`
    /// goes out and is replaced by the bytes clocked in.
    fn spi(&mut self, port: u8, data: &mut [u8]) -> Result<(), NoAnswer>;
}

/// The port number of each of `drivers`, in order: a port is one wire
/// (a UART pin, an SPI chip select), numbered in order of first use; the
/// board wires port `n` to the `n`-th distinct wire.
pub fn port_numbers<'d>(drivers: &'d [TmcDriver<'_>]) -> impl Iterator<Item = u8> + 'd {
    let first_of_port = |k: usize| drivers[..k].iter().all(|e| e.port() != drivers[k].port());
    (0..drivers.len()).map(move |k| {
        let first = (0..=k)
            .find(|&i| drivers[i].port() == drivers[k].port())
            .unwrap_or(k);
        (0..first).filter(|&i| first_of_port(i)).count() as u8
    })
}

/// How often each driver is checked, s (Klipper's period).
pub const CHECK_PERIOD: f64 = 1.0;
/// Further tries of a periodic check whose UART read failed (Klipper's
/// check reads a UART register up to 3 times).
const READ_RETRIES: u8 = 2;
/// The pause before such a try, s (Klipper's).
const READ_RETRY_PAUSE: f64 = 0.050;

/// Why a periodic check failed.
enum Unreached {
    /// A UART driver did not answer a read (tried again later).
    Uart(ErrorText),
    /// Anything else: an SPI driver that did not answer, an error flag.
    Other(ErrorText),
}
/// Tries of one register access before it is an error (Klipper's).
const TRIES: usize = 5;
/// Longest daisy chain a transfer is built for.
const MAX_CHAIN: usize = 8;

/// One driver at run time.
#[derive(Debug, Clone)]
struct Driver<'a> {
    config: TmcDriver<'a>,
    /// Its bus' port number (drivers sharing a wire share it).
    port: u8,
    /// The UART interface counter after our last write.
    ifcnt: Option<u8>,
    /// The hold current last asked for, A (Klipper's `req_hold_current`).
    req_hold: Option<f64>,
    /// The TMC2660's run current, A.
    current_2660: f64,
    /// The engine slots (bit `i`: stepper `i`) whose endstop is this
    /// driver's virtual endstop.
    homes: u32,
    /// During a homing move on its virtual endstop: what to restore.
    homing: Option<Saved>,
}

/// Every TMC driver of the printer.
#[derive(Debug, Clone)]
pub struct Tmc<'a> {
    drivers: heapless::Vec<Driver<'a>, MAX_DRIVERS>,
    /// When the next check is due, s of MCU time (`None`: registers not
    /// written yet).
    next_check: Option<f64>,
    /// The driver the next check looks at.
    next_driver: usize,
    /// Further tries taken of its check after failed UART reads.
    read_retries: u8,
    /// The first register write of a homing move's setup that failed, not
    /// yet reported.
    homing_failure: Option<Failure<'a>>,
}

/// A driver's failure, as Klipper words it.
#[derive(Debug, Clone, Copy)]
enum Failure<'a> {
    Read(&'a str, &'static str, bool),
    Write(&'a str, &'static str, bool),
}

impl From<Failure<'_>> for ErrorText {
    fn from(failure: Failure<'_>) -> Self {
        cut_text(&failure)
    }
}

impl fmt::Display for Failure<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (what, stepper, reg, uart) = match *self {
            Self::Read(s, r, u) => ("read", s, r, u),
            Self::Write(s, r, u) => ("write", s, r, u),
        };
        let bus = if uart { "uart" } else { "spi" };
        write!(f, "Unable to {what} tmc {bus} '{stepper}' register {reg}")
    }
}

impl<'a> Tmc<'a> {
    /// The drivers of `machine`, their ports numbered in order of first
    /// use, each knowing which steppers home on its virtual endstop.
    pub fn new(machine: &Machine<'a>) -> Self {
        let drivers = &machine.tmc;
        let mut out: heapless::Vec<Driver<'a>, MAX_DRIVERS> = heapless::Vec::new();
        for ((k, config), port) in drivers.iter().enumerate().zip(port_numbers(drivers)) {
            let homes = (machine.stall_homing.iter().enumerate())
                .filter(|&(_, &d)| d.is_some_and(|d| usize::from(d) == k))
                .fold(0, |bits, (i, _)| {
                    bits | 1u32.checked_shl(i as u32).unwrap_or(0)
                });
            let _ = out.push(Driver {
                config: config.clone(),
                port,
                ifcnt: None,
                req_hold: config.hold_current,
                current_2660: config.run_current,
                homes,
                homing: None,
            });
        }
        Self {
            drivers: out,
            next_check: None,
            next_driver: 0,
            read_retries: 0,
            homing_failure: None,
        }
    }

    /// [`HomingDrivers`]' begin (`begin`) or end of a homing move.
    fn homing_move(&mut self, link: &mut dyn TmcLink, slots: u32, begin: bool) {
        for i in 0..self.drivers.len() {
            let d = &mut self.drivers[i];
            if d.homes & slots == 0 || d.homing.is_some() == begin {
                continue;
            }
            let field = d.config.diag.and_then(|(_, field)| field);
            let regs = &mut d.config.regs;
            let writes = match d.homing.take() {
                Some(saved) => sensorless::end(regs, field, saved),
                None => {
                    let (writes, saved) = sensorless::begin(regs, field);
                    d.homing = Some(saved);
                    writes
                }
            };
            for (addr, value) in writes.into_iter().flatten() {
                if let Err(failure) = self.write(link, i, addr, value) {
                    self.homing_failure.get_or_insert(failure);
                }
            }
        }
    }

    /// The first register write around a homing move that failed since
    /// last asked, as Klipper words it.
    pub fn take_homing_failure(&mut self) -> Option<ErrorText> {
        self.homing_failure.take().map(ErrorText::from)
    }

    /// True if there is no driver.
    pub fn is_empty(&self) -> bool {
        self.drivers.is_empty()
    }

    /// The port number of stepper `stepper`'s driver (drivers sharing a
    /// wire share it); for simulators that wire up drivers.
    pub fn port_of(&self, stepper: &str) -> Option<u8> {
        self.drivers
            .iter()
            .find(|d| d.config.stepper == stepper)
            .map(|d| d.port)
    }

    /// Register values as last written to stepper `stepper`'s driver.
    pub fn registers(&self, stepper: &str) -> Option<&RegisterFile> {
        self.drivers
            .iter()
            .find(|d| d.config.stepper == stepper)
            .map(|d| &d.config.regs)
    }

    /// At start (the first call) every register of every driver is
    /// written; then each driver is checked once every [`CHECK_PERIOD`] of
    /// MCU time `now` (s), the drivers spread over the period, one per
    /// call (a call on the board's UART waits for its exchanges: two
    /// reads, about 7 ms, so thread code is held no longer). A driver that
    /// was reset is written again (reported on `out`). A UART read that
    /// fails is tried again 50 ms later, twice, as Klipper's check allows;
    /// a driver that cannot be reached then is an error, as is one
    /// reporting an error.
    pub fn poll(
        &mut self,
        link: &mut dyn TmcLink,
        now: f64,
        out: &mut dyn Write,
    ) -> Result<(), ErrorText> {
        match self.next_check {
            None => {
                self.next_check = Some(now + CHECK_PERIOD);
                for i in 0..self.drivers.len() {
                    self.init(link, i)?;
                    self.clear_reset(link, i)?;
                }
            }
            Some(due) if now >= due => {
                // A driver that fails is reported once; checks stop.
                self.next_check = Some(f64::INFINITY);
                let i = self.next_driver;
                match self.check(link, i, out) {
                    Err(Unreached::Uart(_)) if self.read_retries < READ_RETRIES => {
                        self.read_retries += 1;
                        self.next_check = Some(now + READ_RETRY_PAUSE);
                        return Ok(());
                    }
                    Err(Unreached::Uart(e) | Unreached::Other(e)) => return Err(e),
                    Ok(()) => {}
                }
                self.read_retries = 0;
                let n = self.drivers.len().max(1);
                self.next_driver = (i + 1) % n;
                self.next_check = Some(now + CHECK_PERIOD / n as f64);
            }
            Some(_) => {}
        }
        Ok(())
    }

    /// Writes every register of driver `i` in Klipper's order.
    fn init(&mut self, link: &mut dyn TmcLink, i: usize) -> Result<(), ErrorText> {
        let regs = self.drivers[i].config.regs.clone();
        for (addr, value) in regs.iter() {
            self.write(link, i, addr, value)?;
        }
        Ok(())
    }

    /// Driver `i`'s periodic check: its status registers read once each
    /// (DRV_STATUS and GSTAT; the TMC2660's read response). A reset
    /// (GSTAT's `reset` flag; on the TMC2660 a zero current scale `se`
    /// while CS is set) is reported and the registers written again. An
    /// error flag (overtemperature, shorts, driver error, undervoltage) is
    /// Klipper's "TMC '…' reports error: REGISTER: value fields".
    fn check(
        &mut self,
        link: &mut dyn TmcLink,
        i: usize,
        out: &mut dyn Write,
    ) -> Result<(), Unreached> {
        const ERRORS: [&str; 7] = ["ot", "s2ga", "s2gb", "s2vsa", "s2vsb", "drv_err", "uv_cp"];
        let Some(d) = self.drivers.get(i) else {
            return Ok(());
        };
        let (kind, name) = (d.config.kind, d.config.stepper);
        let status = match kind {
            DriverKind::Tmc2660 => ["READRSP@RDSEL2", ""],
            _ => ["DRV_STATUS", "GSTAT"],
        };
        let mut reset = false;
        for reg in status.iter().filter_map(|name| kind.register_any(name)) {
            let value = self.read(link, i, reg.name).map_err(|e| {
                if kind.is_uart() {
                    Unreached::Uart(e)
                } else {
                    Unreached::Other(e)
                }
            })?;
            reset |= match kind {
                DriverKind::Tmc2660 => {
                    (value >> 14) & 0x1f == 0 && self.drivers[i].config.regs.get("cs") > 0
                }
                _ => reg.name == "GSTAT" && value & 1 != 0,
            };
            let failed = reg
                .fields
                .iter()
                .any(|f| ERRORS.contains(&f.name) && f.get(value) != 0);
            if failed {
                return Err(Unreached::Other(cut_text(&format_args!(
                    "TMC '{name}' reports error: {}",
                    Pretty(kind, reg, value)
                ))));
            }
        }
        if reset {
            let _ = writeln!(
                out,
                "// TMC '{name}' was reset (power loss?): registers written again"
            );
            self.init(link, i).map_err(Unreached::Other)?;
            self.clear_reset(link, i).map_err(Unreached::Other)?;
        }
        Ok(())
    }

    /// Clears driver `i`'s GSTAT flags (written back as ones), as Klipper's
    /// start-up check does.
    fn clear_reset(&mut self, link: &mut dyn TmcLink, i: usize) -> Result<(), ErrorText> {
        let Some(gstat) = self.drivers[i].config.regs.kind().register_any("GSTAT") else {
            return Ok(());
        };
        let flags = self.read(link, i, "GSTAT")?;
        // The TMC2130 clears GSTAT by being read.
        if flags != 0 && self.drivers[i].config.kind != DriverKind::Tmc2130 {
            self.write(link, i, gstat.addr, flags)?;
        }
        Ok(())
    }

    /// Writes `value` to register `addr` of driver `i`, checked as Klipper
    /// checks it (UART: the interface counter moved by one; SPI: the
    /// driver echoes the data), up to [`TRIES`] times.
    fn write(
        &mut self,
        link: &mut dyn TmcLink,
        i: usize,
        addr: u8,
        value: u32,
    ) -> Result<(), Failure<'a>> {
        let d = &self.drivers[i];
        let (port, kind) = (d.port, d.config.kind);
        let reg_name = kind.register_at_any(addr).map_or("?", |r| r.name);
        let failed = Failure::Write(d.config.name(), reg_name, kind.is_uart());
        match d.config.bus {
            Bus::Uart { address, .. } => {
                let ifcnt = kind.register_any("IFCNT").map_or(0x02, |r| r.addr);
                let name = d.config.name();
                // IFCNT read as any register is: tried again, and an
                // error of its own if it never answers.
                let read_ifcnt = |link: &mut dyn TmcLink| {
                    (0..TRIES)
                        .find_map(|_| uart_read(link, port, address, ifcnt).ok())
                        .map(|v| v as u8)
                        .ok_or(Failure::Read(name, "IFCNT", true))
                };
                for _ in 0..TRIES {
                    let before = match self.drivers[i].ifcnt {
                        Some(n) => n,
                        None => read_ifcnt(link)?,
                    };
                    let _ = link.uart(port, &wire::uart_write(address, addr, value), &mut []);
                    let after = read_ifcnt(link);
                    self.drivers[i].ifcnt = after.ok();
                    if after? == before.wrapping_add(1) {
                        return Ok(());
                    }
                }
                Err(failed)
            }
            Bus::Spi { .. } if kind == DriverKind::Tmc2660 => {
                let mut d = wire::spi_2660(addr, value);
                link.spi(port, &mut d).map_err(|_| failed)
            }
            Bus::Spi {
                chain_position,
                chain_length,
                ..
            } => {
                for _ in 0..TRIES {
                    let datagram = wire::spi_datagram(addr, Some(value));
                    if spi(link, port, datagram, chain_position, chain_length).is_err() {
                        continue;
                    }
                    let echo = spi(
                        link,
                        port,
                        wire::spi_datagram(0, None),
                        chain_position,
                        chain_length,
                    );
                    if echo == Ok(value) {
                        return Ok(());
                    }
                }
                Err(failed)
            }
        }
    }

    /// Reads register `name` of driver `i`.
    fn read(&mut self, link: &mut dyn TmcLink, i: usize, name: &str) -> Result<u32, ErrorText> {
        let d = &self.drivers[i];
        let (port, kind) = (d.port, d.config.kind);
        let Some(reg) = kind.register_any(name) else {
            return Err(cut_text(&format_args!("Unknown register name '{name}'")));
        };
        let failed = Failure::Read(d.config.name(), reg.name, kind.is_uart());
        let value = match d.config.bus {
            Bus::Uart { address, .. } => {
                (0..TRIES).find_map(|_| uart_read(link, port, address, reg.addr).ok())
            }
            Bus::Spi { .. } if kind == DriverKind::Tmc2660 => {
                // Select the response with DRVCONF's rdsel, then read it
                // with the next datagram.
                let rdsel = i64::from(reg.addr.saturating_sub(TMC2660_READRSP));
                let changed = self.drivers[i].config.regs.get("rdsel") != rdsel;
                let regs = &mut self.drivers[i].config.regs;
                let (drvconf, value) = regs.set("rdsel", rdsel).ok().flatten().unwrap_or((0xe, 0));
                let datagram = wire::spi_2660(drvconf, value);
                if changed {
                    let _ = link.spi(port, &mut datagram.clone());
                }
                let mut d = datagram;
                link.spi(port, &mut d)
                    .ok()
                    .map(|_| u32::from_be_bytes([0, d[0], d[1], d[2]]))
            }
            Bus::Spi {
                chain_position,
                chain_length,
                ..
            } => {
                let datagram = wire::spi_datagram(reg.addr, None);
                let first = spi(link, port, datagram, chain_position, chain_length);
                first
                    .and_then(|_| spi(link, port, datagram, chain_position, chain_length))
                    .ok()
            }
        };
        value.ok_or_else(|| cut_text(&failed))
    }

    /// Runs `line` if it is a TMC command; `None` if it is not one.
    pub fn command(
        &mut self,
        line: &Line<'_>,
        link: &mut dyn TmcLink,
        out: &mut dyn Write,
    ) -> Option<Result<(), ErrorText>> {
        let Command::Extended(e) = line.command else {
            return None;
        };
        let which = ["SET_TMC_CURRENT", "SET_TMC_FIELD", "DUMP_TMC", "INIT_TMC"]
            .iter()
            .position(|c| e.name.eq_ignore_ascii_case(c))?;
        if self.drivers.is_empty() {
            return None;
        }
        let result = self.stepper(&e).and_then(|i| match which {
            0 => self.set_current(&e, i, link, out),
            1 => self.set_field(&e, i, link),
            2 => self.dump(&e, i, link, out),
            _ => self.init(link, i),
        });
        Some(result)
    }

    /// True if `line` is a command that writes registers (SET_TMC_CURRENT,
    /// SET_TMC_FIELD, INIT_TMC) and there are drivers: Klipper sends its
    /// writes for the time the queued moves end, and waits for them.
    pub fn writes_after_moves(&self, line: &Line<'_>) -> bool {
        let Command::Extended(e) = line.command else {
            return false;
        };
        !self.drivers.is_empty()
            && ["SET_TMC_CURRENT", "SET_TMC_FIELD", "INIT_TMC"]
                .iter()
                .any(|c| e.name.eq_ignore_ascii_case(c))
    }

    /// The driver named by STEPPER=.
    fn stepper(&self, e: &Extended<'_>) -> Result<usize, ErrorText> {
        let name = e
            .get("STEPPER")
            .map_err(|err| cut_text(&err))?
            .ok_or_else(|| cut_text(&format_args!("Error on '{}': missing STEPPER", e.name)))?;
        self.drivers
            .iter()
            .position(|d| d.config.name() == name)
            .ok_or_else(|| cut_text(&format_args!("The value '{name}' is not valid for STEPPER")))
    }

    /// SET_TMC_CURRENT [CURRENT=] [HOLDCURRENT=]: sets and reports.
    fn set_current(
        &mut self,
        e: &Extended<'_>,
        i: usize,
        link: &mut dyn TmcLink,
        out: &mut dyn Write,
    ) -> Result<(), ErrorText> {
        let max = self.drivers[i].config.max_current;
        let run = number(e, "CURRENT", Some(0.0), None, max)?;
        let hold = number(e, "HOLDCURRENT", None, Some(0.0), max)?;
        if run.is_some() || hold.is_some() {
            let (now_run, _) = self.currents(i);
            let run = run.unwrap_or(now_run);
            let d = &mut self.drivers[i];
            let hold = hold.or(d.req_hold);
            let writes = set_currents(d, run, hold);
            for (addr, value) in writes.into_iter().flatten() {
                self.write(link, i, addr, value)?;
            }
        }
        let (run, hold) = self.currents(i);
        let _ = match hold {
            Some(hold) => writeln!(
                out,
                "// Run Current: {}A Hold Current: {}A",
                Fixed(run, 2),
                Fixed(hold, 2)
            ),
            None => writeln!(out, "// Run Current: {}A", Fixed(run, 2)),
        };
        Ok(())
    }

    /// Klipper's TMC2660 `idle_current_percent` below 100: the driver's
    /// current is its run current while the printer is printing
    /// (`printing`), that share of it once it is ready (idle); the run
    /// current asked for is kept.
    pub fn follow_motion(
        &mut self,
        link: &mut dyn TmcLink,
        printing: bool,
    ) -> Result<(), ErrorText> {
        for i in 0..self.drivers.len() {
            let d = &mut self.drivers[i];
            if d.config.kind != DriverKind::Tmc2660 || d.config.idle_current_percent >= 100 {
                continue;
            }
            let run = d.current_2660;
            let share = f64::from(d.config.idle_current_percent) / 100.0;
            let current = if printing { run } else { run * share };
            for (addr, value) in current_2660(d, current).into_iter().flatten() {
                self.write(link, i, addr, value)?;
            }
        }
        Ok(())
    }

    /// The run and hold currents the registers give now, A (the TMC2660:
    /// the current asked for, and no hold current).
    fn currents(&self, i: usize) -> (f64, Option<f64>) {
        let d = &self.drivers[i];
        let regs = &d.config.regs;
        if d.config.kind == DriverKind::Tmc2660 {
            return (d.current_2660, None);
        }
        let bits = onechip_planner::tmc::current::CurrentBits {
            irun: regs.get("irun") as u8,
            ihold: regs.get("ihold") as u8,
            vsense: regs.get("vsense") != 0,
            globalscaler: regs.get("globalscaler") as u16,
            current_range: regs.get("current_range") as u8,
        };
        let scale = &d.config.scale;
        (
            scale.current(bits.irun, &bits),
            Some(scale.current(bits.ihold, &bits)),
        )
    }

    /// SET_TMC_FIELD FIELD= VALUE=|VELOCITY=.
    fn set_field(
        &mut self,
        e: &Extended<'_>,
        i: usize,
        link: &mut dyn TmcLink,
    ) -> Result<(), ErrorText> {
        let get = |key| e.get(key).map_err(|err| cut_text(&err));
        let field = get("FIELD")?
            .ok_or_else(|| cut_text(&format_args!("Error on '{}': missing FIELD", e.name)))?;
        let d = &self.drivers[i];
        let Some((reg, field)) = d.config.kind.field_any(field) else {
            return Err(cut_text(&format_args!(
                "Unknown field name '{}'",
                Lower(field)
            )));
        };
        let value = get("VALUE")?;
        let velocity = number(e, "VELOCITY", Some(0.0), None, f64::INFINITY)?;
        let value = match (value, velocity) {
            (Some(v), None) => v.parse::<i64>().map_err(|_| {
                cut_text(&format_args!("Error on '{}': unable to parse {v}", e.name))
            })?,
            (None, Some(v)) => i64::from(
                d.config
                    .tstep(v)
                    .ok_or_else(|| cut_text(&"VELOCITY parameter not supported by this driver"))?,
            ),
            _ => return Err(cut_text(&"Specify either VALUE or VELOCITY")),
        };
        let (addr, new) = self.drivers[i]
            .config
            .regs
            .set_in(reg, field, value)
            .map_err(|_| cut_text(&"too many registers set"))?;
        Ok(self.write(link, i, addr, new)?)
    }

    /// DUMP_TMC [REGISTER=]: written registers as last written, readable
    /// ones as read now, each with its non-zero fields.
    fn dump(
        &mut self,
        e: &Extended<'_>,
        i: usize,
        link: &mut dyn TmcLink,
        out: &mut dyn Write,
    ) -> Result<(), ErrorText> {
        let kind = self.drivers[i].config.kind;
        let requested = e.get("REGISTER").map_err(|err| cut_text(&err))?;
        if let Some(name) = requested {
            let reg = kind.register_any(name);
            let written =
                reg.filter(|r| self.drivers[i].config.regs.iter().any(|(a, _)| a == r.addr));
            return match reg {
                Some(r) if kind.is_read(r.name) => {
                    let value = self.read(link, i, r.name)?;
                    let _ = writeln!(out, "// {}", Pretty(kind, r, value));
                    Ok(())
                }
                Some(r) if written.is_some() => {
                    let value = self.drivers[i].config.regs.value(r.addr);
                    let _ = writeln!(out, "// {}", Pretty(kind, r, value));
                    Ok(())
                }
                _ => Err(cut_text(&format_args!(
                    "Unknown register name '{}'",
                    Upper(name)
                ))),
            };
        }
        let _ = writeln!(out, "// ========== Write-only registers ==========");
        for (addr, value) in self.drivers[i].config.regs.iter() {
            if let Some(r) = kind.register_at_any(addr).filter(|r| !kind.is_read(r.name)) {
                let _ = writeln!(out, "// {}", Pretty(kind, r, value));
            }
        }
        let _ = writeln!(out, "// ========== Queried registers ==========");
        for name in kind.read_registers() {
            let value = self.read(link, i, name)?;
            if let Some(r) = kind.register_any(name) {
                let _ = writeln!(out, "// {}", Pretty(kind, r, value));
            }
        }
        Ok(())
    }
}

/// The drivers' side of homing moves (Klipper's `homing_move_begin` and
/// `homing_move_end` events), as the step side calls it.
pub trait HomingDrivers {
    /// A homing move starts that watches the endstops of engine slots
    /// `slots` (bit `i`: stepper `i`): each driver whose virtual endstop
    /// is among them gets Klipper's setup for sensorless homing (stall
    /// detection on, reported on its DIAG pin). A failed write is kept for
    /// [`Tmc::take_homing_failure`].
    fn homing_move_begin(&mut self, link: &mut dyn TmcLink, slots: u32);
    /// That homing move ended (triggered or not): the registers changed
    /// by [`Self::homing_move_begin`] are put back.
    fn homing_move_end(&mut self, link: &mut dyn TmcLink, slots: u32);
}

impl HomingDrivers for Tmc<'_> {
    fn homing_move_begin(&mut self, link: &mut dyn TmcLink, slots: u32) {
        self.homing_move(link, slots, true);
    }

    fn homing_move_end(&mut self, link: &mut dyn TmcLink, slots: u32) {
        self.homing_move(link, slots, false);
    }
}

/// Sets the current fields of `d` for `run` and `hold` A; the registers to
/// write (Klipper's order).
fn set_currents(d: &mut Driver<'_>, run: f64, hold: Option<f64>) -> [Option<(u8, u32)>; 2] {
    let cfg = &mut d.config;
    let regs = &mut cfg.regs;
    let mut writes = [None, None];
    if cfg.kind == DriverKind::Tmc2660 {
        d.current_2660 = run;
        return current_2660(d, run);
    }
    let hold = hold.unwrap_or(cfg.max_current);
    d.req_hold = Some(hold);
    let bits = cfg.scale.bits(run, hold);
    if regs.kind().field("globalscaler").is_some() {
        writes[0] = regs
            .set("globalscaler", i64::from(bits.globalscaler))
            .ok()
            .flatten();
    } else if i64::from(bits.vsense) != regs.get("vsense") {
        writes[0] = regs.set("vsense", i64::from(bits.vsense)).ok().flatten();
    }
    let _ = regs.set("ihold", i64::from(bits.ihold));
    writes[1] = regs.set("irun", i64::from(bits.irun)).ok().flatten();
    writes
}

/// A TMC2660's register writes for `current` (A, its CS and, only if it
/// changes, VSENSE), its run current left as asked.
fn current_2660(d: &mut Driver<'_>, current: f64) -> [Option<(u8, u32)>; 2] {
    let regs = &mut d.config.regs;
    let bits = d.config.scale.bits(current, current);
    let mut writes = [None, None];
    writes[0] = regs.set("cs", i64::from(bits.irun)).ok().flatten();
    if i64::from(bits.vsense) != regs.get("vsense") {
        writes[1] = regs.set("vsense", i64::from(bits.vsense)).ok().flatten();
    }
    writes
}

/// A number parameter with Klipper's bounds: at least `min`, above
/// `above`, at most `max`.
fn number(
    e: &Extended<'_>,
    key: &'static str,
    min: Option<f64>,
    above: Option<f64>,
    max: f64,
) -> Result<Option<f64>, ErrorText> {
    let Some(text) = e.get(key).map_err(|err| cut_text(&err))? else {
        return Ok(None);
    };
    let name = e.name;
    let v: f64 = decimal::parse(text)
        .filter(|v: &f64| v.is_finite())
        .ok_or_else(|| cut_text(&format_args!("Error on '{name}': unable to parse {text}")))?;
    if let Some(m) = min.filter(|&m| v < m) {
        return Err(cut_text(&format_args!(
            "Error on '{name}': {key} must have minimum of {}",
            decimal::Shortest(m)
        )));
    }
    if let Some(a) = above.filter(|&a| v <= a) {
        return Err(cut_text(&format_args!(
            "Error on '{name}': {key} must be above {}",
            decimal::Shortest(a)
        )));
    }
    if v > max {
        return Err(cut_text(&format_args!(
            "Error on '{name}': {key} must have maximum of {}",
            decimal::Shortest(max)
        )));
    }
    Ok(Some(v))
}

/// Reads register `reg` of the UART driver at `address`.
fn uart_read(link: &mut dyn TmcLink, port: u8, address: u8, reg: u8) -> Result<u32, NoAnswer> {
    let mut reply = [0u8; wire::UART_LONG];
    link.uart(port, &wire::uart_read(address, reg), &mut reply)?;
    wire::uart_decode_reply(reg, &reply).ok_or(NoAnswer)
}

/// One chained SPI transfer of `datagram` for `position` of `length`; the
/// data that position answered.
fn spi(
    link: &mut dyn TmcLink,
    port: u8,
    datagram: [u8; wire::SPI_DATAGRAM],
    position: u8,
    length: u8,
) -> Result<u32, NoAnswer> {
    let mut buf = [0u8; wire::SPI_DATAGRAM * MAX_CHAIN];
    let len = wire::spi_chain(datagram, position, length, &mut buf);
    let data = buf
        .get_mut(..len)
        .filter(|d| !d.is_empty())
        .ok_or(NoAnswer)?;
    link.spi(port, data)?;
    wire::spi_chain_answer(data, position, length).ok_or(NoAnswer)
}

/// Text in lower case.
struct Lower<'t>(&'t str);
impl fmt::Display for Lower<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.0
            .chars()
            .try_for_each(|c| f.write_char(c.to_ascii_lowercase()))
    }
}

/// Text in upper case.
struct Upper<'t>(&'t str);
impl fmt::Display for Upper<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.0
            .chars()
            .try_for_each(|c| f.write_char(c.to_ascii_uppercase()))
    }
}

/// A register as DUMP_TMC shows it (Klipper's `pretty_format`): name,
/// value in hex, then its non-zero fields by bit position.
struct Pretty<'r>(DriverKind, &'r RegDef, u32);

impl fmt::Display for Pretty<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let Self(kind, reg, value) = *self;
        let mut label = heapless::String::<24>::new();
        let _ = write!(label, "{}:", reg.name);
        write!(f, "{label:<11} {value:08x}")?;
        // By mask, each field once (a register's masks are distinct): a
        // pick of the next one each time, instead of a sort's code.
        let above = |mask: Option<u32>| {
            let later = reg.fields.iter().filter(move |fd| mask < Some(fd.mask()));
            later.min_by_key(|fd| fd.mask())
        };
        let mut next = above(None);
        while let Some(field) = next {
            next = above(Some(field.mask()));
            let mut text = heapless::String::<32>::new();
            let _ = format_field(&mut text, kind, field.name, field.get(value));
            if !text.is_empty() && text != "0" {
                write!(f, " {}={text}", field.name)?;
            }
        }
        Ok(())
    }
}

/// A field's value as Klipper's formatters show it.
fn format_field(out: &mut impl Write, kind: DriverKind, name: &str, v: i64) -> fmt::Result {
    let flag = |out: &mut dyn Write, text: &str| {
        if v != 0 {
            write!(out, "1({text})")
        } else {
            Ok(())
        }
    };
    let spi_family = matches!(kind, DriverKind::Tmc5160 | DriverKind::Tmc2240);
    match name {
        "i_scale_analog" => flag(out, "ExtVREF"),
        "shaft" => flag(out, "Reverse"),
        "reset" => flag(out, "Reset"),
        "drv_err" => flag(out, "ErrorShutdown!"),
        "uv_cp" => flag(out, "Undervoltage!"),
        "otpw" => flag(out, "OvertempWarning!"),
        "ot" => flag(out, "OvertempError!"),
        "s2ga" => flag(out, "ShortToGND_A!"),
        "s2gb" => flag(out, "ShortToGND_B!"),
        "ola" => flag(out, "OpenLoad_A!"),
        "olb" => flag(out, "OpenLoad_B!"),
        "s2vsa" if spi_family => flag(out, "ShortToSupply_A!"),
        "s2vsb" if spi_family => flag(out, "ShortToSupply_B!"),
        "s2vsa" => flag(out, "LowSideShort_A!"),
        "s2vsb" => flag(out, "LowSideShort_B!"),
        "sdoff" => flag(out, "Step/Dir disabled!"),
        "diss2g" if kind == DriverKind::Tmc2660 => flag(out, "Short to GND disabled!"),
        "version" => write!(out, "{v:#x}"),
        "mres" => write!(out, "{v}({}usteps)", 0x100i64 >> v.clamp(0, 8)),
        "cs_actual" | "se" if v == 0 => out.write_str("0(Reset?)"),
        "sel_a" => write!(out, "{v}({})", if v != 0 { "TMC220x" } else { "TMC222x" }),
        "chm" if kind == DriverKind::Tmc2660 => out.write_str(if v != 0 {
            "1(constant toff)"
        } else {
            "0(spreadCycle)"
        }),
        "vsense" if kind == DriverKind::Tmc2660 => {
            out.write_str(if v != 0 { "1(165mV)" } else { "0(305mV)" })
        }
        "adc_temp" => write!(out, "0x{v:04x}({}C)", Fixed((v as f64 - 2038.0) / 7.7, 1)),
        _ => write!(out, "{v}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn registers_print_as_klipper_prints_them() {
        let kind = DriverKind::Tmc2209;
        let chopconf = kind.register_any("CHOPCONF").expect("CHOPCONF");
        // toff 3, hstrt 5, tbl 2, mres 4 (16 microsteps), intpol.
        let value = 3 | 5 << 4 | 2 << 15 | 4 << 24 | 1 << 28;
        let mut s = heapless::String::<128>::new();
        let _ = write!(s, "{}", Pretty(kind, chopconf, value));
        assert_eq!(
            s.as_str(),
            "CHOPCONF:   14010053 toff=3 hstrt=5 tbl=2 mres=4(16usteps) intpol=1"
        );
    }
}
