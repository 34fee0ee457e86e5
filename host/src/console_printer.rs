//! The simulated printer as a host on its console sees it: bytes in,
//! replies out, in virtual time. The same path as the board's thread code:
//! the emergency parser on every byte as it arrives, lines through the
//! console (line numbers, SD printing, auto-reports), and between lines
//! the console polled at the board's 10 ms tick.

use crate::files::Folder;
use crate::host_mcu::{HostMcu, RunMcu};
use crate::step_log::StepLog;
use crate::thermal_plant::{ADC_MAX, mcu_sensor};
use crate::{
    HostSession, Options, SimError, load_setup, restart_if_asked, virtual_mcu, with_secondaries,
};
use onechip_app::console::Console;
use onechip_app::emergency::EmergencyParser;
use onechip_app::heaters::{McuSetup, full_scale};
use onechip_app::line::LineAssembler;
use onechip_app::session::{Mcu, profile};
use onechip_app::text::ErrorText;
use onechip_planner::machine::Machine;
use onechip_sched::outputs::{Drive, OutputKind};
use onechip_sched::shutdown::Shutdown;
use std::path::Path;

/// The board's thread code wakes at least this often, s.
const TICK: f64 = 0.010;

/// A printer on a console, in virtual time.
pub struct ConsolePrinter {
    machine: &'static Machine<'static>,
    session: Box<HostSession<'static>>,
    mcu: HostMcu,
    console: Console,
    card: Folder,
    lines: LineAssembler<{ profile::MAX_LINE }>,
    emergency: EmergencyParser,
    freq: f64,
}

impl ConsolePrinter {
    /// The printer of SD folder `sd` (its printer.cfg; the folder is its
    /// card), as `options` say (clock, start position, step files, plot,
    /// faults), its secondary MCUs connected (time then follows the wall
    /// clock). The config is kept for the life of the process.
    pub fn new(sd: &Path, options: &Options) -> Result<Self, SimError> {
        let buf = Box::leak(vec![0u8; crate::files::CONFIG_BUFFER].into_boxed_slice());
        let scratch = Box::leak(Box::new(std::mem::MaybeUninit::uninit()));
        let setup = Box::leak(Box::new(load_setup(sd, options, buf, scratch)?));
        let machine: &'static Machine<'static> = setup.machine();
        let freq = options.mcu_freq;
        let mut session = Box::new(HostSession::new(
            machine,
            freq,
            profile::MAX_STEP_ERROR,
            options.clock_origin,
        ));
        let mcu = virtual_mcu(machine, options)?;
        // Without simulated switches a homing move runs to its end, as in
        // klippy's batch mode.
        session.set_endstops_modelled(mcu.real_position().is_some());
        let mcu = with_secondaries(setup, options, mcu)?;
        Ok(Self {
            machine,
            session,
            mcu,
            console: Console::new(freq),
            card: Folder::new(sd),
            lines: LineAssembler::new(),
            emergency: EmergencyParser::new(),
            freq,
        })
    }

    /// Runs `auto0.g`, `auto1.g`, ... from the card, as the board at boot.
    pub fn autostart(&mut self) {
        self.console.autostart();
    }

    /// Bytes arrive on the console; returns the replies to every line they
    /// complete.
    pub fn receive(&mut self, bytes: &[u8]) -> String {
        let mut out = String::new();
        for &byte in bytes {
            if self.emergency.push(byte) {
                Mcu::shutdown(&mut self.mcu, Shutdown::EmergencyStop);
            }
            if let Some(event) = self.lines.push(byte) {
                // Writing to a String never fails.
                let _ = self.console.line(
                    Some(&mut *self.session),
                    &ErrorText::new(),
                    &event,
                    &mut self.card,
                    &mut self.mcu,
                    &mut out,
                );
                self.after_line();
            }
        }
        out
    }

    /// One console line, `\n` added; returns its replies.
    pub fn send(&mut self, line: &str) -> String {
        self.receive(format!("{line}\n").as_bytes())
    }

