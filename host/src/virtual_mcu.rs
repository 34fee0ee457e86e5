//! The MCU role in virtual time: every stepper's commands go into the
//! same engine the board runs from its timer interrupt
//! ([`onechip_sched::engine::Engine`]), which is run forward as far as
//! step generation has committed, each step recorded with its 64-bit
//! clock. The engine's endstop check reads simulated endstops
//! ([`Physics`]) through the step pins, as the board's interrupt reads its
//! GPIOs. The heaters and fan ([`Heaters`], the io the board runs from its
//! second timer) run in the same virtual time against simulated physics
//! ([`Plant`]); a fault of either shuts both down. With secondary MCUs
//! (the session then drives it through
//! [`onechip_app::secondary::mcu::WithSecondaries`], as the firmware
//! drives its own MCU role), a sensor's reports from there reach the
//! heaters ([`Heaters::remote_reading`]), and the io's output updates are
//! kept for the outputs there. It is the session's [`Mcu`]: a wait runs
//! the next timer event, no earlier than its wall time when virtual time
//! is paced ([`Pace`]).

use crate::pace::Pace;
use crate::plot::Window;
use crate::step_log::{FileError, StepLog};
use crate::thermal_plant::{ADC_MAX, Plant, mcu_sensor};
use crate::tmc_sim::{StallDetect, TmcSim};
use onechip_app::heaters::{FIRST_REPORT, Heaters, ThermalCommand, Wait};
use onechip_app::secondary::sent_steps::each_step;
use onechip_app::secondary::thermal::Reading;
use onechip_app::session::Mcu;
use onechip_planner::kinematics::{StepperKinematics, calc_position};
use onechip_planner::machine::MAX_STEPPERS;
use onechip_planner::machine::Machine;
use onechip_planner::move_sink::TrapqMove;
use onechip_sched::endstop::Endstop;
use onechip_sched::engine::{Engine, Full};
use onechip_sched::shutdown::Shutdown;
use onechip_sched::step_command::StepCommand;
use onechip_sched::stepper::StepPins;
use std::cell::{Cell, RefCell};
use std::path::Path;
use std::rc::Rc;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// Moves each virtual stepper's queue holds, and commands its outbox holds.
pub const MOVE_QUEUE: usize = 256;
const OUTBOX: usize = 64;

/// The machine as physics sees it, for endstops: where the motion steppers
/// really are, and where each rail's endstop switch is.
#[derive(Debug, Clone, PartialEq)]
pub struct Physics {
    /// How the three motion steppers follow the toolhead.
    pub kinematics: [StepperKinematics; 3],
    /// mm per step of each motion stepper.
    pub step_dist: [f64; 3],
    /// The motion steppers' positions at power-on, mm.
    pub start: [f64; 3],
    /// Each rail's endstop: the toolhead coordinate it is pressed at (mm)
    /// and whether it is pressed above (true) or below it.
    pub endstops: [Option<(f64, bool)>; 3],
    /// A delta's towers' endstops instead: the carriage height (the
    /// stepper's position, mm) each is pressed at and above.
    pub towers: [Option<f64>; 3],
    /// The Z probe, if any: its engine slot and where it triggers.
    pub probe: Option<(usize, crate::probe_physics::ProbePhysics)>,
    /// The rails' extra steppers (`[stepper_z1]`), by engine slot.
    pub extras: Vec<ExtraStepper>,
}

/// A rail's extra stepper as physics sees it: it carries its own end of
/// the rail (a second Z lead screw), so its own endstop sees its own
/// position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExtraStepper {
    /// Its engine slot.
    pub slot: usize,
    /// mm per step.
    pub step_dist: f64,
    /// Its position at power-on, mm.
    pub start: f64,
    /// Its own endstop, if it has one: the position it is pressed at (mm)
    /// and whether above (true) or below it.
    pub endstop: Option<(f64, bool)>,
}

impl Physics {
    /// The toolhead's real position after `steps` steps of each motion
    /// stepper, mm.
    fn toolhead(&self, steps: [i64; MAX_STEPPERS]) -> [f64; 3] {
        let s = core::array::from_fn(|k| self.start[k] + steps[k] as f64 * self.step_dist[k]);
        calc_position(&self.kinematics, s)
    }
}

