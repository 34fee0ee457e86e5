//! The MCU role in virtual time: every stepper's commands go into the
//! same engine the board runs from its timer interrupt
//! ([`onechip_sched::engine::Engine`]), which is run forward as far as
//! step generation has committed, each step recorded with its 64-bit
//! clock. Homing moves stop at simulated endstops. The heaters and fan
//! ([`Heaters`], the io the board runs from its second timer) run in the
//! same virtual time against simulated physics ([`Plant`]); a fault of
//! either shuts both down.

use crate::thermal_plant::{ADC_MAX, Plant};
use onechip_app::heaters::{FIRST_REPORT, Heaters, ThermalCommand};
use onechip_planner::homing::HomingMove;
use onechip_planner::kinematics::{StepperKinematics, calc_position};
use onechip_planner::machine::MAX_STEPPERS;
use onechip_planner::machine::Machine;
use onechip_sched::endstop::{Check, Endstop};
use onechip_sched::engine::{Command, Engine};
use onechip_sched::shutdown::Shutdown;
use onechip_sched::stepper::StepPins;
use onechip_stepgen::compress::StepCommand;
use onechip_stepgen::motion::StepSink;

/// Moves each virtual stepper's queue holds, and commands its outbox holds.
pub const MOVE_QUEUE: usize = 256;
const OUTBOX: usize = 64;

/// The machine as physics sees it, for endstops: where the motion steppers
/// really are.
#[derive(Debug, Clone, PartialEq)]
pub struct Physics {
    /// How the three motion steppers follow the toolhead.
    pub kinematics: [StepperKinematics; 3],
    /// mm per step of each motion stepper.
    pub step_dist: [f64; 3],
    /// The motion steppers' positions at power-on, mm.
    pub start: [f64; 3],
    /// MCU clock, Hz.
    pub freq: f64,
}

impl Physics {
    /// The toolhead's real position after `steps` steps of each motion
    /// stepper, mm.
    fn toolhead(&self, steps: [i64; 3]) -> [f64; 3] {
        let s = core::array::from_fn(|k| self.start[k] + steps[k] as f64 * self.step_dist[k]);
        calc_position(&self.kinematics, s)
    }
}

/// The steps one stepper made.
#[derive(Debug, Clone, Default)]
pub struct StepLog {
    /// Every step: 64-bit MCU clock and direction (true: positive).
    pub steps: Vec<(u64, bool)>,
    /// Position in steps (+1 per positive step).
    pub position: i64,
    /// Shortest time between two steps, ticks.
    pub min_interval: Option<u64>,
}

/// A stepper's pins, recording each step at the clock the engine runs at.
#[derive(Debug, Default)]
struct Recorder {
    clock: u64,
    dir: bool,
    log: StepLog,
}

impl StepPins for Recorder {
    fn set_dir(&mut self, positive: bool) {
        self.dir = positive;
    }

    fn step(&mut self) {
        if let Some(&(last, _)) = self.log.steps.last() {
            let gap = self.clock - last;
            self.log.min_interval = Some(self.log.min_interval.map_or(gap, |m| m.min(gap)));
        }
        self.log.steps.push((self.clock, self.dir));
        self.log.position += if self.dir { 1 } else { -1 };
    }
}

/// The virtual MCU.
pub struct VirtualMcu {
    engine: Box<Engine<Recorder, MAX_STEPPERS, MOVE_QUEUE, OUTBOX>>,
    steppers: usize,
    /// Virtual time: the engine has run up to here, ticks.
    now: u64,
    /// When the engine wants to run next (stale while `pushed`).
    wake: Option<u64>,
    /// Commands were pushed since the engine last ran.
    pushed: bool,
    /// With physics, homing moves stop at their endstops; without, they run
    /// to their end (klippy's batch mode).
    physics: Option<Physics>,
    /// Where each endstop triggered: axis, toolhead position, clock.
    triggers: Vec<(usize, [f64; 3], u64)>,
    /// The homing move being watched: its start clock, and its endstop
    /// with the 64-bit clock of its next reading.
    watch: Option<(u64, Endstop, u64)>,
    /// The heaters and fan, and their physics.
    thermal: Option<(Heaters, Plant)>,
    /// When the heaters' io wants to run next, ticks (kept up to date
    /// whenever the io changes, so the engine's steps need not ask).
    io_wake: Option<u64>,
}

