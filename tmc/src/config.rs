//! `[tmcXXXX stepper]` sections to register values, option by option as
//! Klipper's `tmc*.py` read them (same names, defaults, bounds and order).

use super::current::CurrentScale;
use super::{DriverKind, RegisterFile, RegistersFull};
use core::fmt::Write;
use onechip_config::{Bounds, Config, ConfigError, Section};

/// Most TMC driver sections a config may have.
pub const MAX_DRIVERS: usize = 10;
/// The largest TSTEP-based threshold (20 bits).
pub const TSTEP_MAX: u32 = 0xfffff;

/// How the driver is wired to the MCU.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Bus<'a> {
    /// Single-wire UART (TMC2208, TMC2209).
    Uart {
        /// `uart_pin` (receive, and send without `tx_pin`).
        uart_pin: &'a str,
        /// `tx_pin`, if the UART sends on its own pin.
        tx_pin: Option<&'a str>,
        /// `select_pins` of an analog mux in front of the UART, if any.
        select_pins: Option<&'a str>,
        /// `uart_address` (0..=3 for the TMC2209, 0 for the TMC2208).
        address: u8,
    },
    /// SPI (TMC2130, TMC2240, TMC2660, TMC5160).
    Spi {
        /// `cs_pin`.
        cs_pin: &'a str,
        /// `spi_bus`, if a hardware bus is named.
        spi_bus: Option<&'a str>,
        /// `spi_software_miso_pin`, `…_mosi_pin`, `…_sclk_pin` for a
        /// bit-banged bus.
        software: Option<[&'a str; 3]>,
        /// `spi_speed`, Hz.
        speed: u32,
        /// `chain_position` (1 without a chain).
        chain_position: u8,
        /// `chain_length` (1 without a chain).
        chain_length: u8,
    },
}

impl<'a> TmcDriver<'a> {
    /// Its name in G-code (`STEPPER=`) and in Klipper's bus messages: the
    /// last word of its stepper's section name (`e1` for
    /// `extruder_stepper e1`).
    pub fn name(&self) -> &'a str {
        let stepper = self.stepper;
        stepper
            .rsplit(char::is_whitespace)
            .next()
            .unwrap_or(stepper)
    }
}

/// One driver as its section configures it.
#[derive(Debug, Clone, PartialEq)]
pub struct TmcDriver<'a> {
    /// The driver type.
    pub kind: DriverKind,
    /// The stepper it drives (`stepper_x`), as the section names it.
    pub stepper: &'a str,
    /// Its section's name as written (`tmc2209 stepper_x`).
    pub section: &'a str,
    /// How it is wired.
    pub bus: Bus<'a>,
    /// `diag_pin` / `diag0_pin` / `diag1_pin`, if set (sensorless homing),
    /// and the GCONF field that routes stall detection to it (none on the
    /// TMC2209).
    pub diag: Option<(&'a str, Option<&'static str>)>,
    /// How current becomes bits.
    pub scale: CurrentScale,
    /// The largest current the driver accepts, A.
    pub max_current: f64,
    /// The requested run current, A.
    pub run_current: f64,
    /// The requested hold current, A (`None` on the TMC2660).
    pub hold_current: Option<f64>,
    /// `idle_current_percent` (TMC2660; 100 elsewhere).
    pub idle_current_percent: u8,
    /// The stepper's distance per microstep, mm (for VELOCITY).
    pub step_dist: f64,
    /// The register values, as Klipper's config leaves them.
    pub regs: RegisterFile,
}

impl TmcDriver<'_> {
    /// The pin naming the driver's bus (its UART pin or chip select),
    /// without pull-up or inversion marks: drivers with the same one
    /// share the wire.
    pub fn port(&self) -> &str {
        let pin = match self.bus {
            Bus::Uart { uart_pin, .. } => uart_pin,
            Bus::Spi { cs_pin, .. } => cs_pin,
        };
        bare_pin(pin)
    }

    /// TSTEP for `velocity` mm/s (Klipper's `TMCtstepHelper`): the
    /// driver's clock ticks per 1/256 microstep at that speed, rounded,
    /// at most 0xfffff; 0xfffff for 0. `None` on the TMC2660.
    pub fn tstep(&self, velocity: f64) -> Option<u32> {
        tstep(self.kind, self.regs.get("mres"), self.step_dist, velocity)
    }
}

