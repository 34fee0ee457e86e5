//! The front half of the host role: from `printer.cfg` and G-code to planned
//! moves, as Klipper's toolhead plans them (issue #3).
//!
//! Contract for the crates above it: moves come out as trapezoids in
//! move-relative time (accel, cruise, decel durations in s, velocities in
//! mm/s) anchored at integer clock ticks, so nothing drifts over long prints.
//!
//! Reading `printer.cfg` is `onechip-config`'s job; [`machine`] builds the
//! motion side from its sections, and [`gcode`] parses G-code lines, both
//! without allocation.
#![cfg_attr(not(feature = "std"), no_std)]

/// Test fixture: printer.cfg text for a cartesian printer (300 mm/s,
/// 3000 mm/s², three 200 mm rails) and the start of its `[extruder]` (pins,
/// rotation_distance 33.5, 0.4 mm nozzle, 1.75 mm filament); tests add the
/// rest after it (`concat!` or `format!`).
#[cfg(test)]
macro_rules! cartesian_printer {
    () => {
        "[printer]\nkinematics: cartesian\nmax_velocity: 300\nmax_accel: 3000\n\
        [stepper_x]\nstep_pin: PF13\ndir_pin: PF12\nmicrosteps: 16\nrotation_distance: 40\n\
        position_endstop: 0\nposition_max: 200\n\
        [stepper_y]\nstep_pin: PG0\ndir_pin: PG1\nmicrosteps: 16\nrotation_distance: 40\n\
        position_endstop: 0\nposition_max: 200\n\
        [stepper_z]\nstep_pin: PF11\ndir_pin: PG3\nmicrosteps: 16\nrotation_distance: 8\n\
        position_endstop: 0\nposition_max: 200\n\
        [extruder]\nstep_pin: PF9\ndir_pin: PF10\nmicrosteps: 16\nrotation_distance: 33.5\n\
        nozzle_diameter: 0.4\nfilament_diameter: 1.75\n"
    };
}

pub mod accessories;
pub mod adc_temperature;
pub mod bed_screws;
pub mod bltouch;
pub mod board_pins;
pub mod extruder_stepper;
pub mod fan_sections;
pub mod filament_sensor;
pub mod gcode;
pub mod gcode_move;
pub mod homing;
pub mod kinematics;
pub mod lookahead;
pub mod machine;
pub mod math;
pub mod mcu_section;
pub mod move_sink;
pub mod output_pin;
pub mod planned_move;
pub mod probe;
mod reader;
pub mod safe_home;
pub mod screws_tilt;
pub mod sensor_section;
pub mod shaper_config;
pub mod spi_temperature;
pub mod temperature_sensor;
pub mod thermal;
pub mod thermistor;
/// TMC drivers (the `onechip-tmc` crate).
pub use onechip_tmc as tmc;
pub mod toolhead;
