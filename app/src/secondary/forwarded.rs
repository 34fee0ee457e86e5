//! The MCU role's outputs that are on secondary MCUs, as a firmware's
//! heater io holds them: the io runs such an output as its own (the
//! heaters' control and max_duration refresh, in the heaters' interrupt)
//! with no pin behind it, and each update it queues for one is kept here
//! until thread code takes it ([`crate::session::Mcu::take_queued_output`])
//! and [`super::mcu::WithSecondaries`] sends it on, on that MCU's clock.
//! The simulator's plant keeps every output's updates instead (it has
//! room); the queue here is bounded.

use crate::heaters::{McuSetup, OUTPUTS};
use crate::mcu_config::on_main;

/// Updates kept until thread code takes them: it takes them within a
/// millisecond or so, and the io queues one per heater every 0.3 s (a
/// fan's or pin's on a command), so this holds several seconds' worth.
pub const QUEUED: usize = 32;

/// Which outputs are on secondaries, and their updates not taken yet.
#[derive(Debug, Clone)]
pub struct ForwardedOutputs {
    /// Output `i` (the io's numbering: heaters, the fan, the other fans
    /// and pins) is on a secondary.
    elsewhere: [bool; OUTPUTS],
    /// (output, clock, value) as the io queued them (clock: this MCU's,
    /// 32-bit), oldest first. When it is full an update a later one
    /// supersedes goes, so that a one-time change (a fan set once) is
    /// kept.
    queued: heapless::Deque<(usize, u32, u32), QUEUED>,
}

impl ForwardedOutputs {
    /// The outputs of `setup` (the io's configuration) whose pins are on
    /// a secondary (`NAME:PIN`).
    pub fn new(setup: &McuSetup<'_>) -> Self {
        let mut elsewhere = [false; OUTPUTS];
        for (flag, (pin, _)) in elsewhere.iter_mut().zip(&setup.outputs) {
            *flag = !on_main(pin);
        }
        Self {
            elsewhere,
            queued: heapless::Deque::new(),
        }
    }

    /// True if output `index` is on a secondary (it has no pin here).
    pub fn is_elsewhere(&self, index: usize) -> bool {
        self.elsewhere.get(index).copied().unwrap_or(false)
    }

    /// The io queued `value` for output `index` from clock `clock` on
    /// (`Peripherals::queued`): kept if that output is on a secondary.
    pub fn queued(&mut self, index: usize, clock: u32, value: u32) {
        if !self.is_elsewhere(index) {
            return;
        }
        if self.queued.is_full() {
            self.drop_one();
        }
        let _ = self.queued.push_back((index, clock, value));
    }

    /// Makes room in a full queue: the oldest update that a later one of
    /// the same output supersedes goes (a heater's refresh, say), else
    /// the oldest.
    fn drop_one(&mut self) {
        let superseded = (self.queued.iter().enumerate()).find_map(|(i, &(output, ..))| {
            let later = self.queued.iter().skip(i + 1);
            later.into_iter().any(|&(o, ..)| o == output).then_some(i)
        });
        let Some(gone) = superseded else {
            self.queued.pop_front();
            return;
        };
        let mut kept = heapless::Deque::new();
        for (i, &update) in self.queued.iter().enumerate() {
            if i != gone {
                let _ = kept.push_back(update);
            }
        }
        self.queued = kept;
    }

    /// The oldest update not taken yet: (output, clock, value).
    pub fn take(&mut self) -> Option<(usize, u32, u32)> {
        self.queued.pop_front()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use onechip_planner::machine::Machine;

    /// The heaters' test printer with its part fan, a bed heater and its
    /// thermistor on `ext` and a named fan on this MCU.
    const ON_EXT: &str = "[mcu ext]\nserial: /dev/null\n\
        [heater_bed]\nheater_pin: ext:PA1\nsensor_type: EPCOS 100K B57560G104F\n\
        sensor_pin: ext:analog0\ncontrol: watermark\nmin_temp: 0\nmax_temp: 130\n\
        [fan]\npin: ext:PA2\n[fan_generic exhaust]\npin: PA9\n";

    fn with_machine(f: impl FnOnce(&Machine<'_>)) {
        extern crate std;
        let text = std::format!("{}{ON_EXT}", crate::heaters::tests::FAN_ONLY);
        let config = onechip_config::Config::parse("printer.cfg", &text).expect("config");
        let machine = Machine::from_config(&config).expect("machine");
        f(&machine);
    }

    #[test]
    fn only_updates_of_outputs_elsewhere_are_kept_in_order_and_a_full_queue_drops_a_superseded_one()
    {
        with_machine(|machine| {
            let mcu_sensor = crate::heaters::tests::typical_mcu();
            let setup = McuSetup::new(machine, 1e6, 4095, mcu_sensor, 0);
            let mut forwarded = ForwardedOutputs::new(&setup);
            assert!(forwarded.is_elsewhere(0) && forwarded.is_elsewhere(1));
            assert!(!forwarded.is_elsewhere(2));
            forwarded.queued(2, 5, 1);
            assert_eq!(forwarded.take(), None);
            // The fan set once, then the bed heater's refreshes: when the
            // queue is full, the heater's oldest go, the fan's stays.
            forwarded.queued(1, 1, 255);
            for k in 0..QUEUED as u32 + 3 {
                forwarded.queued(0, k, k);
            }
            assert_eq!(forwarded.take(), Some((1, 1, 255)));
            assert_eq!(forwarded.take(), Some((0, 4, 4)));
            // Both outputs in turn: the oldest superseded goes.
            let mut turns = ForwardedOutputs::new(&setup);
            for k in 0..QUEUED as u32 + 1 {
                turns.queued(usize::from(k % 2 == 1), k, k);
            }
            assert_eq!(turns.take(), Some((1, 1, 1)));
        });
    }
}
