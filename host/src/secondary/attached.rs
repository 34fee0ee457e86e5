//! The secondary MCUs of a simulated printer: their steppers' commands go
//! to the real boards (or peers) instead of the virtual MCU, each in that
//! MCU's clock, within its move queue, and their faults stop the printer.

use super::{ConnectError, Heard, Secondary};
use crate::thermal_plant::mcu_sensor;
use onechip_app::heaters::McuSetup;
use onechip_app::mcu_config::{Oids, pin_ref, write_config};
use onechip_app::step_pulse::pulse_ticks;
use onechip_planner::machine::Machine;
use onechip_protocol::transport::LinkStats;
use onechip_sched::engine::Full;
use onechip_sched::shutdown::Shutdown;
use onechip_sched::step_command::StepCommand;
use onechip_secondary_mcu::connection::OUTBOX;
use onechip_secondary_mcu::step_commands::StepCommandEncoder;
use std::cell::Cell;
use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::path::Path;
use std::time::{Duration, Instant};

/// Seconds between two re-fits of the steppers' clock lines (klippy
/// re-fits from its once-a-second stats).
const CALIBRATE_PERIOD: f64 = 1.0;
/// How long a secondary may take to connect.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(15);

/// One connected secondary and its move queue.
struct Attached {
    mcu: Secondary,
    /// Name, for shutdown messages.
    name: &'static str,
    /// End clocks of the `queue_step`s the MCU may still hold, soonest
    /// first: at most `move_count`.
    slots: BinaryHeap<Reverse<u64>>,
}

/// A routed stepper's commands and what they add up to.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SentSteps {
    /// Steps sent.
    pub count: u64,
    /// Their sum, +1 forward and −1 back.
    pub position: i64,
    /// Each step's clock on its MCU, ticks (for comparing with what its
    /// pins did).
    pub clocks: Vec<u64>,
    /// The direction of the next steps.
    forward: bool,
}

/// Every secondary of the printer.
pub struct Secondaries {
    attached: Vec<Attached>,
    /// For each stepper on a secondary: which one, and its encoder.
    routes: Vec<Option<(usize, StepCommandEncoder<'static>)>>,
    /// What each stepper on a secondary was sent.
    sent: Vec<SentSteps>,
    /// Main clock, Hz (host time is the main clock in seconds).
    freq: f64,
    next_calibrate: f64,
    failure: Option<Shutdown>,
    /// When (wall clock) the failure was noticed.
    failed_at: Option<Instant>,
    /// `emergency_stop` went to every secondary.
    stopped: bool,
}

impl Secondaries {
    /// Connects every `[mcu NAME]` of `machine` and configures its
    /// steppers (`pulse(i)`: stepper `i`'s step pulse, s); `now` is host
    /// time (s) on the main clock of `freq` Hz.
    pub fn connect(
        machine: &Machine<'_>,
        pulse: &dyn Fn(usize) -> f64,
        freq: f64,
        now: &dyn Fn() -> f64,
    ) -> Result<Self, ConnectError> {
        let mut all = Self {
            attached: Vec::new(),
            routes: vec![None; machine.steppers.len()],
            sent: vec![SentSteps::default(); machine.steppers.len()],
            freq,
            next_calibrate: 0.0,
            failure: None,
            failed_at: None,
            stopped: false,
        };
        for secondary in &machine.secondaries {
            let name: &'static str = Box::leak(secondary.name.to_string().into_boxed_str());
            // The config depends on the MCU's clock (step pulses in its
            // ticks), which identify tells; its object ids are kept.
            let oids = Cell::new(Oids::default());
            let lines = |mcu_freq: f64| {
                let setup = McuSetup::new(machine, mcu_freq, 0, mcu_sensor(), 0);
                let mut lines = Vec::new();
                let ticks = |i: usize| pulse_ticks(pulse(i), mcu_freq);
                oids.set(write_config(machine, &setup, name, &ticks, &mut |l| {
                    lines.push(l.to_string())
                }));
                lines
            };
            let path = Path::new(secondary.serial);
            let mcu =
                Secondary::connect(name, path, &lines, now, CONNECT_TIMEOUT).map_err(|e| {
                    let (file, line) = secondary.serial_at;
                    ConnectError::Mcu {
                        mcu: name.to_string(),
                        at: (file.to_string(), line),
                        error: Box::new(e),
                    }
                })?;
            let dict = mcu.dictionary();
            let oids = oids.get();
            for (i, oid) in oids.steppers.iter().enumerate() {
                let Some(oid) = *oid else { continue };
                let invert = pin_ref(machine.steppers[i].dir_pin).inverted;
                let encoder = StepCommandEncoder::new(dict, oid, invert)
                    .map_err(|e| ConnectError::Dictionary(e.to_string()))?;
                all.routes[i] = Some((all.attached.len(), encoder));
            }
            all.attached.push(Attached {
                mcu,
                name,
                slots: BinaryHeap::new(),
            });
        }
        Ok(all)
    }

    /// True if stepper `stepper` is on a secondary.
    pub fn routes(&self, stepper: usize) -> bool {
        self.routes.get(stepper).is_some_and(Option::is_some)
    }

