//! `[bed_screws]`, as Klipper's `bed_screws`: BED_SCREWS_ADJUST takes the
//! nozzle to each screw in turn (up to `horizontal_move_z`, over the
//! screw, down to `probe_height`) for the user to adjust it with a sheet
//! of paper, then ACCEPT (next screw), ADJUSTED (next screw, and the
//! coarse round again afterwards) or ABORT; after the coarse round, the
//! screws with a `_fine_adjust` point get a fine round there.

use crate::move_sink::MoveSink;
use crate::reader::{Errors, Read, Reader};
use crate::screws_tilt::{Screw, Screws, read_fine_points, read_screws};
use crate::toolhead::{MoveError, Toolhead};
use onechip_config::{Bounds, Config};

/// The `[bed_screws]` section.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BedScrews<'a> {
    /// The screws (`screwN`, `screwN_name`).
    screws: Screws<'a>,
    /// The fine-adjust points (`screwN_fine_adjust`, with the screw's
    /// name).
    fine: Screws<'a>,
    /// `horizontal_move_z`: the height moves between screws go at, mm.
    pub horizontal_move_z: f64,
    /// `probe_height`: the nozzle's height over a screw, mm.
    pub probe_height: f64,
    /// `speed`: moves between screws, mm/s.
    pub speed: f64,
    /// `probe_speed`: moves up and down, mm/s.
    pub probe_speed: f64,
}

/// Reads `[bed_screws]`, if present.
// Out of line: see `Machine::from_config_in`.
#[inline(never)]
pub(crate) fn read<'c, 'a>(
    config: &'c Config<'a>,
    errors: &Errors<'c>,
) -> Read<Option<BedScrews<'a>>> {
    let Some(s) = config.section("bed_screws") else {
        return Ok(None);
    };
    let s = Reader::new(s, errors);
    let screws = read_screws(&s, "bed_screws: Must have at least three screws")?;
    Ok(Some(BedScrews {
        screws,
        fine: read_fine_points(&s, &screws)?,
        speed: s.float("speed", 50.0, Bounds::POSITIVE)?,
        probe_speed: s.float("probe_speed", 5.0, Bounds::POSITIVE)?,
        horizontal_move_z: s.float("horizontal_move_z", 5.0, Bounds::NONE)?,
        probe_height: s.float("probe_height", 0.0, Bounds::NONE)?,
    }))
}

/// Marks `[bed_screws]` as a section onechip reads.
pub fn is_section(name: &str) -> bool {
    name == "bed_screws"
}

/// Where the tool stands while it waits for the user.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Adjusting {
    /// In the fine round (else the coarse one).
    pub fine: bool,
    /// The screw the nozzle is over (index in its round).
    pub screw: usize,
    /// ADJUSTED was given in this coarse round: another follows.
    pub again: bool,
}

/// What the user answered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Answer {
    /// ACCEPT: the screw is right.
    Accept,
    /// ADJUSTED: a notable adjustment was made (the coarse round runs
    /// again once this one is over).
    Adjusted,
}

impl<'a> BedScrews<'a> {
    /// The screws of the coarse round (`fine` false) or the fine one.
    pub fn round(&self, fine: bool) -> &[Screw<'a>] {
        if fine { &self.fine } else { &self.screws }
    }

    /// BED_SCREWS_ADJUST: up to horizontal_move_z, then to the first
    /// screw; the state to wait in, and the screw to name.
    pub fn start<const N: usize>(
        &self,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
    ) -> Result<(Adjusting, Screw<'a>), MoveError> {
        let mut at = toolhead.position();
        at[2] = self.horizontal_move_z;
        toolhead.move_to(at, self.speed, sink)?;
        let state = Adjusting {
            fine: false,
            screw: 0,
            again: false,
        };
        self.visit(state, toolhead, sink)
    }

    /// ACCEPT or ADJUSTED in `state`: the next screw to wait at (Some),
    /// or the tool is done (None: the nozzle back up at horizontal_move_z),
    /// as Klipper's tool goes: the rest of this round, then the coarse
    /// round again after an ADJUSTED, then the fine round, then done.
    pub fn answer<const N: usize>(
        &self,
        state: Adjusting,
        answer: Answer,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
    ) -> Result<Option<(Adjusting, Screw<'a>)>, MoveError> {
        let again = state.again || answer == Answer::Adjusted;
        let next = if state.screw + 1 < self.round(state.fine).len() {
            Adjusting {
                screw: state.screw + 1,
                again,
                ..state
            }
        } else if again {
            Adjusting {
                fine: false,
                screw: 0,
                again: false,
            }
        } else if !state.fine && !self.fine.is_empty() {
            Adjusting {
                fine: true,
                screw: 0,
                again: false,
            }
        } else {
            let mut at = toolhead.position();
            at[2] = self.horizontal_move_z;
            toolhead.move_to(at, self.probe_speed, sink)?;
            return Ok(None);
        };
        self.visit(next, toolhead, sink).map(Some)
    }

    /// Klipper's move to a screw: up to horizontal_move_z at probe_speed,
    /// over the screw at speed, down to probe_height at probe_speed.
    fn visit<const N: usize>(
        &self,
        state: Adjusting,
        toolhead: &mut Toolhead<N>,
        sink: &mut impl MoveSink,
    ) -> Result<(Adjusting, Screw<'a>), MoveError> {
        let screw = self.round(state.fine)[state.screw];
        let mut at = toolhead.position();
        at[2] = self.horizontal_move_z;
        toolhead.move_to(at, self.probe_speed, sink)?;
        at[0] = screw.at[0];
        at[1] = screw.at[1];
        toolhead.move_to(at, self.speed, sink)?;
        at[2] = self.probe_height;
        toolhead.move_to(at, self.probe_speed, sink)?;
        Ok((state, screw))
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::string::ToString;

    #[test]
    fn screws_and_fine_points_read_as_klipper_reads_them() {
        let text = "[bed_screws]\nscrew1: 30,30\nscrew1_name: front left\n\
                    screw1_fine_adjust: 0,0\nscrew2: 200, 30\nscrew3: 200,200\n\
                    screw3_fine_adjust: 220,220\nprobe_height: 0.1\n";
        let config = Config::parse("printer.cfg", text).expect("parses");
        let b = Errors::run(|errors| read(&config, errors))
            .expect("reads")
            .expect("present");
        let names: std::vec::Vec<_> = b.round(false).iter().map(ToString::to_string).collect();
        assert_eq!(
            names,
            [
                "front left",
                "screw at 200.000,30.000",
                "screw at 200.000,200.000"
            ]
        );
        let fine: std::vec::Vec<_> = (b.round(true).iter())
            .map(|s| (s.to_string(), s.at))
            .collect();
        assert_eq!(
            fine,
            [
                ("front left".to_string(), [0.0, 0.0]),
                ("screw at 200.000,200.000".to_string(), [220.0, 220.0])
            ]
        );
        let options = (b.horizontal_move_z, b.probe_height, b.speed, b.probe_speed);
        assert_eq!(options, (5.0, 0.1, 50.0, 5.0));
        let bad = "[bed_screws]\nscrew1: 30\nscrew2: 1,2\nscrew3: 3,4\n";
        let config = Config::parse("printer.cfg", bad).expect("parses");
        let e = Errors::run(|errors| read(&config, errors))
            .expect_err("not a coordinate")
            .to_string();
        assert!(
            e.contains("screw1") && e.contains("needs to be an x,y coordinate"),
            "{e}"
        );
    }
}
