//! The heaters and fan as physics, for the MCU role's io in virtual time:
//! each heater is a lump that the heater output warms and the room cools
//! (first order, exact between pin changes), read through its temperature
//! sensor (the conversion the firmware's heater control uses, run
//! backwards) and a 12-bit ADC, or an SPI converter chip answering its
//! register reads with the raw value of the temperature (Klipper's
//! conversion run backwards); every output's changes are tallied.

use onechip_app::heaters::PWM_MAX;
use onechip_planner::machine::Machine;
use onechip_planner::sensor_section::{
    Conversion, LinearConversion, SensorInput, TYPICAL_STM32H7_CAL,
};
use onechip_planner::spi_temperature::SpiSensor;
use onechip_planner::temperature_sensor::TemperatureSensor;
use onechip_sched::io::Peripherals;
use onechip_sched::outputs::Drive;

/// Room temperature, °C.
pub const AMBIENT: f64 = 25.0;
/// The simulated ADC's full scale (12 bits, as the STM32H7's ADC3).
pub const ADC_MAX: u16 = 4095;
/// The simulated MCU's die temperature, °C.
pub const MCU_TEMPERATURE: f64 = 40.0;
/// Where a temperature fan's sensor settles with its fan off (the
/// electronics or chamber it cools), °C; at full speed the fan brings
/// it down to [`AMBIENT`].
pub const COOLED_HOT: f64 = 45.0;
/// How fast it follows, s (first order).
pub const COOLED_TIME: f64 = 20.0;

/// A temperature sensor as physics: what it senses, and the fan that
/// cools it, if a temperature fan does.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Sensed {
    conversion: Conversion,
    /// °C at clock `at`.
    temp: f64,
    at: u64,
    /// The output of the fan cooling it.
    cooled_by: Option<usize>,
}

/// The simulated MCU's internal temperature sensor: a typical STM32H7's
/// factory calibration.
pub fn mcu_sensor() -> LinearConversion {
    LinearConversion::stm32h7(TYPICAL_STM32H7_CAL)
}

/// A heater as physics: power, heat loss and capacity.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeaterModel {
    /// Heater power at full on, W.
    pub watts: f64,
    /// Heat loss to the room, W per K above it.
    pub loss: f64,
    /// Heat capacity, J/K.
    pub capacity: f64,
}

impl HeaterModel {
    /// A 40 W hot end: about 45 s from room temperature to 200 °C.
    pub const HOTEND: Self = Self {
        watts: 40.0,
        loss: 40.0 / 325.0,
        capacity: 7.4,
    };
    /// A 250 W bed: about 110 s to 60 °C.
    pub const BED: Self = Self {
        watts: 250.0,
        loss: 250.0 / 115.0,
        capacity: 650.0,
    };

    /// The temperature (°C) `dt` s after `temp` (°C) with the heater at
    /// `power` (0..1) all along, the room at [`AMBIENT`] (first order:
    /// exact for a constant power).
    pub fn advance(&self, temp: f64, power: f64, dt: f64) -> f64 {
        let settle = AMBIENT + power * self.watts / self.loss;
        let decay = (-dt * self.loss / self.capacity).exp();
        settle + (temp - settle) * decay
    }
}

/// What an ADC of full scale `adc_max` reads from a sensor read through
/// `conversion` at `celsius` (°C), rounded.
pub fn adc_raw(conversion: &Conversion, celsius: f64, adc_max: u16) -> u16 {
    let reading = conversion.reading(celsius);
    (reading * f64::from(adc_max))
        .round()
        .clamp(0.0, f64::from(adc_max)) as u16
}

/// What one output did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct OutputLog {
    /// Level changes (or duty changes).
    pub changes: u64,
    /// Ticks spent on (a digital output), or duty × ticks / full scale.
    pub on_ticks: f64,
    /// Its current state.
    pub drive: Option<Drive>,
    /// Clock of its last change, ticks.
    pub since: u64,
}

/// A simulated heater.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Lump {
    model: HeaterModel,
    sensor: TemperatureSensor,
    /// Temperature, °C, at clock `at`.
    temp: f64,
    at: u64,
    /// Power now, 0..1.
    power: f64,
    /// Highest temperature reached, °C.
    peak: f64,
}

