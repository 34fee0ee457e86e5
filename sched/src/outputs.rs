//! Outputs the MCU role drives from its timer: GPIO pins, steady or with
//! software PWM, and hardware PWM channels, as Klipper's `digital_out` and
//! `pwm_out`. Each takes timed updates from a short queue and has Klipper's
//! safety timeout: an output away from its default value must be updated
//! again within `max_duration` ticks, or everything shuts down (a heater
//! must not stay on when the host role stops controlling it).

use crate::clock::{due, earliest, is_before};
use crate::shutdown::Shutdown;

/// Updates an output holds before [`Output::queue`] refuses more.
pub const QUEUE: usize = 8;

/// How an output makes its level.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OutputKind {
    /// A GPIO. With `cycle_ticks` 0 it is steady: value 0 is off, any other
    /// value on. Otherwise it is software PWM with that cycle: on for
    /// `value` ticks of each cycle (0: always off; `cycle_ticks` or more:
    /// always on).
    Digital {
        /// Software PWM cycle, ticks (0: steady on/off).
        cycle_ticks: u32,
    },
    /// A hardware PWM channel: the value is its duty, 0 to the channel's
    /// maximum; the hardware makes the waveform.
    HardPwm {
        /// The channel's period, ticks (Klipper's `cycle_ticks`).
        cycle_ticks: u32,
    },
}

/// An output's configuration (Klipper's `config_digital_out` with
/// `set_digital_out_pwm_cycle`, or `config_pwm_out`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OutputConfig {
    /// What drives the pin.
    pub kind: OutputKind,
    /// Value at start-up (on ticks, or duty).
    pub value: u32,
    /// Value at shutdown, and the safe value the timeout does not apply
    /// to.
    pub default: u32,
    /// Ticks a value other than the default lasts without an update
    /// (0: no limit).
    pub max_duration: u32,
}

/// What the hardware must do to an output.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Drive {
    /// Set the pin active (true) or inactive.
    Level(bool),
    /// Set the hardware PWM channel's duty.
    Duty(u32),
}

/// Why [`Output::queue`] refused an update.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum QueueError {
    /// The queue is full: try again after the first update took effect.
    Full,
    /// The update's clock has passed already (Klipper's "Timer too
    /// close"): everything must shut down.
    Late,
}

/// An output and its queued updates.
#[derive(Debug, Clone)]
pub struct Output {
    config: OutputConfig,
    value: u32,
    /// The pin's level (a digital output).
    level: bool,
    /// Software PWM: clock of the next level change.
    toggle_at: Option<u32>,
    /// Clock by which a new update must take effect (max_duration).
    expires: Option<u32>,
    /// Updates to come: clock, value; in clock order.
    queue: heapless::Deque<(u32, u32), QUEUE>,
}

impl Output {
    /// An output at its start-up value (no timeout runs until the first
    /// update).
    pub fn new(config: OutputConfig) -> Self {
        let mut output = Self {
            config,
            value: config.value,
            level: false,
            toggle_at: None,
            expires: None,
            queue: heapless::Deque::new(),
        };
        output.hold(config.value);
        output
    }

    /// What the hardware must show now.
    pub fn drive(&self) -> Drive {
        match self.config.kind {
            OutputKind::Digital { .. } => Drive::Level(self.level),
            OutputKind::HardPwm { .. } => Drive::Duty(self.value),
        }
    }

    /// The current value (on ticks, or duty).
    pub fn value(&self) -> u32 {
        self.value
    }

    /// Queues `value` to take effect at `clock`, given the time `now`.
    pub fn queue(&mut self, clock: u32, value: u32, now: u32) -> Result<(), QueueError> {
        let last = self.queue.back().map_or(now, |&(at, _)| at);
        if is_before(clock, now) || is_before(clock, last) {
            return Err(QueueError::Late);
        }
        self.queue
            .push_back((clock, value))
            .map_err(|_| QueueError::Full)
    }

    /// The clock of the output's next event (an update, a software PWM
    /// level change, the timeout), if any.
    pub fn next_event(&self) -> Option<u32> {
        let update = self.queue.front().map(|&(at, _)| at);
        earliest(earliest(update, self.toggle_at), self.expires)
    }

    /// Does every event due at clock `now`, in clock order (an update
    /// before a timeout at the same clock). Returns what the hardware must
    /// show if it changed; Err if the timeout expired.
    pub fn run(&mut self, now: u32) -> Result<Option<Drive>, Shutdown> {
        let before = self.drive();
        loop {
            let update = due(self.queue.front().map(|&(at, _)| at), now);
            let toggle = due(self.toggle_at, now);
            let expiry = due(self.expires, now);
            let first = earliest(earliest(update, toggle), expiry);
            match first {
                None => break,
                Some(at) if update == Some(at) => {
                    if let Some((_, value)) = self.queue.pop_front() {
                        self.apply(at, value);
                    }
                }
                Some(at) if expiry == Some(at) => return Err(self.expired()),
                Some(at) => self.toggle(at),
            }
        }
        let after = self.drive();
        Ok((after != before).then_some(after))
    }

    /// Back to the default value, steady, with nothing queued (shutdown);
    /// returns what the hardware must show.
    pub fn reset(&mut self) -> Drive {
        self.queue.clear();
        self.expires = None;
        self.hold(self.config.default);
        self.toggle_at = None;
        self.drive()
    }

