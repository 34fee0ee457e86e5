//! Heater and `[temperature_sensor]` thermistors on a secondary MCU, read
//! as klippy's `MCU_adc` reads them. After the config phase each gets its
//! `query_analog_in` ([`crate::heaters::McuSetup`] at that MCU's
//! clock and ADC_MAX: 8 readings 1 ms apart every 0.3 s, the range from
//! min_temp/max_temp in its ADC counts — none by default for a
//! temperature sensor — and 4 reports out of range in a row shut that MCU
//! down). Each `analog_in_state` becomes readings (0..1 of full scale) at
//! the host time of their first sample, for the MCU role's heater control
//! and temperature fans ([`crate::heaters::Heaters::remote_reading`]).
//!
//! An SPI temperature chip there (MAX6675, MAX31855, MAX31856, MAX31865 on
//! a hardware bus) is read as klippy's `spi_temperature` reads it: its
//! start-up bytes (`spi_send`) and `query_thermocouple` after the config
//! phase, each `thermocouple_result` a reading of the chip's raw value.
//! One with its fault bits set is dropped, as klippy does (the MCU counts
//! it towards its own shutdown), and a MAX31865's fault, which latches,
//! is cleared by writing its configuration again, as klippy's
//! `handle_fault` does.
//!
//! A heater's sensor and output may be on different MCUs.

use super::{AnalogReport, CommandLine, command};
use crate::heaters::SAMPLE_COUNT;
use core::fmt::Write as _;
use onechip_protocol::codec::Decoded;
use onechip_protocol::dictionary::Dictionary;
use onechip_sched::adc::AdcQuery;
use onechip_sched::thermocouple::{SpiChip, SpiQuery};
use onechip_secondary_mcu::clock_sync::ClockSync;

/// Bytes of one report in a batched `analog_in_state` (one `u16` sum:
/// klippy asks heaters' sensors for one report per message).
const BYTES_PER_REPORT: u8 = 2;
/// How far ahead klippy starts the sampling of its ADC inputs, s (whole
/// seconds of print time at least this far ahead, `get_query_slot`).
const QUERY_LEAD: f64 = 1.5;
/// How far apart klippy starts the inputs' sampling, s per object id.
const QUERY_SLOT: f64 = 0.01;

/// One report of a sensor input on a secondary, for the MCU role's io.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reading {
    /// The io input (the heaters', then the temperature sensors').
    pub input: usize,
    /// Host time of the report's first sample, s.
    pub at: f64,
    /// An ADC input's sum of samples, 0..1 of full scale; an SPI chip's
    /// raw value.
    pub value: f64,
}

/// What an SPI chip's `thermocouple_result` says.
#[derive(Debug, Clone, PartialEq)]
pub enum SpiResult {
    /// A temperature reading.
    Reading(Reading),
    /// A fault: no reading, and the bytes that clear it (a MAX31865's
    /// configuration) on its bus object, if the chip needs them.
    Fault(Option<(u8, SpiBytes)>),
}

/// How an input on a secondary is read.
#[derive(Debug, Clone, Copy, PartialEq)]
enum InputKind {
    /// An ADC channel: a report's full scale (sample count × that MCU's
    /// ADC_MAX).
    Adc { full: f64 },
    /// An SPI chip on bus object `spi`. `clear`: the bytes written again
    /// after a fault (a MAX31865's configuration with its fault-clear
    /// bit), if the chip needs them.
    Spi { spi: u8, clear: Option<SpiBytes> },
}

/// Bytes an SPI chip is sent: up to four, `len` of them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SpiBytes {
    bytes: [u8; 4],
    len: u8,
}

impl SpiBytes {
    /// A query's start-up bytes.
    fn init(query: &SpiQuery) -> Self {
        Self {
            bytes: query.init,
            len: query.init_len,
        }
    }