impl Lump {
    /// Runs the physics to clock `now` (exact for constant power).
    fn advance(&mut self, now: u64, freq: f64) {
        if now <= self.at {
            return;
        }
        let dt = (now - self.at) as f64 / freq;
        self.temp = self.model.advance(self.temp, self.power, dt);
        self.peak = self.peak.max(self.temp);
        self.at = now;
    }
}

/// The io's hardware in virtual time.
#[derive(Debug, Clone)]
pub struct Plant {
    /// Virtual time, ticks: set before each run of the io.
    pub now: u64,
    freq: f64,
    /// Heaters, in the machine's order (outputs and ADC inputs 0..).
    lumps: Vec<Lump>,
    /// Every output's log: heaters, the fan, then the named fans and pins.
    pub outputs: Vec<OutputLog>,
    /// Each `[temperature_sensor]`'s conversion and the temperature it
    /// senses, °C (ADC inputs after the heaters').
    sensors: Vec<Sensed>,
    /// From this clock on, heater `.1`'s thermistor reads as open circuit
    /// (fault injection).
    pub open_sensor: Option<(u64, usize)>,
    /// From clock `.0` on, SPI input `.1`'s chip reports fault bits `.2`
    /// (in the word of a MAX6675 or MAX31855, in the fault status register
    /// of a MAX31856 or MAX31865; fault injection).
    pub spi_fault: Option<(u64, usize, u32)>,
    /// Every register write to an SPI chip: its input and the bytes.
    pub spi_writes: Vec<(usize, Vec<u8>)>,
    /// If kept, the output updates queued since last taken: output,
    /// clock, value (for the outputs on secondary MCUs).
    pub queued: Option<Vec<(usize, u32, u32)>>,
}

impl Plant {
    /// The MCU's clock, Hz.
    pub fn freq(&self) -> f64 {
        self.freq
    }

    /// The heaters and fan of `machine` at room temperature, on an MCU
    /// clock of `freq` Hz.
    pub fn new(machine: &Machine<'_>, freq: f64) -> Self {
        let lumps = machine
            .heaters
            .iter()
            .map(|h| Lump {
                model: if h.name == "heater_bed" {
                    HeaterModel::BED
                } else {
                    HeaterModel::HOTEND
                },
                sensor: h.sensor,
                temp: AMBIENT,
                at: 0,
                power: 0.0,
                peak: AMBIENT,
            })
            .collect::<Vec<_>>();
        let outputs =
            lumps.len() + usize::from(machine.fan.is_some()) + machine.accessories.output_count();
        let first_fan = lumps.len() + usize::from(machine.fan.is_some());
        let cooling = |sensor: usize| {
            let fans = &machine.accessories.cooling;
            fans.iter().find(|t| t.sensor == sensor).map(|t| t.fan)
        };
        let sensors = (machine.sensors.iter().enumerate())
            .map(|(i, s)| {
                let cooled_by = cooling(i).map(|fan| first_fan + fan);
                let temp = match (s.input, cooled_by) {
                    (_, Some(_)) => COOLED_HOT,
                    (SensorInput::Mcu(_), None) => MCU_TEMPERATURE,
                    (SensorInput::Adc { .. } | SensorInput::Spi { .. }, None) => AMBIENT,
                };
                Sensed {
                    conversion: s.conversion(mcu_sensor()),
                    temp,
                    at: 0,
                    cooled_by,
                }
            })
            .collect();
        Self {
            now: 0,
            freq,
            lumps,
            outputs: vec![OutputLog::default(); outputs],
            sensors,
            open_sensor: None,
            spi_fault: None,
            spi_writes: Vec::new(),
            queued: None,
        }
    }

    /// Runs a cooled sensor's physics to now (exact for a constant fan
    /// power).
    fn advance_sensor(&mut self, index: usize) {
        let (now, freq) = (self.now, self.freq);
        let Some(s) = self.sensors.get(index).copied() else {
            return;
        };
        let Some(fan) = s.cooled_by.filter(|_| now > s.at) else {
            return;
        };
        let power = self
            .outputs
            .get(fan)
            .and_then(|o| o.drive)
            .map_or(0.0, Self::power);
        let settle = COOLED_HOT - (COOLED_HOT - AMBIENT) * power;
        let decay = (-((now - s.at) as f64 / freq) / COOLED_TIME).exp();
        if let Some(s) = self.sensors.get_mut(index) {
            (s.temp, s.at) = (settle + (s.temp - settle) * decay, now);
        }
    }

