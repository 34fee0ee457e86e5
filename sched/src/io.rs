//! The MCU role's outputs and ADC inputs, run from a timer through a small
//! hardware trait ([`Peripherals`]) that the board implements with GPIO,
//! timers and its ADC, and the host build with a simulation.
//!
//! [`Io::run`] is the timer's work: every update, software PWM edge, ADC
//! reading and timeout due by then, after which [`Io::next_wake`] says when
//! to run again. The host role queues output updates and takes ADC reports
//! (and the reports of SPI temperature chips, inputs of their own kind:
//! [`crate::thermocouple`]).
//! A fault shuts the io down: every output back to its default, sampling
//! stopped, the first reason kept; whoever runs it then stops the steppers
//! too.

use crate::adc::{AdcQuery, AdcReport, AnalogIn};
use crate::clock::{due, earliest};
use crate::outputs::{Drive, Output, OutputConfig, QueueError};
use crate::shutdown::Shutdown;
use crate::thermocouple::{SpiQuery, SpiReport, Thermocouple};

/// The hardware behind the outputs and ADC inputs. Indices are the order
/// in which outputs and inputs were added to the [`Io`].
pub trait Peripherals {
    /// Sets output `index` as `drive` says (a level, or a hardware PWM
    /// duty).
    fn drive(&mut self, index: usize, drive: Drive);
    /// Reads ADC input `index` now, raw counts.
    fn read_adc(&mut self, index: usize) -> u16;
    /// One full-duplex transfer with SPI input `index`'s chip, its chip
    /// select held for the whole of `data`: the bytes sent are replaced
    /// by those received. Hardware without SPI inputs need not implement
    /// it (it reads zeros).
    fn spi_transfer(&mut self, index: usize, data: &mut [u8]) {
        let _ = index;
        data.fill(0);
    }
    /// Output `index` took an update: `value` (on ticks, or duty) from
    /// `clock` on. Hardware that drives some outputs elsewhere (on a
    /// secondary MCU) sends it on from here; the rest need not implement
    /// it.
    fn queued(&mut self, index: usize, clock: u32, value: u32) {
        let _ = (index, clock, value);
    }
}

/// An input: an ADC channel, or an SPI temperature chip.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Input {
    Adc(AnalogIn),
    Spi(Thermocouple),
}

impl Input {
    fn next_event(&self) -> Option<u32> {
        match self {
            Self::Adc(a) => a.next_event(),
            Self::Spi(t) => t.next_event(),
        }
    }
}

/// `O` outputs and `A` inputs (ADC channels or SPI chips).
#[derive(Debug, Clone)]
pub struct Io<const O: usize, const A: usize> {
    outputs: heapless::Vec<Output, O>,
    inputs: heapless::Vec<Input, A>,
    shutdown: Option<Shutdown>,
}

/// Every output or input slot is taken, or the index names none.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NoSuchSlot;

impl<const O: usize, const A: usize> Default for Io<O, A> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const O: usize, const A: usize> Io<O, A> {
    /// Nothing configured.
    pub const fn new() -> Self {
        Self {
            outputs: heapless::Vec::new(),
            inputs: heapless::Vec::new(),
            shutdown: None,
        }
    }

    /// Adds an output, driving its start-up value; returns its index.
    pub fn add_output(
        &mut self,
        config: OutputConfig,
        hw: &mut impl Peripherals,
    ) -> Result<usize, NoSuchSlot> {
        let output = Output::new(config);
        let drive = output.drive();
        self.outputs.push(output).map_err(|_| NoSuchSlot)?;
        let index = self.outputs.len() - 1;
        hw.drive(index, drive);
        Ok(index)
    }

    /// Adds an ADC input, not yet sampled; returns its index.
    pub fn add_input(&mut self) -> Result<usize, NoSuchSlot> {
        self.inputs
            .push(Input::Adc(AnalogIn::default()))
            .map_err(|_| NoSuchSlot)?;
        Ok(self.inputs.len() - 1)
    }

    /// Adds an SPI temperature input, not yet read; returns its index.
    pub fn add_spi_input(&mut self) -> Result<usize, NoSuchSlot> {
        self.inputs
            .push(Input::Spi(Thermocouple::default()))
            .map_err(|_| NoSuchSlot)?;
        Ok(self.inputs.len() - 1)
    }

