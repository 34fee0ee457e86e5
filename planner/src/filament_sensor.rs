//! Klipper's `[filament_switch_sensor NAME]`: a switch that reads
//! filament present; on runout while printing the print pauses (as PAUSE)
//! unless `pause_on_runout` is False. QUERY_FILAMENT_SENSOR and
//! SET_FILAMENT_SENSOR name it `SENSOR=NAME`.

use crate::output_pin::named;
use crate::reader::{Read, Reader};
use onechip_config::Bounds;

/// Most filament switch sensors.
pub const MAX_FILAMENT_SENSORS: usize = 2;

/// A `[filament_switch_sensor NAME]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FilamentSensor<'a> {
    /// NAME.
    pub name: &'a str,
    /// The section as written.
    pub section: &'a str,
    /// switch_pin, as written (`^` pull-up, `!` inverted): active means
    /// filament present.
    pub switch_pin: &'a str,
    /// pause_on_runout.
    pub pause_on_runout: bool,
    /// runout_gcode, if given: G-code run after the pause. Only plain
    /// commands (no templates) are run.
    pub runout_gcode: Option<&'a str>,
    /// insert_gcode, if given: run when filament is inserted while not
    /// printing.
    pub insert_gcode: Option<&'a str>,
    /// event_delay: no new event for this long after one, s.
    pub event_delay: f64,
    /// pause_delay: time the pause is given before runout_gcode, s.
    pub pause_delay: f64,
}

/// True if `section` is a filament switch sensor.
pub fn is_section(section: &str) -> bool {
    named(section, "filament_switch_sensor").is_some()
}

/// Reads a `[filament_switch_sensor NAME]`. G-code templates cannot run
/// here, so a runout or insert G-code using one is refused.
pub(crate) fn read<'c, 'a>(section: &Reader<'_, 'c, 'a>) -> Read<FilamentSensor<'a>> {
    let written = section.name_in_file();
    let gcode = |option: &'c str| match section.get_opt(option) {
        Some(text) if text.contains('{') => Err(section.error_for(
            option,
            "uses a template ({ }), which onechip does not support yet",
        )),
        other => Ok(other),
    };
    // Klipper's debounce option of button pins.
    let _ = section.float("debounce_delay", 0.0, Bounds::NON_NEGATIVE)?;
    Ok(FilamentSensor {
        name: named(written, "filament_switch_sensor").unwrap_or(written),
        section: written,
        switch_pin: section.get("switch_pin")?,
        pause_on_runout: section.get_bool("pause_on_runout", true)?,
        runout_gcode: gcode("runout_gcode")?,
        insert_gcode: gcode("insert_gcode")?,
        event_delay: section.float("event_delay", 3.0, Bounds::NON_NEGATIVE)?,
        pause_delay: section.float("pause_delay", 0.5, Bounds::POSITIVE)?,
    })
}