/// `pin` without `^`, `~`, `!` marks and spaces.
pub fn bare_pin(pin: &str) -> &str {
    pin.trim_start_matches(['^', '~', '!', ' '])
}

fn tstep(kind: DriverKind, mres: i64, step_dist: f64, velocity: f64) -> Option<u32> {
    let freq = kind.clock_hz()?;
    if velocity <= 0.0 {
        return Some(TSTEP_MAX);
    }
    let step_dist_256 = step_dist / f64::from(1u32 << mres.clamp(0, 8));
    let ticks = (freq * step_dist_256 / velocity + 0.5) as i64;
    Some(ticks.clamp(0, i64::from(TSTEP_MAX)) as u32)
}

/// A stepper section's distance per microstep, mm (the planner's
/// `machine::step_distance`, Klipper's `parse_step_distance`).
pub type StepDistance = for<'c, 'a> fn(&Section<'c, 'a>) -> Result<f64, ConfigError<'c>>;

/// Reads every TMC driver section of `config`, in file order, into
/// `drivers` (emptied first; filled in place: ten drivers are some 3.5 KB,
/// not to be returned through a frame), and checks drivers that share a
/// wire (UART addresses, SPI chain positions).
pub fn read_all<'c, 'a>(
    config: &'c Config<'a>,
    step_distance: StepDistance,
    drivers: &mut heapless::Vec<TmcDriver<'a>, MAX_DRIVERS>,
) -> Result<(), ConfigError<'c>> {
    drivers.clear();
    for name in config.section_names() {
        if DriverKind::of_section(name).is_none()
            || drivers
                .iter()
                .any(|d| DriverKind::of_section(name) == Some((d.kind, d.stepper)))
        {
            continue;
        }
        let Some(section) = config.section(name) else {
            continue;
        };
        let driver = read(config, &section, step_distance)?;
        check_shared(&section, &driver, drivers)?;
        drivers
            .push(driver)
            .map_err(|_| section.error_for("run_current", "is one TMC driver too many"))?;
    }
    Ok(())
}

/// Refuses `driver` if it clashes with one already read on its wire.
fn check_shared<'c>(
    section: &Section<'c, '_>,
    driver: &TmcDriver<'_>,
    others: &[TmcDriver<'_>],
) -> Result<(), ConfigError<'c>> {
    for other in others.iter().filter(|o| o.port() == driver.port()) {
        match (driver.bus, other.bus) {
            (
                Bus::Uart {
                    address,
                    select_pins,
                    ..
                },
                Bus::Uart {
                    address: a,
                    select_pins: s,
                    ..
                },
            ) if address == a && select_pins == s => {
                return Err(section.error_for(
                    "uart_address",
                    "must differ from other drivers on the same uart_pin (Klipper: \
                     shared TMC uarts need unique address or select_pins polarity)",
                ));
            }
            (
                Bus::Spi {
                    chain_position,
                    chain_length,
                    ..
                },
                Bus::Spi {
                    chain_position: p,
                    chain_length: l,
                    ..
                },
            ) => {
                if chain_length == 1 {
                    return Err(section.error_for(
                        "cs_pin",
                        "is another driver's cs_pin (set chain_length and chain_position)",
                    ));
                }
                if chain_length != l {
                    return Err(section.error_for(
                        "chain_length",
                        "must be the same on every driver of the chain",
                    ));
                }
                if chain_position == p {
                    return Err(section.error_for(
                        "chain_position",
                        "is another driver's (TMC SPI chain can not have duplicate position)",
                    ));
                }
            }
            _ => {}
        }
    }
    Ok(())
}

