//! Klipper's SPI temperature sensors (`spi_temperature`): the MAX6675,
//! MAX31855 and MAX31856 thermocouple converters and the MAX31865 RTD
//! converter, with Klipper's options and defaults.
//!
//! The MCU reads each chip's raw register value every 0.3 s and checks it
//! (see `onechip_sched::thermocouple`); here is what the host side knows:
//! the raw value to °C and back exactly as Klipper computes them (so the
//! MCU's range check from min_temp/max_temp is Klipper's), the SPI mode,
//! the configuration register bytes written once at start (MAX31856,
//! MAX31865), and the bus (`spi_bus`, or a software bus on
//! `spi_software_sclk_pin`/`…_mosi_pin`/`…_miso_pin`, at `spi_speed`).

use crate::reader::{Read, Reader};
use onechip_config::Bounds;

/// The converter chip, as `sensor_type` names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Chip {
    /// MAX6675: K thermocouple, 16-bit word, 0.25 °C steps.
    Max6675,
    /// MAX31855: thermocouple, 32-bit word, 0.25 °C steps.
    Max31855,
    /// MAX31856: thermocouple of any type, 24-bit register, 1/128 °C.
    Max31856,
    /// MAX31865: platinum RTD (PT100/PT1000) through a reference resistor.
    Max31865,
}

/// `sensor_type` names of the chips, in [`Chip`] order.
pub const NAMES: [&str; 4] = ["MAX6675", "MAX31855", "MAX31856", "MAX31865"];

impl Chip {
    /// The chip `sensor_type` names, if it names one.
    pub fn from_name(name: &str) -> Option<Self> {
        match crate::temperature_sensor::position(&NAMES, name)? {
            0 => Some(Self::Max6675),
            1 => Some(Self::Max31855),
            2 => Some(Self::Max31856),
            _ => Some(Self::Max31865),
        }
    }

    /// Its `sensor_type` name.
    pub fn name(self) -> &'static str {
        NAMES[self as usize]
    }

    /// The SPI mode (clock polarity and phase) Klipper uses for it.
    pub fn spi_mode(self) -> u8 {
        match self {
            Self::Max6675 | Self::Max31855 => 0,
            Self::Max31856 | Self::Max31865 => 1,
        }
    }
}

/// Callendar–Van Dusen coefficients of platinum (above 0 °C), as Klipper
/// uses them for the MAX31865.
const CVD_A: f64 = 3.9083e-3;
const CVD_B: f64 = -5.775e-7;
/// The MAX31865's 15-bit ratio's full scale.
const MAX31865_FULL: f64 = 32768.0;
/// Platinum's melting point, °C: the MAX31865's conversion back stops
/// there.
const PLATINUM_MELTS: f64 = 1768.3;

/// A chip and its conversion settings: the raw register value (as the
/// MCU reads it) to °C and back.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpiSensor {
    /// The chip.
    pub chip: Chip,
    /// MAX31865: Ω per count over the nominal resistance
    /// (`rtd_reference_r / 32768 / rtd_nominal_r`); else 0.
    rtd_ratio: f64,
    /// The configuration bytes written at start (register address with
    /// the write bit, then values), `init_len` of them.
    init: [u8; 4],
    init_len: u8,
}

/// `(shift, sign bit, mask, °C per count)` of a thermocouple word.
fn word_format(chip: Chip) -> (u32, u32, u32, f64) {
    match chip {
        Chip::Max6675 => (3, 0x2000, 0x1FFF, 0.25),
        Chip::Max31855 => (18, 0x2000, 0x1FFF, 0.25),
        _ => (5, 0x4_0000, 0x3_FFFF, 0.007_812_5),
    }
}

/// Python's `int(x)` (toward zero) clamped to `0..=max`.
fn int_clamped(x: f64, max: u32) -> u32 {
    let truncated = x as i64;
    truncated.clamp(0, i64::from(max)) as u32
}

