//! Fans, output pins and stepper enable pins on a secondary, as klippy's
//! `MCU_digital_out` and `MCU_pwm` drive theirs.

use super::{CommandLine, command};
use onechip_protocol::dictionary::Dictionary;

/// Output updates waiting for the one before them to take effect, per
/// output (a fan's kick and its speed, a heater's updates).
const PENDING_UPDATES: usize = 8;

/// How an output on a secondary makes its level.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum RemoteDrive {
    /// On or off: `queue_digital_out` with on_ticks 0 or 1.
    Steady,
    /// Software PWM: `queue_digital_out`, on for on_ticks of each cycle.
    SoftPwm {
        /// The cycle, ticks of that MCU's clock.
        cycle_ticks: u32,
    },
    /// A hardware PWM channel: `queue_pwm_out`, its duty in 0..=pwm_max.
    HardPwm {
        /// The MCU's `PWM_MAX`.
        pwm_max: u32,
    },
}

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
    /// How it makes its level.
    pub(super) drive: RemoteDrive,
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
    /// Output `oid` on MCU `mcu` (index into `attached`), driven as
    /// `drive`, active low if `inverted`; nothing sent yet.
    pub(super) fn new(mcu: usize, oid: u8, drive: RemoteDrive, inverted: bool) -> Self {
        Self {
            mcu,
            oid,
            drive,
            inverted,
            last_clock: 0,
            pending: heapless::Deque::new(),
            delay: 0.0,
            last_at: 0.0,
        }
    }

    /// The update to `level` (0..1) at `clock` as the MCU takes it: on
    /// ticks of its cycle, on/off, or a hardware channel's duty (rounded,
    /// as klippy's `set_pwm`).
    pub(super) fn update(&self, clock: u64, level: f64) -> CommandLine {
        let level = if self.inverted { 1.0 - level } else { level };
        let scaled = |full: u32| (level.clamp(0.0, 1.0) * f64::from(full) + 0.5) as u32;
        let (oid, clock) = (self.oid, clock & 0xffff_ffff);
        let on_ticks = match self.drive {
            RemoteDrive::Steady => u32::from(level != 0.0),
            RemoteDrive::SoftPwm { cycle_ticks } => scaled(cycle_ticks),
            RemoteDrive::HardPwm { pwm_max } => {
                let value = scaled(pwm_max);
                return command(format_args!(
                    "queue_pwm_out oid={oid} clock={clock} value={value}"
                ));
            }
        };
        command(format_args!(
            "queue_digital_out oid={oid} clock={clock} on_ticks={on_ticks}"
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

/// The full scale of an MCU's hardware PWM channels: its dictionary's
/// `PWM_MAX`, if it has a usable one (1..=65535: `queue_pwm_out` takes a
/// 16-bit value).
pub(super) fn pwm_max(dict: &Dictionary<'_>) -> Option<u32> {
    let max = dict.constant_int("PWM_MAX")?;
    u32::try_from(max).ok().filter(|m| (1..=0xffff).contains(m))
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;

    #[test]
    fn a_hardware_channel_takes_its_duty_rounded_on_the_mcus_scale_inverted_on_the_host() {
        let fan = RemoteOutput::new(0, 3, RemoteDrive::HardPwm { pwm_max: 255 }, false);
        // klippy's set_pwm: int(value * PWM_MAX + 0.5).
        let update = fan.update(0x1_0000_0010, 128.0 / 255.0);
        assert_eq!(update.as_str(), "queue_pwm_out oid=3 clock=16 value=128");
        assert_eq!(
            fan.update(5, 0.3).as_str(),
            "queue_pwm_out oid=3 clock=5 value=77"
        );
        let tool = RemoteOutput::new(0, 4, RemoteDrive::HardPwm { pwm_max: 32768 }, true);
        assert_eq!(
            tool.update(9, 0.25).as_str(),
            "queue_pwm_out oid=4 clock=9 value=24576"
        );
        assert_eq!(
            tool.update(9, 1.5).as_str(),
            "queue_pwm_out oid=4 clock=9 value=0"
        );
        // Software PWM and a steady pin stay queue_digital_out.
        let soft = RemoteOutput::new(0, 5, RemoteDrive::SoftPwm { cycle_ticks: 1000 }, false);
        assert_eq!(
            soft.update(7, 0.5).as_str(),
            "queue_digital_out oid=5 clock=7 on_ticks=500"
        );
        let steady = RemoteOutput::new(0, 6, RemoteDrive::Steady, true);
        assert_eq!(
            steady.update(7, 1.0).as_str(),
            "queue_digital_out oid=6 clock=7 on_ticks=0"
        );
    }

    #[test]
    fn pwm_max_is_the_dictionarys_when_a_16_bit_value_can_carry_it() {
        let with = |max: &str| {
            let text = std::format!(r#"{{"commands": {{}}, "config": {{"PWM_MAX": {max}}}}}"#);
            let dict = Dictionary::parse(&text).map(|d| pwm_max(&d));
            dict.expect("dictionary")
        };
        assert_eq!(with("255"), Some(255));
        assert_eq!(with("32768"), Some(32768));
        assert_eq!(with("0"), None);
        assert_eq!(with("65536"), None);
        assert_eq!(with("\"x\""), None);
    }
}
