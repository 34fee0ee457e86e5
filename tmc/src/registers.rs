//! The registers and bit fields of each TMC driver Klipper supports, by
//! the names Klipper gives them (`driver_XXX` options, SET_TMC_FIELD,
//! DUMP_TMC), from the drivers' data sheets.
//!
//! Registers that several drivers lay out the same way are one table.
//! Registers without fields that cannot be read are left out: nothing can
//! set them.

/// One bit field of a register.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FieldDef {
    /// Its name, lower case (`irun`, `mres`).
    pub name: &'static str,
    /// Its lowest bit.
    shift: u8,
    /// Its width, bits.
    width: u8,
    /// Two's complement value (`sgt`, `cur_a`).
    pub signed: bool,
}

/// One register.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RegDef {
    /// Its name, upper case (`CHOPCONF`).
    pub name: &'static str,
    /// Its address (for the TMC2660: the datagram's top address bits, or
    /// for its read responses a number of our own above 0x0f).
    pub addr: u8,
    /// Its fields, in Klipper's order.
    pub fields: &'static [FieldDef],
}

/// An unsigned field occupying the (contiguous) bits of `mask`.
const fn u(name: &'static str, mask: u32) -> FieldDef {
    FieldDef {
        name,
        shift: mask.trailing_zeros() as u8,
        width: mask.count_ones() as u8,
        signed: false,
    }
}

/// A signed field occupying the bits of `mask`.
const fn s(name: &'static str, mask: u32) -> FieldDef {
    FieldDef {
        signed: true,
        ..u(name, mask)
    }
}

const fn r(name: &'static str, addr: u8, fields: &'static [FieldDef]) -> RegDef {
    RegDef { name, addr, fields }
}

impl FieldDef {
    /// The lowest bit of the field.
    pub const fn shift(&self) -> u32 {
        self.shift as u32
    }

    /// The largest value the field holds (unsigned).
    pub const fn max(&self) -> u32 {
        (((1u64 << self.width) - 1) & 0xffff_ffff) as u32
    }

    /// The bits the field occupies.
    pub const fn mask(&self) -> u32 {
        self.max() << self.shift
    }

    /// The field's value in register value `reg` (sign-extended if signed).
    pub fn get(&self, reg: u32) -> i64 {
        let raw = (reg & self.mask()) >> self.shift();
        let width = u32::from(self.width);
        if self.signed && width > 0 && raw >> (width - 1) & 1 != 0 {
            i64::from(raw) - (1i64 << width)
        } else {
            i64::from(raw)
        }
    }

    /// `reg` with this field set to `value` (bits beyond the field are
    /// dropped, as Klipper's `set_field` drops them).
    pub fn set(&self, reg: u32, value: i64) -> u32 {
        let bits = ((value as u64) << self.shift()) as u32;
        (reg & !self.mask()) | (bits & self.mask())
    }
}