    /// Lets `seconds` s of virtual time pass with no console input: the
    /// console is polled (priming, auto-reports, the card's print) as the
    /// board's thread code does; returns what it wrote.
    pub fn run_for(&mut self, seconds: f64) -> String {
        let end = self.mcu.now() + (seconds * self.freq) as u64;
        let mut out = String::new();
        while self.mcu.now() < end && self.mcu.shutdown_reason().is_none() {
            let _ = self.console.poll(
                Some(&mut *self.session),
                &mut self.card,
                &mut self.mcu,
                &mut out,
            );
            self.after_line();
            if !self.console.is_printing() {
                let tick = self.mcu.now() + (TICK * self.freq) as u64;
                self.mcu.run_until(tick.min(end));
            }
        }
        out
    }

    /// After a line or a poll: a restart asked for is carried out. (The
    /// virtual clock moves only while the session waits for the MCU role
    /// and in [`Self::run_for`]: lines arrive as fast as the host sends
    /// them, as on the board.)
    fn after_line(&mut self) {
        restart_if_asked(
            &mut self.console,
            self.machine,
            &mut self.mcu,
            &mut self.session,
            self.freq,
        );
    }

    /// The printer as printer.cfg describes it.
    pub fn machine(&self) -> &'static Machine<'static> {
        self.machine
    }

    /// True while a file prints from the card.
    pub fn is_printing(&self) -> bool {
        self.console.is_printing()
    }

    /// The virtual clock now, ticks.
    pub fn now(&mut self) -> u64 {
        self.mcu.now()
    }

    /// Every stepper's step log.
    pub fn steps(&self) -> impl Iterator<Item = &StepLog> {
        self.mcu.main().logs()
    }

    /// Whether each heater's output is on now.
    pub fn heaters_on(&mut self) -> Vec<bool> {
        self.mcu
            .main_mut()
            .thermal()
            .map_or_else(Vec::new, |(_, plant)| {
                plant
                    .outputs
                    .iter()
                    .take(self.machine.heaters.len())
                    .map(|o| matches!(o.drive, Some(Drive::Level(true))))
                    .collect()
            })
    }

    /// The probe's control pin so far: each change's clock and pulse
    /// width (s; 0: off).
    pub fn probe_servo_log(&self) -> &[(u64, f64)] {
        self.mcu.main().probe_servo_log()
    }

    /// Every endstop trigger so far: axis, the toolhead's real position
    /// (mm) and the clock.
    pub fn triggers(&self) -> &[(usize, [f64; 3], u64)] {
        self.mcu.main().triggers()
    }

    /// The axes of the triggers so far that were a TMC driver's stall
    /// reported on its DIAG pin (sensorless homing), in order.
    pub fn stalls(&self) -> &[usize] {
        self.mcu.main().stalls()
    }

    /// The toolhead's real position now, mm.
    pub fn real_position(&self) -> Option<[f64; 3]> {
        self.mcu.main().real_position()
    }

    /// Every output the heaters' io drives (heaters, the fan, then the
    /// named fans, output pins and static pins): its pin as printer.cfg
    /// writes it and its value now, 0..1 of full scale (on/off pins: 0 or
    /// 1).
    pub fn outputs(&mut self) -> Vec<(&'static str, f64)> {
        let setup = McuSetup::new(self.machine, self.freq, ADC_MAX, mcu_sensor(), 0);
        let Some((heaters, _)) = self.mcu.main_mut().thermal() else {
            return Vec::new();
        };
        setup
            .outputs
            .iter()
            .enumerate()
            .map(|(i, (pin, config))| {
                let full = match config.kind {
                    OutputKind::Digital { cycle_ticks: 0 } => 1,
                    kind => full_scale(kind),
                };
                let value = heaters.output_value(i).unwrap_or(0);
                (*pin, f64::from(value) / f64::from(full.max(1)))
            })
            .collect()
    }

    /// Filament switch sensor `sensor` reads filament `present` from now
    /// on.
    pub fn set_filament(&mut self, sensor: usize, present: bool) {
        self.mcu.main_mut().set_filament(sensor, present);
    }

    /// The simulated TMC drivers.
    pub fn tmc_drivers(&mut self) -> &mut crate::tmc_sim::TmcSim {
        self.mcu.main_mut().tmc_sim()
    }

    /// The TMC drivers as the session last wrote them.
    pub fn tmc(&self) -> &onechip_app::tmc::Tmc<'static> {
        self.session.tmc()
    }

    /// The G-code position (X, Y, Z, E), mm.
    pub fn position(&mut self) -> [f64; 4] {
        self.session.printer().position()
    }
}
