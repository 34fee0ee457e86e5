//! Fans, output pins and stepper enable pins on a secondary, as klippy's
//! `MCU_digital_out` and `MCU_pwm` drive theirs.

use super::{CommandLine, command};

/// Output updates waiting for the one before them to take effect, per
/// output (a fan's kick and its speed, a heater's updates).
const PENDING_UPDATES: usize = 8;

/// A fan's, output pin's or enable pin's output on a secondary, driven as
/// klippy's `MCU_digital_out` and `MCU_pwm` drive theirs: one update at
/// a time on the MCU (each output has one slot of its move queue), the
/// next one sent once the MCU's clock has reached the one before.
#[derive(Debug, Clone)]
pub(super) struct RemoteOutput {
    /// Its MCU (index into `attached`).
    pub(super) mcu: usize,
    /// Its oid there.
    pub(super) oid: u8,
    /// Software PWM cycle on that MCU, ticks (0: steady on/off).
    pub(super) cycle_ticks: u32,
    /// Active low (`!`): klippy inverts the level on the host.
    pub(super) inverted: bool,
    /// The clock (that MCU's, 64-bit) of the last update sent.
    pub(super) last_clock: u64,
    /// Updates not sent yet: clock, level (0..1 of full scale). When full,
    /// the newest is replaced (only the latest level matters).
    pub(super) pending: heapless::Deque<(u64, f64), PENDING_UPDATES>,
    /// How late (s) the updates queued while the last one was still to
    /// come are sent, so that they keep their spacing (a fan's kick).
    pub(super) delay: f64,
    /// Host time of the last update queued (its delay included), s.
    pub(super) last_at: f64,
}

impl RemoteOutput {
    /// Output `oid` on MCU `mcu` (index into `attached`), software PWM of
    /// `cycle_ticks` (0: steady), active low if `inverted`; nothing sent
    /// yet.
    pub(super) fn new(mcu: usize, oid: u8, cycle_ticks: u32, inverted: bool) -> Self {
        Self {
            mcu,
            oid,
            cycle_ticks,
            inverted,
            last_clock: 0,
            pending: heapless::Deque::new(),
            delay: 0.0,
            last_at: 0.0,
        }
    }

    /// The update to `level` (0..1) at `clock` as the MCU takes it: on
    /// ticks of its cycle, or on/off.
    pub(super) fn update(&self, clock: u64, level: f64) -> CommandLine {
        let level = if self.inverted { 1.0 - level } else { level };
        let on_ticks = match self.cycle_ticks {
            0 => u32::from(level != 0.0),
            cycle => (level.clamp(0.0, 1.0) * f64::from(cycle) + 0.5) as u32,
        };
        command(format_args!(
            "queue_digital_out oid={} clock={} on_ticks={on_ticks}",
            self.oid,
            clock & 0xffff_ffff
        ))
    }

    /// Queues `level` at `clock`, never before an update queued earlier.
    pub(super) fn queue(&mut self, clock: u64, level: f64) {
        let after = self.pending.back().map_or(self.last_clock, |p| p.0);
        if self.pending.is_full() {
            self.pending.pop_back();
        }
        let _ = self.pending.push_back((clock.max(after), level));
    }
}

/// A stepper's enable pin on a secondary: shared by the steppers that
/// name the same pin, active while any of them is (klippy's enable
/// count).
#[derive(Debug, Clone)]
pub(super) struct RemoteEnable {
    pub(super) output: RemoteOutput,
    /// Steppers enabled on it.
    pub(super) count: usize,
}

/// An io output's `value` as a level, 0..1 of its `full` scale (0: a
/// steady output, off or on).
pub(super) fn level(value: u32, full: u32) -> f64 {
    match full {
        0 => f64::from(u8::from(value != 0)),
        full => f64::from(value) / f64::from(full),
    }
}