// Registers shared by several drivers.
const GSTAT: RegDef = r(
    "GSTAT",
    0x01,
    &[u("reset", 1), u("drv_err", 1 << 1), u("uv_cp", 1 << 2)],
);
const IHOLD_IRUN: RegDef = r(
    "IHOLD_IRUN",
    0x10,
    &[
        u("ihold", 0x1f),
        u("irun", 0x1f << 8),
        u("iholddelay", 0x0f << 16),
    ],
);
const TPOWERDOWN: RegDef = r("TPOWERDOWN", 0x11, &[u("tpowerdown", 0xff)]);
const TSTEP: RegDef = r("TSTEP", 0x12, &[u("tstep", 0xfffff)]);
const TPWMTHRS: RegDef = r("TPWMTHRS", 0x13, &[u("tpwmthrs", 0xfffff)]);
const TCOOLTHRS: RegDef = r("TCOOLTHRS", 0x14, &[u("tcoolthrs", 0xfffff)]);
const THIGH: RegDef = r("THIGH", 0x15, &[u("thigh", 0xfffff)]);
const MSLUT: [RegDef; 8] = [
    r("MSLUT0", 0x60, &[u("mslut0", u32::MAX)]),
    r("MSLUT1", 0x61, &[u("mslut1", u32::MAX)]),
    r("MSLUT2", 0x62, &[u("mslut2", u32::MAX)]),
    r("MSLUT3", 0x63, &[u("mslut3", u32::MAX)]),
    r("MSLUT4", 0x64, &[u("mslut4", u32::MAX)]),
    r("MSLUT5", 0x65, &[u("mslut5", u32::MAX)]),
    r("MSLUT6", 0x66, &[u("mslut6", u32::MAX)]),
    r("MSLUT7", 0x67, &[u("mslut7", u32::MAX)]),
];
const MSLUTSEL: RegDef = r(
    "MSLUTSEL",
    0x68,
    &[
        u("x3", 0xff << 24),
        u("x2", 0xff << 16),
        u("x1", 0xff << 8),
        u("w3", 0x03 << 6),
        u("w2", 0x03 << 4),
        u("w1", 0x03 << 2),
        u("w0", 0x03),
    ],
);
const MSLUTSTART: RegDef = r(
    "MSLUTSTART",
    0x69,
    &[u("start_sin", 0xff), u("start_sin90", 0xff << 16)],
);
const MSCNT: RegDef = r("MSCNT", 0x6a, &[u("mscnt", 0x3ff)]);
const MSCURACT: RegDef = r(
    "MSCURACT",
    0x6b,
    &[s("cur_a", 0x1ff), s("cur_b", 0x1ff << 16)],
);
/// COOLCONF of the TMC2130, TMC2240 and TMC5160.
const COOLCONF: RegDef = r(
    "COOLCONF",
    0x6d,
    &[
        u("semin", 0x0f),
        u("seup", 0x03 << 5),
        u("semax", 0x0f << 8),
        u("sedn", 0x03 << 13),
        u("seimin", 1 << 15),
        s("sgt", 0x7f << 16),
        u("sfilt", 1 << 24),
    ],
);
const LOST_STEPS: RegDef = r("LOST_STEPS", 0x73, &[u("lost_steps", 0xfffff)]);
const PWM_AUTO: RegDef = r(
    "PWM_AUTO",
    0x72,
    &[u("pwm_ofs_auto", 0xff), u("pwm_grad_auto", 0xff << 16)],
);
/// PWMCONF of the TMC2208, TMC2209 and TMC5160.
const PWMCONF_AUTO: RegDef = r(
    "PWMCONF",
    0x70,
    &[
        u("pwm_ofs", 0xff),
        u("pwm_grad", 0xff << 8),
        u("pwm_freq", 0x03 << 16),
        u("pwm_autoscale", 1 << 18),
        u("pwm_autograd", 1 << 19),
        u("freewheel", 0x03 << 20),
        u("pwm_reg", 0x0f << 24),
        u("pwm_lim", 0x0f << 28),
    ],
);
const PWM_SCALE_AUTO: RegDef = r(
    "PWM_SCALE",
    0x71,
    &[u("pwm_scale_sum", 0xff), s("pwm_scale_auto", 0x1ff << 16)],
);
/// CHOPCONF of the TMC5160 and TMC2240.
const CHOPCONF_5160: RegDef = r(
    "CHOPCONF",
    0x6c,
    &[
        u("toff", 0x0f),
        u("hstrt", 0x07 << 4),
        u("hend", 0x0f << 7),
        u("fd3", 1 << 11),
        u("disfdcc", 1 << 12),
        u("chm", 1 << 14),
        u("tbl", 0x03 << 15),
        u("vhighfs", 1 << 18),
        u("vhighchm", 1 << 19),
        u("tpfd", 0x0f << 20),
        u("mres", 0x0f << 24),
        u("intpol", 1 << 28),
        u("dedge", 1 << 29),
        u("diss2g", 1 << 30),
        u("diss2vs", 1 << 31),
    ],
);
const GLOBALSCALER: RegDef = r("GLOBALSCALER", 0x0b, &[u("globalscaler", 0xff)]);
const IFCNT: RegDef = r("IFCNT", 0x02, &[u("ifcnt", 0xff)]);

