//! SPI temperature chips read from the MCU role's timer, as Klipper's
//! `thermocouple.c`: once every `rest_ticks` the chip's value (and, for
//! the MAX31856 and MAX31865, its fault register) is read over SPI and
//! reported; a value outside `[min, max]`, or a fault (a fault register
//! not 0, the MAX31855's fault bit 16, the MAX6675's open-input bit 2),
//! more than `max_invalid` reads in a row shuts everything down.
//!
//! The transfers go through a closure that runs one chip-select-framed,
//! full-duplex transfer (the bytes sent are replaced by those received).

use crate::shutdown::Shutdown;

/// The chip, which decides what is read and how.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SpiChip {
    /// 16-bit word; bit 2 set: no thermocouple.
    Max6675,
    /// 32-bit word; bit 16 set: a fault.
    Max31855,
    /// Linearized temperature registers 0x0C..0x0E, fault status 0x0F.
    Max31856,
    /// RTD registers 0x01..0x02, fault status 0x07.
    Max31865,
}

/// Klipper's `query_thermocouple` with the chip and its start-up bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SpiQuery {
    /// The chip.
    pub chip: SpiChip,
    /// Clock of the first read, ticks.
    pub clock: u32,
    /// Ticks between reads.
    pub rest_ticks: u32,
    /// Lowest good value (raw).
    pub min: u32,
    /// Highest good value (raw).
    pub max: u32,
    /// Bad reads in a row that are tolerated (Klipper's 3: the fourth
    /// shuts down).
    pub max_invalid: u8,
    /// Configuration written when the query starts (and, for the
    /// MAX31865, again after a fault, which clears it), `init_len` bytes.
    pub init: [u8; 4],
    /// How many of `init` to write.
    pub init_len: u8,
}

/// One read: the chip's value and fault register.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SpiReport {
    /// Clock of the read, ticks.
    pub clock: u32,
    /// The raw value.
    pub value: u32,
    /// The fault register (MAX31856, MAX31865; 0 for the others).
    pub fault: u8,
}

/// An SPI temperature input and its state.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Thermocouple {
    query: Option<SpiQuery>,
    next: u32,
    invalid: u8,
    report: Option<SpiReport>,
}

impl Thermocouple {
    /// Starts reading as `query` says; its configuration bytes are
    /// written through `transfer` first.
    pub fn query(&mut self, query: SpiQuery, transfer: &mut impl FnMut(&mut [u8])) {
        *self = Self {
            query: Some(query),
            next: query.clock,
            ..Self::default()
        };
        Self::write_init(&query, transfer);
    }

    fn write_init(query: &SpiQuery, transfer: &mut impl FnMut(&mut [u8])) {
        let mut init = query.init;
        let len = usize::from(query.init_len).min(init.len());
        if len > 0 {
            transfer(&mut init[..len]);
        }
    }

    /// Stops reading (shutdown).
    pub fn stop(&mut self) {
        self.query = None;
    }

    /// Clock of the next read, while reading.
    pub fn next_event(&self) -> Option<u32> {
        self.query.map(|_| self.next)
    }

    /// The newest report not yet taken.
    pub fn take_report(&mut self) -> Option<SpiReport> {
        self.report.take()
    }

