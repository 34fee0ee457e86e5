//! Sensors read by linear interpolation in a table of (°C, volts) or
//! (°C, Ω) points, as Klipper's `adc_temperature`: the built-in types
//! (`sensor_type: AD595`, `PT1000`, ...) and custom `[adc_temperature
//! NAME]` sections.
//!
//! A volts table is read through the heater's `adc_voltage` (the ADC's
//! full scale, V) and `voltage_offset` (V): a point at `v` volts is the
//! ADC reading `(v − voltage_offset) / adc_voltage`, and points outside
//! 0..1 are dropped. An Ω table is read through a pullup resistor
//! (`pullup_resistor`), as a thermistor. Between points, and past the
//! ends, the temperature follows the straight line through neighbouring
//! points, with Klipper's rules for which line applies (including its
//! merging of lines that are exactly alike).

use crate::reader::{Read, Reader};
use crate::temperature_sensor::position;
use onechip_config::Bounds;

/// Most points a `[adc_temperature NAME]` section may have.
pub const MAX_POINTS: usize = 16;

/// A built-in table: (°C, raw) points, `temps[i]` with `raws[i]`, in
/// rising order; a point's volts (or Ω) are `(raw + offset) / scale`,
/// which gives Klipper's decimal numbers exactly. Tables with the same
/// temperatures share them.
#[derive(Debug, PartialEq, Eq)]
pub struct Table {
    offset: i16,
    scale: u16,
    temps: &'static [i16],
    raws: &'static [u16],
}

/// The points of a custom section: (°C, volts or Ω), in rising second
/// column (then rising temperature).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Points {
    len: u8,
    points: [(f32, f32); MAX_POINTS],
}

impl Points {
    /// Sorts the points by their second column, then temperature (the
    /// order Klipper interpolates in).
    fn sort(&mut self) {
        let points = &mut self.points[..usize::from(self.len)];
        for i in 1..points.len() {
            let mut j = i;
            while j > 0 && (points[j - 1].1, points[j - 1].0) > (points[j].1, points[j].0) {
                points.swap(j - 1, j);
                j -= 1;
            }
        }
    }
}

/// A sensor's table, built in or custom.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Samples {
    /// A built-in table.
    Table(&'static Table),
    /// A `[adc_temperature NAME]` section's points.
    Custom(Points),
}

/// What a table's second column is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Column {
    /// Volts at the ADC pin.
    Volts,
    /// The sensor's resistance, Ω.
    Ohms,
}

/// How a table's second column becomes an ADC reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Input {
    /// Volts: the ADC reads 0..`adc_voltage` V, less `offset` V.
    Voltage {
        /// adc_voltage, V.
        adc_voltage: f64,
        /// voltage_offset, V.
        offset: f64,
    },
    /// Ω, behind a pullup resistor of `pullup` Ω.
    Resistance {
        /// pullup_resistor, Ω.
        pullup: f64,
    },
}

/// Why a table cannot be used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TableError {
    /// Fewer than two points (within the ADC's range).
    TooFew,
    /// Two points at the same ADC reading.
    Duplicate,
}

impl TableError {
    /// Why, as a config error's reason (about `sensor_type`).
    pub fn reason(self) -> &'static str {
        match self {
            Self::TooFew => "has fewer than two points in the ADC's range (adc_voltage)",
            Self::Duplicate => "has two points at one voltage or resistance",
        }
    }
}

/// A sensor read by linear interpolation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinearSensor {
    samples: Samples,
    input: Input,
}

/// One straight piece of the curve: it applies to keys below `end` (the
/// key of its last point), as `value = key · gain + offset`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Segment {
    end: f64,
    gain: f64,
    offset: f64,
}

impl Segment {
    /// The value at the segment's last point.
    fn end_value(&self) -> f64 {
        self.end * self.gain + self.offset
    }
}

/// The pieces of a sensor's curve, one at a time: a point on the line of
/// the piece before it does not start a new piece, and the next piece then
/// starts from the last point that did (Klipper's rule).
struct Pieces<'s> {
    sensor: &'s LinearSensor,
    /// Next point to look at.
    next: usize,
    /// The last point that started a piece: (key, °C).
    last: Option<(f64, f64)>,
    /// The last piece's line: (gain, offset).
    line: Option<(f64, f64)>,
}