    /// What stepper `stepper` was sent (nothing if it is not on a
    /// secondary).
    pub fn sent(&self, stepper: usize) -> Option<&SentSteps> {
        self.sent.get(stepper)
    }

    /// Queues a step command for a stepper on a secondary, `clock` (its
    /// first step, on that MCU's clock) 64-bit. A `queue_step` waits for
    /// a free slot of the MCU's move queue: it goes out once the oldest
    /// command it displaces has run.
    pub fn push(&mut self, stepper: usize, cmd: StepCommand, clock: u64) -> Result<(), Full> {
        let Some(Some((index, encoder))) = self.routes.get(stepper) else {
            return Ok(());
        };
        let attached = &mut self.attached[*index];
        let conn = attached.mcu.connection();
        if conn.queued() + 1 >= OUTBOX {
            return Err(Full);
        }
        let mut bytes = [0u8; 32];
        let Ok(len) = encoder.encode(&cmd, &mut bytes) else {
            return Ok(());
        };
        let mut min_clock = 0;
        let sent = &mut self.sent[stepper];
        match cmd {
            StepCommand::Steps {
                interval,
                count,
                add,
            } => {
                if attached.slots.len() >= usize::from(attached.mcu.move_count) {
                    min_clock = attached.slots.pop().map_or(0, |Reverse(c)| c);
                }
                // Step k comes at clock + k × interval + k(k+1)/2 × add.
                let mut at = clock;
                let mut step = i64::from(interval);
                for _ in 0..count {
                    sent.clocks.push(at);
                    step += i64::from(add);
                    at = at.saturating_add_signed(step);
                }
                let last = sent.clocks.last().copied().unwrap_or(clock);
                attached.slots.push(Reverse(last));
                sent.count += u64::from(count);
                sent.position += if sent.forward { 1 } else { -1 } * i64::from(count);
            }
            StepCommand::Dir(forward) => sent.forward = forward,
            StepCommand::ResetClock(_) => {}
        }
        let _ = attached.mcu.connection().send(&bytes[..len], min_clock);
        Ok(())
    }

    /// Runs every link's I/O at host time `now` (s): sends what is due,
    /// takes what arrived; a secondary's shutdown or silence becomes the
    /// printer's shutdown.
    pub fn service(&mut self, now: f64) {
        for a in &mut self.attached {
            let mut heard = Vec::new();
            let io = a.mcu.service(now, Duration::ZERO, &mut heard);
            if self.failure.is_some() {
                continue;
            }
            let lost = Shutdown::LostCommunication { mcu: a.name };
            let mut failure = io.is_err().then_some(lost);
            for h in heard {
                match h {
                    Heard::Shutdown(reason) => {
                        let reason: &'static str = Box::leak(reason.into_boxed_str());
                        failure = Some(Shutdown::Secondary {
                            mcu: a.name,
                            reason,
                        });
                    }
                    Heard::Failed(_) => failure = Some(lost),
                    Heard::Response(_) => {}
                }
            }
            if failure.is_some() {
                self.failure = failure;
                self.failed_at = Some(Instant::now());
            }
        }
    }

    /// A secondary's fault, if one stopped the printer.
    pub fn failure(&self) -> Option<Shutdown> {
        self.failure
    }

    /// When (wall clock) the secondary's fault was noticed, if one was.
    pub fn failed_at(&self) -> Option<Instant> {
        self.failed_at
    }

    /// Each secondary's name and link counters (retransmissions, bytes).
    pub fn links(&self) -> impl Iterator<Item = (&'static str, LinkStats)> + '_ {
        self.attached.iter().map(|a| (a.name, a.mcu.link_stats()))
    }

    /// Every secondary stops at once (`emergency_stop`), as klippy does
    /// when the printer shuts down.
    pub fn emergency_stop(&mut self, now: f64) {
        if std::mem::replace(&mut self.stopped, true) {
            return;
        }
        for a in &mut self.attached {
            let _ = a.mcu.connection().send_text("emergency_stop", 0);
        }
        self.service(now);
    }

    /// Re-fits each secondary stepper's clock line for moves queued up to
    /// `print_time` (s), at most once a [`CALIBRATE_PERIOD`] of host time
    /// `now` (s): `set(stepper, offset, freq)`.
    pub fn calibrate(&mut self, print_time: f64, now: f64, set: &mut dyn FnMut(usize, f64, f64)) {
        if now < self.next_calibrate {
            return;
        }
        self.next_calibrate = now + CALIBRATE_PERIOD;
        let lines: Vec<Option<(f64, f64)>> = self
            .attached
            .iter_mut()
            .map(|a| {
                a.mcu
                    .connection()
                    .clock_mut()
                    .map(|c| c.calibrate(print_time, now))
            })
            .collect();
        for (stepper, route) in self.routes.iter().enumerate() {
            if let Some((index, _)) = route
                && let Some(Some((offset, freq))) = lines.get(*index)
            {
                set(stepper, *offset, *freq);
            }
        }
    }

    /// Main clock, Hz.
    pub fn freq(&self) -> f64 {
        self.freq
    }
}
