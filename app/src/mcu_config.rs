//! The config commands klippy sends an MCU for the objects printer.cfg
//! puts on it, in klippy's order and with its object ids, so that a stock
//! Klipper MCU (a secondary board) is configured exactly as klippy would
//! configure it, and its `finalize_config` CRC is klippy's.
//!
//! Object ids: endstops (with their trsync) and steppers take theirs when
//! created: the `[extruder_stepper]`s' (klippy loads them with the other
//! extra sections, before the toolhead), the rails, then the extruder's
//! stepper, and an SPI temperature chip's bus and reader (with its
//! `config_spi`, added then); enable pins, ADC inputs and heater, fan and
//! pin outputs take theirs when their config is written. Config order: the
//! `[static_digital_output]` pins (klippy adds their commands as the
//! sections load, before any config callback runs); each
//! `[extruder_stepper]`'s stepper and enable pin; the part fan, the named
//! fans and the `[output_pin]`s, then
//! the `[temperature_sensor]`s on an ADC pin (extra sections, which klippy
//! loads before the toolhead), an SPI chip's `spi_set_bus` and
//! `config_thermocouple` where an ADC input's `config_analog_in` would
//! be; each rail's endstop,
//! trsync, stepper and enable pin (an enable pin on its own MCU, which
//! may not be the stepper's); the extruder's heater (sensor, output)
//! before its stepper and enable pin; then the other heaters. (Checked
//! against klippy for the golden configs, which have no `[heater_bed]`,
//! `[extruder_stepper]`, fan or pin: the order of those follows from when
//! klippy creates them, not from a recorded session; among the extra
//! sections klippy follows printer.cfg's order, here the order above.)
//!
//! Fans and pins are configured as klippy's `MCU_pwm` and
//! `MCU_digital_out`: `config_digital_out` with the start and shutdown
//! levels (inverted for a `!` pin, as klippy inverts on the host) and
//! max_duration, `set_digital_out_pwm_cycle` for software PWM; a static
//! pin is `set_digital_out` and has no object id. A hardware PWM output
//! is klippy's `config_pwm_out`, its start and shutdown values scaled by
//! the MCU's PWM_MAX.
//!
//! A pin belongs to the MCU its prefix names (`ext:PA4`, `!ext:PA4`);
//! without one, or with `mcu:`, to the main MCU.

use crate::heaters::{INPUTS, McuSetup, OUTPUTS, full_scale, input_buses, input_chips};
use core::fmt::{self, Write};
use onechip_planner::extruder_stepper::EXTRUDER;
use onechip_planner::machine::{MAX_STEPPERS, Machine};
use onechip_planner::sensor_section::{MAX_SENSORS, SensorInput};
use onechip_planner::spi_temperature::{NAMES, SpiBus, SpiBusPins, SpiSensor};
use onechip_sched::outputs::OutputKind;

/// The main MCU's name (`[mcu]`).
pub const MAIN: &str = "mcu";

/// The MCU a config is written for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConfigTarget<'a> {
    /// Its name ([`MAIN`] or a `[mcu NAME]`'s).
    pub mcu: &'a str,
    /// Full scale of its hardware PWM channels (its dictionary's
    /// `PWM_MAX`; 0 if it has none).
    pub pwm_max: u32,
    /// Its SPI bus of value 0, which a chip without `spi_bus` is on (the
    /// dictionary's name for it; "0" if it names none).
    pub spi_bus: &'a str,
}

/// A pin as printer.cfg writes it, split up.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PinRef<'a> {
    /// The MCU it is on ([`MAIN`] or a `[mcu NAME]`'s name).
    pub mcu: &'a str,
    /// The pin's name on that MCU.
    pub pin: &'a str,
    /// Active low (`!`).
    pub inverted: bool,
    /// Pull-up wanted (`^`).
    pub pull_up: bool,
}