impl SpiSensor {
    /// `chip` with Klipper's defaults (K type, no 50 Hz filter, no
    /// averaging; a 2-wire PT100 on a 430 Ω reference).
    pub fn new(chip: Chip) -> Self {
        let mut sensor = Self {
            chip,
            rtd_ratio: 0.0,
            init: [0; 4],
            init_len: 0,
        };
        match chip {
            Chip::Max31856 => sensor.set_init(&[0x80, CR0_AUTOCONVERT, TC_TYPE_K, MASK_DEFAULT]),
            Chip::Max31865 => {
                sensor.rtd_ratio = 430.0 / MAX31865_FULL / 100.0;
                sensor.set_init(&[0x80, RTD_CONFIG_DEFAULT]);
            }
            _ => {}
        }
        sensor
    }

    fn set_init(&mut self, bytes: &[u8]) {
        let n = bytes.len().min(self.init.len());
        self.init[..n].copy_from_slice(&bytes[..n]);
        self.init_len = n as u8;
    }

    /// The bytes written to the chip once at start (empty for the
    /// MAX6675 and MAX31855).
    pub fn init_bytes(&self) -> &[u8] {
        &self.init[..usize::from(self.init_len)]
    }

    /// °C at raw register value `raw`, as Klipper's `calc_temp`.
    ///
    /// For the thermocouple chips the sign is fixed as Klipper does it
    /// (`-((value & mask) + 1)` when the sign bit is set), which is not
    /// two's complement: Klipper's readings below 0 °C are kept as they
    /// are.
    pub fn temperature(&self, raw: u32) -> f64 {
        if self.chip == Chip::Max31865 {
            let counts = f64::from(raw >> 1);
            let r = counts * self.rtd_ratio;
            let discriminant = crate::math::sqrt(CVD_A * CVD_A - 4.0 * CVD_B * (1.0 - r));
            return (-CVD_A + discriminant) / (2.0 * CVD_B);
        }
        let (shift, sign, mask, step) = word_format(self.chip);
        let counts = raw >> shift;
        let signed = if counts & sign != 0 {
            -(i64::from(counts & mask) + 1)
        } else {
            i64::from(counts)
        };
        step * signed as f64
    }

    /// The raw register value at `celsius`, as Klipper's `calc_adc`
    /// (rounded half up toward zero as Python's `int(x + 0.5)`, then
    /// limited to the chip's positive range).
    pub fn raw(&self, celsius: f64) -> u32 {
        if self.chip == Chip::Max31865 {
            let t = celsius.min(PLATINUM_MELTS);
            let r = 1.0 + CVD_A * t + CVD_B * t * t;
            return int_clamped(r / self.rtd_ratio + 0.5, MAX31865_FULL as u32) << 1;
        }
        let (shift, _, mask, step) = word_format(self.chip);
        int_clamped(celsius / step + 0.5, mask) << shift
    }

    /// The raw values of `min_temp` and `max_temp`, lowest first: the
    /// MCU's accepted range (Klipper's `setup_minmax`).
    pub fn raw_range(&self, min_temp: f64, max_temp: f64) -> (u32, u32) {
        let (a, b) = (self.raw(min_temp), self.raw(max_temp));
        (a.min(b), a.max(b))
    }

    /// A simulated chip's answer to the transfer `data` (bytes sent,
    /// replaced by those received) at `celsius` with fault bits `fault`
    /// (in the word of a MAX6675 or MAX31855, in the fault status
    /// register of a MAX31856 or MAX31865), for the reads Klipper's MCU
    /// code makes; false for a register write (address bit 7 set), which
    /// is not answered.
    pub fn simulate_reply(&self, celsius: f64, fault: u32, data: &mut [u8]) -> bool {
        let raw = self.raw(celsius);
        let register = data.first().copied().unwrap_or(0);
        let (reply, from): ([u8; 4], usize) = match self.chip {
            Chip::Max6675 => {
                let word = ((raw | fault) as u16).to_be_bytes();
                ([word[0], word[1], 0, 0], 0)
            }
            Chip::Max31855 => ((raw | fault).to_be_bytes(), 0),
            _ if register & 0x80 != 0 => return false,
            Chip::Max31856 => match register {
                0x0C => ((raw & 0x00FF_FFFF).to_be_bytes(), 1),
                0x0F => ([0, fault as u8, 0, 0], 1),
                _ => ([0; 4], 1),
            },
            Chip::Max31865 => match register {
                0x01 => {
                    let value = (raw as u16).to_be_bytes();
                    ([0, value[0], value[1], 0], 1)
                }
                0x07 => ([0, fault as u8, 0, 0], 1),
                _ => ([0; 4], 1),
            },
        };
        // The word chips answer from the first byte; the register chips
        // after the address byte.
        for (i, byte) in data.iter_mut().enumerate().skip(from) {
            *byte = reply.get(i).copied().unwrap_or(0);
        }
        true
    }