impl VirtualMcu {
    /// An MCU with `steppers` idle steppers, at clock `start`.
    pub fn new(steppers: usize, start: u64) -> Self {
        let mut mcu = Self {
            engine: Box::new(Engine::new(Default::default())),
            steppers: steppers.min(MAX_STEPPERS),
            now: 0,
            wake: None,
            pushed: false,
            physics: None,
            triggers: Vec::new(),
            watch: None,
            thermal: None,
            io_wake: None,
        };
        mcu.advance_clock(start);
        mcu
    }

    /// The same MCU with `machine`'s heaters and fan, simulated, on a
    /// clock of `freq` Hz; first temperature readings 0.2 s from now.
    pub fn with_heaters(mut self, machine: &Machine<'_>, freq: f64) -> Self {
        let mut plant = Plant::new(machine, freq);
        plant.now = self.now;
        let first = self.now + (FIRST_REPORT * freq) as u64;
        let heaters = Heaters::new(machine, freq, ADC_MAX, first as u32, &mut plant);
        self.thermal = Some((heaters, plant));
        self.update_io_wake();
        self
    }

    /// The heaters and fan with their physics, if simulated.
    pub fn thermal(&mut self) -> Option<(&Heaters, &mut Plant)> {
        let now = self.now;
        self.thermal.as_mut().map(|(h, p)| {
            p.now = now;
            (&*h, p)
        })
    }

    /// Carries out a heater or fan command now.
    pub fn thermal_command(&mut self, command: ThermalCommand) {
        let now = self.now;
        if let Some((heaters, plant)) = &mut self.thermal {
            plant.now = now;
            if let Err(reason) = heaters.command(command, now as u32, plant) {
                self.engine.stop(reason);
            }
            self.update_io_wake();
        }
    }

    /// The virtual time, ticks.
    pub fn now(&self) -> u64 {
        self.now
    }

    /// The same MCU with endstops where `physics` puts them.
    pub fn with_physics(mut self, physics: Physics) -> Self {
        self.physics = Some(physics);
        self
    }

    /// Runs every step and heater event before clock `until`, in time
    /// order, and moves virtual time there (with `u64::MAX`: until the
    /// steppers are idle).
    pub fn run_until(&mut self, until: u64) {
        self.refresh();
        while let Some(at) = self.wake.filter(|&w| w < until) {
            self.run_at(at);
        }
        if until != u64::MAX {
            self.advance_clock(until);
        }
    }

    /// Runs the heaters' io at each of its wakes before clock `at`.
    fn run_io_before(&mut self, at: u64) {
        while let Some(wake) = self.io_wake.filter(|&w| w < at) {
            self.run_io(wake);
        }
    }

    /// Reads when the heaters' io wants to run next (a wake already due
    /// counts as now).
    fn update_io_wake(&mut self) {
        self.io_wake = self.thermal.as_ref().and_then(|(heaters, _)| {
            let ahead = heaters.next_wake()?.wrapping_sub(self.now as u32) as i32;
            Some(self.now + u64::try_from(ahead).unwrap_or(0))
        });
    }

    /// The heaters' timer at clock `at`; a fault stops the steppers too.
    fn run_io(&mut self, at: u64) {
        self.now = self.now.max(at);
        let Some((heaters, plant)) = &mut self.thermal else {
            return;
        };
        plant.now = self.now;
        if let Err(reason) = heaters.run(self.now as u32, plant) {
            self.engine.stop(reason);
            self.wake = None;
        }
        self.update_io_wake();
    }

    /// Why the MCU shut down, if it did.
    pub fn shutdown(&self) -> Option<Shutdown> {
        self.engine.shutdown_reason().or_else(|| {
            self.thermal
                .as_ref()
                .and_then(|(heaters, _)| heaters.shutdown_reason())
        })
    }

    /// The steps each stepper made.
    pub fn logs(&self) -> impl Iterator<Item = &StepLog> {
        self.engine.pins().take(self.steppers).map(|r| &r.log)
    }