// TMC2130.
const GCONF_2130: RegDef = r(
    "GCONF",
    0x00,
    &[
        u("i_scale_analog", 1),
        u("internal_rsense", 1 << 1),
        u("en_pwm_mode", 1 << 2),
        u("enc_commutation", 1 << 3),
        u("shaft", 1 << 4),
        u("diag0_error", 1 << 5),
        u("diag0_otpw", 1 << 6),
        u("diag0_stall", 1 << 7),
        u("diag1_stall", 1 << 8),
        u("diag1_index", 1 << 9),
        u("diag1_onstate", 1 << 10),
        u("diag1_steps_skipped", 1 << 11),
        u("diag0_int_pushpull", 1 << 12),
        u("diag1_pushpull", 1 << 13),
        u("small_hysteresis", 1 << 14),
        u("stop_enable", 1 << 15),
        u("direct_mode", 1 << 16),
        u("test_mode", 1 << 17),
    ],
);
const DRV_STATUS_2130: RegDef = r(
    "DRV_STATUS",
    0x6f,
    &[
        u("sg_result", 0x3ff),
        u("fsactive", 1 << 15),
        u("cs_actual", 0x1f << 16),
        u("stallguard", 1 << 24),
        u("ot", 1 << 25),
        u("otpw", 1 << 26),
        u("s2ga", 1 << 27),
        u("s2gb", 1 << 28),
        u("ola", 1 << 29),
        u("olb", 1 << 30),
        u("stst", 1 << 31),
    ],
);
/// The TMC2130's registers.
pub const TMC2130: &[RegDef] = &[
    GCONF_2130,
    IHOLD_IRUN,
    TPOWERDOWN,
    TPWMTHRS,
    TCOOLTHRS,
    THIGH,
    MSLUT[0],
    MSLUT[1],
    MSLUT[2],
    MSLUT[3],
    MSLUT[4],
    MSLUT[5],
    MSLUT[6],
    MSLUT[7],
    MSLUTSEL,
    MSLUTSTART,
    r(
        "CHOPCONF",
        0x6c,
        &[
            u("toff", 0x0f),
            u("hstrt", 0x07 << 4),
            u("hend", 0x0f << 7),
            u("fd3", 1 << 11),
            u("disfdcc", 1 << 12),
            u("rndtf", 1 << 13),
            u("chm", 1 << 14),
            u("tbl", 0x03 << 15),
            u("vsense", 1 << 17),
            u("vhighfs", 1 << 18),
            u("vhighchm", 1 << 19),
            u("sync", 0x0f << 20),
            u("mres", 0x0f << 24),
            u("intpol", 1 << 28),
            u("dedge", 1 << 29),
            u("diss2g", 1 << 30),
        ],
    ),
    COOLCONF,
    r(
        "PWMCONF",
        0x70,
        &[
            u("pwm_ampl", 0xff),
            u("pwm_grad", 0xff << 8),
            u("pwm_freq", 0x03 << 16),
            u("pwm_autoscale", 1 << 18),
            u("pwm_symmetric", 1 << 19),
            u("freewheel", 0x03 << 20),
        ],
    ),
];
/// Its registers that only the run-time checks and DUMP_TMC read (or
/// SET_TMC_FIELD sets).
pub const TMC2130_STATUS: &[RegDef] = &[
    GSTAT,
    r(
        "IOIN",
        0x04,
        &[
            u("step", 1),
            u("dir", 1 << 1),
            u("dcen_cfg4", 1 << 2),
            u("dcin_cfg5", 1 << 3),
            u("drv_enn_cfg6", 1 << 4),
            u("dco", 1 << 5),
            u("version", 0xff << 24),
        ],
    ),
    TSTEP,
    r("XDIRECT", 0x2d, &[]),
    MSCNT,
    MSCURACT,
    DRV_STATUS_2130,
    r("PWM_SCALE", 0x71, &[u("pwm_scale", 0xff)]),
    LOST_STEPS,
];
/// Registers of the TMC2130 that Klipper reads (DUMP_TMC order).
pub const TMC2130_READ: &[&str] = &[
    "GCONF",
    "GSTAT",
    "IOIN",
    "TSTEP",
    "XDIRECT",
    "MSCNT",
    "MSCURACT",
    "CHOPCONF",
    "DRV_STATUS",
    "PWM_SCALE",
    "LOST_STEPS",
];

