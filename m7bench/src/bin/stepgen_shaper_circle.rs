//! Instructions per generated and compressed step on a Cortex-M7 with
//! input shaping: the golden shaper circle case (X mzv 40 Hz, Y ei 35 Hz)
//! through the whole step-generation pipeline.
#![no_std]
#![no_main]

use cortex_m_rt::entry;

#[entry]
fn main() -> ! {
    onechip_m7bench::stepgen::run(
        "stepgen_shaper_circle",
        "cartesian_shaper.cfg",
        include_str!("../../../../shared/golden/configs/cartesian_shaper.cfg"),
        include_str!("../../../../shared/golden/gcode/shaper_circle.gcode"),
    )
}
