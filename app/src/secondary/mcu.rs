//! One MCU role over this board's own and the secondaries': the session
//! drives [`WithSecondaries`] as it drives any [`Mcu`], and it routes what
//! concerns a secondary there. Steppers on a secondary get their commands
//! on its clock ([`Secondaries::push`]), a homing whose endstop or
//! steppers are on secondaries runs across the MCUs with trsync, motors
//! off reaches the enable pins there, and the links are served whenever
//! the session waits. A fault on either side stops both: a secondary's
//! shutdown or silence shuts this MCU down with its message, this MCU's
//! shutdown sends every secondary `emergency_stop`.

use super::SecondaryLink;
use super::attached::Secondaries;
use crate::heaters::{ThermalCommand, Wait};
use crate::outputs::AccessoryCommand;
use crate::session::Mcu;
use crate::tmc::TmcLink;
use core::cell::RefCell;
use core::fmt;
use onechip_planner::move_sink::TrapqMove;
use onechip_sched::clock::widen;
use onechip_sched::endstop::Endstop;
use onechip_sched::engine::Full;
use onechip_sched::shutdown::Shutdown;
use onechip_sched::step_command::StepCommand;
use onechip_secondary_mcu::trsync::reason;

/// Longest wait between two services of the secondaries' links, s (a
/// trsync report period is 10 ms; klippy's reactor serves its serial
/// ports as bytes arrive).
pub const SERVICE_PERIOD: f64 = 0.001;
/// How long after a motor off's command its enable pins on secondaries go
/// inactive, s (klippy's DISABLE_STALL_TIME).
const DISABLE_STALL_TIME: f64 = 0.100;

/// This board's MCU role `main` with the secondary MCUs (at most `N`), if
/// printer.cfg has any.
pub struct WithSecondaries<M, L: 'static, const N: usize> {
    main: M,
    /// Made once where the firmware keeps it (a static): it is large.
    secondaries: Option<&'static mut Secondaries<L, N>>,
    /// The main clock, Hz: host time is that clock in seconds.
    freq: f64,
    /// The stepper whose endstop the homing across MCUs watches.
    watched: usize,
    /// The last trigger taken ended a homing across MCUs by a
    /// communication timeout.
    comms_timeout: bool,
    /// This MCU's own endstop triggered the homing across MCUs running
    /// (taken from it to relay).
    triggered_here: bool,
}

impl<M: Mcu, L: SecondaryLink, const N: usize> WithSecondaries<M, L, N> {
    /// `main` (this board's MCU role, its clock `freq` Hz) with
    /// `secondaries`, if printer.cfg has any.
    pub fn new(
        mut main: M,
        secondaries: Option<&'static mut Secondaries<L, N>>,
        freq: f64,
    ) -> Self {
        // Updates the io queued for outputs on secondaries before they
        // were connected: their connection queued their start values
        // instead (and these could be too old to place on the clock).
        while main.take_queued_output().is_some() {}
        Self {
            main,
            secondaries,
            freq,
            watched: 0,
            comms_timeout: false,
            triggered_here: false,
        }
    }

    /// This board's MCU role.
    pub fn main(&self) -> &M {
        &self.main
    }

    /// This board's MCU role, to act on.
    pub fn main_mut(&mut self) -> &mut M {
        &mut self.main
    }

    /// The secondaries, if any.
    pub fn secondaries(&self) -> Option<&Secondaries<L, N>> {
        self.secondaries.as_deref()
    }

    /// The secondaries, if any, to restart them.
    pub fn secondaries_mut(&mut self) -> Option<&mut Secondaries<L, N>> {
        self.secondaries.as_deref_mut()
    }

    /// Host time now, s.
    fn host_time(&mut self) -> f64 {
        self.main.now() as f64 / self.freq
    }

    /// Serves the links: what the secondaries said is taken in (their
    /// inputs' readings go to this MCU role's io), a trigger of this
    /// MCU's endstop is relayed to them, and a fault on either side stops
    /// both.
    pub fn serve(&mut self) {
        let now = self.host_time();
        let Some(s) = &mut self.secondaries else {
            return;
        };
        if s.is_homing()
            && let Some((_, trigger)) = self.main.take_trigger()
        {
            // This MCU's endstop ended a homing across MCUs: the others
            // are triggered at once (its own steppers stopped already).
            let clock = widen(trigger, self.main.now());
            s.main_triggered(clock as f64 / self.freq, now);
            self.triggered_here = true;
        }
        let main = &mut self.main;
        s.service(now, &mut |stops| main.stop_steppers(stops));
        while let Some(reading) = s.take_reading() {
            self.main.remote_reading(reading);
        }
        self.forward_outputs();
        let Some(s) = &mut self.secondaries else {
            return;
        };
        let main_down = self.main.shutdown_reason().is_some();
        match s.failure() {
            Some(reason) if !main_down => self.main.shutdown(reason),
            None if main_down => s.emergency_stop(now),
            _ => {}
        }
    }

    /// Sends the updates this MCU role's io queued for outputs on
    /// secondaries there.
    fn forward_outputs(&mut self) {
        let now = self.host_time();
        let Some(s) = &mut self.secondaries else {
            return;
        };
        while let Some((index, clock, value)) = self.main.take_queued_output() {
            s.queue_output(index, clock, value, now);
        }
    }
}

impl<M: Mcu, L: SecondaryLink, const N: usize> Mcu for WithSecondaries<M, L, N> {
    fn now(&mut self) -> u64 {
        self.main.now()
    }