/// True if `pin` (as printer.cfg writes it) is on the main MCU: not
/// written `NAME:PIN`.
pub fn on_main(pin: &str) -> bool {
    pin_ref(pin).mcu == MAIN
}

/// Splits `text` (`[!][^|~]` modifiers, then `[MCU:]PIN`).
pub fn pin_ref(text: &str) -> PinRef<'_> {
    let (mut inverted, mut pull_up) = (false, false);
    let mut rest = text.trim();
    while let Some(c) = rest.chars().next() {
        match c {
            '!' => inverted = true,
            '^' => pull_up = true,
            '~' => {}
            _ => break,
        }
        rest = rest[1..].trim_start();
    }
    let (mcu, pin) = match rest.split_once(':') {
        Some((mcu, pin)) => (mcu.trim(), pin.trim()),
        None => (MAIN, rest),
    };
    PinRef {
        mcu,
        pin,
        inverted,
        pull_up,
    }
}

/// The object ids given out on one MCU, by the machine's indices.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Oids {
    /// Each stepper's (by `machine.steppers` index), if on this MCU.
    pub steppers: [Option<u8>; MAX_STEPPERS],
    /// Each stepper's endstop and its trsync, if on this MCU.
    pub endstops: [Option<(u8, u8)>; MAX_STEPPERS],
    /// Each stepper's enable pin output, if on this MCU.
    pub enables: [Option<u8>; MAX_STEPPERS],
    /// Each heater's sensor and output (by `machine.heaters` index), each
    /// if on this MCU.
    pub heaters: [(Option<u8>, Option<u8>); 2],
    /// Each temperature sensor's ADC input or SPI chip reader (by
    /// `machine.sensors` index).
    pub sensors: [Option<u8>; MAX_SENSORS],
    /// Each SPI chip's bus object, by io input (the heaters', then the
    /// temperature sensors'); its reader is the heater's or sensor's.
    pub spi: [Option<u8>; INPUTS],
    /// Each fan's or pin's output, by its index in [`McuSetup::outputs`]
    /// (the MCU role's io order; heaters and static pins have none).
    pub outputs: [Option<u8>; OUTPUTS],
    /// Object ids in all (`allocate_oids count`).
    pub count: u8,
}

/// An object klippy writes config for.
#[derive(Debug, Clone, Copy)]
enum Object {
    /// Stepper `i` of the machine (its endstop, stepper and enable pin).
    Stepper(usize),
    /// Heater `h` of the machine (its sensor and output).
    Heater(usize),
    /// Output `k` of [`McuSetup::outputs`]: the part fan, a named fan, an
    /// output pin or a static pin.
    Output(usize),
    /// Temperature sensor `i` of the machine.
    Sensor(usize),
}

impl Object {
    /// The io input of a heater's or temperature sensor's sensor (the
    /// heaters', then the temperature sensors').
    fn input(self, machine: &Machine<'_>) -> Option<usize> {
        match self {
            Self::Heater(h) => Some(h),
            Self::Sensor(i) => Some(machine.heaters.len() + i),
            Self::Stepper(_) | Self::Output(_) => None,
        }
    }

    /// A heater's or temperature sensor's SPI chip: its io input, its
    /// bus and the chip.
    fn spi_chip<'a>(self, machine: &Machine<'a>) -> Option<(usize, SpiBus<'a>, SpiSensor)> {
        let input = self.input(machine)?;
        let bus = input_buses(machine).nth(input).flatten()?;
        let chip = input_chips(machine).nth(input).flatten()?;
        Some((input, bus, chip))
    }
}

/// The `[extruder_stepper]`s' steppers (by `machine.steppers` index), in
/// printer.cfg's order: klippy creates them with the other extra
/// sections, before the toolhead's rails and extruder.
fn extra_extruder_steppers<'m>(machine: &'m Machine<'_>) -> impl Iterator<Item = usize> + 'm {
    (machine.extruder_steppers.iter())
        .filter(|e| e.name != EXTRUDER)
        .map(|e| e.stepper)
}