// TMC2208 and TMC2209.
const GCONF_2208: RegDef = r(
    "GCONF",
    0x00,
    &[
        u("i_scale_analog", 1),
        u("internal_rsense", 1 << 1),
        u("en_spreadcycle", 1 << 2),
        u("shaft", 1 << 3),
        u("index_otpw", 1 << 4),
        u("index_step", 1 << 5),
        u("pdn_disable", 1 << 6),
        u("mstep_reg_select", 1 << 7),
        u("multistep_filt", 1 << 8),
        u("test_mode", 1 << 9),
    ],
);
const SLAVECONF_2208: RegDef = r("SLAVECONF", 0x03, &[u("senddelay", 0x0f << 8)]);
const OTP_PROG: RegDef = r(
    "OTP_PROG",
    0x04,
    &[
        u("otpbit", 0x07),
        u("otpbyte", 0x03 << 4),
        u("otpmagic", 0xff << 8),
    ],
);
const OTP_READ_2208: RegDef = r(
    "OTP_READ",
    0x05,
    &[
        u("otp_fclktrim", 0x1f),
        u("otp_ottrim", 1 << 5),
        u("otp_internalrsense", 1 << 6),
        u("otp_tbl", 1 << 7),
        u("otp_pwm_grad", 0x0f << 8),
        u("otp_pwm_autograd", 1 << 12),
        u("otp_tpwmthrs", 0x07 << 13),
        u("otp_pwm_ofs", 1 << 16),
        u("otp_pwm_reg", 1 << 17),
        u("otp_pwm_freq", 1 << 18),
        u("otp_iholddelay", 0x03 << 19),
        u("otp_ihold", 0x03 << 21),
        u("otp_en_spreadcycle", 1 << 23),
    ],
);
const FACTORY_CONF_2208: RegDef = r(
    "FACTORY_CONF",
    0x07,
    &[u("fclktrim", 0x1f), u("ottrim", 0x03 << 8)],
);
const VACTUAL_2208: RegDef = r("VACTUAL", 0x22, &[u("vactual", 0xffffff)]);
const CHOPCONF_2208: RegDef = r(
    "CHOPCONF",
    0x6c,
    &[
        u("toff", 0x0f),
        u("hstrt", 0x07 << 4),
        u("hend", 0x0f << 7),
        u("tbl", 0x03 << 15),
        u("vsense", 1 << 17),
        u("mres", 0x0f << 24),
        u("intpol", 1 << 28),
        u("dedge", 1 << 29),
        u("diss2g", 1 << 30),
        u("diss2vs", 1 << 31),
    ],
);
const DRV_STATUS_2208: RegDef = r(
    "DRV_STATUS",
    0x6f,
    &[
        u("otpw", 1),
        u("ot", 1 << 1),
        u("s2ga", 1 << 2),
        u("s2gb", 1 << 3),
        u("s2vsa", 1 << 4),
        u("s2vsb", 1 << 5),
        u("ola", 1 << 6),
        u("olb", 1 << 7),
        u("t120", 1 << 8),
        u("t143", 1 << 9),
        u("t150", 1 << 10),
        u("t157", 1 << 11),
        u("cs_actual", 0x1f << 16),
        u("stealth", 1 << 30),
        u("stst", 1 << 31),
    ],
);
/// The TMC2208's registers (IOIN as the TMC220x lays it out, SEL_A = 1).
pub const TMC2208: &[RegDef] = &[
    GCONF_2208,
    SLAVECONF_2208,
    IHOLD_IRUN,
    TPOWERDOWN,
    TPWMTHRS,
    CHOPCONF_2208,
    PWMCONF_AUTO,
];
/// Its registers that only the run-time checks and DUMP_TMC read (or
/// SET_TMC_FIELD sets).
pub const TMC2208_STATUS: &[RegDef] = &[
    GSTAT,
    IFCNT,
    OTP_PROG,
    OTP_READ_2208,
    r(
        "IOIN",
        0x06,
        &[
            u("enn", 1),
            u("ms1", 1 << 2),
            u("ms2", 1 << 3),
            u("diag", 1 << 4),
            u("pdn_uart", 1 << 6),
            u("step", 1 << 7),
            u("sel_a", 1 << 8),
            u("dir", 1 << 9),
            u("version", 0xff << 24),
        ],
    ),
    FACTORY_CONF_2208,
    TSTEP,
    VACTUAL_2208,
    MSCNT,
    MSCURACT,
    DRV_STATUS_2208,
    PWM_SCALE_AUTO,
    PWM_AUTO,
];
/// Registers of the TMC2208 that Klipper reads.
pub const TMC2208_READ: &[&str] = &[
    "GCONF",
    "GSTAT",
    "IFCNT",
    "OTP_READ",
    "IOIN",
    "FACTORY_CONF",
    "TSTEP",
    "MSCNT",
    "MSCURACT",
    "CHOPCONF",
    "DRV_STATUS",
    "PWMCONF",
    "PWM_SCALE",
    "PWM_AUTO",
];
/// The TMC2209's registers.
pub const TMC2209: &[RegDef] = &[
    GCONF_2208,
    SLAVECONF_2208,
    IHOLD_IRUN,
    TPOWERDOWN,
    TPWMTHRS,
    TCOOLTHRS,
    r("SGTHRS", 0x40, &[u("sgthrs", 0xff)]),
    r(
        "COOLCONF",
        0x42,
        &[
            u("semin", 0x0f),
            u("seup", 0x03 << 5),
            u("semax", 0x0f << 8),
            u("sedn", 0x03 << 13),
            u("seimin", 1 << 15),
        ],
    ),
    CHOPCONF_2208,
    PWMCONF_AUTO,
];
/// Its registers that only the run-time checks and DUMP_TMC read (or
/// SET_TMC_FIELD sets).
pub const TMC2209_STATUS: &[RegDef] = &[
    GSTAT,
    IFCNT,
    OTP_PROG,
    OTP_READ_2208,
    r(
        "IOIN",
        0x06,
        &[
            u("enn", 1),
            u("ms1", 1 << 2),
            u("ms2", 1 << 3),
            u("diag", 1 << 4),
            u("pdn_uart", 1 << 6),
            u("step", 1 << 7),
            u("spread_en", 1 << 8),
            u("dir", 1 << 9),
            u("version", 0xff << 24),
        ],
    ),
    FACTORY_CONF_2208,
    TSTEP,
    VACTUAL_2208,
    r("SG_RESULT", 0x41, &[u("sg_result", 0x3ff)]),
    MSCNT,
    MSCURACT,
    DRV_STATUS_2208,
    PWM_SCALE_AUTO,
    PWM_AUTO,
];
/// Registers of the TMC2209 that Klipper reads.
pub const TMC2209_READ: &[&str] = &[
    "GCONF",
    "GSTAT",
    "IFCNT",
    "OTP_READ",
    "IOIN",
    "FACTORY_CONF",
    "TSTEP",
    "MSCNT",
    "MSCURACT",
    "CHOPCONF",
    "DRV_STATUS",
    "PWMCONF",
    "PWM_SCALE",
    "PWM_AUTO",
    "SG_RESULT",
];

