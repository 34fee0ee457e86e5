//! Simulated TMC drivers: they decode the datagrams the firmware sends
//! (`onechip_planner::tmc::wire`), hold their registers for tests to read,
//! answer reads as the chips do, and can lose power (registers back to
//! zero, GSTAT's `reset` flag set, the UART interface counter at 0).
//!
//! A driver with a DIAG pin reports a stall there ([`StallDetect`]) when
//! its motor is driven into the end of its axis while its registers have
//! stall detection on, as the chips do: StallGuard4 (TMC2209) in
//! stealthChop with SGTHRS above 0, StallGuard2 (TMC2130, TMC2240,
//! TMC5160) in spreadCycle with the stall routed to the pin wired
//! (`diag0_stall` / `diag1_stall`); both only while TSTEP lies between
//! the thresholds (at most TCOOLTHRS). The stall threshold's finer
//! effects (SGT, load) are not modelled: a blocked motor stalls.

use onechip_app::tmc::{NoAnswer, Tmc, TmcLink};
use onechip_planner::machine::Machine;
use onechip_planner::tmc::config::{Bus, TSTEP_MAX};
use onechip_planner::tmc::{DriverKind, wire};
use std::cell::Cell;
use std::rc::Rc;

/// When a driver reports a stall on its DIAG pin, as its registers set it
/// now.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StallDetect {
    /// Stall detection reaches the DIAG pin (mode, routing, threshold).
    pub on: bool,
    /// It works while TSTEP lies in this range (inclusive), driver clocks
    /// per 1/256 microstep.
    pub tstep: (u32, u32),
    /// TSTEP per second between two steps: the driver's clock over the
    /// 1/256 microsteps of one step (fclk / 2^mres), 1/s.
    pub tstep_per_s: f64,
}

impl StallDetect {
    /// True if a blocked motor, its last steps `interval` s apart (`None`:
    /// not stepped yet), has its stall reported. A motor that slow that
    /// TSTEP overflows stands still: StallGuard measures nothing.
    pub fn reports(&self, interval: Option<f64>) -> bool {
        let Some(tstep) = interval.map(|t| t * self.tstep_per_s) else {
            return false;
        };
        let (low, high) = self.tstep;
        self.on
            && tstep < f64::from(TSTEP_MAX)
            && (f64::from(low)..=f64::from(high)).contains(&tstep)
    }
}

/// One simulated driver.
#[derive(Debug, Clone)]
pub struct SimDriver {
    /// Its type.
    pub kind: DriverKind,
    /// The stepper it drives.
    pub stepper: String,
    /// Its port (as the firmware numbers them).
    pub port: u8,
    /// UART address, or SPI chain position.
    pub slot: u8,
    /// SPI chain length (1 without a chain; UART: 1).
    pub chain_length: u8,
    /// Register values by address.
    regs: [u32; 128],
    /// UART interface counter (writes received).
    ifcnt: u8,
    /// SPI: what the next datagram's answer carries.
    pending: u32,
    /// Datagrams received (all kinds), for tests.
    pub datagrams: usize,
    /// Every register write received, in order: (address, value).
    pub written: Vec<(u8, u32)>,
    /// Its DIAG pin, if wired: the GCONF field routing a stall to it
    /// (`None` on the TMC2209).
    diag: Option<Option<&'static str>>,
    /// When it reports a stall on DIAG, kept up to date with the
    /// registers (shared with the endstop input reading DIAG).
    stall: Rc<Cell<StallDetect>>,
}

const GSTAT: usize = 0x01;
const IFCNT: u8 = 0x02;

impl SimDriver {
    /// Register `addr`'s value as the driver holds it.
    pub fn register(&self, addr: u8) -> u32 {
        self.regs[usize::from(addr & 0x7f)]
    }

    /// Register `name`'s value as the driver holds it (0 if unknown).
    pub fn register_named(&self, name: &str) -> u32 {
        self.kind
            .register(name)
            .map_or(0, |r| self.register(r.addr))
    }