/// The motion steppers' positions, shared by their pins so that an
/// endstop sees where the toolhead really is.
#[derive(Debug)]
struct Rails {
    physics: Physics,
    /// Every slot's steps (the rails' first).
    steps: Cell<[i64; MAX_STEPPERS]>,
    /// The probe's control pin: each change's clock and pulse width (s).
    servo: RefCell<Vec<(u64, f64)>>,
}

impl Rails {
    /// True while rail `axis`'s endstop (a delta: tower `axis`'s) is
    /// pressed.
    fn pressed(&self, axis: usize) -> bool {
        if let Some(Some(at)) = self.physics.towers.get(axis).copied() {
            let p = &self.physics;
            let carriage = p.start[axis] + self.steps.get()[axis] as f64 * p.step_dist[axis];
            return carriage >= at;
        }
        if let Some(extra) = self.physics.extras.iter().find(|e| e.slot == axis) {
            let Some((at, above)) = extra.endstop else {
                return false;
            };
            let own = extra.start + self.steps.get()[axis] as f64 * extra.step_dist;
            return if above { own >= at } else { own <= at };
        }
        let Some(Some((at, above))) = self.physics.endstops.get(axis).copied() else {
            return false;
        };
        let coord = self.physics.toolhead(self.steps.get())[axis];
        if above { coord >= at } else { coord <= at }
    }

    /// True while the probe's input reads triggered at clock `now`.
    fn probe_pressed(&self, now: u64) -> bool {
        let Some((_, probe)) = &self.physics.probe else {
            return false;
        };
        let servo = self.servo.borrow();
        probe.pressed(self.physics.toolhead(self.steps.get()), now, &servo)
    }
}

/// A stepper's pins, recording each step at the clock the engine runs at;
/// a motion stepper's also read its rail's simulated endstop.
#[derive(Debug, Default)]
struct Recorder {
    clock: u64,
    dir: bool,
    log: StepLog,
    /// Which motion stepper this is, and the rails it shares.
    rail: Option<(usize, Rc<Rails>)>,
    /// This slot's endstop input is the probe's, which sees the rails.
    probe: Option<Rc<Rails>>,
    /// This slot's endstop input is a TMC driver's DIAG pin.
    diag: Option<Diag>,
}

/// A DIAG pin as an endstop input: the driver reports a stall while its
/// motor is driven into the end of its axis (where the rail's endstop
/// switch would be) with stall detection on.
#[derive(Debug)]
struct Diag {
    /// When the driver reports a stall, as its registers say.
    detect: Rc<Cell<StallDetect>>,
    /// The MCU clock, Hz.
    freq: f64,
    /// The clock of the motor's last step and the interval before it,
    /// ticks.
    last: Option<(u64, Option<u64>)>,
}

impl Diag {
    /// True while the DIAG output is active at clock `now`, the motor
    /// being blocked or not.
    fn active(&self, now: u64, blocked: bool) -> bool {
        // The driver measures the time between the last two steps; a
        // motor not stepped for longer is slower (standing still: none).
        let interval = self.last.and_then(|(at, before)| {
            let ticks = before?.max(now.saturating_sub(at));
            Some(ticks as f64 / self.freq)
        });
        blocked && self.detect.get().reports(interval)
    }
}

impl StepPins for Recorder {
    fn set_dir(&mut self, positive: bool) {
        self.dir = positive;
    }

    fn step(&mut self) {
        self.log.record(self.clock, self.dir);
        if let Some(diag) = &mut self.diag {
            let before = diag.last.map(|(at, _)| self.clock.saturating_sub(at));
            diag.last = Some((self.clock, before));
        }
        if let Some((k, rails)) = &self.rail {
            let mut steps = rails.steps.get();
            steps[*k] = self.log.position;
            rails.steps.set(steps);
        }
    }

