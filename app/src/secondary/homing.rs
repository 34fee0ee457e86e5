//! Homing across MCUs with trsync, as klippy drives it: each secondary's
//! trsync started and its steppers tied to it, the endstop armed on its
//! own MCU, and every `trsync_state` report relayed to the others
//! ([`onechip_secondary_mcu::trsync::Dispatch`]) while their links are
//! served. The main MCU (the session's [`Mcu`], our own engine) may take
//! part as one more member: a secondary's trigger stops its steppers at
//! once ([`Mcu::stop_steppers`]), its own endstop's trigger
//! ([`Homing::main_triggered`]) goes to every secondary as
//! `trsync_trigger`, and it stops by itself if the secondaries' reports
//! stop coming (klippy's main MCU's trsync timeout).

use super::{Heard, LinkError, Secondary, SecondaryLink, Text, command, text};
use crate::session::Mcu;
use core::fmt;
use onechip_protocol::codec::Decoded;
use onechip_secondary_mcu::connection::SendTextError;
use onechip_secondary_mcu::trsync::{Dispatch, MAX_MCUS, Member, Relay, reason};

/// A homing in progress over some secondaries (`mcus[i]` with trsync
/// `trsyncs[i]`), and perhaps the main MCU.
pub struct Homing {
    dispatch: Dispatch,
    /// Why each MCU's trsync stopped its steppers, once it reported it.
    stopped: heapless::Vec<Option<u8>, MAX_MCUS>,
    /// Host time (s) the first trigger was heard and relayed.
    relayed_at: Option<f64>,
    /// The main MCU's part, if it takes part.
    main: Option<MainPart>,
}

/// The main MCU in a homing.
#[derive(Debug, Clone, Copy)]
struct MainPart {
    /// Its member index in the dispatch (after the secondaries).
    index: usize,
    /// Its steppers in the homing move (bit `i`: stepper `i`).
    stops: u32,
    /// Host time (s) and reason its steppers were stopped.
    stopped: Option<(f64, u8)>,
}

/// Why a homing command could not be queued.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HomingError(pub Text);

impl fmt::Display for HomingError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

fn send<L: SecondaryLink>(mcu: &mut Secondary<L>, line: &str) -> Result<(), HomingError> {
    mcu.connection().send_text(line, 0).map_err(|e| {
        let why = match e {
            SendTextError::Encode => "not in its dictionary",
            SendTextError::Full => "its outbox is full",
        };
        HomingError(text(format_args!("MCU '{}': {line}: {why}", mcu.name)))
    })
}

impl Homing {
    /// Starts every MCU's trsync (`trsyncs[i]` on `mcus[i]`) at host time
    /// `start` (s) and ties their steppers to it (`steppers[i]`: the
    /// stepper oids on `mcus[i]`).
    pub fn start<L: SecondaryLink>(
        mcus: &mut [&mut Secondary<L>],
        trsyncs: &[u8],
        steppers: &[&[u8]],
        start: f64,
    ) -> Result<Self, HomingError> {
        Self::start_with_main(mcus, trsyncs, steppers, None, start)
    }

    /// [`Self::start`] with the main MCU taking part if `main` is given:
    /// `(stops, freq)`, its steppers in the homing move (bit `i`: stepper
    /// `i`) and its clock, Hz (host time is that clock in seconds).
    pub fn start_with_main<L: SecondaryLink>(
        mcus: &mut [&mut Secondary<L>],
        trsyncs: &[u8],
        steppers: &[&[u8]],
        main: Option<(u32, f64)>,
        start: f64,
    ) -> Result<Self, HomingError> {
        let members_count = mcus.len() + usize::from(main.is_some());
        if trsyncs.len() != mcus.len() || members_count > MAX_MCUS {
            return Err(HomingError(text(format_args!(
                "{} MCUs with {} trsyncs (one each, at most {MAX_MCUS})",
                mcus.len(),
                trsyncs.len()
            ))));
        }
        let mut members = heapless::Vec::<Member, MAX_MCUS>::new();
        for (mcu, &trsync) in mcus.iter_mut().zip(trsyncs) {
            let sync = mcu.connection().clock().copied().ok_or_else(|| {
                HomingError(text(format_args!(
                    "MCU '{}' has no clock sync yet",
                    mcu.name
                )))
            })?;
            // At most MAX_MCUS members, checked above.
            let _ = members.push(Member::new(trsync, sync));
        }
        let main = main.map(|(stops, freq)| {
            let _ = members.push(Member::local(freq));
            MainPart {
                index: mcus.len(),
                stops,
                stopped: None,
            }
        });
        let dispatch = Dispatch::new(&members, start);
        for (i, (mcu, &trsync)) in mcus.iter_mut().zip(trsyncs).enumerate() {
            for line in dispatch.start_lines(i, start) {
                send(mcu, &line)?;
            }
            for oid in steppers.get(i).copied().unwrap_or_default() {
                let line = command(format_args!(
                    "stepper_stop_on_trigger oid={oid} trsync_oid={trsync}"
                ));
                send(mcu, &line)?;
            }
        }
        Ok(Self {
            dispatch,
            stopped: core::iter::repeat_n(None, mcus.len()).collect(),
            relayed_at: None,
            main,
        })
    }