    /// The read due at [`Self::next_event`], through `transfer`; Err when
    /// the range or fault check fails.
    pub fn read(&mut self, transfer: &mut impl FnMut(&mut [u8])) -> Result<(), Shutdown> {
        let Some(q) = self.query else {
            return Ok(());
        };
        let (value, fault) = match q.chip {
            SpiChip::Max6675 => {
                let mut msg = [0u8; 2];
                transfer(&mut msg);
                (u32::from(u16::from_be_bytes(msg)), 0)
            }
            SpiChip::Max31855 => {
                let mut msg = [0u8; 4];
                transfer(&mut msg);
                (u32::from_be_bytes(msg), 0)
            }
            SpiChip::Max31856 => {
                let mut msg = [0x0C, 0, 0, 0];
                transfer(&mut msg);
                let value = u32::from_be_bytes(msg) & 0x00FF_FFFF;
                let mut status = [0x0F, 0];
                transfer(&mut status);
                (value, status[1])
            }
            SpiChip::Max31865 => {
                let mut msg = [0x01, 0, 0];
                transfer(&mut msg);
                let value = u32::from(u16::from_be_bytes([msg[1], msg[2]]));
                let mut status = [0x07, 0];
                transfer(&mut status);
                if status[1] != 0 {
                    // Klipper's host writes the configuration again to
                    // clear the fault.
                    Self::write_init(&q, transfer);
                }
                (value, status[1])
            }
        };
        self.report = Some(SpiReport {
            clock: self.next,
            value,
            fault,
        });
        self.next = self.next.wrapping_add(q.rest_ticks);
        let faulted = fault != 0
            || (q.chip == SpiChip::Max31855 && value & 0x1_0000 != 0)
            || (q.chip == SpiChip::Max6675 && value & 0x04 != 0);
        let reason = if !(q.min..=q.max).contains(&value) {
            Shutdown::ThermocoupleOutOfRange
        } else if faulted {
            Shutdown::ThermocoupleFault
        } else {
            self.invalid = 0;
            return Ok(());
        };
        self.invalid = self.invalid.saturating_add(1);
        if self.invalid > q.max_invalid {
            return Err(reason);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec::Vec;

    fn query(chip: SpiChip, init: &[u8]) -> SpiQuery {
        let mut bytes = [0; 4];
        bytes[..init.len()].copy_from_slice(init);
        SpiQuery {
            chip,
            clock: u32::MAX - 5,
            rest_ticks: 300,
            min: 0,
            max: 0x0C80 << 18,
            max_invalid: 3,
            init: bytes,
            init_len: init.len() as u8,
        }
    }

    /// A chip that answers with `reply` for each register read, recording
    /// what was sent.
    struct Chip {
        sent: Vec<Vec<u8>>,
        reply: fn(u8) -> [u8; 4],
    }

    impl Chip {
        fn transfer(&mut self, data: &mut [u8]) {
            self.sent.push(data.to_vec());
            let reply = (self.reply)(data[0]);
            // Register 0 is never read: a word chip (MAX6675, MAX31855)
            // answers from the first byte.
            let skip = usize::from(data[0] != 0);
            for (i, byte) in data.iter_mut().enumerate().skip(skip) {
                *byte = reply[i];
            }
        }
    }

    #[test]
    fn a_max31855_is_read_once_every_rest_ticks_and_reported() {
        let mut chip = Chip {
            sent: Vec::new(),
            reply: |_| (0x0190u32 << 18).to_be_bytes(),
        };
        let mut tc = Thermocouple::default();
        let mut t = |d: &mut [u8]| chip.transfer(d);
        tc.query(query(SpiChip::Max31855, &[]), &mut t);
        assert_eq!(tc.next_event(), Some(u32::MAX - 5));
        tc.read(&mut t).expect("good");
        assert_eq!(tc.next_event(), Some(294));
        assert_eq!(
            tc.take_report(),
            Some(SpiReport {
                clock: u32::MAX - 5,
                value: 0x0190 << 18,
                fault: 0
            })
        );
        assert_eq!(tc.take_report(), None);
        assert_eq!(chip.sent, [std::vec![0u8; 4]]);
    }

    #[test]
    fn four_bad_reads_in_a_row_shut_down_with_klippers_messages() {
        // MAX31855 with its fault bit (16) and open-circuit bit set.
        let mut chip = Chip {
            sent: Vec::new(),
            reply: |_| ((0x0190u32 << 18) | 0x1_0001).to_be_bytes(),
        };
        let mut tc = Thermocouple::default();
        let mut t = |d: &mut [u8]| chip.transfer(d);
        tc.query(query(SpiChip::Max31855, &[]), &mut t);
        for _ in 0..3 {
            assert_eq!(tc.read(&mut t), Ok(()));
        }
        assert_eq!(tc.read(&mut t), Err(Shutdown::ThermocoupleFault));
        assert_eq!(
            Shutdown::ThermocoupleFault.message(),
            "Thermocouple reader fault"
        );
        // Out of range (above max): the same count, the other message; a
        // good read in between starts the count again.
        let mut chip = Chip {
            sent: Vec::new(),
            reply: |_| (0x0D00u32 << 18).to_be_bytes(),
        };
        let mut t = |d: &mut [u8]| chip.transfer(d);
        tc.query(query(SpiChip::Max31855, &[]), &mut t);
        for _ in 0..3 {
            assert_eq!(tc.read(&mut t), Ok(()));
        }
        assert_eq!(tc.read(&mut t), Err(Shutdown::ThermocoupleOutOfRange));
        assert_eq!(
            Shutdown::ThermocoupleOutOfRange.message(),
            "Thermocouple ADC out of range"
        );
    }

    #[test]
    fn register_chips_are_configured_then_read_value_and_fault_status() {
        // MAX31856: 200 °C (0x0C8000) in 0x0C..0x0E, no fault.
        let mut chip = Chip {
            sent: Vec::new(),
            reply: |reg| match reg {
                0x0C => [0, 0x0C, 0x80, 0x00],
                _ => [0; 4],
            },
        };
        let mut tc = Thermocouple::default();
        let mut t = |d: &mut [u8]| chip.transfer(d);
        let q = SpiQuery {
            max: 0x10_0000,
            ..query(SpiChip::Max31856, &[0x80, 0x80, 0x03, 0x03])
        };
        tc.query(q, &mut t);
        tc.read(&mut t).expect("good");
        assert_eq!(tc.take_report().map(|r| r.value), Some(0x0C_8000));
        assert_eq!(
            chip.sent,
            [
                std::vec![0x80, 0x80, 0x03, 0x03],
                std::vec![0x0C, 0, 0, 0],
                std::vec![0x0F, 0]
            ]
        );
        // MAX31865 with a fault: reported, and the configuration written
        // again (which clears it).
        let mut chip = Chip {
            sent: Vec::new(),
            reply: |reg| match reg {
                0x01 => [0, 0x3B, 0x88, 0],
                0x07 => [0, 0x80, 0, 0],
                _ => [0; 4],
            },
        };
        let mut t = |d: &mut [u8]| chip.transfer(d);
        let q = SpiQuery {
            max: 0x1_0000,
            ..query(SpiChip::Max31865, &[0x80, 0xC2])
        };
        tc.query(q, &mut t);
        assert_eq!(tc.read(&mut t), Ok(()));
        assert_eq!(
            tc.take_report().map(|r| (r.value, r.fault)),
            Some((0x3B88, 0x80))
        );
        assert_eq!(chip.sent.len(), 4);
        assert_eq!(chip.sent[3], [0x80, 0xC2]);
    }

    #[test]
    fn a_max6675_without_a_thermocouple_is_a_fault() {
        let mut chip = Chip {
            sent: Vec::new(),
            reply: |_| [0x0C, 0x84, 0, 0],
        };
        let mut tc = Thermocouple::default();
        let mut t = |d: &mut [u8]| chip.transfer(d);
        let q = SpiQuery {
            max: 0x1FFF << 3,
            ..query(SpiChip::Max6675, &[])
        };
        tc.query(q, &mut t);
        for _ in 0..3 {
            assert_eq!(tc.read(&mut t), Ok(()));
        }
        assert_eq!(tc.take_report().map(|r| r.value), Some(0x0C84));
        assert_eq!(tc.read(&mut t), Err(Shutdown::ThermocoupleFault));
        tc.stop();
        assert_eq!(tc.next_event(), None);
    }
}