/// Calls `f` with each object klippy configures in its config callbacks,
/// in their order: the `[extruder_stepper]`s, the fans and pins but the
/// static ones (`outputs`: how many [`McuSetup::outputs`] there are), the
/// temperature sensors, the rails, then the heaters, the extruder's
/// stepper right after the extruder's heater (or after the heaters if it
/// has none).
fn in_config_order(machine: &Machine<'_>, outputs: usize, mut f: impl FnMut(Object)) {
    extra_extruder_steppers(machine).for_each(|i| f(Object::Stepper(i)));
    let statics = first_static(machine).min(outputs);
    (machine.heaters.len()..statics).for_each(|k| f(Object::Output(k)));
    (0..machine.sensors.len()).for_each(|i| f(Object::Sensor(i)));
    (0..machine.motion_steppers()).for_each(|i| f(Object::Stepper(i)));
    let extruder = machine
        .extruder_steppers
        .iter()
        .find(|e| e.name == EXTRUDER);
    let mut extruder_done = false;
    for (h, heater) in machine.heaters.iter().enumerate() {
        f(Object::Heater(h));
        if heater.name == EXTRUDER {
            if let Some(e) = extruder {
                f(Object::Stepper(e.stepper));
            }
            extruder_done = true;
        }
    }
    if let Some(e) = extruder.filter(|_| !extruder_done) {
        f(Object::Stepper(e.stepper));
    }
}

/// Writes the config commands for MCU `target` to `out` (`setup` made
/// for its clock), one line each, `allocate_oids` first and without
/// `finalize_config`; `pulse_ticks(i)` is stepper `i`'s
/// `step_pulse_ticks`. Returns the ids.
pub fn write_config(
    machine: &Machine<'_>,
    setup: &McuSetup<'_>,
    target: ConfigTarget<'_>,
    pulse_ticks: &dyn Fn(usize) -> u32,
    out: &mut dyn FnMut(&str),
) -> Oids {
    let oids = assign(machine, setup, target.mcu);
    let mut line = Line::new();
    let mut enables = heapless::Vec::new();
    line.emit(out, format_args!("allocate_oids count={}", oids.count));
    // klippy adds a static pin's command, and an SPI chip's
    // `config_spi`, as the section loads, before its config callbacks
    // write the others'.
    for k in first_static(machine)..setup.outputs.len() {
        write_output(machine, setup, target, &oids, k, &mut line, out);
    }
    in_config_order(machine, 0, |object| {
        if let Some((input, bus, _)) = object.spi_chip(machine)
            && let Some(oid) = oids.spi[input]
        {
            let pin = pin_ref(bus.cs_pin).pin;
            line.emit(
                out,
                format_args!("config_spi oid={oid} pin={pin} cs_active_high=0"),
            );
        }
    });
    in_config_order(machine, setup.outputs.len(), |object| match object {
        Object::Stepper(i) => {
            let ticks = pulse_ticks(i);
            write_stepper(machine, &oids, i, ticks, &mut enables, &mut line, out);
        }
        Object::Heater(h) => {
            write_spi_chip(machine, &oids, object, target, &mut line, out);
            write_heater(machine, setup, &oids, h, &mut line, out);
        }
        Object::Output(k) => write_output(machine, setup, target, &oids, k, &mut line, out),
        Object::Sensor(i) => {
            if object.spi_chip(machine).is_some() {
                write_spi_chip(machine, &oids, object, target, &mut line, out);
            } else if let (Some(oid), Some(sensor)) = (oids.sensors[i], machine.sensors.get(i)) {
                let pin = pin_ref(sensor.input.pin()).pin;
                line.emit(out, format_args!("config_analog_in oid={oid} pin={pin}"));
            }
        }
    });
    oids
}