    /// `spi_send` of these bytes on bus object `spi`, if there are any.
    pub fn send(self, spi: u8) -> Option<CommandLine> {
        let bytes = self.bytes.get(..usize::from(self.len)).unwrap_or(&[]);
        let mut line = command(format_args!("spi_send oid={spi} data="));
        let fits = bytes.iter().all(|b| write!(line, "{b:02x}").is_ok());
        (!bytes.is_empty() && fits).then_some(line)
    }
}

/// A heater's or temperature sensor's input on a secondary: an ADC
/// channel or an SPI chip.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RemoteInput {
    /// Its MCU (index into the attached secondaries).
    pub mcu: usize,
    /// Its oid there.
    pub oid: u8,
    /// Its input in the MCU role's io (the heaters', then the
    /// temperature sensors').
    pub index: usize,
    /// Ticks between two reports on that MCU.
    rest_ticks: u32,
    kind: InputKind,
}

impl RemoteInput {
    /// Input `index` of the io, `oid` on MCU `mcu`, sampled as `query`
    /// says by an ADC reading 0..=`adc_max`.
    pub fn new(mcu: usize, oid: u8, index: usize, query: &AdcQuery, adc_max: u16) -> Self {
        Self {
            mcu,
            oid,
            index,
            rest_ticks: query.rest_ticks,
            kind: InputKind::Adc {
                full: f64::from(query.sample_count) * f64::from(adc_max),
            },
        }
    }

    /// Input `index` of the io, the reader `oid` of an SPI chip on MCU
    /// `mcu` (its bus object `spi`), read as `query` says.
    pub fn spi(mcu: usize, (spi, oid): (u8, u8), index: usize, query: &SpiQuery) -> Self {
        let latches = query.chip == SpiChip::Max31865;
        Self {
            mcu,
            oid,
            index,
            rest_ticks: query.rest_ticks,
            kind: InputKind::Spi {
                spi,
                clear: latches.then(|| SpiBytes::init(query)),
            },
        }
    }

    /// What an SPI chip's `thermocouple_result` (`msg`) says, if it is
    /// one for this input: a reading at the host time of its read
    /// (klippy's `next_clock` less one report period), or a fault.
    pub fn spi_result(&self, msg: &Decoded<'_, '_, '_>, sync: &ClockSync) -> Option<SpiResult> {
        let InputKind::Spi { spi, clear } = self.kind else {
            return None;
        };
        let field = |name| msg.int(name);
        let is_this = msg.message.name() == "thermocouple_result"
            && field("oid") == Some(i64::from(self.oid));
        let (next_clock, value, fault) = (field("next_clock")?, field("value")?, field("fault")?);
        if !is_this {
            return None;
        }
        if fault != 0 {
            return Some(SpiResult::Fault(clear.map(|bytes| (spi, bytes))));
        }
        let next = sync.widen(next_clock as u32);
        Some(SpiResult::Reading(Reading {
            input: self.index,
            at: sync.time_at(next.saturating_sub(u64::from(self.rest_ticks))),
            value: value as f64,
        }))
    }

    /// The readings in `report` of this input (its MCU's clock line
    /// `sync`), each at its first sample's host time: klippy's
    /// `next_clock` less one report period per report still to come.
    pub fn readings<'r>(
        &self,
        report: &'r AnalogReport,
        sync: &'r ClockSync,
    ) -> impl Iterator<Item = Reading> + 'r {
        let next = sync.widen(report.next_clock);
        let full = match self.kind {
            InputKind::Adc { full } => full,
            InputKind::Spi { .. } => 1.0,
        };
        let (rest, count) = (u64::from(self.rest_ticks), report.values.len());
        let input = self.index;
        report.values.iter().enumerate().map(move |(i, &v)| {
            let periods = (count - i) as u64;
            let clock = next.saturating_sub(periods * rest);
            Reading {
                input,
                at: sync.time_at(clock),
                value: f64::from(v) / full.max(1.0),
            }
        })
    }
}