    /// Field `name` of the register holding it.
    pub fn field(&self, name: &str) -> Option<i64> {
        let (reg, field) = self.kind.field_any(name)?;
        Some(field.get(self.register(reg.addr)))
    }

    /// Sets register `addr` as the chip would (a status flag raised, for
    /// tests).
    pub fn inject(&mut self, addr: u8, value: u32) {
        self.regs[usize::from(addr & 0x7f)] = value;
        self.update_stall();
    }

    /// When it reports a stall on DIAG (shared, kept up to date).
    pub fn stall_detect(&self) -> Rc<Cell<StallDetect>> {
        Rc::clone(&self.stall)
    }

    /// Reads stall detection afresh from the registers.
    fn update_stall(&mut self) {
        let field = |name| self.field(name).unwrap_or(0);
        let threshold = |name| u32::try_from(field(name)).unwrap_or(0);
        let (tpwmthrs, tcoolthrs) = (threshold("tpwmthrs"), threshold("tcoolthrs"));
        let (on, tstep) = match (self.kind, self.diag) {
            // StallGuard4: in stealthChop (TSTEP at least TPWMTHRS).
            (DriverKind::Tmc2209, Some(_)) => (
                field("en_spreadcycle") == 0 && field("sgthrs") > 0,
                (tpwmthrs, tcoolthrs),
            ),
            // StallGuard2: in spreadCycle (stealthChop off, or TSTEP
            // below TPWMTHRS), above THIGH.
            (_, Some(Some(route))) => {
                let stealth = field("en_pwm_mode") != 0;
                let top = if stealth {
                    tcoolthrs.min(tpwmthrs.saturating_sub(1))
                } else {
                    tcoolthrs
                };
                let low = threshold("thigh").saturating_add(1);
                (field(route) != 0, (low, top))
            }
            _ => (false, (0, 0)),
        };
        let freq = self.kind.clock_hz().unwrap_or(0.0);
        let mres = field("mres").clamp(0, 8);
        self.stall.set(StallDetect {
            on,
            tstep,
            tstep_per_s: freq / f64::from(1u32 << mres),
        });
    }

    /// Power lost and back: every register 0, GSTAT's reset flag set, the
    /// interface counter back to 0.
    pub fn power_cycle(&mut self) {
        self.regs = [0; 128];
        self.regs[GSTAT] = 1;
        self.ifcnt = 0;
        self.pending = 0;
        self.update_stall();
    }

    /// A write to `addr`: GSTAT flags are cleared by writing ones.
    fn write(&mut self, addr: u8, value: u32) {
        let a = usize::from(addr & 0x7f);
        self.written.push((addr & 0x7f, value));
        if a == GSTAT && self.kind != DriverKind::Tmc2660 {
            self.regs[a] &= !value;
        } else {
            self.regs[a] = value;
        }
        self.update_stall();
    }

    /// A read of `addr`, as the chip answers it.
    fn read(&mut self, addr: u8) -> u32 {
        match addr {
            IFCNT if self.kind.is_uart() => u32::from(self.ifcnt),
            _ => {
                let value = self.register(addr);
                // The TMC2130 clears GSTAT when it is read.
                if self.kind == DriverKind::Tmc2130 && usize::from(addr) == GSTAT {
                    self.regs[GSTAT] = 0;
                }
                value
            }
        }
    }

    /// A TMC2660 datagram: the answer (20 bits in the top of 24) comes
    /// from the read selection before the datagram.
    fn datagram_2660(&mut self, d: [u8; wire::SPI_2660]) -> u32 {
        let drvconf = self.register(0xe);
        let flags = 1 << 7; // standstill
        let answer = match (drvconf >> 4) & 3 {
            2 => (self.register(0xc) & 0x1f) << 10 | flags,
            _ => flags,
        };
        let (reg, value) = wire::spi_2660_decode(d);
        self.write(reg, value);
        answer << 4
    }
}

/// Every simulated driver, by port.
#[derive(Debug, Clone, Default)]
pub struct TmcSim {
    /// The drivers.
    pub drivers: Vec<SimDriver>,
}

