//! Instructions per generated and compressed step on a Cortex-M7, for
//! every kind of golden case (cartesian, corexy, delta, input shaping; a
//! circle and an extrusion print of each) through the whole
//! step-generation pipeline: one measured region per case, in this order.
#![no_std]
#![no_main]

use cortex_m_rt::entry;
use onechip_m7bench::stepgen::{Case, run};

/// The golden case `label` on golden config `cfg`.
macro_rules! golden {
    ($label:literal, $cfg:literal) => {
        Case {
            label: $label,
            config_name: $cfg,
            config: include_str!(concat!("../../../../shared/golden/configs/", $cfg)),
            gcode: include_str!(concat!(
                "../../../../shared/golden/gcode/",
                $label,
                ".gcode"
            )),
        }
    };
}

#[entry]
fn main() -> ! {
    run(&[
        golden!("cart_circle", "cartesian.cfg"),
        golden!("cart_extrude", "cartesian.cfg"),
        golden!("corexy_circle", "corexy.cfg"),
        golden!("corexy_extrude", "corexy.cfg"),
        golden!("delta_circle", "delta.cfg"),
        golden!("delta_extrude", "delta.cfg"),
        golden!("shaper_circle", "cartesian_shaper.cfg"),
        golden!("shaper_extrude", "cartesian_shaper.cfg"),
    ])
}