/// Reads one TMC driver section.
// Not inlined: its reader and register file would widen `read_all`'s
// frame past short stack addressing (1 KB more flash).
#[inline(never)]
pub fn read<'c, 'a>(
    config: &'c Config<'a>,
    section: &Section<'c, 'a>,
    step_distance: StepDistance,
) -> Result<TmcDriver<'a>, ConfigError<'c>> {
    let (kind, stepper_name) = DriverKind::of_section(section.name_in_file())
        .ok_or(section.error_for("run_current", "is in a section that is not a TMC driver"))?;
    let Some(stepper) = config.section(stepper_name) else {
        // Klipper: "Could not find config section '[…]' required by tmc
        // driver"; named at the driver's section header.
        let (file, line) = section.locate("[");
        return Err(ConfigError {
            file,
            line,
            kind: onechip_config::ConfigErrorKind::MissingSection(stepper_name),
        });
    };
    let mut r = Reader {
        section,
        regs: RegisterFile::new(kind),
        error: None,
    };
    let bus = read_bus(section, kind)?;
    let diag = match kind {
        DriverKind::Tmc2209 => opt(section, "diag_pin").map(|p| (p, None)),
        DriverKind::Tmc2130 | DriverKind::Tmc2240 | DriverKind::Tmc5160 => {
            match opt(section, "diag0_pin") {
                Some(pin) => Some((pin, Some("diag0_stall"))),
                None => section
                    .get_opt("diag1_pin")
                    .map(|p| (p, Some("diag1_stall"))),
            }
        }
        DriverKind::Tmc2208 | DriverKind::Tmc2660 => None,
    };
    let defaults = Defaults::of(kind);
    for &(field, value) in defaults.fixed {
        r.set(field, i64::from(value));
    }
    let current = read_current(&mut r, kind)?;
    // Microsteps come from the stepper's section.
    let microsteps = stepper.get_int("microsteps", None, Some(1))?;
    let mres = match microsteps {
        1..=256 if (microsteps as u32).is_power_of_two() => {
            8 - i64::from((microsteps as u32).trailing_zeros())
        }
        _ => {
            return Err(stepper.error_for(
                "microsteps",
                "is not a valid choice for a TMC driver (1, 2, 4, ... 256)",
            ));
        }
    };
    r.set("mres", mres);
    let interpolate = section.get_bool("interpolate", true)?;
    r.set("intpol", i64::from(interpolate));
    let step_dist = step_distance(&stepper)?;
    for &(field, value) in defaults.fixed_late {
        r.set(field, i64::from(value));
    }
    r.fields(defaults.pre);
    if let Some((coolstep, high)) = defaults.thresholds {
        r.thresholds(step_dist, coolstep, high);
    }
    r.fields(defaults.post);
    if kind == DriverKind::Tmc2660
        && r.regs.get("chm") == 0
        && r.regs.get("hstrt") + r.regs.get("hend") > 15
    {
        let option = section.option_name("driver_hend").unwrap_or("driver_HEND");
        return Err(section.error_for(option, "plus driver_HSTRT must be at most 15"));
    }
    if let Some(e) = r.error {
        return Err(e);
    }
    Ok(TmcDriver {
        kind,
        stepper: stepper_name,
        section: section.name_in_file(),
        bus,
        diag,
        scale: current.scale,
        max_current: current.max,
        run_current: current.run,
        hold_current: current.hold,
        idle_current_percent: current.idle_percent,
        step_dist,
        regs: r.regs,
    })
}