impl TmcSim {
    /// The drivers of `machine`'s TMC sections, on the ports the firmware
    /// numbers, all at power-on (registers 0, GSTAT reset).
    pub fn new(machine: &Machine<'_>) -> Self {
        let ports = Tmc::new(machine);
        let drivers = machine
            .tmc
            .iter()
            .map(|d| {
                let (slot, chain_length) = match d.bus {
                    Bus::Uart { address, .. } => (address, 1),
                    Bus::Spi {
                        chain_position,
                        chain_length,
                        ..
                    } => (chain_position, chain_length),
                };
                let mut sim = SimDriver {
                    kind: d.kind,
                    stepper: d.stepper.to_string(),
                    port: ports.port_of(d.stepper).unwrap_or(0),
                    slot,
                    chain_length,
                    regs: [0; 128],
                    ifcnt: 0,
                    pending: 0,
                    datagrams: 0,
                    written: Vec::new(),
                    diag: d.diag.map(|(_, route)| route),
                    stall: Rc::default(),
                };
                sim.power_cycle();
                sim
            })
            .collect();
        Self { drivers }
    }

    /// The driver of `stepper`.
    pub fn driver(&mut self, stepper: &str) -> Option<&mut SimDriver> {
        self.drivers.iter_mut().find(|d| d.stepper == stepper)
    }
}

impl TmcLink for TmcSim {
    fn uart(&mut self, port: u8, tx: &[u8], rx: &mut [u8]) -> Result<(), NoAnswer> {
        let request = wire::uart_decode_request(tx).ok_or(NoAnswer)?;
        let driver = self
            .drivers
            .iter_mut()
            .find(|d| d.port == port && d.kind.is_uart() && d.slot == request.address)
            .ok_or(NoAnswer)?;
        driver.datagrams += 1;
        match request.write {
            Some(value) => {
                driver.write(request.reg, value);
                driver.ifcnt = driver.ifcnt.wrapping_add(1);
                Ok(())
            }
            None => {
                let reply = wire::uart_reply(request.reg, driver.read(request.reg));
                let out = rx.get_mut(..reply.len()).ok_or(NoAnswer)?;
                out.copy_from_slice(&reply);
                Ok(())
            }
        }
    }