impl Iterator for Pieces<'_> {
    type Item = Segment;

    #[inline(never)]
    fn next(&mut self) -> Option<Segment> {
        while self.next < self.sensor.len() {
            let i = self.next;
            self.next += 1;
            let Some((key, value)) = self.sensor.key_value(i) else {
                continue;
            };
            let Some((last_key, last_value)) = self.last else {
                self.last = Some((key, value));
                continue;
            };
            let gain = (value - last_value) / (key - last_key);
            let offset = last_value - last_key * gain;
            if self.line == Some((gain, offset)) {
                continue;
            }
            self.last = Some((key, value));
            self.line = Some((gain, offset));
            return Some(Segment {
                end: key,
                gain,
                offset,
            });
        }
        None
    }
}

impl LinearSensor {
    /// The sensor of `samples` read through `input`, if its table has two
    /// points or more (within the ADC's range) at distinct readings.
    pub fn new(samples: Samples, input: Input) -> Result<Self, TableError> {
        let sensor = Self { samples, input };
        let mut last = None;
        let mut count = 0;
        for i in 0..sensor.len() {
            let Some((key, _)) = sensor.key_value(i) else {
                continue;
            };
            if last.is_some_and(|k| key <= k) {
                return Err(TableError::Duplicate);
            }
            last = Some(key);
            count += 1;
        }
        if count < 2 {
            return Err(TableError::TooFew);
        }
        Ok(sensor)
    }

    /// Number of points in the table.
    fn len(&self) -> usize {
        match &self.samples {
            Samples::Table(t) => t.raws.len(),
            Samples::Custom(p) => usize::from(p.len),
        }
    }

    /// Point `i` as (key, °C), where the key is the ADC reading (volts)
    /// or the resistance (Ω); None if it is out of the ADC's range.
    #[inline(never)]
    fn key_value(&self, i: usize) -> Option<(f64, f64)> {
        let (celsius, raw) = match &self.samples {
            Samples::Table(t) => {
                let (&celsius, &raw) = t.temps.get(i).zip(t.raws.get(i))?;
                let raw = (f64::from(raw) + f64::from(t.offset)) / f64::from(t.scale);
                (f64::from(celsius), raw)
            }
            Samples::Custom(p) => {
                let &(celsius, raw) = p.points.get(i)?;
                (f64::from(celsius), f64::from(raw))
            }
        };
        match self.input {
            Input::Voltage {
                adc_voltage,
                offset,
            } => {
                let adc = (raw - offset) / adc_voltage;
                (0.0..=1.0).contains(&adc).then_some((adc, celsius))
            }
            Input::Resistance { .. } => Some((raw, celsius)),
        }
    }

    /// The curve's straight pieces, in rising key, as Klipper builds them.
    fn pieces(&self) -> Pieces<'_> {
        Pieces {
            sensor: self,
            next: 0,
            last: None,
            line: None,
        }
    }

    /// The value at `key`: on the first piece whose end lies above it, or
    /// else on the last.
    fn interpolate(&self, key: f64) -> f64 {
        let mut piece = None;
        for s in self.pieces() {
            piece = Some(s);
            if key < s.end {
                break;
            }
        }
        // `new` checked there is a piece.
        piece.map_or(f64::NAN, |s| key * s.gain + s.offset)
    }

    /// The key at `value`: on the first piece whose end value reaches it
    /// (in the direction the table runs from its first piece's end to its
    /// last's), or else on the last. A flat piece gives its end.
    fn reverse_interpolate(&self, value: f64) -> f64 {
        let (mut first, mut up, mut down, mut last) = (None, None, None, None);
        for s in self.pieces() {
            let v = s.end_value();
            first.get_or_insert(v);
            if up.is_none() && v >= value {
                up = Some(s);
            }
            if down.is_none() && v <= value {
                down = Some(s);
            }
            last = Some(s);
        }
        let Some(last) = last else {
            return f64::NAN;
        };
        let rising = first.is_some_and(|f| f < last.end_value());
        let s = if rising { up } else { down }.unwrap_or(last);
        if s.gain != 0.0 {
            (value - s.offset) / s.gain
        } else {
            s.end
        }
    }

    /// Temperature at ADC reading `adc` (fraction of full scale), °C.
    pub fn temperature(&self, adc: f64) -> f64 {
        match self.input {
            Input::Voltage { .. } => self.interpolate(adc),
            Input::Resistance { pullup } => {
                let adc = crate::math::clamp(adc, 0.00001, 0.99999);
                self.interpolate(pullup * adc / (1.0 - adc))
            }
        }
    }

    /// ADC reading (fraction of full scale) at temperature `t`, °C.
    pub fn adc(&self, t: f64) -> f64 {
        let key = self.reverse_interpolate(t);
        match self.input {
            Input::Voltage { .. } => key,
            Input::Resistance { pullup } => key / (pullup + key),
        }
    }
}