/// A field and its default (or fixed value).
type FieldValue = (&'static str, u32);

/// What Klipper sets for one driver type, in its order.
struct Defaults {
    /// Fields set (not from the config) before the currents.
    fixed: &'static [FieldValue],
    /// Fields set (not from the config) after the microsteps.
    fixed_late: &'static [FieldValue],
    /// `driver_XXX` fields before the velocity thresholds.
    pre: &'static [FieldValue],
    /// Which thresholds it has: (coolstep, high velocity); `None`: none
    /// at all (no stealthchop_threshold either).
    thresholds: Option<(bool, bool)>,
    /// `driver_XXX` fields after them.
    post: &'static [FieldValue],
}

/// Klipper's default microstep wave table (the drivers' reset values).
const WAVE_TABLE: [FieldValue; 17] = [
    ("mslut0", 0xAAAA_B554),
    ("mslut1", 0x4A95_54AA),
    ("mslut2", 0x2449_2929),
    ("mslut3", 0x1010_4222),
    ("mslut4", 0xFBFF_FFFF),
    ("mslut5", 0xB5BB_777D),
    ("mslut6", 0x4929_5556),
    ("mslut7", 0x0040_4222),
    ("w0", 2),
    ("w1", 1),
    ("w2", 1),
    ("w3", 1),
    ("x1", 128),
    ("x2", 255),
    ("x3", 255),
    ("start_sin", 0),
    ("start_sin90", 247),
];

/// The wave table, then the TMC2240's offset_sin90.
const WAVE_TABLE_2240: [FieldValue; 18] = {
    let mut t = [("offset_sin90", 0); 18];
    let mut i = 0;
    while i < 17 {
        t[i] = WAVE_TABLE[i];
        i += 1;
    }
    t
};

const TMC2130_POST: &[FieldValue] = &[
    ("toff", 4),
    ("hstrt", 0),
    ("hend", 7),
    ("tbl", 1),
    ("vhighfs", 0),
    ("vhighchm", 0),
    ("semin", 0),
    ("seup", 0),
    ("semax", 0),
    ("sedn", 0),
    ("seimin", 0),
    ("sgt", 0),
    ("sfilt", 0),
    ("iholddelay", 8),
    ("pwm_ampl", 128),
    ("pwm_grad", 4),
    ("pwm_freq", 1),
    ("pwm_autoscale", 1),
    ("tpowerdown", 0),
];

/// The TMC2208's fields after the thresholds: CHOPCONF, IHOLD_IRUN,
/// PWMCONF, TPOWERDOWN.
const TMC2208_POST: &[FieldValue] = &[
    ("multistep_filt", 1),
    ("toff", 3),
    ("hstrt", 5),
    ("hend", 0),
    ("tbl", 2),
    ("iholddelay", 8),
    ("pwm_ofs", 36),
    ("pwm_grad", 14),
    ("pwm_freq", 1),
    ("pwm_autoscale", 1),
    ("pwm_autograd", 1),
    ("freewheel", 0),
    ("pwm_reg", 8),
    ("pwm_lim", 12),
    ("tpowerdown", 20),
];

/// The TMC2209's: the TMC2208's with COOLCONF before IHOLD_IRUN and
/// SGTHRS last.
const TMC2209_POST: &[FieldValue] = &[
    ("multistep_filt", 1),
    ("toff", 3),
    ("hstrt", 5),
    ("hend", 0),
    ("tbl", 2),
    ("semin", 0),
    ("seup", 0),
    ("semax", 0),
    ("sedn", 0),
    ("seimin", 0),
    ("iholddelay", 8),
    ("pwm_ofs", 36),
    ("pwm_grad", 14),
    ("pwm_freq", 1),
    ("pwm_autoscale", 1),
    ("pwm_autograd", 1),
    ("freewheel", 0),
    ("pwm_reg", 8),
    ("pwm_lim", 12),
    ("tpowerdown", 20),
    ("sgthrs", 0),
];

const TMC5160_POST: &[FieldValue] = &[
    ("multistep_filt", 1),
    ("toff", 3),
    ("hstrt", 5),
    ("hend", 2),
    ("fd3", 0),
    ("disfdcc", 0),
    ("chm", 0),
    ("tbl", 2),
    ("vhighfs", 0),
    ("vhighchm", 0),
    ("tpfd", 4),
    ("diss2g", 0),
    ("diss2vs", 0),
    ("semin", 0),
    ("seup", 0),
    ("semax", 0),
    ("sedn", 0),
    ("seimin", 0),
    ("sgt", 0),
    ("sfilt", 0),
    ("drvstrength", 0),
    ("bbmclks", 4),
    ("bbmtime", 0),
    ("filt_isense", 0),
    ("iholddelay", 6),
    ("pwm_ofs", 30),
    ("pwm_grad", 0),
    ("pwm_freq", 0),
    ("pwm_autoscale", 1),
    ("pwm_autograd", 1),
    ("freewheel", 0),
    ("pwm_reg", 4),
    ("pwm_lim", 12),
    ("tpowerdown", 10),
];

const TMC2240_POST: &[FieldValue] = &[
    ("multistep_filt", 1),
    ("toff", 3),
    ("hstrt", 5),
    ("hend", 2),
    ("fd3", 0),
    ("disfdcc", 0),
    ("chm", 0),
    ("tbl", 2),
    ("vhighfs", 0),
    ("vhighchm", 0),
    ("tpfd", 4),
    ("diss2g", 0),
    ("diss2vs", 0),
    ("semin", 0),
    ("seup", 0),
    ("semax", 0),
    ("sedn", 0),
    ("seimin", 0),
    ("sgt", 0),
    ("sfilt", 0),
    ("iholddelay", 6),
    ("irundelay", 4),
    ("pwm_ofs", 29),
    ("pwm_grad", 0),
    ("pwm_freq", 0),
    ("pwm_autoscale", 1),
    ("pwm_autograd", 1),
    ("freewheel", 0),
    ("pwm_reg", 4),
    ("pwm_lim", 12),
    ("tpowerdown", 10),
    ("sg4_angle_offset", 1),
];

/// CHOPCONF, SMARTEN, SGCSCONF and DRVCONF in Klipper's order.
const TMC2660_POST: &[FieldValue] = &[
    ("tbl", 2),
    ("rndtf", 0),
    ("hdec", 0),
    ("chm", 0),
    ("hend", 3),
    ("hstrt", 3),
    ("toff", 4),
    ("seimin", 0),
    ("sedn", 0),
    ("semax", 0),
    ("seup", 0),
    ("semin", 0),
    ("sfilt", 0),
    ("sgt", 0),
    ("slph", 0),
    ("slpl", 0),
    ("diss2g", 0),
    ("ts2g", 3),
];

impl Defaults {
    fn of(kind: DriverKind) -> Self {
        let none: &[FieldValue] = &[];
        match kind {
            DriverKind::Tmc2130 => Self {
                fixed: none,
                fixed_late: none,
                pre: &WAVE_TABLE,
                thresholds: Some((true, true)),
                post: TMC2130_POST,
            },
            DriverKind::Tmc2208 | DriverKind::Tmc2209 => {
                let is_2209 = kind == DriverKind::Tmc2209;
                Self {
                    // The TMC2209 answers shared UARTs after a delay.
                    fixed: if is_2209 {
                        &[("pdn_disable", 1), ("senddelay", 2)]
                    } else {
                        &[("pdn_disable", 1)]
                    },
                    fixed_late: &[("mstep_reg_select", 1)],
                    pre: none,
                    thresholds: Some((is_2209, false)),
                    post: if is_2209 { TMC2209_POST } else { TMC2208_POST },
                }
            }
            DriverKind::Tmc5160 | DriverKind::Tmc2240 => {
                let is_2240 = kind == DriverKind::Tmc2240;
                Self {
                    fixed: none,
                    fixed_late: none,
                    pre: if is_2240 {
                        &WAVE_TABLE_2240
                    } else {
                        &WAVE_TABLE
                    },
                    thresholds: Some((true, true)),
                    post: if is_2240 { TMC2240_POST } else { TMC5160_POST },
                }
            }
            // DRVCTRL in step/dir mode.
            DriverKind::Tmc2660 => Self {
                fixed: &[("sdoff", 0)],
                fixed_late: none,
                pre: none,
                thresholds: None,
                post: TMC2660_POST,
            },
        }
    }
}

/// Currents as a section sets them.
struct Currents {
    scale: CurrentScale,
    max: f64,
    run: f64,
    hold: Option<f64>,
    idle_percent: u8,
}

/// Reads run/hold current and the resistor options, and sets the current
/// fields.
fn read_current<'c>(
    r: &mut Reader<'_, 'c, '_>,
    kind: DriverKind,
) -> Result<Currents, ConfigError<'c>> {
    let s = r.section;
    let upto = |max: f64| Bounds {
        above: Some(0.0),
        maxval: Some(max),
        ..Bounds::NONE
    };
    if kind == DriverKind::Tmc2660 {
        let bounds = Bounds {
            minval: Some(0.1),
            maxval: Some(2.4),
            ..Bounds::NONE
        };
        let run = s.get_float("run_current", None, bounds)?;
        let sense = s.get_float("sense_resistor", None, Bounds::POSITIVE)?;
        let scale = CurrentScale::Vsense {
            resistance: sense,
            vref_high: 0.310,
            vref_low: 0.165,
        };
        let bits = scale.bits(run, run);
        r.set("cs", i64::from(bits.irun));
        r.set("vsense", i64::from(bits.vsense));
        let percent = s.get_int("idle_current_percent", Some(100), Some(0))?;
        if percent > 100 {
            let option = s.option_name("idle_current_percent").unwrap_or("");
            return Err(s.error_for(option, "is above its maximum"));
        }
        return Ok(Currents {
            scale,
            max: 2.4,
            run,
            hold: None,
            idle_percent: percent as u8,
        });
    }
    let rref = match kind {
        DriverKind::Tmc2240 => Some(s.get_float(
            "rref",
            Some(12000.0),
            Bounds {
                minval: Some(12000.0),
                maxval: Some(60000.0),
                ..Bounds::NONE
            },
        )?),
        _ => None,
    };
    let max = match (kind, rref) {
        (_, Some(rref)) => CurrentScale::ifs_rms(rref, 3),
        (DriverKind::Tmc5160, _) => 10.0,
        _ => 2.0,
    };
    let run = s.get_float("run_current", None, upto(max))?;
    let hold = s.get_float("hold_current", Some(max), upto(max))?;
    let scale = match (kind, rref) {
        (_, Some(rref)) => {
            let range = CurrentScale::range_for(rref, run);
            r.set("current_range", i64::from(range));
            CurrentScale::Rref { rref, range }
        }
        (DriverKind::Tmc5160, _) => CurrentScale::GlobalScaler {
            sense_resistor: s.get_float("sense_resistor", Some(0.075), Bounds::POSITIVE)?,
        },
        _ => CurrentScale::Vsense {
            resistance: s.get_float("sense_resistor", Some(0.110), Bounds::POSITIVE)? + 0.020,
            vref_high: 0.32,
            vref_low: 0.18,
        },
    };
    let bits = scale.bits(run, hold);
    match scale {
        CurrentScale::Vsense { .. } => r.set("vsense", i64::from(bits.vsense)),
        _ => r.set("globalscaler", i64::from(bits.globalscaler)),
    }
    r.set("ihold", i64::from(bits.ihold));
    r.set("irun", i64::from(bits.irun));
    Ok(Currents {
        scale,
        max,
        run,
        hold: Some(hold),
        idle_percent: 100,
    })
}