    /// Host time (s) and reason the main MCU's steppers were stopped
    /// (`HOST_REQUEST`: a secondary triggered; `ENDSTOP_HIT`: its own
    /// endstop; `COMMS_TIMEOUT`: the secondaries' reports stopped coming).
    pub fn main_stopped(&self) -> Option<(f64, u8)> {
        self.main.and_then(|m| m.stopped)
    }

    /// The main MCU's endstop triggered at host time `at` (s; its engine
    /// stopped its steppers): every secondary's trsync is triggered.
    pub fn main_triggered<L: SecondaryLink>(
        &mut self,
        mcus: &mut [&mut Secondary<L>],
        at: f64,
        now: f64,
    ) -> Result<(), HomingError> {
        let Some(main) = &mut self.main else {
            return Ok(());
        };
        main.stopped.get_or_insert((at, reason::ENDSTOP_HIT));
        let relay = self
            .dispatch
            .on_news(main.index, false, reason::ENDSTOP_HIT, at);
        self.relay(mcus, relay, now)
    }

    /// Sends what the dispatch decided.
    fn relay<L: SecondaryLink>(
        &mut self,
        mcus: &mut [&mut Secondary<L>],
        relay: Relay,
        now: f64,
    ) -> Result<(), HomingError> {
        let lines = match relay {
            Relay::None => return Ok(()),
            Relay::Extend(lines) => lines,
            Relay::Triggered(_, _, lines) => {
                self.relayed_at.get_or_insert(now);
                lines
            }
        };
        for (j, line) in lines {
            if let Some(mcu) = mcus.get_mut(j) {
                send(mcu, &line)?;
            }
        }
        Ok(())
    }