    /// Fault injection: heater `index`'s element gives `factor` times its
    /// power from now on (0: a broken element).
    pub fn weaken(&mut self, index: usize, factor: f64) {
        let (now, freq) = (self.now, self.freq);
        if let Some(lump) = self.lumps.get_mut(index) {
            lump.advance(now, freq);
            lump.model.watts *= factor.max(0.0);
        }
    }

    /// Heater `index`'s temperature now and the highest it reached, °C.
    pub fn temperature(&mut self, index: usize) -> Option<(f64, f64)> {
        let (now, freq) = (self.now, self.freq);
        let lump = self.lumps.get_mut(index)?;
        lump.advance(now, freq);
        Some((lump.temp, lump.peak))
    }

    /// An output's power (0..1).
    fn power(drive: Drive) -> f64 {
        match drive {
            Drive::Level(on) => f64::from(u8::from(on)),
            Drive::Duty(d) => f64::from(d) / f64::from(PWM_MAX),
        }
    }

    /// Input `index` (a heater's, then a temperature sensor's): its
    /// conversion and the temperature it senses now, °C.
    fn input(&mut self, index: usize) -> Option<(Conversion, f64)> {
        let (now, freq) = (self.now, self.freq);
        if let Some(lump) = self.lumps.get_mut(index) {
            lump.advance(now, freq);
            return Some((Conversion::Sensor(lump.sensor), lump.temp));
        }
        let sensor = index - self.lumps.len();
        self.advance_sensor(sensor);
        self.sensors.get(sensor).map(|s| (s.conversion, s.temp))
    }

    /// Input `index`'s SPI chip and the temperature it senses now, °C.
    fn spi_chip(&mut self, index: usize) -> Option<(SpiSensor, f64)> {
        match self.input(index)? {
            (Conversion::Sensor(sensor), celsius) => Some((*sensor.spi()?, celsius)),
            (Conversion::Linear(_), _) => None,
        }
    }

    /// Ends every output's log at the current time.
    pub fn finish(&mut self) {
        for index in 0..self.outputs.len() {
            if let Some(drive) = self.outputs[index].drive {
                self.drive(index, drive);
            }
        }
    }
}

impl Peripherals for Plant {
    fn drive(&mut self, index: usize, drive: Drive) {
        // What the old power did to the sensors this output cools.
        for sensor in 0..self.sensors.len() {
            if self.sensors[sensor].cooled_by == Some(index) {
                self.advance_sensor(sensor);
            }
        }
        let now = self.now;
        let Some(log) = self.outputs.get_mut(index) else {
            return;
        };
        if let Some(before) = log.drive {
            log.on_ticks += Self::power(before) * (now - log.since) as f64;
            log.changes += u64::from(before != drive);
        }
        log.drive = Some(drive);
        log.since = now;
        let power = Self::power(drive);
        let freq = self.freq;
        if let Some(lump) = self.lumps.get_mut(index) {
            lump.advance(now, freq);
            lump.power = power;
        }
    }

    fn queued(&mut self, index: usize, clock: u32, value: u32) {
        if let Some(queued) = &mut self.queued {
            queued.push((index, clock, value));
        }
    }

    fn read_adc(&mut self, index: usize) -> u16 {
        let now = self.now;
        if self
            .open_sensor
            .is_some_and(|(from, heater)| heater == index && now >= from)
        {
            return ADC_MAX;
        }
        let Some((conversion, celsius)) = self.input(index) else {
            return 0;
        };
        adc_raw(&conversion, celsius, ADC_MAX)
    }

    /// The chip answers as the real one does to the reads Klipper's MCU
    /// code makes ([`SpiSensor::simulate_reply`]); writes are recorded.
    fn spi_transfer(&mut self, index: usize, data: &mut [u8]) {
        let Some((chip, celsius)) = self.spi_chip(index) else {
            data.fill(0);
            return;
        };
        let now = self.now;
        let fault = self
            .spi_fault
            .filter(|&(from, input, _)| input == index && now >= from)
            .map_or(0, |f| f.2);
        if !chip.simulate_reply(celsius, fault, data) {
            self.spi_writes.push((index, data.to_vec()));
        }
    }
}