/// `option`'s text if set (one call site for the many optional options).
#[inline(never)]
fn opt<'a>(section: &Section<'_, 'a>, option: &str) -> Option<&'a str> {
    section.get_opt(option)
}

/// Reads the wiring options.
fn read_bus<'c, 'a>(
    section: &Section<'c, 'a>,
    kind: DriverKind,
) -> Result<Bus<'a>, ConfigError<'c>> {
    if kind.is_uart() {
        let uart_pin = section.get("uart_pin")?;
        let tx_pin = opt(section, "tx_pin");
        let select_pins = opt(section, "select_pins");
        let max = if kind == DriverKind::Tmc2209 { 3 } else { 0 };
        let address = section.get_int("uart_address", Some(0), Some(0))?;
        if address > max {
            let option = section.option_name("uart_address").unwrap_or("");
            return Err(section.error_for(option, "is above its maximum"));
        }
        return Ok(Bus::Uart {
            uart_pin,
            tx_pin,
            select_pins,
            address: address as u8,
        });
    }
    let cs_pin = section.get("cs_pin")?;
    let speed = section.get_int("spi_speed", Some(4_000_000), Some(100_000))?;
    let (mut spi_bus, mut software) = (None, None);
    if opt(section, "spi_software_sclk_pin").is_some() {
        software = Some([
            section.get("spi_software_miso_pin")?,
            section.get("spi_software_mosi_pin")?,
            section.get("spi_software_sclk_pin")?,
        ]);
    } else {
        spi_bus = opt(section, "spi_bus");
    }
    let (mut chain_position, mut chain_length) = (1, 1);
    if kind != DriverKind::Tmc2660 && opt(section, "chain_length").is_some() {
        let length = section.get_int("chain_length", None, Some(2))?;
        let position = section.get_int("chain_position", None, Some(1))?;
        if length > 255 {
            let option = section.option_name("chain_length").unwrap_or("");
            return Err(section.error_for(option, "is above its maximum"));
        }
        if position > length {
            let option = section.option_name("chain_position").unwrap_or("");
            return Err(section.error_for(option, "is above chain_length"));
        }
        (chain_position, chain_length) = (position as u8, length as u8);
    }
    Ok(Bus::Spi {
        cs_pin,
        spi_bus,
        software,
        speed: speed.min(i64::from(u32::MAX)) as u32,
        chain_position,
        chain_length,
    })
}