/// The table of the built-in type `name`, and what its second column is.
pub fn built_in(name: &str) -> Option<(Samples, Column)> {
    let table = TABLES.get(position(&NAMES, name)?)?;
    // Only PT1000's table is of Ω.
    let column = if core::ptr::eq(*table, &PT1000) {
        Column::Ohms
    } else {
        Column::Volts
    };
    Some((Samples::Table(table), column))
}

/// Reads the options of a heater section that a table of `column` reads:
/// `adc_voltage` (V, default 5) and `voltage_offset` (V, default 0) for
/// volts, `pullup_resistor` (Ω, default 4700) for Ω.
pub(crate) fn read_input(section: &Reader<'_, '_, '_>, column: Column) -> Read<Input> {
    Ok(match column {
        Column::Volts => Input::Voltage {
            adc_voltage: section.float("adc_voltage", 5.0, Bounds::POSITIVE)?,
            offset: section.float("voltage_offset", 0.0, Bounds::NONE)?,
        },
        Column::Ohms => Input::Resistance {
            pullup: section.float("pullup_resistor", 4700.0, Bounds::POSITIVE)?,
        },
    })
}

/// The names of one numbered option, 1 to [`MAX_POINTS`] + 1.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Numbered {
    /// `prefix1prefix2...prefix17`.
    names: &'static str,
    /// The prefix's length, bytes.
    prefix: usize,
}

/// `prefix1` to `prefix17` in one string.
macro_rules! numbered {
    ($p:literal) => {
        Numbered {
            names: concat!(
                $p, "1", $p, "2", $p, "3", $p, "4", $p, "5", $p, "6", $p, "7", $p, "8", $p, "9",
                $p, "10", $p, "11", $p, "12", $p, "13", $p, "14", $p, "15", $p, "16", $p, "17"
            ),
            prefix: $p.len(),
        }
    };
}

/// `temperature1`, ...: °C.
const TEMPERATURE: Numbered = numbered!("temperature");
/// `voltage1`, ...: V.
const VOLTAGE: Numbered = numbered!("voltage");
/// `resistance1`, ...: Ω.
const RESISTANCE: Numbered = numbered!("resistance");

impl Numbered {
    /// The option numbered `n` (1 to [`MAX_POINTS`] + 1).
    fn name(&self, n: usize) -> &'static str {
        let p = self.prefix;
        let (start, len) = if n <= 9 {
            (n.saturating_sub(1) * (p + 1), p + 1)
        } else {
            (9 * (p + 1) + (n - 10) * (p + 2), p + 2)
        };
        self.names.get(start..start + len).unwrap_or(self.names)
    }
}

/// Reads a `[adc_temperature NAME]` section: `temperature1`, `voltage1`,
/// `temperature2`, `voltage2`, ... (or `resistance1`, ... if it has
/// `resistance1`), up to the first temperature missing; at most
/// [`MAX_POINTS`] points.
#[inline(never)]
pub(crate) fn read_section(section: &Reader<'_, '_, '_>) -> Read<(Samples, Column)> {
    let (column, names) = match section.get_opt("resistance1") {
        Some(_) => (Column::Ohms, RESISTANCE),
        None => (Column::Volts, VOLTAGE),
    };
    let mut points = Points {
        len: 0,
        points: [(0.0, 0.0); MAX_POINTS],
    };
    for n in 1..=MAX_POINTS + 1 {
        let temperature = TEMPERATURE.name(n);
        let Some(celsius) = section.get_float_opt(temperature, Bounds::NONE)? else {
            break;
        };
        let Some(slot) = points.points.get_mut(n - 1) else {
            return Err(section.error_for(temperature, "is past the 16 points onechip holds"));
        };
        let column_name = names.name(n);
        let raw = section.required_float(column_name, Bounds::NONE)? as f32;
        if !raw.is_finite() || !(celsius as f32).is_finite() {
            return Err(section.error_for(column_name, "is too large"));
        }
        *slot = (celsius as f32, raw);
        points.len += 1;
    }
    points.sort();
    Ok((Samples::Custom(points), column))
}