// TMC5160.
/// The TMC5160's registers.
pub const TMC5160: &[RegDef] = &[
    r(
        "GCONF",
        0x00,
        &[
            u("recalibrate", 1),
            u("faststandstill", 1 << 1),
            u("en_pwm_mode", 1 << 2),
            u("multistep_filt", 1 << 3),
            u("shaft", 1 << 4),
            u("diag0_error", 1 << 5),
            u("diag0_otpw", 1 << 6),
            u("diag0_stall", 1 << 7),
            u("diag1_stall", 1 << 8),
            u("diag1_index", 1 << 9),
            u("diag1_onstate", 1 << 10),
            u("diag1_steps_skipped", 1 << 11),
            u("diag0_int_pushpull", 1 << 12),
            u("diag1_poscomp_pushpull", 1 << 13),
            u("small_hysteresis", 1 << 14),
            u("stop_enable", 1 << 15),
            u("direct_mode", 1 << 16),
            u("test_mode", 1 << 17),
        ],
    ),
    r(
        "DRV_CONF",
        0x0a,
        &[
            u("bbmtime", 0x1f),
            u("bbmclks", 0x0f << 8),
            u("otselect", 0x03 << 16),
            u("drvstrength", 0x03 << 18),
            u("filt_isense", 0x03 << 20),
        ],
    ),
    GLOBALSCALER,
    IHOLD_IRUN,
    TPOWERDOWN,
    TPWMTHRS,
    TCOOLTHRS,
    THIGH,
    MSLUT[0],
    MSLUT[1],
    MSLUT[2],
    MSLUT[3],
    MSLUT[4],
    MSLUT[5],
    MSLUT[6],
    MSLUT[7],
    MSLUTSEL,
    MSLUTSTART,
    CHOPCONF_5160,
    COOLCONF,
    PWMCONF_AUTO,
];
/// Its registers that only the run-time checks and DUMP_TMC read (or
/// SET_TMC_FIELD sets).
pub const TMC5160_STATUS: &[RegDef] = &[
    GSTAT,
    r(
        "IOIN",
        0x04,
        &[
            u("refl_step", 1),
            u("refr_dir", 1 << 1),
            u("encb_dcen_cfg4", 1 << 2),
            u("enca_dcin_cfg5", 1 << 3),
            u("drv_enn", 1 << 4),
            u("enc_n_dco_cfg6", 1 << 5),
            u("sd_mode", 1 << 6),
            u("swcomp_in", 1 << 7),
            u("version", 0xff << 24),
        ],
    ),
    r(
        "OTP_READ",
        0x07,
        &[
            u("otp_fclktrim", 0x1f),
            u("otp_s2_level", 1 << 5),
            u("otp_bbm", 1 << 6),
            u("otp_tbl", 1 << 7),
        ],
    ),
    r("FACTORY_CONF", 0x08, &[u("factory_conf", 0x1f)]),
    TSTEP,
    MSCNT,
    MSCURACT,
    r(
        "DRV_STATUS",
        0x6f,
        &[
            u("sg_result", 0x3ff),
            u("s2vsa", 1 << 12),
            u("s2vsb", 1 << 13),
            u("stealth", 1 << 14),
            u("fsactive", 1 << 15),
            u("cs_actual", 0x1f << 16),
            u("stallguard", 1 << 24),
            u("ot", 1 << 25),
            u("otpw", 1 << 26),
            u("s2ga", 1 << 27),
            u("s2gb", 1 << 28),
            u("ola", 1 << 29),
            u("olb", 1 << 30),
            u("stst", 1 << 31),
        ],
    ),
    PWM_SCALE_AUTO,
    PWM_AUTO,
    LOST_STEPS,
];
/// Registers of the TMC5160 that Klipper reads.
pub const TMC5160_READ: &[&str] = &[
    "GCONF",
    "CHOPCONF",
    "GSTAT",
    "DRV_STATUS",
    "FACTORY_CONF",
    "IOIN",
    "LOST_STEPS",
    "MSCNT",
    "MSCURACT",
    "OTP_READ",
    "PWM_SCALE",
    "PWM_AUTO",
    "TSTEP",
];