    fn spi(&mut self, port: u8, data: &mut [u8]) -> Result<(), NoAnswer> {
        let mut answered = false;
        for d in self
            .drivers
            .iter_mut()
            .filter(|d| d.port == port && !d.kind.is_uart())
        {
            d.datagrams += 1;
            answered = true;
            if d.kind == DriverKind::Tmc2660 {
                let bytes: [u8; wire::SPI_2660] = data.try_into().map_err(|_| NoAnswer)?;
                let answer = d.datagram_2660(bytes).to_be_bytes();
                data.copy_from_slice(&answer[1..]);
                continue;
            }
            let at = wire::chain_offset(d.slot, d.chain_length);
            let Some(slot) = data.get_mut(at..at + wire::SPI_DATAGRAM) else {
                return Err(NoAnswer);
            };
            let addr = slot[0];
            let value = u32::from_be_bytes([slot[1], slot[2], slot[3], slot[4]]);
            // Status byte: GSTAT's reset and drv_err flags.
            let status = (d.register(GSTAT as u8) & 3) as u8;
            let answer = d.pending.to_be_bytes();
            slot.copy_from_slice(&[status, answer[0], answer[1], answer[2], answer[3]]);
            d.pending = if addr & 0x80 != 0 {
                d.write(addr, value);
                value
            } else {
                d.read(addr)
            };
        }
        if answered { Ok(()) } else { Err(NoAnswer) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A driver of `kind` at power-on, UART address or chain position
    /// `slot`, its DIAG pin routed by `diag` if wired.
    fn driver(kind: DriverKind, slot: u8, diag: Option<Option<&'static str>>) -> SimDriver {
        let mut d = SimDriver {
            kind,
            stepper: "stepper_x".into(),
            port: 0,
            slot,
            chain_length: 1,
            regs: [0; 128],
            ifcnt: 0,
            pending: 0,
            datagrams: 0,
            written: Vec::new(),
            diag,
            stall: Rc::default(),
        };
        d.power_cycle();
        d
    }

    /// Sets field `name` of `d` as a register write would.
    fn set(d: &mut SimDriver, name: &str, value: i64) {
        let (reg, field) = d.kind.field_any(name).expect("field");
        let new = field.set(d.register(reg.addr), value);
        d.write(reg.addr, new);
    }

    #[test]
    fn stallguard2_reports_in_spreadcycle_between_thigh_and_tcoolthrs() {
        let mut d = driver(DriverKind::Tmc5160, 1, Some(Some("diag1_stall")));
        // 16 microsteps: TSTEP = 12 MHz / 16 × the step interval.
        set(&mut d, "mres", 4);
        let at = |tstep: f64| Some(tstep * 16.0 / 12e6);
        set(&mut d, "tcoolthrs", 1000);
        set(&mut d, "thigh", 10);
        // Not routed to the DIAG pin wired: nothing.
        assert!(!d.stall_detect().get().reports(at(500.0)));
        set(&mut d, "diag1_stall", 1);
        let stall = d.stall_detect();
        assert!(stall.get().reports(at(500.0)));
        assert!(!stall.get().reports(at(2000.0)), "slower than TCOOLTHRS");
        assert!(!stall.get().reports(at(5.0)), "faster than THIGH");
        assert!(!stall.get().reports(None), "not stepped");
        // stealthChop below TPWMTHRS' speed: StallGuard2 measures nothing.
        set(&mut d, "en_pwm_mode", 1);
        set(&mut d, "tpwmthrs", 100);
        assert!(!stall.get().reports(at(500.0)));
        assert!(stall.get().reports(at(50.0)), "spreadCycle above it");
    }

    #[test]
    fn stallguard4_reports_in_stealthchop_with_a_threshold() {
        let mut d = driver(DriverKind::Tmc2209, 0, Some(None));
        set(&mut d, "mres", 4);
        let at = |tstep: f64| Some(tstep * 16.0 / 12e6);
        set(&mut d, "tcoolthrs", 0xfffff);
        let stall = d.stall_detect();
        // SGTHRS 0: never.
        assert!(!stall.get().reports(at(500.0)));
        set(&mut d, "sgthrs", 80);
        assert!(stall.get().reports(at(500.0)));
        // spreadCycle: no StallGuard4.
        set(&mut d, "en_spreadcycle", 1);
        assert!(!stall.get().reports(at(500.0)));
        set(&mut d, "en_spreadcycle", 0);
        // Above TPWMTHRS' speed the chopper leaves stealthChop.
        set(&mut d, "tpwmthrs", 1000);
        assert!(!stall.get().reports(at(500.0)));
        // Without a DIAG pin nothing is reported.
        let mut unwired = driver(DriverKind::Tmc2209, 0, None);
        set(&mut unwired, "sgthrs", 80);
        set(&mut unwired, "tcoolthrs", 0xfffff);
        assert!(!unwired.stall_detect().get().reports(at(500.0)));
    }

    #[test]
    fn a_uart_driver_counts_writes_and_answers_reads() {
        let mut sim = TmcSim {
            drivers: vec![driver(DriverKind::Tmc2209, 2, None)],
        };
        sim.uart(0, &wire::uart_write(2, 0x10, 0x0008_1010), &mut [])
            .expect("write");
        let mut reply = [0u8; 8];
        sim.uart(0, &wire::uart_read(2, 0x02), &mut reply)
            .expect("read");
        assert_eq!(wire::uart_decode_reply(0x02, &reply), Some(1));
        assert_eq!(sim.drivers[0].register(0x10), 0x0008_1010);
        // Another address on the same wire: nobody answers.
        assert_eq!(
            sim.uart(0, &wire::uart_read(1, 0x02), &mut reply),
            Err(NoAnswer)
        );
    }
}