    /// Starts sampling ADC input `index` as `query` says.
    pub fn query(&mut self, index: usize, query: AdcQuery) -> Result<(), NoSuchSlot> {
        if self.shutdown.is_none() {
            match self.inputs.get_mut(index) {
                Some(Input::Adc(adc)) => adc.query(query),
                _ => return Err(NoSuchSlot),
            }
        }
        Ok(())
    }

    /// Starts reading SPI input `index` as `query` says (its
    /// configuration bytes are written at once).
    pub fn query_spi(
        &mut self,
        index: usize,
        query: SpiQuery,
        hw: &mut impl Peripherals,
    ) -> Result<(), NoSuchSlot> {
        if self.shutdown.is_none() {
            match self.inputs.get_mut(index) {
                Some(Input::Spi(chip)) => chip.query(query, &mut |d| hw.spi_transfer(index, d)),
                _ => return Err(NoSuchSlot),
            }
        }
        Ok(())
    }

    /// Queues `value` (on ticks, or duty) for output `index` at `clock`,
    /// given the time `now`. Err(Full) asks to try again later; an update
    /// for a clock already passed shuts everything down ("Timer too
    /// close"). After a shutdown, updates are dropped.
    pub fn queue(
        &mut self,
        index: usize,
        clock: u32,
        value: u32,
        now: u32,
        hw: &mut impl Peripherals,
    ) -> Result<(), QueueError> {
        if self.shutdown.is_some() {
            return Ok(());
        }
        let Some(output) = self.outputs.get_mut(index) else {
            return Ok(());
        };
        match output.queue(clock, value, now) {
            Err(QueueError::Late) => {
                self.shutdown(Shutdown::TimerTooClose, hw);
                Err(QueueError::Late)
            }
            Ok(()) => {
                hw.queued(index, clock, value);
                Ok(())
            }
            other => other,
        }
    }

    /// The newest report of ADC input `index` not yet taken.
    pub fn take_report(&mut self, index: usize) -> Option<AdcReport> {
        match self.inputs.get_mut(index)? {
            Input::Adc(adc) => adc.take_report(),
            Input::Spi(_) => None,
        }
    }

    /// The newest report of SPI input `index` not yet taken.
    pub fn take_spi_report(&mut self, index: usize) -> Option<SpiReport> {
        match self.inputs.get_mut(index)? {
            Input::Spi(chip) => chip.take_report(),
            Input::Adc(_) => None,
        }
    }

    /// The current value of output `index` (on ticks, or duty).
    pub fn value(&self, index: usize) -> Option<u32> {
        self.outputs.get(index).map(Output::value)
    }

    /// When [`Self::run`] has work next (None: nothing to do until
    /// something is queued). May be due already.
    pub fn next_wake(&self) -> Option<u32> {
        let outputs = self.outputs.iter().map(Output::next_event);
        let inputs = self.inputs.iter().map(Input::next_event);
        outputs.chain(inputs).fold(None, earliest)
    }

    /// The timer's work at clock `now`: everything due. A fault shuts
    /// everything down and is returned.
    pub fn run(&mut self, now: u32, hw: &mut impl Peripherals) -> Result<(), Shutdown> {
        if let Some(reason) = self.shutdown {
            return Err(reason);
        }
        let outcome = self.run_due(now, hw);
        if let Err(reason) = outcome {
            self.shutdown(reason, hw);
        }
        outcome
    }

    fn run_due(&mut self, now: u32, hw: &mut impl Peripherals) -> Result<(), Shutdown> {
        for (index, output) in self.outputs.iter_mut().enumerate() {
            if let Some(drive) = output.run(now)? {
                hw.drive(index, drive);
            }
        }
        for (index, input) in self.inputs.iter_mut().enumerate() {
            while due(input.next_event(), now).is_some() {
                match input {
                    Input::Adc(adc) => adc.sample(hw.read_adc(index))?,
                    Input::Spi(chip) => chip.read(&mut |d| hw.spi_transfer(index, d))?,
                }
            }
        }
        Ok(())
    }

    /// Why the io shut down, if it did.
    pub fn shutdown_reason(&self) -> Option<Shutdown> {
        self.shutdown
    }