/// The `query_analog_in` for `query` (its clock ignored) as `dict`'s
/// firmware takes it (Klipper's newer form has `bytes_per_report`), the
/// first sampling at that MCU's clock `clock`.
pub fn query_command(dict: &Dictionary<'_>, oid: u8, query: &AdcQuery, clock: u64) -> CommandLine {
    let batched = dict
        .by_name("query_analog_in")
        .is_some_and(|m| m.params().any(|(name, _)| name == "bytes_per_report"));
    let mut line = command(format_args!(
        "query_analog_in oid={oid} clock={} sample_ticks={} sample_count={} rest_ticks={}",
        clock & 0xffff_ffff,
        query.sample_ticks,
        query.sample_count,
        query.rest_ticks,
    ));
    let per_report = batched.then_some(BYTES_PER_REPORT);
    let fits = per_report.is_none_or(|n| write!(line, " bytes_per_report={n}").is_ok())
        && write!(
            line,
            " min_value={} max_value={} range_check_count={}",
            query.min, query.max, query.range_check_count
        )
        .is_ok();
    if !fits {
        line.clear();
    }
    line
}

/// The commands that start reading an SPI chip (reader `oid`, its bus
/// object `spi`) as `query` says, the first read at that MCU's clock
/// `clock`: its start-up bytes if it has any (klippy's `spi_send`), then
/// `query_thermocouple`.
pub fn spi_query_commands(
    spi: u8,
    oid: u8,
    query: &SpiQuery,
    clock: u64,
) -> heapless::Vec<CommandLine, 2> {
    let send = SpiBytes::init(query).send(spi);
    let query = command(format_args!(
        "query_thermocouple oid={oid} clock={} rest_ticks={} min_value={} max_value={} max_invalid_count={}",
        clock & 0xffff_ffff,
        query.rest_ticks,
        query.min,
        query.max,
        query.max_invalid
    ));
    send.into_iter().chain([query]).collect()
}

/// Where klippy starts sampling input `oid` (`get_query_slot`): the whole
/// second at least 1.5 s after host time `now` (s), plus 10 ms per oid, on
/// the MCU's clock line `sync`.
pub fn query_slot(sync: &ClockSync, oid: u8, now: f64) -> u64 {
    let slot = (f64::from(oid) * QUERY_SLOT * sync.mcu_freq()) as u64;
    sync.clock_at(libm::floor(now + QUERY_LEAD)) + slot
}

/// The name `dict`'s MCU gives its SPI bus of value 0, which klippy puts
/// a chip without `spi_bus` on ("0" if its dictionary names no buses).
pub fn default_spi_bus(dict: &Dictionary<'_>) -> heapless::String<24> {
    let mut name = heapless::String::new();
    let buses = dict
        .enumeration_for("spi_bus")
        .or_else(|| dict.enumeration_for("bus"));
    match buses {
        Some(buses) if buses.write_name(0, &mut name).is_ok() => {}
        _ => {
            name.clear();
            let _ = name.push('0');
        }
    }
    name
}

