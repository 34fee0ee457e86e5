//! The MCU role as the session sees it on this machine: the stepper
//! engine in timer 0's interrupt, the heaters in the dual timer's. The
//! same delegation as the board's `BoardMcu`; thread code waits until an
//! interrupt has run ([`crate::machine::sleep`]).

use crate::{heater_io, step_timer};
use onechip_app::heaters::{ThermalCommand, Wait};
use onechip_app::secondary::thermal::Reading;
use onechip_app::session::Mcu;
use onechip_sched::clock::widen;
use onechip_sched::endstop::Endstop;
use onechip_sched::engine::Full;
use onechip_sched::shutdown::Shutdown;
use onechip_sched::step_command::StepCommand;

/// This machine's MCU role.
pub struct QemuMcu;

/// Every stepper stops and every heater and fan output goes off, for
/// `reason` (M112: [`Shutdown::EmergencyStop`]).
pub fn shutdown(reason: Shutdown) {
    step_timer::stop(reason);
    heater_io::shutdown(reason);
}

impl Mcu for QemuMcu {
    fn now(&mut self) -> u64 {
        step_timer::now64()
    }

    fn push(&mut self, stepper: usize, cmd: StepCommand, clock: u64) -> Result<(), Full> {
        step_timer::push(stepper, cmd, clock)
    }

    fn wait(&mut self, _until: u64) {
        crate::machine::sleep();
    }

    fn watch_endstop(&mut self, stepper: usize, endstop: Endstop, stops: u32) {
        step_timer::watch_endstop(stepper, endstop, stops);
    }

    fn stop_watching(&mut self) {
        step_timer::stop_watching();
    }

    fn take_trigger(&mut self) -> Option<(usize, u32)> {
        step_timer::take_trigger()
    }

    fn stop_steppers(&mut self, stops: u32) {
        step_timer::stop_steppers(stops);
    }

    fn thermal(&mut self, command: ThermalCommand) {
        heater_io::command(command);
    }

    fn thermal_waiting(&mut self, wait: Wait) -> bool {
        heater_io::waiting(wait)
    }

    fn report_temperatures(&mut self, mut out: &mut dyn core::fmt::Write) -> core::fmt::Result {
        heater_io::report(&mut out);
        Ok(())
    }

    fn take_queued_output(&mut self) -> Option<(usize, u64, u32)> {
        let (index, clock, value) = heater_io::take_forwarded()?;
        Some((index, widen(clock, step_timer::now64()), value))
    }

    fn remote_reading(&mut self, reading: Reading) {
        heater_io::remote_report(reading);
    }

    fn shutdown_reason(&mut self) -> Option<Shutdown> {
        step_timer::shutdown_reason()
    }

    fn endstop_triggered(&mut self, stepper: usize) -> bool {
        step_timer::endstop_triggered(stepper)
    }

    fn shutdown(&mut self, reason: Shutdown) {
        shutdown(reason);
    }

    fn can_extrude(&mut self) -> bool {
        heater_io::can_extrude()
    }

    /// No filament switch is modelled: filament is always present.
    fn filament_present(&mut self, _sensor: usize) -> bool {
        true
    }
}