/// The built-in tables' `sensor_type` names (Klipper's
/// `adc_temperature.py`), in [`TABLES`]' order.
static NAMES: [&str; 8] = [
    "AD595",
    "AD597",
    "AD8494",
    "AD8495",
    "AD8496",
    "AD8497",
    "PT100 INA826",
    "PT1000",
];

/// The tables of [`NAMES`].
static TABLES: [&Table; 8] = [
    &AD595,
    &AD597,
    &AD8494,
    &AD8495,
    &AD8496,
    &AD8497,
    &PT100_INA826,
    &PT1000,
];

/// The AD8494 to AD8497 tables' temperatures, °C (the AD8494 and AD8496
/// tables use -180 to 1200 °C, [4..75]).
#[rustfmt::skip]
static AD849X_TEMPS: [i16; 84] = [
    -260, -240, -220, -200, -180, -160, -140, -120, -100, -80, -60, -40, -20, 0, 20, 25, 40,
    60, 80, 100, 120, 140, 160, 180, 200, 220, 240, 260, 280, 300, 320, 340, 360, 380, 400,
    420, 440, 460, 480, 500, 520, 540, 560, 580, 600, 620, 640, 660, 680, 700, 720, 740, 760,
    780, 800, 820, 840, 860, 880, 900, 920, 940, 960, 980, 1000, 1020, 1040, 1060, 1080, 1100,
    1120, 1140, 1160, 1180, 1200, 1220, 1240, 1260, 1280, 1300, 1320, 1340, 1360, 1380,
];

/// The AD595 and AD597 tables' temperatures, °C (AD595: [..29]).
#[rustfmt::skip]
static AD59X_TEMPS: [i16; 30] = [
    0, 10, 20, 25, 30, 40, 50, 60, 80, 100, 120, 140, 160, 180, 200, 220, 240, 260, 280, 300,
    320, 340, 360, 380, 400, 420, 440, 460, 480, 500,
];

/// The PT100 INA826 table's temperatures, °C.
#[rustfmt::skip]
static PT100_TEMPS: [i16; 49] = [
    0, 1, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100, 110, 120, 130, 140, 150, 160, 170, 180, 190,
    200, 210, 220, 230, 240, 250, 260, 270, 280, 290, 300, 310, 320, 330, 340, 350, 360, 370,
    380, 390, 400, 500, 600, 700, 800, 900, 1000, 1100,
];

/// The PT1000 table's temperatures, °C.
#[rustfmt::skip]
static PT1000_TEMPS: [i16; 6] = [
    0, 100, 200, 300, 400, 500,
];

/// Analog Devices AD595 thermocouple amplifier (type K), volts.
#[rustfmt::skip]
static AD595: Table = Table {
    offset: 0,
    scale: 10000,
    temps: AD59X_TEMPS.split_at(29).0,
    raws: &[
        27, 1010, 2000, 2500, 3000, 4010, 5030, 6050, 8100, 10150, 12190, 14200, 16200, 18170,
        20150, 22130, 24130, 26140, 28170, 30220, 32270, 34340, 36410, 38490, 40570, 42660, 44760,
        46860, 48960,
    ],
};

/// AD597 thermocouple amplifier (type K), volts.
#[rustfmt::skip]
static AD597: Table = Table {
    offset: 0,
    scale: 1000,
    temps: &AD59X_TEMPS,
    raws: &[
        0, 97, 196, 245, 295, 395, 496, 598, 802, 1005, 1207, 1407, 1605, 1801, 1997, 2194, 2392,
        2592, 2794, 2996, 3201, 3406, 3611, 3817, 4024, 4232, 4440, 4649, 4857, 5066,
    ],
};

