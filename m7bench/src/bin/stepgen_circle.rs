//! Instructions per generated and compressed step on a Cortex-M7: the
//! golden cartesian circle case through the whole step-generation
//! pipeline (no input shaping).
#![no_std]
#![no_main]

use cortex_m_rt::entry;

#[entry]
fn main() -> ! {
    onechip_m7bench::stepgen::run(
        "stepgen_circle",
        "cartesian.cfg",
        include_str!("../../../../shared/golden/configs/cartesian.cfg"),
        include_str!("../../../../shared/golden/gcode/cart_circle.gcode"),
    )
}
