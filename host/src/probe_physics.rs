//! The simulated Z probe: it triggers where its tip, `x_offset`,
//! `y_offset` from the nozzle, touches the simulated bed, that is when the
//! nozzle is `z_offset` above the bed under the probe. The bed is a plane
//! ([`crate::Options::bed`]); the probe is read by the engine's endstop
//! check through its own slot's pins, as the board reads the probe pin.

use onechip_planner::machine::Machine;

/// Where the simulated probe triggers.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbePhysics {
    /// The probe's x_offset, y_offset, z_offset, mm.
    pub offsets: [f64; 3],
    /// The bed: height at X = Y = 0 (mm) and slopes along X and Y.
    pub bed: [f64; 3],
}

impl ProbePhysics {
    /// The bed's height at (`x`, `y`), mm.
    pub fn bed_height(&self, x: f64, y: f64) -> f64 {
        self.bed[0] + self.bed[1] * x + self.bed[2] * y
    }

    /// True while the probe touches the bed with the toolhead (nozzle)
    /// really at `toolhead` (mm).
    pub fn pressed(&self, toolhead: [f64; 3]) -> bool {
        let [xo, yo, zo] = self.offsets;
        toolhead[2] <= self.bed_height(toolhead[0] + xo, toolhead[1] + yo) + zo
    }
}

/// The probe of `machine` over the bed `bed`, with its engine slot.
pub fn for_machine(machine: &Machine<'_>, bed: [f64; 3]) -> Option<(usize, ProbePhysics)> {
    let probe = machine.probe.as_ref()?;
    let slot = machine.probe_slot()?;
    Some((
        slot,
        ProbePhysics {
            offsets: probe.offsets,
            bed,
        },
    ))
}