/// The first of [`McuSetup::outputs`] that is a static pin: they come
/// last.
fn first_static(machine: &Machine<'_>) -> usize {
    let a = &machine.accessories;
    machine.heaters.len() + usize::from(machine.fan.is_some()) + a.fans.len() + a.output_pins.len()
}

/// Writes fan or pin output `k` of `setup`, if on MCU `target`.
fn write_output(
    machine: &Machine<'_>,
    setup: &McuSetup<'_>,
    target: ConfigTarget<'_>,
    oids: &Oids,
    k: usize,
    line: &mut Line,
    out: &mut dyn FnMut(&str),
) {
    let Some(&(written, config)) = setup.outputs.get(k) else {
        return;
    };
    let pin = pin_ref(written);
    if pin.mcu != target.mcu {
        return;
    }
    if k >= first_static(machine) {
        let on = u8::from(!pin.inverted);
        line.emit(
            out,
            format_args!("set_digital_out pin={} value={on}", pin.pin),
        );
        return;
    }
    let Some(oid) = oids.outputs.get(k).copied().flatten() else {
        return;
    };
    // Levels as fractions of full scale, inverted for a `!` pin.
    let full = full_scale(config.kind);
    let level = |value: u32| {
        let f = if full == 0 {
            f64::from(u8::from(value != 0))
        } else {
            f64::from(value) / f64::from(full)
        };
        if pin.inverted { 1.0 - f } else { f }
    };
    let (start, shutdown) = (level(config.value), level(config.default));
    if let (OutputKind::HardPwm { cycle_ticks }, Some(levels)) = (config.kind, setup.levels.get(k))
    {
        // klippy writes printer.cfg's levels (inverted for a `!` pin)
        // times PWM_MAX with `%d`: truncated.
        let duty = |level: f64| {
            let level = if pin.inverted { 1.0 - level } else { level };
            (level.clamp(0.0, 1.0) * f64::from(target.pwm_max)) as u32
        };
        let (start, shutdown) = (levels.start, levels.shutdown);
        line.emit(
            out,
            format_args!(
                "config_pwm_out oid={oid} pin={} cycle_ticks={cycle_ticks} value={} default_value={} max_duration={}",
                pin.pin,
                duty(start),
                duty(shutdown),
                config.max_duration
            ),
        );
        return;
    }
    line.emit(
        out,
        format_args!(
            "config_digital_out oid={oid} pin={} value={} default_value={} max_duration={}",
            pin.pin,
            u8::from(start >= 1.0),
            u8::from(shutdown >= 0.5),
            config.max_duration
        ),
    );
    if let OutputKind::Digital { cycle_ticks } = config.kind
        && cycle_ticks > 0
    {
        line.emit(
            out,
            format_args!("set_digital_out_pwm_cycle oid={oid} cycle_ticks={cycle_ticks}"),
        );
    }
}

/// Writes the bus and the reader of `object`'s SPI chip, if it has one
/// on this MCU, as klippy's config callbacks of its `MCU_SPI` and its
/// sensor do. A bit-banged bus is not written (refused as printer.cfg
/// loads).
fn write_spi_chip(
    machine: &Machine<'_>,
    oids: &Oids,
    object: Object,
    target: ConfigTarget<'_>,
    line: &mut Line,
    out: &mut dyn FnMut(&str),
) {
    let Some((input, bus, chip)) = object.spi_chip(machine) else {
        return;
    };
    let (Some(spi), Some(reader)) = (oids.spi[input], reader_oid(oids, machine, input)) else {
        return;
    };
    let SpiBusPins::Hardware(name) = bus.pins else {
        return;
    };
    let (speed, mode) = (bus.speed, bus.mode);
    let name = name.unwrap_or(target.spi_bus);
    line.emit(
        out,
        format_args!("spi_set_bus oid={spi} spi_bus={name} mode={mode} rate={speed}"),
    );
    let chip = NAMES[chip.chip as usize];
    line.emit(
        out,
        format_args!("config_thermocouple oid={reader} spi_oid={spi} thermocouple_type={chip}"),
    );
}