    /// What Klipper's host logs for fault bits `fault` of a report
    /// (`handle_fault`), one message per bit set.
    pub fn fault_messages(&self, fault: u8) -> impl Iterator<Item = &'static str> {
        let table: &'static [(u8, &'static str)] = match self.chip {
            Chip::Max6675 => &[
                (0x02, "Max6675 : Device ID error"),
                (0x04, "Max6675 : Thermocouple Open Fault"),
            ],
            Chip::Max31855 => &[
                (0x01, "MAX31855 : Open Circuit"),
                (0x02, "MAX31855 : Short to GND"),
                (0x04, "MAX31855 : Short to Vcc"),
            ],
            Chip::Max31856 => &[
                (0x80, "Max31856: Cold Junction Range Fault"),
                (0x40, "Max31856: Thermocouple Range Fault"),
                (0x20, "Max31856: Cold Junction High Fault"),
                (0x10, "Max31856: Cold Junction Low Fault"),
                (0x08, "Max31856: Thermocouple High Fault"),
                (0x04, "Max31856: Thermocouple Low Fault"),
                (0x02, "Max31856: Over/Under Voltage Fault"),
                (0x01, "Max31856: Thermocouple Open Fault"),
            ],
            Chip::Max31865 => &[
                (0x80, "Max31865 RTD input is disconnected"),
                (0x40, "Max31865 RTD input is shorted"),
                (
                    0x20,
                    "Max31865 VREF- is greater than 0.85 * VBIAS, FORCE- open",
                ),
                (
                    0x10,
                    "Max31865 VREF- is less than 0.85 * VBIAS, FORCE- open",
                ),
                (
                    0x08,
                    "Max31865 VRTD- is less than 0.85 * VBIAS, FORCE- open",
                ),
                (0x04, "Max31865 Overvoltage or undervoltage fault"),
            ],
        };
        table
            .iter()
            .filter(move |(bit, _)| fault & bit != 0)
            .map(|(_, m)| *m)
    }
}

/// MAX31856 CR0: automatic conversions.
const CR0_AUTOCONVERT: u8 = 0x80;
/// MAX31856 CR0: 50 Hz mains filter (else 60 Hz).
const CR0_FILTER_50HZ: u8 = 0x01;
/// MAX31856 CR1's type bits for a K thermocouple.
const TC_TYPE_K: u8 = 0b0011;
/// MAX31856 fault mask: over/under voltage and open thermocouple masked.
const MASK_DEFAULT: u8 = 0x02 | 0x01;
/// MAX31865 configuration: bias on, automatic conversions, fault clear.
const RTD_CONFIG_DEFAULT: u8 = 0x80 | 0x40 | 0x02;
/// MAX31865 configuration: 3-wire RTD.
const RTD_3WIRE: u8 = 0x10;
/// MAX31865 configuration: 50 Hz filter.
const RTD_FILTER_50HZ: u8 = 0x01;

/// Thermocouple types the MAX31856 converts, in CR1's type code order.
const TC_TYPES: [&str; 8] = ["B", "E", "J", "K", "N", "R", "S", "T"];
/// MAX31856 averaging counts and their CR1 bits.
const AVERAGES: [(&str, u8); 5] = [
    ("1", 0x00),
    ("2", 0x10),
    ("4", 0x20),
    ("8", 0x30),
    ("16", 0x70),
];

/// How the MCU reaches the chip.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SpiBusPins<'a> {
    /// A hardware bus: `spi_bus` as written (None: the MCU's default).
    Hardware(Option<&'a str>),
    /// A bit-banged bus on GPIOs.
    Software {
        /// `spi_software_sclk_pin`.
        sclk: &'a str,
        /// `spi_software_mosi_pin`.
        mosi: &'a str,
        /// `spi_software_miso_pin`.
        miso: &'a str,
    },
}