// TMC2240.
/// The TMC2240's registers.
pub const TMC2240: &[RegDef] = &[
    r(
        "GCONF",
        0x00,
        &[
            u("faststandstill", 1 << 1),
            u("en_pwm_mode", 1 << 2),
            u("multistep_filt", 1 << 3),
            u("shaft", 1 << 4),
            u("diag0_error", 1 << 5),
            u("diag0_otpw", 1 << 6),
            u("diag0_stall", 1 << 7),
            u("diag1_stall", 1 << 8),
            u("diag1_index", 1 << 9),
            u("diag1_onstate", 1 << 10),
            u("diag0_pushpull", 1 << 12),
            u("diag1_pushpull", 1 << 13),
            u("small_hysteresis", 1 << 14),
            u("stop_enable", 1 << 15),
            u("direct_mode", 1 << 16),
        ],
    ),
    r(
        "DRV_CONF",
        0x0a,
        &[u("current_range", 0x03), u("slope_control", 0x03 << 4)],
    ),
    GLOBALSCALER,
    r(
        "IHOLD_IRUN",
        0x10,
        &[
            u("ihold", 0x1f),
            u("irun", 0x1f << 8),
            u("iholddelay", 0x0f << 16),
            u("irundelay", 0x0f << 24),
        ],
    ),
    TPOWERDOWN,
    TPWMTHRS,
    TCOOLTHRS,
    THIGH,
    MSLUT[0],
    MSLUT[1],
    MSLUT[2],
    MSLUT[3],
    MSLUT[4],
    MSLUT[5],
    MSLUT[6],
    MSLUT[7],
    MSLUTSEL,
    r(
        "MSLUTSTART",
        0x69,
        &[
            u("start_sin", 0xff),
            u("start_sin90", 0xff << 16),
            s("offset_sin90", 0xff << 24),
        ],
    ),
    CHOPCONF_5160,
    COOLCONF,
    r(
        "PWMCONF",
        0x70,
        &[
            u("pwm_ofs", 0xff),
            u("pwm_grad", 0xff << 8),
            u("pwm_freq", 0x03 << 16),
            u("pwm_autoscale", 1 << 18),
            u("pwm_autograd", 1 << 19),
            u("freewheel", 0x03 << 20),
            u("pwm_meas_sd_enable", 1 << 22),
            u("pwm_dis_reg_stst", 1 << 23),
            u("pwm_reg", 0x0f << 24),
            u("pwm_lim", 0x0f << 28),
        ],
    ),
    r(
        "SG4_THRS",
        0x74,
        &[
            u("sg4_thrs", 0xff),
            u("sg4_filt_en", 1 << 8),
            u("sg4_angle_offset", 1 << 9),
        ],
    ),
];
/// Its registers that only the run-time checks and DUMP_TMC read (or
/// SET_TMC_FIELD sets).
pub const TMC2240_STATUS: &[RegDef] = &[
    r(
        "GSTAT",
        0x01,
        &[
            u("reset", 1),
            u("drv_err", 1 << 1),
            u("uv_cp", 1 << 2),
            u("register_reset", 1 << 3),
            u("vm_uvlo", 1 << 4),
        ],
    ),
    r(
        "IOIN",
        0x04,
        &[
            u("step", 1),
            u("dir", 1 << 1),
            u("encb", 1 << 2),
            u("enca", 1 << 3),
            u("drv_enn", 1 << 4),
            u("encn", 1 << 5),
            u("uart_en", 1 << 6),
            u("comp_a", 1 << 8),
            u("comp_b", 1 << 9),
            u("comp_a1_a2", 1 << 10),
            u("comp_b1_b2", 1 << 11),
            u("output", 1 << 12),
            u("ext_res_det", 1 << 13),
            u("ext_clk", 1 << 14),
            u("adc_err", 1 << 15),
            u("silicon_rv", 0x07 << 16),
            u("version", 0xff << 24),
        ],
    ),
    TSTEP,
    r(
        "ADC_VSUPPLY_AIN",
        0x50,
        &[u("adc_vsupply", 0x1fff), u("adc_ain", 0x1fff << 16)],
    ),
    r("ADC_TEMP", 0x51, &[u("adc_temp", 0x1fff)]),
    r(
        "OTW_OV_VTH",
        0x52,
        &[
            u("overvoltage_vth", 0x1fff),
            u("overtempprewarning_vth", 0x1fff << 16),
        ],
    ),
    MSCNT,
    MSCURACT,
    r(
        "DRV_STATUS",
        0x6f,
        &[
            u("sg_result", 0x3ff),
            u("s2vsa", 1 << 12),
            u("s2vsb", 1 << 13),
            u("stealth", 1 << 14),
            u("fsactive", 1 << 15),
            u("csactual", 0x1f << 16),
            u("stallguard", 1 << 24),
            u("ot", 1 << 25),
            u("otpw", 1 << 26),
            u("s2ga", 1 << 27),
            u("s2gb", 1 << 28),
            u("ola", 1 << 29),
            u("olb", 1 << 30),
            u("stst", 1 << 31),
        ],
    ),
    r(
        "PWM_SCALE",
        0x71,
        &[u("pwm_scale_sum", 0x3ff), s("pwm_scale_auto", 0x1ff << 16)],
    ),
    PWM_AUTO,
    r("SG4_RESULT", 0x75, &[u("sg4_result", 0x3ff)]),
    r(
        "SG4_IND",
        0x76,
        &[
            u("sg4_ind_0", 0xff),
            u("sg4_ind_1", 0xff << 8),
            u("sg4_ind_2", 0xff << 16),
            u("sg4_ind_3", 0xff << 24),
        ],
    ),
];
/// Registers of the TMC2240 that Klipper reads.
pub const TMC2240_READ: &[&str] = &[
    "GCONF",
    "GSTAT",
    "IOIN",
    "DRV_CONF",
    "GLOBALSCALER",
    "IHOLD_IRUN",
    "TPOWERDOWN",
    "TSTEP",
    "TPWMTHRS",
    "TCOOLTHRS",
    "THIGH",
    "ADC_VSUPPLY_AIN",
    "ADC_TEMP",
    "MSCNT",
    "MSCURACT",
    "CHOPCONF",
    "COOLCONF",
    "DRV_STATUS",
    "PWMCONF",
    "PWM_SCALE",
    "PWM_AUTO",
    "SG4_THRS",
    "SG4_RESULT",
    "SG4_IND",
];