/// The reader object of io input `input` (the heaters', then the
/// temperature sensors'): its ADC input or SPI chip.
pub fn reader_oid(oids: &Oids, machine: &Machine<'_>, input: usize) -> Option<u8> {
    match input.checked_sub(machine.heaters.len()) {
        None => oids.heaters.get(input)?.0,
        Some(i) => *oids.sensors.get(i)?,
    }
}

/// Writes heater `h`'s sensor (on an ADC pin) and output, those on this
/// MCU.
fn write_heater(
    machine: &Machine<'_>,
    setup: &McuSetup<'_>,
    oids: &Oids,
    h: usize,
    line: &mut Line,
    out: &mut dyn FnMut(&str),
) {
    let (Some((adc, pwm)), Some(heater), Some((_, output))) = (
        oids.heaters.get(h),
        machine.heaters.get(h),
        setup.outputs.get(h),
    ) else {
        return;
    };
    if let Some(adc) = adc.filter(|_| oids.spi[h].is_none()) {
        let pin = pin_ref(heater.sensor_pin).pin;
        line.emit(out, format_args!("config_analog_in oid={adc} pin={pin}"));
    }
    let Some(pwm) = pwm else {
        return;
    };
    let heater_pin = pin_ref(heater.heater_pin);
    let (value, max) = (u8::from(heater_pin.inverted), output.max_duration);
    line.emit(
        out,
        format_args!(
            "config_digital_out oid={pwm} pin={} value={value} default_value={value} max_duration={max}",
            heater_pin.pin
        ),
    );
    if let OutputKind::Digital { cycle_ticks } = output.kind {
        line.emit(
            out,
            format_args!("set_digital_out_pwm_cycle oid={pwm} cycle_ticks={cycle_ticks}"),
        );
    }
}

/// Gives out the object ids as klippy does (see the module doc).
fn assign(machine: &Machine<'_>, setup: &McuSetup<'_>, mcu: &str) -> Oids {
    let mut oids = Oids::default();
    let mut next = 0u8;
    let mut take = || {
        let oid = next;
        next += 1;
        oid
    };
    let on_mcu = |pin: Option<&str>| pin.is_some_and(|p| pin_ref(p).mcu == mcu);
    // Created with their objects, as printer.cfg loads: endstops (with
    // their trsyncs) and steppers, an SPI chip's bus and reader.
    in_config_order(machine, 0, |object| {
        if let Object::Stepper(i) = object {
            let stepper = &machine.steppers[i];
            if on_mcu(stepper.endstop_pin) {
                oids.endstops[i] = Some((take(), take()));
            }
            if on_mcu(Some(stepper.step_pin)) {
                oids.steppers[i] = Some(take());
            }
        }
        if let Some((input, bus, _)) = object.spi_chip(machine)
            && on_mcu(Some(bus.cs_pin))
        {
            oids.spi[input] = Some(take());
            let reader = match object {
                Object::Heater(h) => &mut oids.heaters[h].0,
                _ => &mut oids.sensors[input - machine.heaters.len()],
            };
            *reader = Some(take());
        }
    });
    // Given out as the config is written.
    in_config_order(machine, setup.outputs.len(), |object| match object {
        Object::Stepper(i) => {
            let stepper = &machine.steppers[i];
            // Its enable pin may be on another MCU than the stepper.
            if on_mcu(stepper.enable_pin) {
                // Steppers sharing an enable pin share its output (the
                // first one's, given out already).
                let shared = (machine.steppers.iter().zip(oids.enables))
                    .filter(|(other, _)| other.enable_pin == stepper.enable_pin)
                    .find_map(|(_, oid)| oid);
                oids.enables[i] = Some(shared.unwrap_or_else(&mut take));
            }
        }
        Object::Heater(h) => {
            // klippy creates the sensor's ADC (an SPI chip's reader is
            // given already), then the heater's output.
            let heater = machine
                .heaters
                .get(h)
                .filter(|_| setup.outputs.get(h).is_some());
            if on_mcu(heater.map(|heater| heater.sensor_pin)) && oids.spi[h].is_none() {
                oids.heaters[h].0 = Some(take());
            }
            if on_mcu(heater.map(|heater| heater.heater_pin)) {
                oids.heaters[h].1 = Some(take());
            }
        }
        Object::Output(k) => {
            let on_this = (setup.outputs.get(k)).is_some_and(|(pin, _)| on_mcu(Some(pin)));
            if on_this {
                oids.outputs[k] = Some(take());
            }
        }
        Object::Sensor(i) => {
            // On an ADC pin of this MCU (an SPI chip or the MCU's own
            // sensor has no analog input).
            let adc = machine.sensors.get(i).and_then(|s| match s.input {
                SensorInput::Adc { pin, .. } => Some(pin),
                _ => None,
            });
            if on_mcu(adc) {
                oids.sensors[i] = Some(take());
            }
        }
    });
    oids.count = next;
    oids
}

