//! The MCU role as the session sees it on this board: the stepper engine
//! in TIM5's interrupt and the heaters in TIM2's. Thread code reaches them
//! through [`onechip_board_rt::step_timer`] and [`onechip_board_rt::heater_io`], and waits by
//! sleeping until the next interrupt (`wfe`): the steppers' interrupt runs
//! at every step, the heaters' at least every 10 ms, the I/O executor's
//! tick every 10 ms, so a wait never spins and never oversleeps long.

use onechip_app::heaters::{ThermalCommand, Wait};
use onechip_app::secondary::thermal::Reading;
use onechip_app::session::Mcu;
use onechip_board_rt::{heater_io, step_timer};
use onechip_sched::clock::widen;
use onechip_sched::endstop::Endstop;
use onechip_sched::engine::Full;
use onechip_sched::shutdown::Shutdown;
use onechip_sched::step_command::StepCommand;

/// The board's MCU role, with the filament switch sensors' inputs and
/// the wires to the TMC drivers.
#[derive(Default)]
pub struct BoardMcu {
    /// Each filament switch sensor's switch_pin (active: filament).
    pub filament: heapless::Vec<
        onechip_board_rt::step_pins::InPin,
        { onechip_app::filament::MAX_FILAMENT_SENSORS },
    >,
    /// The TMC drivers' UART pins and SPI chip selects, if there are
    /// drivers.
    pub tmc: Option<onechip_board_rt::tmc_link::BoardTmc>,
}

/// Every stepper stops and every heater and fan output goes off at once,
/// for `reason` (M112: [`Shutdown::EmergencyStop`]). Called by thread
/// code, and by the USB receive path the moment an `M112` arrives (both
/// below the stepper and heater interrupts, whose state they reach with
/// those interrupts masked).
pub fn shutdown(reason: Shutdown) {
    step_timer::stop(reason);
    heater_io::shutdown(reason);
}

impl Mcu for BoardMcu {
    fn now(&mut self) -> u64 {
        step_timer::now64()
    }

    fn push(&mut self, stepper: usize, cmd: StepCommand, clock: u64) -> Result<(), Full> {
        step_timer::push(stepper, cmd, clock)
    }

    fn wait(&mut self, _until: u64) {
        cortex_m::asm::wfe();
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

    fn probe_servo(&mut self, clock: u64, pulse_width: f64) {
        onechip_board_rt::probe_servo::set(clock, pulse_width);
    }

    fn can_extrude(&mut self) -> bool {
        heater_io::can_extrude()
    }

    fn filament_present(&mut self, sensor: usize) -> bool {
        self.filament.get(sensor).is_none_or(|pin| pin.is_active())
    }

    fn tmc_link(&mut self) -> Option<&mut dyn onechip_app::tmc::TmcLink> {
        self.tmc
            .as_mut()
            .map(|t| t as &mut dyn onechip_app::tmc::TmcLink)
    }
}