// TMC2660: five write-only registers, three read responses selected by
// DRVCONF's rdsel.
const READRSP_FLAGS: [FieldDef; 8] = [
    u("stallguard", 1 << 4),
    u("ot", 1 << 5),
    u("otpw", 1 << 6),
    u("s2ga", 1 << 7),
    u("s2gb", 1 << 8),
    u("ola", 1 << 9),
    u("olb", 1 << 10),
    u("stst", 1 << 11),
];
/// The flags, then `extra` (`M` = 8 + its length).
const fn readrsp<const M: usize>(extra: &[FieldDef]) -> [FieldDef; M] {
    let mut out = [u("", 1); M];
    let mut i = 0;
    while i < M {
        out[i] = if i < 8 {
            READRSP_FLAGS[i]
        } else {
            extra[i - 8]
        };
        i += 1;
    }
    out
}
const RDSEL0: [FieldDef; 9] = readrsp(&[u("mstep", 0x3ff << 14)]);
const RDSEL1: [FieldDef; 9] = readrsp(&[u("sg_result", 0x3ff << 14)]);
const RDSEL2: [FieldDef; 10] = readrsp(&[u("se", 0x1f << 14), u("sg_result@rdsel2", 0x1f << 19)]);
/// Our number for the TMC2660's first read response (`READRSP@RDSEL0`);
/// the others follow.
pub const TMC2660_READRSP: u8 = 0x10;
/// The TMC2660's registers.
pub const TMC2660: &[RegDef] = &[
    r(
        "DRVCTRL",
        0x0,
        &[u("mres", 0x0f), u("dedge", 1 << 8), u("intpol", 1 << 9)],
    ),
    r(
        "CHOPCONF",
        0x8,
        &[
            u("toff", 0x0f),
            u("hstrt", 0x07 << 4),
            u("hend", 0x0f << 7),
            u("hdec", 0x03 << 11),
            u("rndtf", 1 << 13),
            u("chm", 1 << 14),
            u("tbl", 0x03 << 15),
        ],
    ),
    r(
        "SMARTEN",
        0xa,
        &[
            u("semin", 0x0f),
            u("seup", 0x03 << 5),
            u("semax", 0x0f << 8),
            u("sedn", 0x03 << 13),
            u("seimin", 1 << 15),
        ],
    ),
    r(
        "SGCSCONF",
        0xc,
        &[u("cs", 0x1f), s("sgt", 0x7f << 8), u("sfilt", 1 << 16)],
    ),
    r(
        "DRVCONF",
        0xe,
        &[
            u("rdsel", 0x03 << 4),
            u("vsense", 1 << 6),
            u("sdoff", 1 << 7),
            u("ts2g", 0x03 << 8),
            u("diss2g", 1 << 10),
            u("slpl", 0x03 << 12),
            u("slph", 0x03 << 14),
            u("tst", 1 << 16),
        ],
    ),
];
/// Its registers that only the run-time checks and DUMP_TMC read (or
/// SET_TMC_FIELD sets).
pub const TMC2660_STATUS: &[RegDef] = &[
    r("READRSP@RDSEL0", TMC2660_READRSP, &RDSEL0),
    r("READRSP@RDSEL1", TMC2660_READRSP + 1, &RDSEL1),
    r("READRSP@RDSEL2", TMC2660_READRSP + 2, &RDSEL2),
];
/// The TMC2660's read responses.
pub const TMC2660_READ: &[&str] = &["READRSP@RDSEL0", "READRSP@RDSEL1", "READRSP@RDSEL2"];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn signed_fields_sign_extend_and_set_masks() {
        let sgt = COOLCONF.fields[5];
        // sgt = -1 is 0x7f in bits 16..22.
        let reg = sgt.set(0, -1);
        assert_eq!(reg, 0x7f << 16);
        assert_eq!(sgt.get(reg), -1);
        assert_eq!(sgt.get(63 << 16), 63);
        assert_eq!(sgt.get(64 << 16), -64);
        // Bits past the field are dropped.
        let ihold = IHOLD_IRUN.fields[0];
        assert_eq!(ihold.set(0xffff_ffff, 0x20), 0xffff_ffe0);
    }

    #[test]
    fn field_names_are_unique_per_driver() {
        for (config, status) in [
            (TMC2130, TMC2130_STATUS),
            (TMC2208, TMC2208_STATUS),
            (TMC2209, TMC2209_STATUS),
            (TMC5160, TMC5160_STATUS),
            (TMC2240, TMC2240_STATUS),
            (TMC2660, TMC2660_STATUS),
        ] {
            let regs = || config.iter().chain(status);
            let names = regs().flat_map(|r| r.fields.iter().map(|f| f.name));
            for (i, a) in names.clone().enumerate() {
                let repeats = names.clone().skip(i + 1).filter(|b| *b == a).count();
                // The TMC2660's three read responses share their flags.
                assert!(repeats == 0 || config == TMC2660, "{a}");
            }
            assert!(regs().all(|a| regs().filter(|r| r.addr == a.addr).count() == 1));
        }
    }

    #[test]
    fn fields_of_a_register_have_distinct_masks() {
        // DUMP_TMC lists a register's fields by mask, each once.
        for driver in [
            TMC2130,
            TMC2130_STATUS,
            TMC2208,
            TMC2208_STATUS,
            TMC2209,
            TMC2209_STATUS,
            TMC5160,
            TMC5160_STATUS,
            TMC2240,
            TMC2240_STATUS,
            TMC2660,
            TMC2660_STATUS,
        ] {
            for reg in driver {
                for (i, a) in reg.fields.iter().enumerate() {
                    let same = reg.fields[i + 1..].iter().any(|b| b.mask() == a.mask());
                    assert!(!same, "{} {}", reg.name, a.name);
                }
            }
        }
    }
}