/// AD8494 thermocouple amplifier (type J), volts.
#[rustfmt::skip]
static AD8494: Table = Table {
    offset: -714,
    scale: 1000,
    temps: AD849X_TEMPS.split_at(4).1.split_at(71).0,
    raws: &[
        0, 56, 120, 191, 268, 349, 436, 526, 619, 716, 814, 839, 915, 1017, 1120, 1225, 1331, 1437,
        1543, 1651, 1758, 1865, 1973, 2080, 2187, 2294, 2401, 2508, 2615, 2722, 2828, 2935, 3042,
        3149, 3256, 3364, 3473, 3582, 3693, 3804, 3917, 4030, 4145, 4262, 4380, 4500, 4620, 4743,
        4866, 4990, 5115, 5240, 5364, 5488, 5611, 5732, 5852, 5971, 6088, 6204, 6320, 6434, 6547,
        6660, 6772, 6884, 6996, 7108, 7219, 7330, 7441,
    ],
};

/// AD8495 thermocouple amplifier (type K), volts.
#[rustfmt::skip]
static AD8495: Table = Table {
    offset: -786,
    scale: 1000,
    temps: &AD849X_TEMPS,
    raws: &[
        0, 12, 35, 67, 109, 159, 217, 282, 354, 431, 514, 602, 693, 789, 886, 911, 986, 1087, 1188,
        1290, 1391, 1491, 1589, 1687, 1785, 1883, 1982, 2081, 2182, 2283, 2385, 2487, 2589, 2692,
        2796, 2899, 3003, 3107, 3211, 3315, 3420, 3524, 3629, 3733, 3837, 3941, 4045, 4148, 4251,
        4354, 4456, 4558, 4660, 4761, 4862, 4962, 5061, 5160, 5259, 5357, 5455, 5552, 5649, 5745,
        5841, 5936, 6031, 6125, 6218, 6311, 6403, 6495, 6586, 6677, 6766, 6855, 6944, 7031, 7118,
        7204, 7289, 7373, 7457, 7540,
    ],
};

/// AD8496 thermocouple amplifier (type J), volts.
#[rustfmt::skip]
static AD8496: Table = Table {
    offset: -642,
    scale: 1000,
    temps: AD849X_TEMPS.split_at(4).1.split_at(71).0,
    raws: &[
        0, 52, 112, 178, 250, 327, 407, 492, 579, 669, 761, 784, 855, 950, 1047, 1145, 1243, 1343,
        1442, 1542, 1643, 1743, 1843, 1944, 2044, 2144, 2244, 2344, 2443, 2543, 2643, 2742, 2842,
        2942, 3043, 3144, 3245, 3347, 3450, 3554, 3659, 3766, 3873, 3982, 4093, 4204, 4317, 4431,
        4546, 4662, 4779, 4896, 5012, 5128, 5242, 5356, 5468, 5579, 5689, 5797, 5905, 6011, 6117,
        6223, 6328, 6432, 6537, 6641, 6745, 6849, 6953,
    ],
};

/// AD8497 thermocouple amplifier (type K), volts.
#[rustfmt::skip]
static AD8497: Table = Table {
    offset: -785,
    scale: 1000,
    temps: &AD849X_TEMPS,
    raws: &[
        0, 12, 34, 67, 109, 159, 217, 282, 353, 431, 514, 601, 693, 788, 886, 911, 985, 1086, 1188,
        1290, 1390, 1490, 1589, 1687, 1784, 1882, 1981, 2081, 2181, 2283, 2384, 2486, 2589, 2692,
        2795, 2899, 3003, 3107, 3211, 3315, 3419, 3524, 3628, 3733, 3837, 3941, 4044, 4148, 4251,
        4354, 4456, 4558, 4659, 4761, 4861, 4961, 5061, 5160, 5259, 5357, 5455, 5552, 5648, 5745,
        5840, 5936, 6030, 6124, 6218, 6311, 6403, 6495, 6586, 6676, 6766, 6855, 6943, 7031, 7117,
        7203, 7288, 7373, 7456, 7539,
    ],
};

/// PT100 behind an INA826 amplifier, volts.
#[rustfmt::skip]
static PT100_INA826: Table = Table {
    offset: 0,
    scale: 100,
    temps: &PT100_TEMPS,
    raws: &[
        0, 111, 115, 120, 124, 128, 132, 136, 140, 144, 148, 152, 156, 161, 165, 168, 172, 176,
        180, 184, 188, 192, 196, 200, 204, 207, 211, 215, 218, 222, 226, 229, 233, 237, 241, 244,
        248, 251, 255, 258, 262, 266, 300, 333, 363, 393, 421, 448, 473,
    ],
};