    /// [`Self::service`] with the main MCU `main` taking part: its news
    /// (it can still trigger, as long as the host serves the links) moves
    /// the secondaries' timeouts on, its own timeout stops its steppers,
    /// and a secondary's trigger stops them at once.
    pub fn service_with_main<L: SecondaryLink, M: Mcu>(
        &mut self,
        mcus: &mut [&mut Secondary<L>],
        main: &mut M,
        now: f64,
        wait: f64,
        heard: &mut dyn FnMut(usize, Heard<'_>),
    ) -> Result<(), HomingError> {
        self.main_news(mcus, now, &mut |stops| main.stop_steppers(stops))?;
        self.service_inner(
            mcus,
            &mut |stops| main.stop_steppers(stops),
            now,
            wait,
            heard,
        )
    }

    /// The main MCU's news at host time `now` (s): it can still trigger,
    /// which moves the secondaries' timeouts on; past its own timeout
    /// `stop_main(stops)` stops its steppers and every secondary is
    /// triggered.
    pub fn main_news<L: SecondaryLink>(
        &mut self,
        mcus: &mut [&mut Secondary<L>],
        now: f64,
        stop_main: &mut dyn FnMut(u32),
    ) -> Result<(), HomingError> {
        let Some(part) = self.main else {
            return Ok(());
        };
        if part.stopped.is_some() || self.dispatch.triggered().is_some() {
            return Ok(());
        }
        let relay = self.dispatch.on_news(part.index, true, 0, now);
        self.relay(mcus, relay, now)?;
        if self.dispatch.expire(part.index).is_some_and(|e| now > e) {
            // No news from a secondary in time: the main stops by itself,
            // and so must the others.
            stop_main(part.stops);
            self.set_main_stopped(now, reason::COMMS_TIMEOUT);
            let relay = self
                .dispatch
                .on_news(part.index, false, reason::COMMS_TIMEOUT, now);
            self.relay(mcus, relay, now)?;
        }
        Ok(())
    }

    fn set_main_stopped(&mut self, at: f64, why: u8) {
        if let Some(part) = &mut self.main {
            part.stopped.get_or_insert((at, why));
        }
    }

    /// Why each MCU's trsync stopped its steppers (`trsync::reason`), as
    /// it reported: the endstop's MCU `ENDSTOP_HIT`, the others
    /// `HOST_REQUEST` if the relay came in time (`COMMS_TIMEOUT` if not).
    pub fn stop_reasons(&self) -> &[Option<u8>] {
        &self.stopped
    }

    /// Host time (s) the first trigger was heard and relayed to the other
    /// MCUs.
    pub fn relayed_at(&self) -> Option<f64> {
        self.relayed_at
    }

    /// The first trigger: host time (s) and reason.
    pub fn triggered(&self) -> Option<(f64, u8)> {
        self.dispatch.triggered()
    }

    /// Serves every link once at host time `now` (s), waiting up to
    /// `wait` s on each, and relays the trsync reports; what else they
    /// said goes to `heard` as `(mcu, what)`.
    pub fn service<L: SecondaryLink>(
        &mut self,
        mcus: &mut [&mut Secondary<L>],
        now: f64,
        wait: f64,
        heard: &mut dyn FnMut(usize, Heard<'_>),
    ) -> Result<(), HomingError> {
        self.service_inner(mcus, &mut |_| {}, now, wait, heard)
    }

    /// Serves the links; `stop_main(stops)` stops the main MCU's steppers.
    fn service_inner<L: SecondaryLink>(
        &mut self,
        mcus: &mut [&mut Secondary<L>],
        stop_main: &mut dyn FnMut(u32),
        now: f64,
        wait: f64,
        heard: &mut dyn FnMut(usize, Heard<'_>),
    ) -> Result<(), HomingError> {
        for i in 0..mcus.len() {
            // The reports of one round, relayed once it is over.
            let mut states = heapless::Vec::<TrsyncState, 16>::new();
            let mcu = &mut *mcus[i];
            let name = mcu.name;
            let served = mcu.service(&|| now, wait, &mut |h| {
                if let Heard::Response(msg) = &h
                    && let Some(state) = TrsyncState::from_message(msg)
                {
                    // Only the latest reports count if a round brings
                    // more than fit.
                    if states.is_full() {
                        states.remove(0);
                    }
                    let _ = states.push(state);
                } else {
                    heard(i, h);
                }
            });
            served.map_err(|e: LinkError| HomingError(text(format_args!("MCU '{name}': {e}"))))?;
            for state in states {
                self.on_state(mcus, i, state, now, stop_main)?;
            }
        }
        Ok(())
    }

    /// Takes `mcus[i]`'s trsync report `state`, heard at host time `now`
    /// (s).
    pub fn on_state<L: SecondaryLink>(
        &mut self,
        mcus: &mut [&mut Secondary<L>],
        i: usize,
        state: TrsyncState,
        now: f64,
        stop_main: &mut dyn FnMut(u32),
    ) -> Result<(), HomingError> {
        if !self.dispatch.is_current(i, state.clock) {
            return Ok(());
        }
        if let Some(stopped @ None) = self.stopped.get_mut(i)
            && !state.can_trigger
        {
            *stopped = Some(state.reason);
        }
        let relay = self
            .dispatch
            .on_state(i, state.can_trigger, state.reason, state.clock);
        if let (Relay::Triggered(..), Some(part)) = (&relay, self.main)
            && part.stopped.is_none()
        {
            // Another MCU triggered: the main's steppers stop now, before
            // the other secondaries hear of it.
            stop_main(part.stops);
            self.set_main_stopped(now, reason::HOST_REQUEST);
        }
        self.relay(mcus, relay, now)
    }

    /// Ends the homing at host time `now` (s): every secondary's trsync
    /// not triggered yet is (`HOST_REQUEST`), as klippy ends a homing
    /// move that ran to its end.
    pub fn finish<L: SecondaryLink>(
        &mut self,
        mcus: &mut [&mut Secondary<L>],
        now: f64,
    ) -> Result<(), HomingError> {
        if let Relay::Triggered(_, _, lines) = self.dispatch.end(now) {
            for (j, line) in lines {
                if let Some(mcu) = mcus.get_mut(j) {
                    send(mcu, &line)?;
                }
            }
        }
        Ok(())
    }
}

/// A `trsync_state oid=… can_trigger=… trigger_reason=… clock=…` report.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TrsyncState {
    can_trigger: bool,
    reason: u8,
    clock: u32,
}

impl TrsyncState {
    /// The report in a response, if it is one.
    pub(crate) fn from_message(msg: &Decoded<'_, '_, '_>) -> Option<Self> {
        if msg.message.name() != "trsync_state" {
            return None;
        }
        Some(Self {
            can_trigger: msg.int("can_trigger")? != 0,
            reason: u8::try_from(msg.int("trigger_reason")?).ok()?,
            clock: msg.int("clock")? as u32,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use onechip_protocol::dictionary::Dictionary;

    #[test]
    fn a_trsync_report_is_read_from_its_message() {
        let dict = Dictionary::parse(
            r#"{"commands": {}, "responses": {"trsync_state oid=%c can_trigger=%c trigger_reason=%c clock=%u": 5,
                "stepper_position oid=%c pos=%i": 6}}"#,
        )
        .expect("dictionary");
        let read = |line: &str| {
            let mut buf = [0u8; 32];
            let n = dict.encode_text(line, &mut buf).expect("encodes");
            let (msg, _) = dict.decode(&buf[..n]).expect("decodes");
            TrsyncState::from_message(&msg)
        };
        assert_eq!(
            read("trsync_state oid=2 can_trigger=0 trigger_reason=1 clock=4000"),
            Some(TrsyncState {
                can_trigger: false,
                reason: 1,
                clock: 4000
            })
        );
        assert_eq!(read("stepper_position oid=0 pos=3"), None);
    }
}