/// Writes stepper `i`'s endstop, trsync, stepper and enable pin, those on
/// this MCU; `enables`: the enable outputs written so far.
fn write_stepper(
    machine: &Machine<'_>,
    oids: &Oids,
    i: usize,
    pulse_ticks: u32,
    enables: &mut heapless::Vec<u8, MAX_STEPPERS>,
    line: &mut Line,
    out: &mut dyn FnMut(&str),
) {
    let stepper = &machine.steppers[i];
    if let (Some((endstop, trsync)), Some(pin)) = (oids.endstops[i], stepper.endstop_pin) {
        let pin = pin_ref(pin);
        line.emit(
            out,
            format_args!(
                "config_endstop oid={endstop} pin={} pull_up={}",
                pin.pin,
                u8::from(pin.pull_up)
            ),
        );
        line.emit(out, format_args!("config_trsync oid={trsync}"));
    }
    if let Some(oid) = oids.steppers[i] {
        let (step, dir) = (pin_ref(stepper.step_pin), pin_ref(stepper.dir_pin));
        line.emit(
        out,
        format_args!(
            "config_stepper oid={oid} step_pin={} dir_pin={} invert_step={} step_pulse_ticks={pulse_ticks}",
            step.pin,
            dir.pin,
            u8::from(step.inverted)
        ),
    );
    }
    // A shared enable output is configured with its first stepper (on
    // its own MCU, which may not be the stepper's).
    if let (Some(enable), Some(pin)) = (oids.enables[i], stepper.enable_pin)
        && !enables.contains(&enable)
        && enables.push(enable).is_ok()
    {
        let pin = pin_ref(pin);
        let off = u8::from(pin.inverted);
        line.emit(
            out,
            format_args!(
                "config_digital_out oid={enable} pin={} value={off} default_value={off} max_duration=0",
                pin.pin
            ),
        );
    }
}

/// A command line being written.
struct Line(heapless::String<128>);

impl Line {
    fn new() -> Self {
        Self(heapless::String::new())
    }