    /// Every output back to its default, sampling stopped; the first
    /// reason is kept.
    pub fn shutdown(&mut self, reason: Shutdown, hw: &mut impl Peripherals) {
        self.shutdown.get_or_insert(reason);
        for (index, output) in self.outputs.iter_mut().enumerate() {
            hw.drive(index, output.reset());
        }
        for input in &mut self.inputs {
            match input {
                Input::Adc(adc) => adc.stop(),
                Input::Spi(chip) => chip.stop(),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::outputs::OutputKind;
    use std::vec::Vec;

    /// Records what the outputs did; ADC inputs read `adc`.
    #[derive(Default)]
    struct Bench {
        now: u32,
        drives: Vec<(u32, usize, Drive)>,
        adc: u16,
        reads: usize,
    }

    impl Peripherals for Bench {
        fn drive(&mut self, index: usize, drive: Drive) {
            self.drives.push((self.now, index, drive));
        }
        fn read_adc(&mut self, _: usize) -> u16 {
            self.reads += 1;
            self.adc
        }
    }

    /// A heater (soft PWM, 1000-tick cycle, 10_000-tick max_duration), a
    /// fan (hardware PWM, no limit) and a thermistor sampled 4 times a
    /// report every 2000 ticks.
    fn printer(hw: &mut Bench) -> Io<2, 1> {
        let mut io = Io::new();
        let heater = OutputConfig {
            kind: OutputKind::Digital { cycle_ticks: 1000 },
            value: 0,
            default: 0,
            max_duration: 10_000,
        };
        let fan = OutputConfig {
            kind: OutputKind::HardPwm { cycle_ticks: 1000 },
            value: 0,
            default: 0,
            max_duration: 0,
        };
        assert_eq!(io.add_output(heater, hw), Ok(0));
        assert_eq!(io.add_output(fan, hw), Ok(1));
        assert_eq!(io.add_input(), Ok(0));
        io.query(
            0,
            AdcQuery {
                clock: 100,
                sample_ticks: 10,
                sample_count: 4,
                rest_ticks: 2000,
                min: 1000,
                max: 15000,
                range_check_count: 2,
            },
        )
        .expect("input 0");
        io
    }

    /// Runs `io` at each wake before `until`.
    fn run_until(io: &mut Io<2, 1>, hw: &mut Bench, until: u32) -> Result<(), Shutdown> {
        while let Some(at) = io.next_wake().filter(|&at| at < until) {
            hw.now = at;
            io.run(at, hw)?;
        }
        Ok(())
    }

    #[test]
    fn outputs_and_inputs_run_at_their_clocks() {
        let mut hw = Bench {
            adc: 2000,
            ..Bench::default()
        };
        let mut io = printer(&mut hw);
        io.queue(0, 500, 300, 0, &mut hw).expect("room");
        io.queue(1, 700, 128, 0, &mut hw).expect("room");
        run_until(&mut io, &mut hw, 2600).expect("no fault");
        let heater: Vec<_> = hw.drives.iter().filter(|d| d.1 == 0).collect();
        assert_eq!(
            heater
                .iter()
                .map(|&&(at, _, d)| (at, d))
                .collect::<Vec<_>>(),
            [
                (0, Drive::Level(false)),
                (500, Drive::Level(true)),
                (800, Drive::Level(false)),
                (1500, Drive::Level(true)),
                (1800, Drive::Level(false)),
                (2500, Drive::Level(true)),
            ]
        );
        assert!(hw.drives.contains(&(700, 1, Drive::Duty(128))));
        // Reports at 100 and 2100, 4 readings each.
        assert_eq!(hw.reads, 8);
        assert_eq!(
            io.take_report(0),
            Some(AdcReport {
                clock: 2100,
                value: 8000
            })
        );
    }

    #[test]
    fn an_adc_reading_out_of_range_shuts_every_output_down() {
        let mut hw = Bench {
            adc: 4000,
            ..Bench::default()
        };
        let mut io = printer(&mut hw);
        io.queue(0, 500, 1000, 0, &mut hw).expect("room");
        io.queue(1, 500, 255, 0, &mut hw).expect("room");
        // 4 × 4000 = 16000 > 15000: the second such report faults.
        assert_eq!(
            run_until(&mut io, &mut hw, 10_000),
            Err(Shutdown::AdcOutOfRange)
        );
        assert_eq!(hw.now, 2130);
        assert_eq!(
            &hw.drives[hw.drives.len() - 2..],
            [(2130, 0, Drive::Level(false)), (2130, 1, Drive::Duty(0))]
        );
        assert_eq!(io.next_wake(), None);
        assert_eq!(
            io.shutdown_reason().map(Shutdown::message),
            Some("ADC out of range")
        );
    }

    /// A MAX6675 whose word is `word`.
    struct SpiBench {
        word: u16,
        reads: usize,
    }

    impl Peripherals for SpiBench {
        fn drive(&mut self, _: usize, _: Drive) {}
        fn read_adc(&mut self, _: usize) -> u16 {
            0
        }
        fn spi_transfer(&mut self, index: usize, data: &mut [u8]) {
            assert_eq!((index, data.len()), (1, 2));
            self.reads += 1;
            data.copy_from_slice(&self.word.to_be_bytes());
        }
    }

    #[test]
    fn spi_inputs_are_read_beside_adc_inputs_and_their_faults_shut_down() {
        use crate::thermocouple::SpiChip;
        let mut hw = SpiBench {
            word: 100 << 5,
            reads: 0,
        };
        let mut io: Io<0, 2> = Io::new();
        assert_eq!(io.add_input(), Ok(0));
        assert_eq!(io.add_spi_input(), Ok(1));
        let query = SpiQuery {
            chip: SpiChip::Max6675,
            clock: 50,
            rest_ticks: 300,
            min: 0,
            max: 1040 << 3,
            max_invalid: 3,
            init: [0; 4],
            init_len: 0,
        };
        assert_eq!(io.query(1, adc_query()), Err(NoSuchSlot));
        io.query_spi(1, query, &mut hw).expect("spi input");
        assert_eq!(io.next_wake(), Some(50));
        io.run(50, &mut hw).expect("good");
        assert_eq!(io.take_report(1), None);
        assert_eq!(
            io.take_spi_report(1),
            Some(SpiReport {
                clock: 50,
                value: 100 << 5,
                fault: 0
            })
        );
        // Open thermocouple (bit 2): the fourth read in a row shuts down.
        hw.word |= 0x04;
        for at in [350, 650, 950] {
            io.run(at, &mut hw).expect("tolerated");
        }
        assert_eq!(io.run(1250, &mut hw), Err(Shutdown::ThermocoupleFault));
        assert_eq!((hw.reads, io.next_wake()), (5, None));
    }

    fn adc_query() -> AdcQuery {
        AdcQuery {
            clock: 0,
            sample_ticks: 1,
            sample_count: 1,
            rest_ticks: 10,
            min: 0,
            max: 10,
            range_check_count: 0,
        }
    }

    #[test]
    fn a_heater_not_updated_within_max_duration_shuts_everything_down() {
        let mut hw = Bench {
            adc: 2000,
            ..Bench::default()
        };
        let mut io = printer(&mut hw);
        io.queue(0, 500, 300, 0, &mut hw).expect("room");
        io.queue(1, 500, 255, 0, &mut hw).expect("room");
        assert_eq!(
            run_until(&mut io, &mut hw, 20_000),
            Err(Shutdown::DigitalOutExpired)
        );
        assert_eq!(hw.now, 10_500);
        assert_eq!(io.value(0), Some(0));
        assert_eq!(io.value(1), Some(0));
        assert_eq!(
            io.shutdown_reason().map(Shutdown::message),
            Some("Missed scheduling of next digital out event")
        );
        // Later updates are dropped; the first reason stays.
        assert_eq!(io.queue(0, 30_000, 300, 20_000, &mut hw), Ok(()));
        assert_eq!(io.next_wake(), None);
    }

    #[test]
    fn an_update_for_a_clock_already_passed_shuts_everything_down() {
        let mut hw = Bench::default();
        let mut io = printer(&mut hw);
        io.queue(1, 500, 255, 0, &mut hw).expect("room");
        run_until(&mut io, &mut hw, 1000).expect("no fault");
        hw.now = 1000;
        assert_eq!(io.queue(0, 900, 300, 1000, &mut hw), Err(QueueError::Late));
        assert_eq!(
            io.shutdown_reason().map(Shutdown::message),
            Some("Timer too close")
        );
        assert_eq!(hw.drives.last(), Some(&(1000, 1, Drive::Duty(0))));
    }
}
