//! The simulator's MCU role as the session drives it: the virtual MCU,
//! with the secondary MCUs on serial devices driven as the firmware drives
//! its own ([`WithSecondaries`]). Without secondaries it is the virtual
//! MCU alone; with them, virtual time is paced by the wall clock (they run
//! in real time) and their links are served at least every
//! [`SERVICE_PERIOD`] of it.

use crate::secondary::{SerialDevices, leak, port::Port};
use crate::virtual_mcu::VirtualMcu;
use onechip_app::secondary::mcu::{SERVICE_PERIOD, WithSecondaries};
use onechip_app::session::Mcu;
use onechip_planner::machine::Machine;
use onechip_planner::mcu_section::MAX_SECONDARIES;
use onechip_sched::shutdown::Shutdown;

/// The session's MCU role in the simulator.
pub type HostMcu = WithSecondaries<VirtualMcu, Port, MAX_SECONDARIES>;

/// Running the simulator's MCU role outside the session's waits.
pub trait RunMcu {
    /// Runs every event before clock `until` (ticks; `u64::MAX`: until
    /// the steppers here are idle), serving the secondaries' links
    /// meanwhile.
    fn run_until(&mut self, until: u64);
    /// With a pace: runs every event the wall clock has passed.
    fn run_to_wall_clock(&mut self);
    /// FIRMWARE_RESTART: the virtual MCU leaves its shutdown (heaters
    /// rebuilt for `machine`, clock `freq` Hz), the secondaries are reset
    /// and configured again; one that cannot be is the printer's shutdown
    /// with Klipper's message.
    fn restart(&mut self, machine: &Machine<'_>, freq: f64);
}

impl RunMcu for HostMcu {
    fn run_until(&mut self, until: u64) {
        if self.secondaries().is_none() {
            return self.main_mut().run_until(until);
        }
        let freq = self.secondaries().map_or(1.0, |s| s.freq());
        let period = (freq * SERVICE_PERIOD) as u64;
        loop {
            self.serve();
            let now = self.main_mut().now();
            if now >= until || self.shutdown_reason().is_some() {
                return;
            }
            let limit = until.min(now + period);
            if until != u64::MAX {
                self.main_mut().run_until(limit);
            } else if !self.main_mut().run_next_before(limit) && !self.main_mut().steppers_busy() {
                return;
            }
        }
    }

    fn run_to_wall_clock(&mut self) {
        self.main_mut().run_to_wall_clock();
        self.serve();
    }

    fn restart(&mut self, machine: &Machine<'_>, freq: f64) {
        self.main_mut().restart(machine, freq);
        let Some(pace) = self.main().pace() else {
            return;
        };
        let now = move || pace.clock_now() as f64 / freq;
        let Some(s) = self.secondaries_mut() else {
            return;
        };
        if let Err(e) = s.restart(machine, &mut SerialDevices, &now) {
            // Klipper's message alone: the config loaded before.
            let message = leak(&e.to_string());
            s.fail(Shutdown::SecondaryNotReady { message });
        } else {
            self.main_mut().secondaries_restarted();
        }
        // Time went on while they were brought back.
        self.run_to_wall_clock();
    }
}