    /// Writes `args` and hands the line to `out`.
    fn emit(&mut self, out: &mut dyn FnMut(&str), args: fmt::Arguments<'_>) {
        self.0.clear();
        let _ = self.0.write_fmt(args);
        out(&self.0);
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::heaters::tests::typical_mcu;
    use onechip_config::Config;

    /// A cartesian printer with a secondary MCU `ext`: its Z stepper's
    /// `z_pins` (step, dir, enable options), then `extra` sections.
    fn with_ext(z_pins: &str, extra: &str) -> std::string::String {
        std::format!(
            "[mcu ext]\nserial: /dev/null\n\
             [printer]\nkinematics: cartesian\nmax_velocity: 300\nmax_accel: 3000\n\
             [stepper_x]\nstep_pin: PF13\ndir_pin: PF12\nmicrosteps: 16\n\
             rotation_distance: 40\nposition_endstop: 0\nposition_max: 200\n\
             [stepper_y]\nstep_pin: PG0\ndir_pin: PG1\nmicrosteps: 16\nrotation_distance: 40\n\
             position_endstop: 0\nposition_max: 200\n\
             [stepper_z]\n{z_pins}\
             microsteps: 16\nrotation_distance: 8\nposition_endstop: 0\nposition_max: 200\n\
             {extra}"
        )
    }

    /// The config lines `ext` gets for printer.cfg `text` (16 MHz, 1023
    /// ADC counts), and its object ids.
    fn ext_config(text: &str) -> (std::vec::Vec<std::string::String>, Oids) {
        let config = Config::parse("printer.cfg", text).expect("config");
        let machine = Machine::from_config(&config).expect("machine");
        let setup = McuSetup::new(&machine, 16e6, 1023, typical_mcu(), 0);
        let mut lines = std::vec::Vec::new();
        let ext = ConfigTarget {
            mcu: "ext",
            pwm_max: 255,
            spi_bus: "spi",
        };
        let oids = write_config(&machine, &setup, ext, &|_| 32, &mut |l| {
            lines.push(std::string::String::from(l));
        });
        (lines, oids)
    }

    #[test]
    fn fans_and_pins_on_a_secondary_are_configured_as_klippys_pwm_and_digital_outs() {
        let text = with_ext(
            "step_pin: ext:PB0\ndir_pin: ext:PB1\nenable_pin: !ext:PA1\n",
            "[fan]\npin: ext:PC0\n\
             [fan_generic aux]\npin: PA8\n\
             [heater_fan hot]\npin: !ext:PC1\nheater:\n\
             [output_pin light]\npin: ext:PC2\nvalue: 1\nshutdown_value: 1\nmaximum_mcu_duration: 2\n\
             [static_digital_output leds]\npins: ext:PC3, !ext:PC4\n",
        );
        let (lines, oids) = ext_config(&text);
        // The stepper's oid is given at creation; the outputs' (and the
        // enable pin's) as their config is written: the fans and pins
        // first (klippy loads them before the toolhead).
        let expected = [
            "allocate_oids count=5",
            "set_digital_out pin=PC3 value=1",
            "set_digital_out pin=PC4 value=0",
            "config_digital_out oid=1 pin=PC0 value=0 default_value=0 max_duration=0",
            "set_digital_out_pwm_cycle oid=1 cycle_ticks=160000",
            "config_digital_out oid=2 pin=PC1 value=1 default_value=0 max_duration=0",
            "set_digital_out_pwm_cycle oid=2 cycle_ticks=160000",
            "config_digital_out oid=3 pin=PC2 value=1 default_value=1 max_duration=32000000",
            "config_stepper oid=0 step_pin=PB0 dir_pin=PB1 invert_step=0 step_pulse_ticks=32",
            "config_digital_out oid=4 pin=PA1 value=1 default_value=1 max_duration=0",
        ];
        assert_eq!(lines, expected);
        // Io order: no heaters, the part fan, the named fans, the pin.
        assert_eq!(oids.outputs[..4], [Some(1), None, Some(2), Some(3)]);
        assert_eq!(oids.enables[2], Some(4));
    }

    #[test]
    fn hardware_pwm_outputs_on_a_secondary_are_klippys_config_pwm_out_scaled_by_its_pwm_max() {
        let text = with_ext(
            "step_pin: ext:PB0\ndir_pin: ext:PB1\n",
            "[fan]\npin: ext:PH6\nhardware_pwm: True\ncycle_time: 0.002\nshutdown_speed: 0.5\n\
             [output_pin tool]\npin: !ext:PB4\npwm: True\nhardware_pwm: True\n\
             cycle_time: 0.001\nvalue: 0.3\nshutdown_value: 0.3\nmaximum_mcu_duration: 2\n",
        );
        let (lines, oids) = ext_config(&text);
        // klippy: cycle_ticks = int(cycle_time * 16 MHz); values =
        // int(level * 255), the tool's inverted (1 - 0.3).
        let expected = [
            "allocate_oids count=3",
            "config_pwm_out oid=1 pin=PH6 cycle_ticks=32000 value=0 default_value=127 max_duration=0",
            "config_pwm_out oid=2 pin=PB4 cycle_ticks=16000 value=178 default_value=178 max_duration=32000000",
            "config_stepper oid=0 step_pin=PB0 dir_pin=PB1 invert_step=0 step_pulse_ticks=32",
        ];
        assert_eq!(lines, expected);
        assert_eq!(oids.outputs[..2], [Some(1), Some(2)]);
    }

    #[test]
    fn an_spi_chip_on_a_secondary_is_klippys_mcu_spi_and_thermocouple_reader() {
        let text = with_ext(
            "step_pin: ext:PB4\ndir_pin: ext:PB5\n",
            "[temperature_sensor chamber]\nsensor_type: MAX31865\nsensor_pin: ext:PB0\n\
             rtd_reference_r: 430\n\
             [temperature_sensor here]\nsensor_type: MAX31855\nsensor_pin: PA4\n",
        );
        let (lines, oids) = ext_config(&text);
        // The chip's bus and reader take their ids as the section loads
        // (before the Z stepper's); `config_spi` is added then, the
        // rest by their config callbacks.
        let expected = [
            "allocate_oids count=3",
            "config_spi oid=0 pin=PB0 cs_active_high=0",
            "spi_set_bus oid=0 spi_bus=spi mode=1 rate=4000000",
            "config_thermocouple oid=1 spi_oid=0 thermocouple_type=MAX31865",
            "config_stepper oid=2 step_pin=PB4 dir_pin=PB5 invert_step=0 step_pulse_ticks=32",
        ];
        assert_eq!(lines, expected);
        assert_eq!(
            (oids.spi[0], oids.sensors[0], oids.sensors[1]),
            (Some(0), Some(1), None)
        );
    }

    #[test]
    fn an_enable_pin_is_configured_on_its_own_mcu_whichever_steps_its_stepper() {
        let text = with_ext("step_pin: PB4\ndir_pin: PB5\nenable_pin: !ext:PA1\n", "");
        let (lines, oids) = ext_config(&text);
        let expected = [
            "allocate_oids count=1",
            "config_digital_out oid=0 pin=PA1 value=1 default_value=1 max_duration=0",
        ];
        assert_eq!(lines, expected);
        assert_eq!((oids.steppers[2], oids.enables[2]), (None, Some(0)));
    }

    #[test]
    fn temperature_sensors_are_configured_on_the_mcu_of_their_adc_pin() {
        let text = with_ext(
            "step_pin: PB0\ndir_pin: PB1\n",
            "[temperature_sensor here]\nsensor_type: EPCOS 100K B57560G104F\nsensor_pin: PF5\n\
             [temperature_sensor there]\nsensor_type: EPCOS 100K B57560G104F\nsensor_pin: ext:PA2\n",
        );
        let (lines, oids) = ext_config(&text);
        assert_eq!(
            lines,
            ["allocate_oids count=1", "config_analog_in oid=0 pin=PA2"]
        );
        assert_eq!(oids.sensors[..2], [None, Some(0)]);
    }

    #[test]
    fn pins_name_their_mcu_after_the_modifiers() {
        let p = pin_ref("!ext:PA4");
        assert_eq!(
            (p.mcu, p.pin, p.inverted, p.pull_up),
            ("ext", "PA4", true, false)
        );
        let p = pin_ref("^PG6");
        assert_eq!((p.mcu, p.pin, p.pull_up), (MAIN, "PG6", true));
        let p = pin_ref("~!mcu:PB1");
        assert_eq!((p.mcu, p.pin, p.inverted), (MAIN, "PB1", true));
    }
}