    fn push(&mut self, stepper: usize, cmd: StepCommand, clock: u64) -> Result<(), Full> {
        match &mut self.secondaries {
            Some(s) if s.routes(stepper) => {
                s.push(stepper, cmd, clock)?;
                self.main.sent_elsewhere(stepper, cmd, clock);
                Ok(())
            }
            Some(s) => {
                self.main.push(stepper, cmd, clock)?;
                // Its enable pin may be on a secondary.
                if let StepCommand::Steps { .. } = cmd {
                    s.enable_for(stepper, clock as f64 / self.freq);
                }
                Ok(())
            }
            None => self.main.push(stepper, cmd, clock),
        }
    }

    fn wait(&mut self, until: u64) {
        if self.secondaries.is_none() {
            return self.main.wait(until);
        }
        self.serve();
        let soon = self.main.now() + (self.freq * SERVICE_PERIOD) as u64;
        self.main.wait(until.min(soon));
    }

    fn watch_endstop(&mut self, stepper: usize, endstop: Endstop, stops: u32) {
        self.watched = stepper;
        self.triggered_here = false;
        let now = self.main.now();
        if let Some(s) = &mut self.secondaries {
            // Steppers or the endstop on a secondary: a homing across MCUs.
            let start = widen(endstop.next(), now) as f64 / self.freq;
            if let Some((main_stops, main_endstop)) =
                s.start_homing(stepper, endstop.sampling(), stops, start)
            {
                if main_endstop {
                    self.main.watch_endstop(stepper, endstop, main_stops);
                }
                return;
            }
        }
        self.main.watch_endstop(stepper, endstop, stops);
    }

    fn stop_watching(&mut self) {
        self.main.stop_watching();
        let now = self.host_time();
        if let Some(s) = &mut self.secondaries {
            s.end_homing(now);
        }
    }

    fn take_trigger(&mut self) -> Option<(usize, u32)> {
        if !self.secondaries().is_some_and(Secondaries::is_homing) {
            return self.main.take_trigger();
        }
        self.serve();
        let now = self.host_time();
        let s = self.secondaries.as_deref_mut()?;
        // The homing across MCUs: its first trigger, on any of them.
        let (at, why) = s.take_homing_trigger()?;
        self.comms_timeout = why == reason::COMMS_TIMEOUT;
        s.end_homing(now);
        self.main.stop_watching();
        let clock = (at * self.freq).max(0.0) as u64;
        if !core::mem::take(&mut self.triggered_here) {
            self.main.triggered_elsewhere(self.watched, clock);
        }
        Some((self.watched, clock as u32))
    }

    fn stop_steppers(&mut self, stops: u32) {
        self.main.stop_steppers(stops);
    }

    fn homing_comms_timeout(&mut self) -> bool {
        core::mem::take(&mut self.comms_timeout) || self.main.homing_comms_timeout()
    }

    fn moved_since(&mut self, stepper: usize, clock: u64) -> i64 {
        let freq = self.freq;
        match &mut self.secondaries {
            Some(s) if s.routes(stepper) => {
                let main = RefCell::new(&mut self.main);
                let now = || main.borrow_mut().now() as f64 / freq;
                let mut sleep = |seconds: f64| {
                    let mut main = main.borrow_mut();
                    let until = main.now() + (seconds * freq) as u64;
                    main.wait(until);
                };
                let at = clock as f64 / freq;
                s.moved_since(stepper, at, &now, &mut sleep).unwrap_or(0)
            }
            _ => self.main.moved_since(stepper, clock),
        }
    }

    fn thermal(&mut self, command: ThermalCommand) {
        if command == ThermalCommand::Accessory(AccessoryCommand::Motors(false)) {
            let at = self.host_time() + DISABLE_STALL_TIME;
            if let Some(s) = &mut self.secondaries {
                s.motors_off(at);
            }
        }
        self.main.thermal(command);
        self.forward_outputs();
    }

    fn thermal_waiting(&mut self, wait: Wait) -> bool {
        self.main.thermal_waiting(wait)
    }

    fn report_temperatures(&mut self, out: &mut dyn fmt::Write) -> fmt::Result {
        self.main.report_temperatures(out)
    }

    fn shutdown_reason(&mut self) -> Option<Shutdown> {
        let secondary = self.secondaries.as_deref().and_then(Secondaries::failure);
        self.main.shutdown_reason().or(secondary)
    }

    fn endstop_triggered(&mut self, stepper: usize) -> bool {
        self.main.endstop_triggered(stepper)
    }

    fn probe_servo(&mut self, clock: u64, pulse_width: f64) {
        self.main.probe_servo(clock, pulse_width);
    }

    fn shutdown(&mut self, reason: Shutdown) {
        self.main.shutdown(reason);
        let now = self.host_time();
        if let Some(s) = &mut self.secondaries {
            s.emergency_stop(now);
        }
    }

    fn can_extrude(&mut self) -> bool {
        self.main.can_extrude()
    }

    fn filament_present(&mut self, sensor: usize) -> bool {
        self.main.filament_present(sensor)
    }

    fn stepper_clocks(&mut self, print_time: f64, set: &mut dyn FnMut(usize, f64, f64)) {
        let now = self.host_time();
        if let Some(s) = &mut self.secondaries {
            s.calibrate(print_time, now, set);
        }
    }

    fn planned(&mut self, m: &TrapqMove, extruder: bool) {
        self.main.planned(m, extruder);
    }

    fn tmc_link(&mut self) -> Option<&mut dyn TmcLink> {
        self.main.tmc_link()
    }
}