/// Sets fields while reading a section; the first error is kept (and
/// reported once the section is read), later fields keep their defaults.
struct Reader<'s, 'c, 'a> {
    section: &'s Section<'c, 'a>,
    regs: RegisterFile,
    error: Option<ConfigError<'c>>,
}

impl<'c> Reader<'_, 'c, '_> {
    /// Sets `field` to `value` (not from the config).
    fn set(&mut self, field: &str, value: i64) {
        if self.regs.set(field, value) == Err(RegistersFull) {
            let e = self
                .section
                .error_for("run_current", "needs more registers than onechip holds");
            self.fail(e);
        }
    }

    /// Keeps `e` if it is the first error.
    fn fail(&mut self, e: ConfigError<'c>) {
        if self.error.is_none() {
            self.error = Some(e);
        }
    }

    /// Each field from its `driver_XXX` option, else its default
    /// (Klipper's `set_config_field`): a 1-bit field is a boolean, a signed
    /// one an integer in its two's complement range, others 0..=max.
    fn fields(&mut self, fields: &[FieldValue]) {
        for &(name, default) in fields {
            match self.config_value(name, i64::from(default)) {
                Ok(value) => self.set(name, value),
                Err(e) => self.fail(e),
            }
        }
    }

    fn config_value(&self, name: &str, default: i64) -> Result<i64, ConfigError<'c>> {
        let Some((_, field)) = self.regs.kind().field(name) else {
            return Ok(default);
        };
        let mut option = heapless::String::<32>::new();
        let _ = write!(option, "driver_{name}");
        let Some(option) = self.section.option_name(&option) else {
            return Ok(default);
        };
        let max = i64::from(field.max());
        if max == 1 {
            return Ok(i64::from(self.section.get_bool(option, default != 0)?));
        }
        let (min, max) = if field.signed {
            (-(max / 2 + 1), max / 2)
        } else {
            (0, max)
        };
        let value = self.section.get_int(option, Some(default), Some(min))?;
        if value > max {
            return Err(self.section.error_for(option, "is above its maximum"));
        }
        Ok(value)
    }

    /// stealthchop_threshold (TPWMTHRS and the stealthChop switch),
    /// coolstep_threshold (TCOOLTHRS) and high_velocity_threshold (THIGH),
    /// mm/s, as TSTEP values at the stepper's step distance.
    fn thresholds(&mut self, step_dist: f64, coolstep: bool, high: bool) {
        let kind = self.regs.kind();
        let mres = self.regs.get("mres");
        // (option, field, value without the option); stealthChop first.
        let thresholds = [
            ("stealthchop_threshold", "tpwmthrs", TSTEP_MAX, true),
            ("coolstep_threshold", "tcoolthrs", 0, coolstep),
            ("high_velocity_threshold", "thigh", 0, high),
        ];
        for (i, (option, field, absent, present)) in thresholds.into_iter().enumerate() {
            if !present {
                continue;
            }
            let velocity = match self.section.get_float_opt(option, Bounds::NON_NEGATIVE) {
                Ok(v) => v,
                Err(e) => {
                    self.fail(e);
                    None
                }
            };
            let ticks = velocity.map_or(absent, |v| {
                tstep(kind, mres, step_dist, v).unwrap_or(TSTEP_MAX)
            });
            self.set(field, i64::from(ticks));
            if i == 0 {
                let stealth = i64::from(velocity.is_some());
                if kind.field("en_pwm_mode").is_some() {
                    self.set("en_pwm_mode", stealth);
                } else {
                    self.set("en_spreadcycle", 1 - stealth);
                }
            }
        }
    }
}