    /// The fault of an output that outlived max_duration.
    fn expired(&self) -> Shutdown {
        match self.config.kind {
            OutputKind::Digital { .. } => Shutdown::DigitalOutExpired,
            OutputKind::HardPwm { .. } => Shutdown::PwmExpired,
        }
    }

    /// Holds `value` steady, without software PWM timing.
    fn hold(&mut self, value: u32) {
        self.value = value;
        self.level = value != 0;
    }

    /// An update of value `value` taking effect at clock `at`.
    fn apply(&mut self, at: u32, value: u32) {
        let config = self.config;
        self.expires = (config.max_duration > 0 && value != config.default)
            .then(|| at.wrapping_add(config.max_duration));
        self.hold(value);
        self.toggle_at = match config.kind {
            OutputKind::Digital { cycle_ticks } if value > 0 && value < cycle_ticks => {
                Some(at.wrapping_add(value))
            }
            _ => None,
        };
    }

    /// A software PWM level change due at clock `at`.
    fn toggle(&mut self, at: u32) {
        let OutputKind::Digital { cycle_ticks } = self.config.kind else {
            self.toggle_at = None;
            return;
        };
        self.level = !self.level;
        let hold = if self.level {
            self.value
        } else {
            cycle_ticks - self.value
        };
        self.toggle_at = Some(at.wrapping_add(hold));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn soft_pwm(cycle_ticks: u32, max_duration: u32) -> Output {
        Output::new(OutputConfig {
            kind: OutputKind::Digital { cycle_ticks },
            value: 0,
            default: 0,
            max_duration,
        })
    }

    /// Runs `output` at each of its events up to `end`, from `start`;
    /// returns the ticks it spent on.
    fn on_time(output: &mut Output, start: u32, end: u32) -> u32 {
        let (mut on, mut last) = (0, start);
        let mut level = matches!(output.drive(), Drive::Level(true));
        while let Some(at) = output.next_event().filter(|&at| is_before(at, end)) {
            if level {
                on += at.wrapping_sub(last);
            }
            last = at;
            if let Some(Drive::Level(l)) = output.run(at).expect("no timeout") {
                level = l;
            }
        }
        if level {
            on += end.wrapping_sub(last);
        }
        on
    }

    #[test]
    fn soft_pwm_spends_its_on_ticks_high_each_cycle_across_a_wrap() {
        let start = u32::MAX - 4321;
        let mut fan = soft_pwm(1000, 0);
        fan.queue(start, 250, start).expect("room");
        assert_eq!(on_time(&mut fan, start, start.wrapping_add(10_000)), 2500);
        // 0 and a full cycle hold a steady level: no events.
        let at = start.wrapping_add(10_000);
        fan.queue(at, 0, at).expect("room");
        fan.queue(at.wrapping_add(10), 1000, at).expect("room");
        assert_eq!(fan.run(at), Ok(None));
        assert_eq!(fan.drive(), Drive::Level(false));
        assert_eq!(fan.next_event(), Some(at.wrapping_add(10)));
        assert_eq!(fan.run(at.wrapping_add(10)), Ok(Some(Drive::Level(true))));
        assert_eq!(fan.next_event(), None);
    }

    #[test]
    fn an_output_away_from_its_default_past_max_duration_is_a_fault() {
        let mut heater = soft_pwm(100, 5000);
        heater.queue(1000, 40, 0).expect("room");
        heater.queue(5900, 60, 0).expect("room");
        // Refreshed at 5900, so good until 10900 (its last toggle before
        // then is at 10800).
        assert_eq!(on_time(&mut heater, 0, 10_899), 40 * 49 + 60 * 50);
        assert_eq!(heater.run(10_900), Err(Shutdown::DigitalOutExpired));
        // Turned off (the default) in time: no timeout.
        let mut heater = soft_pwm(100, 5000);
        heater.queue(1000, 40, 0).expect("room");
        heater.queue(5999, 0, 0).expect("room");
        assert_eq!(heater.run(1_000_000), Ok(None));
        assert_eq!(heater.drive(), Drive::Level(false));
        assert_eq!(heater.next_event(), None);
        // The same for a hardware channel, with its own message.
        let mut pwm = Output::new(OutputConfig {
            kind: OutputKind::HardPwm { cycle_ticks: 1000 },
            value: 0,
            default: 0,
            max_duration: 100,
        });
        pwm.queue(10, 200, 0).expect("room");
        assert_eq!(pwm.run(109), Ok(Some(Drive::Duty(200))));
        assert_eq!(pwm.run(110), Err(Shutdown::PwmExpired));
    }

    #[test]
    fn updates_queue_in_clock_order_with_back_pressure() {
        let mut out = soft_pwm(0, 0);
        assert_eq!(out.queue(5, 1, 10), Err(QueueError::Late));
        for k in 0..QUEUE as u32 {
            assert_eq!(out.queue(100 + k, k % 2, 10), Ok(()));
        }
        assert_eq!(out.queue(200, 1, 10), Err(QueueError::Full));
        assert_eq!(out.run(100), Ok(None));
        assert_eq!(out.queue(99, 1, 100), Err(QueueError::Late));
        assert_eq!(out.queue(200, 1, 100), Ok(()));
        assert_eq!(out.run(150), Ok(Some(Drive::Level(true))));
        assert_eq!(out.value(), 1);
        // Shutdown: default, nothing left to do.
        assert_eq!(out.reset(), Drive::Level(false));
        assert_eq!(out.next_event(), None);
    }
}