/// A chip's SPI connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SpiBus<'a> {
    /// `sensor_pin`: the chip select, as written.
    pub cs_pin: &'a str,
    /// The bus.
    pub pins: SpiBusPins<'a>,
    /// `spi_speed`, Hz.
    pub speed: u32,
    /// SPI mode (0..=3).
    pub mode: u8,
}

/// Reads the SPI sensor of `section` (a heater or a
/// `[temperature_sensor]`), whose `sensor_type` names `chip`: the chip's
/// own options, then the bus's, with Klipper's defaults and limits.
pub(crate) fn read<'a>(section: &Reader<'_, '_, 'a>, chip: Chip) -> Read<(SpiSensor, SpiBus<'a>)> {
    let mut sensor = SpiSensor::new(chip);
    match chip {
        Chip::Max31856 => {
            let mut cr0 = CR0_AUTOCONVERT;
            if section.get_bool("tc_use_50Hz_filter", false)? {
                cr0 |= CR0_FILTER_50HZ;
            }
            let tc = section.get_choice("tc_type", &TC_TYPES, Some("K"))?;
            let code = crate::temperature_sensor::position(&TC_TYPES, tc).unwrap_or(3) as u8;
            let counts = AVERAGES.map(|(n, _)| n);
            let avg = section.get_choice("tc_averaging_count", &counts, Some("1"))?;
            let avg_bits = AVERAGES.iter().find(|(n, _)| *n == avg).map_or(0, |a| a.1);
            sensor.set_init(&[0x80, cr0, code | avg_bits, MASK_DEFAULT]);
        }
        Chip::Max31865 => {
            let nominal = section.float("rtd_nominal_r", 100.0, Bounds::POSITIVE)?;
            let reference = section.float("rtd_reference_r", 430.0, Bounds::POSITIVE)?;
            sensor.rtd_ratio = reference / MAX31865_FULL / nominal;
            let mut config = RTD_CONFIG_DEFAULT;
            if section.get_bool("rtd_use_50Hz_filter", false)? {
                config |= RTD_FILTER_50HZ;
            }
            if section.get_int("rtd_num_of_wires", Some(2), None)? == 3 {
                config |= RTD_3WIRE;
            }
            sensor.set_init(&[0x80, config]);
        }
        Chip::Max6675 | Chip::Max31855 => {}
    }
    let cs_pin = section.get("sensor_pin")?;
    let speed = section.get_int("spi_speed", Some(4_000_000), Some(100_000))?;
    let pins = if section.get_opt("spi_software_sclk_pin").is_some() {
        SpiBusPins::Software {
            miso: section.get("spi_software_miso_pin")?,
            mosi: section.get("spi_software_mosi_pin")?,
            sclk: section.get("spi_software_sclk_pin")?,
        }
    } else {
        SpiBusPins::Hardware(section.get_opt("spi_bus"))
    };
    let bus = SpiBus {
        cs_pin,
        pins,
        speed: speed.min(i64::from(u32::MAX)) as u32,
        mode: chip.spi_mode(),
    };
    Ok((sensor, bus))
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::reader::Errors;
    use onechip_config::Config;
    use std::string::{String, ToString};

    /// The sensor and bus of a `[temperature_sensor t]` with `options`, or
    /// the config error as text.
    fn read_text(chip: Chip, options: &str) -> Result<(SpiSensor, SpiBus<'static>), String> {
        let text = std::format!("[temperature_sensor t]\n{options}");
        let text: &'static str = std::boxed::Box::leak(text.into_boxed_str());
        let config = Config::parse("printer.cfg", text).map_err(|e| e.to_string())?;
        let config: &'static Config<'static> = std::boxed::Box::leak(std::boxed::Box::new(config));
        let section = config.section("temperature_sensor t").expect("section");
        Errors::run(|errors| read(&Reader::new(section, errors), chip)).map_err(|e| e.to_string())
    }

    fn close(a: f64, b: f64, tolerance: f64) -> bool {
        (a - b).abs() <= tolerance
    }

    // The expected values below are worked from Klipper's documented
    // formulas (docs: the chips' datasheets as Klipper's spi_temperature
    // applies them): a thermocouple word is `raw >> shift` counts of
    // 0.25 °C (MAX6675: shift 3, MAX31855: 18) or 1/128 °C (MAX31856:
    // shift 5); back, `int(t / step + 0.5) << shift` clamped to the
    // positive range.

    #[test]
    fn max6675_words_are_quarter_degrees_above_three_status_bits() {
        let s = SpiSensor::new(Chip::Max6675);
        // 0x0C80 >> 3 = 400 counts × 0.25 = 100 °C.
        assert_eq!(s.temperature(0x0C80), 100.0);
        // 200 °C: int(800.5) = 800 << 3 = 6400; 25.1 °C: int(100.9) = 100.
        assert_eq!(s.raw(200.0), 6400);
        assert_eq!(s.raw(25.1), 800);
        // Clamped: negative to 0, above 2047.75 °C to 0x1FFF << 3.
        assert_eq!(s.raw(-10.0), 0);
        assert_eq!(s.raw(5000.0), 0x1FFF << 3);
        // The sign fix is Klipper's: counts 0x2001 read as -(1 + 1).
        assert_eq!(s.temperature(0x2001 << 3), -0.5);
        assert_eq!(s.raw_range(0.0, 260.0), (0, 1040 << 3));
        assert_eq!(
            s.fault_messages(0x04).collect::<std::vec::Vec<_>>(),
            ["Max6675 : Thermocouple Open Fault"]
        );
    }

    #[test]
    fn max31855_words_are_quarter_degrees_in_the_top_fourteen_bits() {
        let s = SpiSensor::new(Chip::Max31855);
        // 25 °C: int(100.5) = 100 << 18 = 26_214_400 (0x0190_0000).
        assert_eq!(s.raw(25.0), 0x0190_0000);
        // The low 18 bits (cold junction, fault bits) do not count.
        assert_eq!(s.temperature(0x0190_0000 | 0x1_0001 | 0xFFF0), 25.0);
        assert_eq!(s.temperature(0x0C80 << 18), 800.0);
        // Counts 0x3FFF: sign bit set, -((0x1FFF) + 1) × 0.25 = -2048 °C
        // (Klipper's fix, not two's complement).
        assert_eq!(s.temperature(0xFFFC_0000), -2048.0);
        assert_eq!(s.chip.spi_mode(), 0);
    }

    #[test]
    fn max31856_registers_are_128ths_of_a_degree_and_its_config_is_klippers() {
        let (s, bus) = read_text(Chip::Max31856, "sensor_pin: PA4").expect("defaults");
        // 200 °C: int(25600.5) = 25600 << 5 = 819_200 (0x0C_8000).
        assert_eq!(s.raw(200.0), 0x0C_8000);
        assert_eq!(s.temperature(0x0C_8000), 200.0);
        // 0x0C_8000 + 0x20 is one count more: 200 + 1/128 °C.
        assert_eq!(s.temperature(0x0C_8020), 200.0078125);
        // Written at start: CR0 (auto-convert), CR1 (K, 1 sample), MASK
        // (over/under voltage and open masked), from register 0 with the
        // write bit.
        assert_eq!(s.init_bytes(), [0x80, 0x80, 0x03, 0x03]);
        assert_eq!(
            bus,
            SpiBus {
                cs_pin: "PA4",
                pins: SpiBusPins::Hardware(None),
                speed: 4_000_000,
                mode: 1
            }
        );
        let (s, _) = read_text(
            Chip::Max31856,
            "sensor_pin: PA4\ntc_type: J\ntc_averaging_count: 16\ntc_use_50Hz_filter: True",
        )
        .expect("options");
        // J is 0b0010, 16 samples 0x70; CR0 gains the 50 Hz bit.
        assert_eq!(s.init_bytes(), [0x80, 0x81, 0x72, 0x03]);
        assert_eq!(s.fault_messages(0x41).count(), 2);
    }

    #[test]
    fn max31865_follows_callendar_van_dusen_through_the_reference_resistor() {
        let (s, _) = read_text(Chip::Max31865, "sensor_pin: PA4").expect("defaults");
        // PT100 on 430 Ω, 15-bit ratio: R/R0 = counts × 430 / 32768 / 100.
        // At 0 °C R/R0 = 1: int(32768 × 100 / 430 + 0.5) = int(7620.96)
        // = 7620, shifted left past the fault bit: 15240.
        assert_eq!(s.raw(0.0), 15240);
        // At 100 °C R/R0 = 1 + 0.39083 - 0.005775 = 1.385055:
        // int(1.385055 × 7620.465116 + 0.5) = int(10555.08) = 10554 ...
        let counts = libm::floor(1.385055 * 32768.0 * 100.0 / 430.0 + 0.5) as u32;
        assert_eq!(s.raw(100.0), counts << 1);
        // ... and back: t = (-A + sqrt(A² - 4B(1 - R/R0))) / 2B with the
        // counts' R/R0; within one count (0.03 °C) of 100 °C.
        let r = f64::from(counts) * 430.0 / 32768.0 / 100.0;
        let t = (-3.9083e-3
            + crate::math::sqrt(3.9083e-3 * 3.9083e-3 + 4.0 * 5.775e-7 * (1.0 - r)))
            / (2.0 * -5.775e-7);
        assert!(close(s.temperature(counts << 1), t, 1e-9));
        assert!(close(t, 100.0, 0.03), "{t}");
        // The fault bit (bit 0) is not part of the value.
        assert_eq!(s.temperature(15241), s.temperature(15240));
        // Platinum melts at 1768.3 °C; the range is clamped to 32768 << 1.
        assert_eq!(s.raw(5000.0), s.raw(1768.3));
        assert!(s.raw(1768.3) <= 32768 << 1);
        // Bias, auto conversion, fault clear.
        assert_eq!(s.init_bytes(), [0x80, 0xC2]);
        let (s, _) = read_text(
            Chip::Max31865,
            "sensor_pin: PA4\nrtd_nominal_r: 1000\nrtd_reference_r: 4300\n\
             rtd_num_of_wires: 3\nrtd_use_50Hz_filter: True",
        )
        .expect("PT1000");
        assert_eq!(s.init_bytes(), [0x80, 0xD3]);
        // A PT1000 on 4300 Ω has the PT100's ratios.
        assert_eq!(s.raw(100.0), counts << 1);
    }

    #[test]
    fn bus_options_are_klippers() {
        let (_, bus) = read_text(
            Chip::Max6675,
            "sensor_pin: PE3\nspi_software_miso_pin: PE5\nspi_software_sclk_pin: PE2\n\
             spi_software_mosi_pin: PA1\nspi_speed: 1000000",
        )
        .expect("software");
        assert_eq!(
            bus.pins,
            SpiBusPins::Software {
                sclk: "PE2",
                mosi: "PA1",
                miso: "PE5"
            }
        );
        assert_eq!((bus.speed, bus.mode), (1_000_000, 0));
        let (_, bus) =
            read_text(Chip::Max31855, "sensor_pin: PH9\nspi_bus: spi2b").expect("hardware");
        assert_eq!(bus.pins, SpiBusPins::Hardware(Some("spi2b")));
        for (options, option) in [
            ("sensor_pin: PA4\nspi_speed: 99999", "spi_speed"),
            (
                "sensor_pin: PA4\nspi_software_sclk_pin: PA5",
                "spi_software_miso_pin",
            ),
            ("spi_bus: spi1", "sensor_pin"),
        ] {
            let e = read_text(Chip::Max31855, options).expect_err(options);
            assert!(e.contains(&std::format!("option '{option}'")), "{e}");
        }
        for (options, line, option) in [
            ("sensor_pin: PA4\ntc_type: X", 3, "tc_type"),
            (
                "sensor_pin: PA4\ntc_averaging_count: 3",
                3,
                "tc_averaging_count",
            ),
            (
                "sensor_pin: PA4\ntc_use_50Hz_filter: maybe",
                3,
                "tc_use_50Hz_filter",
            ),
        ] {
            let e = read_text(Chip::Max31856, options).expect_err(options);
            let at = std::format!("printer.cfg:{line}: option '{option}'");
            assert!(e.contains(&at), "{e}");
        }
        for (options, option) in [
            ("sensor_pin: PA4\nrtd_nominal_r: 0", "rtd_nominal_r"),
            ("sensor_pin: PA4\nrtd_reference_r: -4", "rtd_reference_r"),
            ("sensor_pin: PA4\nrtd_num_of_wires: two", "rtd_num_of_wires"),
        ] {
            let e = read_text(Chip::Max31865, options).expect_err(options);
            assert!(e.contains(&std::format!("option '{option}'")), "{e}");
        }
    }
}