/// The secondary's ADC full scale (`ADC_MAX` in its dictionary), if it
/// has one a report's sum fits in.
pub fn adc_max(dict: &Dictionary<'_>) -> Option<u16> {
    let max = dict.constant_int("ADC_MAX")?;
    let sum_fits = max.checked_mul(i64::from(SAMPLE_COUNT))? < 1 << 16;
    u16::try_from(max).ok().filter(|&m| m > 0 && sum_fits)
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::format;
    use std::vec::Vec;

    /// Klipper's newer firmware: batched reports.
    const BATCHED: &str = r#"{"commands": {
        "query_analog_in oid=%c clock=%u sample_ticks=%u sample_count=%c rest_ticks=%u bytes_per_report=%c min_value=%hu max_value=%hu range_check_count=%c": 10},
        "responses": {"analog_in_state oid=%c next_clock=%u values=%*s": 11,
            "clock clock=%u": 12},
        "config": {"ADC_MAX": 4095, "CLOCK_FREQ": 50000000}}"#;
    /// Its older firmware: one value a report.
    const SINGLE: &str = r#"{"commands": {
        "query_analog_in oid=%c clock=%u sample_ticks=%u sample_count=%c rest_ticks=%u min_value=%hu max_value=%hu range_check_count=%c": 10},
        "responses": {"analog_in_state oid=%c next_clock=%u value=%hu": 11},
        "config": {"ADC_MAX": 16383, "CLOCK_FREQ": 50000000}}"#;

    fn query() -> AdcQuery {
        AdcQuery {
            clock: 0,
            sample_ticks: 50_000,
            sample_count: 8,
            rest_ticks: 15_000_000,
            min: 1503,
            max: 32303,
            range_check_count: 4,
        }
    }

    /// `line` sent by an MCU of dictionary `dict`, as the host decodes it.
    fn heard(dict: &Dictionary<'_>, line: &str) -> Option<AnalogReport> {
        let mut buf = [0u8; 64];
        let n = dict.encode_text(line, &mut buf).expect("encodes");
        let (msg, _) = dict.decode(&buf[..n]).expect("decodes");
        AnalogReport::from_message(&msg)
    }

    #[test]
    fn the_query_has_bytes_per_report_only_for_firmware_that_takes_it() {
        let batched = Dictionary::parse(BATCHED).expect("dictionary");
        assert_eq!(
            query_command(&batched, 4, &query(), (1 << 32) + 70_024_765),
            "query_analog_in oid=4 clock=70024765 sample_ticks=50000 sample_count=8 \
             rest_ticks=15000000 bytes_per_report=2 min_value=1503 max_value=32303 \
             range_check_count=4"
        );
        let single = Dictionary::parse(SINGLE).expect("dictionary");
        let command = query_command(&single, 4, &query(), 5);
        assert!(!command.contains("bytes_per_report") && command.contains("clock=5 "));
    }

    #[test]
    fn reports_are_read_at_their_first_samples_host_time() {
        let dict = Dictionary::parse(BATCHED).expect("dictionary");
        // The MCU's clock read 1e9 at host time 10 s.
        let sync = ClockSync::new(50e6, 1_000_000_000, 10.0);
        let rest = 15_000_000;
        let next = 1_000_000_000 + 3 * rest;
        // Two reports in one message: sums 1000 and 2000, little-endian.
        let line = format!("analog_in_state oid=3 next_clock={next} values=e803d007");
        let report = heard(&dict, &line).expect("a report");
        assert_eq!(report.values, [1000, 2000]);
        let input = RemoteInput::new(0, 3, 1, &query(), 4095);
        let readings: Vec<Reading> = input.readings(&report, &sync).collect();
        let full = 8.0 * 4095.0;
        let expected = [(10.3, 1000.0 / full), (10.6, 2000.0 / full)];
        for (r, (at, value)) in readings.iter().zip(expected) {
            let close = (r.at - at).abs() < 1e-9 && (r.value - value).abs() < 1e-12;
            assert!(close && r.input == 1, "{r:?}");
        }
        assert_eq!(readings.len(), 2);
        let other = heard(&dict, "clock clock=5");
        assert!(other.is_none());
    }

    #[test]
    fn older_firmware_reports_one_value_and_an_adc_too_wide_is_refused() {
        let dict = Dictionary::parse(SINGLE).expect("dictionary");
        let line = "analog_in_state oid=2 next_clock=77 value=31000";
        let got = heard(&dict, line).expect("a report");
        assert_eq!(
            (got.oid, got.next_clock, &got.values[..]),
            (2, 77, &[31000][..])
        );
        // 8 readings of 16383 do not fit the report's 16 bits.
        assert_eq!(adc_max(&dict), None);
        let dict = Dictionary::parse(BATCHED).expect("dictionary");
        assert_eq!(adc_max(&dict), Some(4095));
    }
}
