//! The MCU role's state as one: steppers, digital outputs, ADC inputs and
//! timers, and shutdown, which stops all of them and keeps the first
//! reason.

use crate::outputs::{AnalogIn, DigitalOut};
use crate::shutdown::Shutdown;
use crate::stepper::Stepper;
use crate::timer::Timers;

/// An MCU role with `S` steppers (queues of `M` moves), `D` digital
/// outputs, `A` ADC inputs and `T` timers.
#[derive(Debug, Clone)]
pub struct McuRole<const S: usize, const M: usize, const D: usize, const A: usize, const T: usize> {
    /// The steppers.
    pub steppers: [Stepper<M>; S],
    /// The digital outputs.
    pub outputs: heapless::Vec<DigitalOut, D>,
    /// The ADC inputs.
    pub inputs: heapless::Vec<AnalogIn, A>,
    /// The timers.
    pub timers: Timers<T>,
    shutdown: Option<Shutdown>,
}

impl<const S: usize, const M: usize, const D: usize, const A: usize, const T: usize> Default
    for McuRole<S, M, D, A, T>
{
    fn default() -> Self {
        Self::new()
    }
}

impl<const S: usize, const M: usize, const D: usize, const A: usize, const T: usize>
    McuRole<S, M, D, A, T>
{
    /// Idle, nothing configured.
    pub fn new() -> Self {
        Self {
            steppers: core::array::from_fn(|_| Stepper::new()),
            outputs: heapless::Vec::new(),
            inputs: heapless::Vec::new(),
            timers: Timers::new(),
            shutdown: None,
        }
    }

    /// Why the MCU shut down, if it did.
    pub fn shutdown_reason(&self) -> Option<Shutdown> {
        self.shutdown
    }

    /// Takes the outcome of an operation: a fault shuts everything down.
    pub fn check(&mut self, outcome: Result<(), Shutdown>) -> Result<(), Shutdown> {
        outcome.inspect_err(|&reason| self.shutdown(reason))
    }

    /// Checks every output's timeout at clock `now`.
    pub fn check_outputs(&mut self, now: u32) -> Result<(), Shutdown> {
        let expired = self.outputs.iter().find_map(|o| o.check(now).err());
        self.check(expired.map_or(Ok(()), Err))
    }

    /// Stops every stepper, returns every output to its default, disarms
    /// every timer; the first reason is kept.
    pub fn shutdown(&mut self, reason: Shutdown) {
        self.shutdown.get_or_insert(reason);
        for s in &mut self.steppers {
            s.stop();
        }
        for o in &mut self.outputs {
            o.reset();
        }
        self.timers.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    type Mcu = McuRole<2, 8, 2, 1, 4>;

    /// A printing MCU: both steppers busy, a heater on, a thermistor read.
    fn printing() -> Mcu {
        let mut mcu = Mcu::new();
        for s in &mut mcu.steppers {
            s.set_next_dir(true);
            s.queue(1000, 100, 0, 0).expect("room");
        }
        let mut heater = DigitalOut::new(false, false, 50_000, 0);
        heater.set(true, 0);
        let _ = mcu.outputs.push(heater);
        let _ = mcu.inputs.push(AnalogIn::new(100, 4000, 2));
        mcu.timers.arm(0, 5000, 0).expect("future");
        mcu
    }

    fn assert_all_stopped(mcu: &Mcu, reason: Shutdown, message: &str) {
        assert_eq!(mcu.shutdown_reason(), Some(reason));
        assert_eq!(reason.message(), message);
        assert!(mcu.steppers.iter().all(Stepper::is_idle));
        assert!(mcu.outputs.iter().all(|o| !o.value()));
        assert_eq!(mcu.timers.next(0), None);
    }

    #[test]
    fn a_step_queue_running_dry_mid_move_shuts_everything_down() {
        let mut mcu = printing();
        // Stepper 1 ran out of moves; the next one arrives after its first
        // step was due.
        mcu.steppers[1].stop();
        mcu.steppers[1].reset_clock(100_000);
        let late = mcu.steppers[1].queue(1000, 10, 0, 200_000);
        assert!(mcu.check(late).is_err());
        assert_all_stopped(
            &mcu,
            Shutdown::StepperTooFarInPast,
            "Stepper too far in past",
        );
    }

    #[test]
    fn a_timer_in_the_past_shuts_everything_down() {
        let mut mcu = printing();
        let past = mcu.timers.arm(1, 900, 1000);
        assert!(mcu.check(past).is_err());
        assert_all_stopped(&mcu, Shutdown::TimerTooClose, "Timer too close");
    }

    #[test]
    fn an_adc_out_of_range_shuts_everything_down() {
        let mut mcu = printing();
        for reading in [4095, 4095] {
            let outcome = mcu.inputs[0].sample(reading);
            if mcu.check(outcome).is_err() {
                break;
            }
        }
        assert_all_stopped(&mcu, Shutdown::AdcOutOfRange, "ADC out of range");
    }

    #[test]
    fn an_expired_output_shuts_everything_down() {
        let mut mcu = printing();
        assert_eq!(mcu.check_outputs(49_999), Ok(()));
        assert!(mcu.check_outputs(50_000).is_err());
        assert_all_stopped(
            &mcu,
            Shutdown::DigitalOutExpired,
            "Missed scheduling of next digital out event",
        );
        // The first reason stays.
        mcu.shutdown(Shutdown::TimerTooClose);
        assert_eq!(mcu.shutdown_reason(), Some(Shutdown::DigitalOutExpired));
    }
}