    fn endstop_triggered(&mut self) -> bool {
        if let Some(rails) = &self.probe {
            return rails.probe_pressed(self.clock);
        }
        let at_end = self
            .rail
            .as_ref()
            .is_some_and(|(k, rails)| rails.pressed(*k));
        match &self.diag {
            Some(diag) => diag.active(self.clock, at_end),
            None => at_end,
        }
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
    rails: Option<Rc<Rails>>,
    /// Where each endstop triggered: axis (a delta: tower), toolhead
    /// position, clock.
    triggers: Vec<(usize, [f64; 3], u64)>,
    /// The axes of those triggers read on a TMC driver's DIAG pin (a
    /// stall), in order.
    stalls: Vec<usize>,
    /// The probe's control pin: each change's clock and pulse width (s).
    servo: Vec<(u64, f64)>,
    /// Planned moves kept for a plot, and the print-time window they
    /// must touch (s).
    plan: Option<(Window, Vec<TrapqMove>)>,
    /// The heaters and fan, and their physics.
    thermal: Option<(Heaters, Plant)>,
    /// When the heaters' io wants to run next, ticks (kept up to date
    /// whenever the io changes, so the engine's steps need not ask).
    io_wake: Option<u64>,
    /// If set, timer events wait for their wall time.
    pace: Option<Pace>,
    /// Raised by the serial reader when an M112 arrives.
    emergency: Option<Arc<AtomicBool>>,
    /// Filament switch sensors reading no filament (all others read
    /// filament present).
    no_filament: Vec<usize>,
    /// The io's output updates are kept for outputs on secondary MCUs.
    forwards_outputs: bool,
    /// Each stepper's steps sent to a secondary: their clocks on its MCU,
    /// ticks (for comparing with what its pins did).
    secondary_steps: Vec<Vec<u64>>,
    /// When (wall clock) a secondary's fault was noticed, if one was.
    secondary_fault_at: Option<Instant>,
    /// The simulated TMC drivers.
    tmc: TmcSim,
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
            rails: None,
            triggers: Vec::new(),
            stalls: Vec::new(),
            servo: Vec::new(),
            plan: None,
            thermal: None,
            io_wake: None,
            pace: None,
            forwards_outputs: false,
            secondary_steps: Vec::new(),
            secondary_fault_at: None,
            emergency: None,
            no_filament: Vec::new(),
            tmc: TmcSim::default(),
        };
        mcu.advance_clock(start);
        mcu
    }

    /// The same MCU with `machine`'s TMC drivers, simulated, on a clock of
    /// `freq` Hz: a rail homing on a driver's virtual endstop reads its
    /// DIAG pin.
    pub fn with_tmc(mut self, machine: &Machine<'_>, freq: f64) -> Self {
        self.tmc = TmcSim::new(machine);
        let rails = machine.motion_steppers();
        for (i, pins) in self.engine.pins_mut().enumerate().take(rails) {
            let driver = machine.stall_driver(i);
            if let Some(sim) = driver.and_then(|d| self.tmc.driver(d.stepper)) {
                pins.diag = Some(Diag {
                    detect: sim.stall_detect(),
                    freq,
                    last: None,
                });
            }
        }
        self
    }

    /// The simulated TMC drivers.
    pub fn tmc_sim(&mut self) -> &mut TmcSim {
        &mut self.tmc
    }

    /// The same MCU with `machine`'s heaters and fan, simulated, on a
    /// clock of `freq` Hz; first temperature readings 0.2 s from now.
    pub fn with_heaters(mut self, machine: &Machine<'_>, freq: f64) -> Self {
        self.start_heaters(machine, freq);
        self
    }

    /// Builds `machine`'s heaters and fan, and their physics, from now.
    fn start_heaters(&mut self, machine: &Machine<'_>, freq: f64) {
        let mut plant = Plant::new(machine, freq);
        plant.now = self.now;
        if self.forwards_outputs {
            plant.queued = Some(Vec::new());
        }
        let first = self.now + (FIRST_REPORT * freq) as u64;
        let heaters = Heaters::new(
            machine,
            freq,
            ADC_MAX,
            mcu_sensor(),
            first as u32,
            &mut plant,
        );
        self.thermal = Some((heaters, plant));
        self.update_io_wake();
    }

    /// Leaves a shutdown (FIRMWARE_RESTART): the engine idle and
    /// unfaulted, the heaters and fan rebuilt for `machine` (their physics
    /// from ambient again) if they were simulated.
    pub fn restart(&mut self, machine: &Machine<'_>, freq: f64) {
        self.engine.restart();
        self.pushed = true;
        if self.thermal.is_some() {
            self.start_heaters(machine, freq);
        }
    }

    /// The secondary MCUs were brought back: what their steppers were
    /// sent, and their fault, count from here.
    pub fn secondaries_restarted(&mut self) {
        self.secondary_steps.iter_mut().for_each(Vec::clear);
        self.secondary_fault_at = None;
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

    /// Filament switch sensor `sensor`'s switch reads filament `present`
    /// from now on.
    pub fn set_filament(&mut self, sensor: usize, present: bool) {
        self.no_filament.retain(|&s| s != sensor);
        if !present {
            self.no_filament.push(sensor);
        }
    }

    /// The virtual time, ticks.
    pub fn now(&self) -> u64 {
        self.now
    }

    /// The same MCU with endstops where `physics` puts them.
    pub fn with_physics(mut self, physics: Physics) -> Self {
        let rails = Rc::new(Rails {
            physics,
            steps: Cell::new([0; MAX_STEPPERS]),
            servo: RefCell::new(Vec::new()),
        });
        let motion = 3 + rails.physics.extras.len();
        for (k, pins) in self.engine.pins_mut().take(motion).enumerate() {
            pins.rail = Some((k, Rc::clone(&rails)));
        }
        if let Some((slot, _)) = rails.physics.probe
            && let Some(pins) = self.engine.pins_mut().nth(slot)
        {
            pins.probe = Some(Rc::clone(&rails));
        }
        self.rails = Some(rails);
        self
    }

    /// The same MCU keeping, for a plot, the planned moves that touch
    /// print-time `window` (s) and the steps within it (and perhaps a tick
    /// either side), on a clock of `freq` Hz.
    pub fn with_plot(mut self, window: Window, freq: f64) -> Self {
        // Rounded outwards: the plot picks the steps in the window itself.
        let clock = |t: f64| (t * freq).max(0.0) as u64;
        let clocks = clock(window.from).saturating_sub(1)..=clock(window.to).saturating_add(2);
        for pins in self.engine.pins_mut() {
            pins.log.keep_window(clocks.clone());
        }
        self.plan = Some((window, Vec::new()));
        self
    }

    /// The same MCU writing each stepper's steps into `dir` as
    /// `steps-<name>.txt` as it makes them, `names` in stepper order;
    /// [`Self::flush_steps`] writes out the rest at the end.
    pub fn with_step_files<'n>(
        mut self,
        dir: &Path,
        names: impl IntoIterator<Item = &'n str>,
    ) -> Result<Self, FileError> {
        for (pins, name) in self.engine.pins_mut().take(self.steppers).zip(names) {
            pins.log.write_to(dir, name)?;
        }
        Ok(self)
    }

    /// Writes out what the steps files still buffer.
    pub fn flush_steps(&mut self) -> Result<(), FileError> {
        let steppers = self.steppers;
        self.engine
            .pins_mut()
            .take(steppers)
            .try_for_each(|pins| pins.log.flush())
    }

    /// The planned moves kept for the plot.
    pub fn plan(&self) -> &[TrapqMove] {
        self.plan.as_ref().map_or(&[], |(_, moves)| moves)
    }

    /// Paces virtual time by the wall clock from now on: each timer event
    /// runs no earlier than `pace` says.
    pub fn set_pace(&mut self, pace: Pace) {
        self.pace = Some(pace);
    }

    /// True if virtual time follows the wall clock.
    pub fn is_paced(&self) -> bool {
        self.pace.is_some()
    }

    /// The wall clock virtual time follows, if it does.
    pub fn pace(&self) -> Option<Pace> {
        self.pace.clone()
    }

    /// Runs the steppers' next event if it comes before clock `limit`:
    /// true; else only the heaters' events before `limit`, and virtual
    /// time moves there (no earlier than its wall time when paced):
    /// false, and the steppers are idle if they have no event at all
    /// ([`Self::steppers_busy`]).
    pub fn run_next_before(&mut self, limit: u64) -> bool {
        self.refresh();
        if let Some(at) = self.wake.filter(|&w| w < limit) {
            self.run_at(at);
            return true;
        }
        self.run_io_before(limit);
        self.pace_to(limit);
        self.now = self.now.max(limit);
        false
    }

    /// True while the steppers here have steps to make.
    pub fn steppers_busy(&mut self) -> bool {
        self.refresh();
        self.wake.is_some()
    }

    /// Some steppers and outputs are on secondary MCUs from now on
    /// (virtual time must be paced: they run in real time): the steps
    /// sent there are recorded, and the io's output updates kept.
    pub fn with_secondaries(&mut self) {
        self.forwards_outputs = true;
        self.secondary_steps = vec![Vec::new(); MAX_STEPPERS];
        if let Some((_, plant)) = &mut self.thermal {
            plant.queued = Some(Vec::new());
        }
    }

    /// The clocks (on its MCU, ticks) of every step sent to stepper
    /// `stepper` on a secondary.
    pub fn secondary_steps(&self, stepper: usize) -> Option<&[u64]> {
        self.secondary_steps.get(stepper).map(Vec::as_slice)
    }

    /// When (wall clock) a secondary's shutdown or silence was noticed.
    pub fn secondary_fault_at(&self) -> Option<Instant> {
        self.secondary_fault_at
    }

    /// Every stepper stops and every heater goes off, for `reason`.
    fn stop_all(&mut self, reason: Shutdown) {
        if matches!(
            reason,
            Shutdown::Secondary { .. }
                | Shutdown::LostCommunication { .. }
                | Shutdown::SecondaryNotReady { .. }
        ) {
            self.secondary_fault_at.get_or_insert_with(Instant::now);
        }
        self.engine.stop(reason);
        let now = self.now;
        if let Some((heaters, plant)) = &mut self.thermal {
            plant.now = now;
            heaters.shutdown(reason, plant);
        }
        self.update_io_wake();
    }

    /// With a pace: runs every event the wall clock has passed, and moves
    /// virtual time to the wall clock's.
    pub fn run_to_wall_clock(&mut self) {
        self.check_emergency();
        if let Some(clock) = self.pace.as_ref().map(Pace::clock_now) {
            self.run_until(clock);
        }
    }

    /// Sleeps until the wall time of clock `at`, if paced; an M112 seen
    /// meanwhile stops everything before the event.
    fn pace_to(&mut self, at: u64) {
        if let Some(pace) = &self.pace {
            pace.sleep_until(at);
        }
        self.check_emergency();
    }

    /// From now on, a raised `flag` (an M112 the serial reader saw) shuts
    /// the MCU role down before its next event, as the board's USB path
    /// does at once.
    pub fn set_emergency(&mut self, flag: Arc<AtomicBool>) {
        self.emergency = Some(flag);
    }

    /// Carries out a raised emergency flag.
    fn check_emergency(&mut self) {
        if self
            .emergency
            .as_ref()
            .is_some_and(|flag| flag.swap(false, Ordering::Relaxed))
        {
            Mcu::shutdown(self, Shutdown::EmergencyStop);
        }
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
        self.pace_to(at);
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

    /// The axes of the triggers so far that were a TMC driver's stall
    /// reported on its DIAG pin, in order.
    pub fn stalls(&self) -> &[usize] {
        &self.stalls
    }

    /// The probe's control pin so far: each change's clock and pulse
    /// width (s; 0: signal off).
    pub fn probe_servo_log(&self) -> &[(u64, f64)] {
        &self.servo
    }

    /// The toolhead's real position now, if physics is modelled, mm.
    pub fn real_position(&self) -> Option<[f64; 3]> {
        let rails = self.rails.as_ref()?;
        Some(rails.physics.toolhead(rails.steps.get()))
    }

    /// The engine's timer interrupt at clock `at`, after the heaters'
    /// events before it.
    fn run_at(&mut self, at: u64) {
        self.run_io_before(at);
        self.pace_to(at);
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

impl VirtualMcu {
    /// The axis an endstop on engine slot `slot` homes: the probe's slot
    /// stops Z, so its triggers count as Z's.
    fn axis_of(&self, slot: usize) -> usize {
        let probe_slot = self
            .rails
            .as_ref()
            .and_then(|r| r.physics.probe)
            .map(|p| p.0);
        if probe_slot == Some(slot) { 2 } else { slot }
    }
}

impl Mcu for VirtualMcu {
    fn tmc_link(&mut self) -> Option<&mut dyn onechip_app::tmc::TmcLink> {
        Some(&mut self.tmc)
    }
    fn push(&mut self, stepper: usize, cmd: StepCommand, clock: u64) -> Result<(), Full> {
        if stepper >= self.steppers {
            // A stepper the engine does not drive here: dropped.
            return Ok(());
        }
        self.engine.push(stepper, cmd, clock)?;
        self.pushed = true;
        Ok(())
    }

    /// Runs the next timer event (the engine's or the heaters'), if it
    /// comes before `until`; else moves time to `until`.
    fn wait(&mut self, until: u64) {
        self.refresh();
        let next = match (self.wake, self.io_wake) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
        match next {
            Some(at) if at < until && self.wake == Some(at) => self.run_at(at),
            Some(at) if at < until => self.run_io(at),
            _ if until != u64::MAX => self.advance_clock(until),
            _ => {}
        }
    }

    fn now(&mut self) -> u64 {
        self.now
    }

    fn watch_endstop(&mut self, stepper: usize, endstop: Endstop, stops: u32) {
        self.pushed = true;
        self.engine.watch_endstop(stepper, endstop, stops);
    }

    fn stop_watching(&mut self) {
        self.engine.stop_watching();
        self.pushed = true;
    }

    fn take_trigger(&mut self) -> Option<(usize, u32)> {
        let (stepper, trigger) = self.engine.take_trigger()?;
        let axis = self.axis_of(stepper);
        if self
            .engine
            .pins()
            .nth(stepper)
            .is_some_and(|p| p.diag.is_some())
        {
            self.stalls.push(axis);
        }
        let real = self.real_position().unwrap_or_default();
        let clock = onechip_sched::clock::widen(trigger, self.now);
        self.triggers.push((axis, real, clock));
        Some((stepper, trigger))
    }

    fn moved_since(&mut self, stepper: usize, clock: u64) -> i64 {
        self.logs()
            .nth(stepper)
            .map_or(0, |log| log.moved_since(clock))
    }

    fn stop_steppers(&mut self, stops: u32) {
        // A real MCU has made every step due before now: in paced virtual
        // time the engine first catches up with the wall clock.
        self.run_to_wall_clock();
        self.refresh();
        self.engine.stop_steppers(stops);
        // Its next wake is read afresh.
        self.pushed = true;
    }

    fn thermal(&mut self, command: ThermalCommand) {
        self.thermal_command(command);
    }

    fn thermal_waiting(&mut self, wait: Wait) -> bool {
        self.thermal.as_ref().is_some_and(|(h, _)| h.waiting(wait))
    }

    fn report_temperatures(&mut self, mut out: &mut dyn std::fmt::Write) -> std::fmt::Result {
        match &self.thermal {
            Some((heaters, _)) => heaters.report(&mut out),
            None => Ok(()),
        }
    }

    fn shutdown_reason(&mut self) -> Option<Shutdown> {
        VirtualMcu::shutdown(self)
    }

    fn endstop_triggered(&mut self, stepper: usize) -> bool {
        // Read now, not when the engine last ran.
        let now = self.now;
        self.engine.pins_mut().nth(stepper).is_some_and(|pins| {
            pins.clock = now;
            pins.endstop_triggered()
        })
    }

    fn probe_servo(&mut self, clock: u64, pulse_width: f64) {
        self.servo.push((clock, pulse_width));
        if let Some(rails) = &self.rails {
            rails.servo.borrow_mut().push((clock, pulse_width));
        }
    }

    fn shutdown(&mut self, reason: Shutdown) {
        self.stop_all(reason);
    }

    fn can_extrude(&mut self) -> bool {
        self.thermal.as_ref().is_none_or(|(h, _)| h.can_extrude())
    }

    fn filament_present(&mut self, sensor: usize) -> bool {
        !self.no_filament.contains(&sensor)
    }

    fn planned(&mut self, m: &TrapqMove, extruder: bool) {
        if let Some((w, moves)) = &mut self.plan
            && !extruder
        {
            let end = m.print_time + m.accel_t + m.cruise_t + m.decel_t;
            if end >= w.from && m.print_time <= w.to {
                moves.push(*m);
            }
        }
    }

    fn take_queued_output(&mut self) -> Option<(usize, u64, u32)> {
        let (_, plant) = self.thermal.as_mut()?;
        let queued = plant.queued.as_mut().filter(|q| !q.is_empty())?;
        let (index, clock, value) = queued.remove(0);
        Some((index, onechip_sched::clock::widen(clock, self.now), value))
    }

    fn remote_reading(&mut self, reading: Reading) {
        let now = self.now;
        let Some((heaters, plant)) = &mut self.thermal else {
            return;
        };
        plant.now = now;
        let freq = plant.freq();
        match heaters.remote_reading(&reading, freq, now as u32, plant) {
            Err(reason) => self.stop_all(reason),
            Ok(()) => self.update_io_wake(),
        }
    }

    fn sent_elsewhere(&mut self, stepper: usize, cmd: StepCommand, clock: u64) {
        if let (
            StepCommand::Steps {
                interval,
                count,
                add,
            },
            Some(steps),
        ) = (cmd, self.secondary_steps.get_mut(stepper))
        {
            each_step(clock, interval, count, add, |at| steps.push(at));
        }
    }

    fn triggered_elsewhere(&mut self, stepper: usize, clock: u64) {
        let real = self.real_position().unwrap_or_default();
        self.triggers.push((self.axis_of(stepper), real, clock));
    }
}