    /// Every endstop trigger so far: axis, the toolhead's real position
    /// when the steppers stopped (mm), and the clock.
    pub fn triggers(&self) -> &[(usize, [f64; 3], u64)] {
        &self.triggers
    }

    /// The toolhead's real position now, if physics is modelled, mm.
    pub fn real_position(&self) -> Option<[f64; 3]> {
        let physics = self.physics.as_ref()?;
        Some(physics.toolhead(self.motion_steps()))
    }

    fn motion_steps(&self) -> [i64; 3] {
        core::array::from_fn(|k| self.engine.position(k).unwrap_or(0))
    }

    /// The engine's timer interrupt at clock `at`, after the heaters'
    /// events before it.
    fn run_at(&mut self, at: u64) {
        self.run_io_before(at);
        for pins in self.engine.pins_mut() {
            pins.clock = at;
        }
        self.now = self.now.max(at);
        let next = self.engine.run(at as u32);
        self.wake = next.map(|n| at + u64::from(n.wrapping_sub(at as u32)));
        self.pushed = false;
        if let Some(reason) = self.engine.shutdown_reason()
            && let Some((heaters, plant)) = &mut self.thermal
            && heaters.shutdown_reason().is_none()
        {
            plant.now = self.now;
            heaters.shutdown(reason, plant);
            self.update_io_wake();
        }
    }

    /// Lets the engine see commands pushed since it last ran.
    fn refresh(&mut self) {
        if self.pushed {
            self.run_at(self.now);
        }
    }

    /// Moves virtual time to `until` with nothing due before it, running
    /// the engine there (as its heartbeat would) so its clock follows.
    fn advance_clock(&mut self, until: u64) {
        if until > self.now {
            // The 32-bit clock must be read at least once a wrap.
            while until - self.now > u64::from(u32::MAX >> 1) {
                let step = self.now + u64::from(u32::MAX >> 1);
                self.run_at(step);
            }
            self.run_at(until);
        }
    }
}

impl StepSink for VirtualMcu {
    fn command(&mut self, index: usize, cmd: StepCommand, clock: u64) {
        if index >= self.steppers || self.shutdown().is_some() {
            return;
        }
        let cmd = Command::from(cmd);
        while self.engine.push(index, cmd, clock).is_err() {
            // Outbox full: time runs on until the engine makes room.
            self.refresh();
            match self.wake {
                Some(at) => self.run_at(at),
                None => return,
            }
        }
        self.pushed = true;
    }

    fn home(
        &mut self,
        homing: &HomingMove,
        start_clock: u64,
        until_clock: u64,
    ) -> Option<[i64; MAX_STEPPERS]> {
        let physics = self.physics.clone()?;
        let freq = physics.freq;
        // Sampled about once per step of the homing move's finest stepper.
        let finest = physics
            .step_dist
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min);
        let reached = |pos: [f64; 3]| {
            let coord = pos[homing.axis];
            if homing.positive_dir {
                coord >= homing.position_endstop
            } else {
                coord <= homing.position_endstop
            }
        };
        let (mut endstop, mut read_at) = match self.watch {
            Some((start, endstop, at)) if start == start_clock => (endstop, at),
            _ => {
                let at = start_clock.max(self.now);
                let endstop = Endstop::for_homing(at as u32, freq, homing.speed, finest);
                (endstop, at)
            }
        };
        self.refresh();
        let triggered_at = loop {
            match self.wake {
                Some(at) if at < read_at => self.run_at(at),
                _ if read_at >= until_clock => {
                    self.watch = Some((start_clock, endstop, read_at));
                    return None;
                }
                _ => match endstop.read(reached(physics.toolhead(self.motion_steps()))) {
                    Check::Triggered(_) => break read_at,
                    Check::At(next) => read_at += u64::from(next.wrapping_sub(read_at as u32)),
                },
            }
        };
        // Triggered: the steppers stop at once, so none overshoots the
        // trigger; their remaining steps are dropped.
        self.watch = None;
        self.engine.halt();
        self.wake = None;
        self.advance_clock(triggered_at);
        let real = physics.toolhead(self.motion_steps());
        self.triggers.push((homing.axis, real, triggered_at));
        Some([0; MAX_STEPPERS])
    }
}