/// PT1000 platinum resistor, ohms.
#[rustfmt::skip]
static PT1000: Table = Table {
    offset: 0,
    scale: 10,
    temps: &PT1000_TEMPS,
    raws: &[
        10000, 13851, 17586, 21205, 24709, 28098,
    ],
};

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;

    fn volts(adc_voltage: f64, offset: f64) -> Input {
        Input::Voltage {
            adc_voltage,
            offset,
        }
    }

    const OHMS: Input = Input::Resistance { pullup: 4700.0 };

    fn sensor(name: &str, input: Input) -> LinearSensor {
        let (samples, _) = built_in(name).expect("built in");
        LinearSensor::new(samples, input).expect("usable")
    }

    fn custom(points: &[(f32, f32)], input: Input) -> Result<LinearSensor, TableError> {
        let mut p = Points {
            len: points.len() as u8,
            points: [(0.0, 0.0); MAX_POINTS],
        };
        p.points[..points.len()].copy_from_slice(points);
        p.sort();
        LinearSensor::new(Samples::Custom(p), input)
    }

    #[test]
    fn built_in_tables_rise_and_decode_to_klippers_numbers() {
        for (name, table) in NAMES.iter().zip(TABLES) {
            assert_eq!(table.temps.len(), table.raws.len(), "{name}");
            assert!(table.temps.windows(2).all(|w| w[0] < w[1]), "{name}");
            assert!(table.raws.windows(2).all(|w| w[0] < w[1]), "{name}");
        }
        // The shared temperatures: AD8494 and AD8496 run -180..1200 °C,
        // AD595 0..480 °C.
        assert_eq!((AD8494.temps[0], AD8494.temps[70]), (-180, 1200));
        assert_eq!(AD8496.temps, AD8494.temps);
        assert_eq!((AD595.temps.len(), AD595.temps[28]), (29, 480));
        // The first point's volts, read back from its ADC reading on a
        // -10..10 V input.
        let decoded = |name| {
            let s = sensor(name, volts(20.0, -10.0));
            let (adc, _) = s.key_value(0).expect("in range");
            adc * 20.0 - 10.0
        };
        // Klipper's first points: AD595 (0 °C, .0027 V), AD8495 (-260 °C,
        // -0.786 V), PT100 INA826 (0 °C, 0.00 V).
        assert!((decoded("AD595") - 0.0027).abs() < 1e-12);
        assert!((decoded("AD8495") + 0.786).abs() < 1e-12);
        assert!(decoded("PT100 INA826").abs() < 1e-12);
        assert_eq!((PT1000.temps[1], PT1000.raws[1]), (100, 13851));
        assert_eq!(built_in("AD595").map(|(_, c)| c), Some(Column::Volts));
        assert_eq!(built_in("PT1000").map(|(_, c)| c), Some(Column::Ohms));
        assert_eq!(built_in("Generic 3950"), None);
    }

    #[test]
    fn readings_convert_to_klippers_temperatures() {
        // Expected values from Klipper's rules (the table's points as ADC
        // readings, (volts - voltage_offset) / adc_voltage, those outside
        // 0..1 dropped; the line of the first piece whose last point lies
        // above the reading, else of the last piece; Ω through the 4.7 kΩ
        // divider), evaluated in Python for these readings.
        let cases = [
            ("AD595", volts(5.0, 0.0), 0.4, 198.4848484848485),
            ("AD595", volts(3.3, 0.0), 1.0, 327.1219512195122),
            ("AD597", volts(5.0, 0.0), 0.31, 154.44444444444443),
            ("AD8494", volts(5.0, 0.0), 0.1, 97.90476190476191),
            ("AD8495", volts(5.0, 0.0), 0.0, -0.6185567010309279),
            ("AD8495", volts(3.3, 0.5), 0.6, 490.5769230769231),
            ("AD8496", volts(5.0, 0.0), 0.25, 249.65174129353233),
            ("AD8497", volts(5.0, 0.0), 0.9, 885.3807106598985),
            ("PT100 INA826", volts(5.0, 0.0), 0.5, 356.66666666666663),
            ("PT100 INA826", volts(5.0, 0.0), 0.01, 0.045045045045045036),
            ("PT1000", OHMS, 0.25, 148.61222668451586),
            ("PT1000", OHMS, 0.4, 595.46572243533),
        ];
        for (name, input, adc, celsius) in cases {
            let got = sensor(name, input).temperature(adc);
            assert!((got - celsius).abs() < 1e-9, "{name} at {adc}: {got}");
        }
        // On the points themselves: AD595 at 1.015 V is 100 °C; PT1000 at
        // 1385.1 Ω is 100 °C.
        let ad595 = sensor("AD595", volts(5.0, 0.0));
        assert!((ad595.temperature(1.015 / 5.0) - 100.0).abs() < 1e-9);
        let pt1000 = sensor("PT1000", OHMS);
        assert!((pt1000.temperature(1385.1 / 6085.1) - 100.0).abs() < 1e-9);
    }

    #[test]
    fn temperatures_convert_back_to_klippers_readings() {
        let pt1000 = sensor("PT1000", OHMS);
        assert!((pt1000.adc(150.0) - 0.2506198330636096).abs() < 1e-12);
        let ad595 = sensor("AD595", volts(5.0, 0.0));
        assert!((ad595.adc(250.0) - 0.5026999999999999).abs() < 1e-12);
        for (name, input) in [
            ("AD8495", volts(5.0, 0.0)),
            ("PT100 INA826", volts(5.0, 0.0)),
            ("PT1000", OHMS),
        ] {
            let s = sensor(name, input);
            for celsius in [20.0, 60.0, 110.0, 210.0, 290.0] {
                let back = s.temperature(s.adc(celsius));
                assert!((back - celsius).abs() < 1e-9, "{name} {celsius}: {back}");
            }
        }
    }

    #[test]
    fn a_point_on_the_line_before_it_merges_pieces_as_in_klipper() {
        // 0, 1, 2 V lie on one line (100 °C a volt): Klipper keeps the
        // first piece and draws the next from 1 V (100 °C) to 2.5 V
        // (300 °C), past the 2 V point.
        let points = [(0.0, 0.0), (100.0, 1.0), (200.0, 2.0), (300.0, 2.5)];
        let s = custom(&points, volts(5.0, 0.0)).expect("usable");
        assert!((s.temperature(0.1) - 50.0).abs() < 1e-9);
        assert!((s.temperature(0.3) - 166.66666666666669).abs() < 1e-9);
        assert!((s.temperature(0.45) - 266.66666666666674).abs() < 1e-9);
        assert!((s.adc(250.0) - 0.425).abs() < 1e-12);
    }

    #[test]
    fn a_falling_resistance_table_reads_both_ways() {
        // An NTC as (°C, Ω) points.
        let points = [
            (150.0, 1600.0),
            (100.0, 5600.0),
            (50.0, 30_000.0),
            (25.0, 100_000.0),
        ];
        let s = custom(&points, OHMS).expect("usable");
        assert!((s.temperature(0.5) - 111.25).abs() < 1e-9);
        assert!((s.adc(120.0) - 0.45977011494252873).abs() < 1e-12);
    }

    #[test]
    fn unusable_tables_are_refused() {
        let one = [(0.0, 0.0)];
        assert_eq!(custom(&one, volts(5.0, 0.0)), Err(TableError::TooFew));
        let twice = [(0.0, 1.0), (10.0, 1.0)];
        assert_eq!(custom(&twice, volts(5.0, 0.0)), Err(TableError::Duplicate));
        // Only one point within 0..1 V.
        let high = [(0.0, 0.5), (100.0, 2.0), (200.0, 3.0)];
        assert_eq!(custom(&high, volts(1.0, 0.0)), Err(TableError::TooFew));
        assert!(custom(&high, volts(5.0, 0.0)).is_ok());
    }

    #[test]
    fn numbered_names_are_cut_right() {
        for n in 1..=MAX_POINTS + 1 {
            assert_eq!(TEMPERATURE.name(n), std::format!("temperature{n}"));
            assert_eq!(VOLTAGE.name(n), std::format!("voltage{n}"));
            assert_eq!(RESISTANCE.name(n), std::format!("resistance{n}"));
        }
    }
}
