//! The toolhead: checks moves against the machine, queues them for
//! lookahead and hands planned moves, stamped with their print time, to the
//! motion queues (trapq) of the toolhead and the extruder.
//!
//! Print time is in seconds on the MCU's clock. Timing follows Klipper in
//! batch mode (no live MCU clock, so the estimated print time is 0): the
//! first move after an idle queue starts at the later of 0.25 s
//! (BUFFER_TIME_START) and the step generator's restart time, which is the
//! later of 0.1 s and the time steps were last flushed through, plus the
//! step-generation scan delay; steps are flushed through whenever the
//! position is set. Afterwards moves follow one another without gaps; a
//! dwell adds its time, M400 only flushes the lookahead.

use crate::lookahead::LookAhead;
use crate::move_sink::{ExtruderStepperMotion, MoveSink, TrapqMove};
use crate::planned_move::{E, Limits, Move};
use core::fmt;
use onechip_config::decimal::Fixed;

/// Time to buffer before the first move, s.
pub const BUFFER_TIME_START: f64 = 0.250;
/// Lookahead time gathered while priming, s.
pub const BUFFER_TIME_HIGH: f64 = 2.0;
/// When the moves released to step generation end less than this after
/// the MCU's clock, the lookahead is flushed whole, s (Klipper's
/// `BUFFER_TIME_LOW`).
pub const BUFFER_TIME_LOW: f64 = 1.0;
/// Minimum time to the first step generation, s.
pub const MIN_KIN_TIME: f64 = 0.100;
/// Step+dir+step filter window of stepcompress, s (the least scan delay).
pub const SDS_CHECK_TIME: f64 = 0.001;

/// How one axis homes (from its stepper section).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HomingInfo {
    /// position_endstop, mm.
    pub position_endstop: f64,
    /// True if the endstop is at the positive end of the axis.
    pub positive_dir: bool,
    /// homing_speed, mm/s.
    pub speed: f64,
    /// second_homing_speed, mm/s.
    pub second_speed: f64,
    /// homing_retract_dist, mm (0: no second homing move).
    pub retract_dist: f64,
    /// homing_retract_speed, mm/s.
    pub retract_speed: f64,
    /// The axis' travel (position_min, position_max), mm.
    pub range: (f64, f64),
    /// The axis homes on the probe (`probe:z_virtual_endstop`).
    pub probe: bool,
}

/// How a linear delta homes (Klipper's delta `home`): all three towers
/// at once, each carriage up to its own endstop.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DeltaHoming {
    /// stepper_a's homing options (speeds, retract), which Klipper's
    /// `home_rails` uses for all three towers.
    pub info: HomingInfo,
    /// Where homing ends: the toolhead position with every carriage at
    /// its endstop (position_endstop + sqrt(arm² - radius²) high), mm.
    pub home: [f64; 3],
    /// The Z the toolhead is taken to be at (X and Y those of `home`)
    /// before the first homing move: -1.5 × sqrt(largest arm² - max
    /// XY radius²), low enough for a carriage anywhere to reach its
    /// endstop, mm.
    pub force_z: f64,
}

/// Why a move was refused.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MoveError {
    /// What is wrong (the first line of Klipper's message).
    pub reason: &'static str,
    /// The requested end position.
    pub end: [f64; 4],
    /// What the message quotes after the reason.
    pub detail: Detail,
}

/// What a [`MoveError`]'s message quotes after its reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Detail {
    /// The requested end position (`reason: X Y Z [E]`, as Klipper's
    /// move errors).
    Position,
    /// A value against its limit, in `unit` (`reason (1.000mm vs
    /// 0.500mm)`).
    Limit {
        /// The move's value.
        value: f64,
        /// The configured limit.
        limit: f64,
        /// Unit written after both (`mm`, `mm^2`).
        unit: &'static str,
    },
    /// Nothing: the reason says it all.
    Nothing,
}

impl MoveError {
    /// The line Klipper adds under the message naming the option that
    /// sets the limit, if any (Klipper echoes both lines as `// ` info
    /// before the `!! ` line with the reason).
    pub fn hint(&self) -> Option<&'static str> {
        match self.reason {
            EXTRUDE_COLD => Some("See the 'min_extrude_temp' config option for details"),
            EXTRUDE_ONLY_TOO_LONG => {
                Some("See the 'max_extrude_only_distance' config option for details")
            }
            OVER_EXTRUSION => Some("See the 'max_extrude_cross_section' config option for details"),
            _ => None,
        }
    }
}

impl fmt::Display for MoveError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let e = &self.end;
        match self.detail {
            Detail::Limit { value, limit, unit } => {
                write!(
                    f,
                    "{} ({}{unit} vs {}{unit})",
                    self.reason,
                    Fixed(value, 3),
                    Fixed(limit, 3)
                )
            }
            Detail::Position => write!(
                f,
                "{}: {} {} {} [{}]",
                self.reason,
                Fixed(e[0], 3),
                Fixed(e[1], 3),
                Fixed(e[2], 3),
                Fixed(e[3], 3)
            ),
            Detail::Nothing => f.write_str(self.reason),
        }
    }
}

/// Klipper's refusal of an extrusion while the extruder is below
/// min_extrude_temp.
pub const EXTRUDE_COLD: &str = "Extrude below minimum temp";
/// Klipper's refusal of an extrude-only move (or retraction) longer than
/// max_extrude_only_distance.
pub const EXTRUDE_ONLY_TOO_LONG: &str = "Extrude only move too long";
/// Klipper's refusal of an extrusion wider than max_extrude_cross_section.
pub const OVER_EXTRUSION: &str = "Move exceeds maximum extrusion";

fn move_error(m: &Move, reason: &'static str) -> MoveError {
    MoveError {
        reason,
        end: m.end_pos,
        detail: Detail::Position,
    }
}

/// Travel limits and Z speed limits of a cartesian-style machine
/// (cartesian, corexy, corexz).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CartesianLimits {
    /// Allowed range per axis once homed; `(1, -1)` while not homed.
    pub range: [(f64, f64); 3],
    /// Configured range per axis (position_min, position_max).
    pub configured: [(f64, f64); 3],
    /// max_z_velocity, mm/s.
    pub max_z_velocity: f64,
    /// max_z_accel, mm/s².
    pub max_z_accel: f64,
    /// How each axis homes, if configured.
    pub homing: [Option<HomingInfo>; 3],
    /// The rails' extra steppers in engine-slot order from slot 3
    /// (`[stepper_z1]`: axis 2, number 1), for Klipper's messages.
    pub extra_steppers: [Option<(u8, u8)>; MAX_EXTRA_STEPPERS],
}

/// Most extra steppers of the rails (`[stepper_z1]`, …): the steppers
/// besides the three rails' and the extruder's.
pub const MAX_EXTRA_STEPPERS: usize = crate::machine::MAX_STEPPERS - 4;

const NOT_HOMED: (f64, f64) = (1.0, -1.0);

impl CartesianLimits {
    /// Limits of a machine not yet homed.
    pub fn new(configured: [(f64, f64); 3], max_z_velocity: f64, max_z_accel: f64) -> Self {
        Self {
            range: [NOT_HOMED; 3],
            homing: [None; 3],
            extra_steppers: [None; MAX_EXTRA_STEPPERS],
            configured,
            max_z_velocity,
            max_z_accel,
        }
    }

    /// Marks `axes` (0 = X, 1 = Y, 2 = Z) homed.
    pub fn set_homed(&mut self, axes: &[usize]) {
        for &a in axes {
            self.range[a] = self.configured[a];
        }
    }

    fn check_endstops(&self, m: &Move) -> Result<(), MoveError> {
        for i in 0..3 {
            let (low, high) = self.range[i];
            if m.axes_d[i] != 0.0 && (m.end_pos[i] < low || m.end_pos[i] > high) {
                return Err(move_error(
                    m,
                    if low > high {
                        "Must home axis first"
                    } else {
                        "Move out of range"
                    },
                ));
            }
        }
        Ok(())
    }

    /// Checks the move's range and applies the Z limits.
    pub fn check_move(&self, m: &mut Move) -> Result<(), MoveError> {
        let [x, y] = [m.end_pos[0], m.end_pos[1]];
        let (rx, ry) = (self.range[0], self.range[1]);
        if x < rx.0 || x > rx.1 || y < ry.0 || y > ry.1 {
            self.check_endstops(m)?;
        }
        if m.axes_d[2] == 0.0 {
            return Ok(());
        }
        self.check_endstops(m)?;
        let z_ratio = m.move_d / m.axes_d[2].abs();
        m.limit_speed(self.max_z_velocity * z_ratio, self.max_z_accel * z_ratio);
        Ok(())
    }
}

/// Travel limits of a linear delta: a cylinder tapered at the top, with
/// moves slowed near its edge where towers move fast for small XY motion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DeltaLimits {
    /// Squared XY radius within which plain XY moves skip the checks
    /// (learned from previous moves; -1 forces a full check).
    limit_xy2: f64,
    /// Largest allowed XY radius, squared, mm².
    pub max_xy2: f64,
    /// XY radius squared beyond which moves run at half speed, mm².
    pub slow_xy2: f64,
    /// XY radius squared beyond which moves run at quarter speed, mm².
    pub very_slow_xy2: f64,
    /// Highest reachable Z (the lowest tower endstop), mm.
    pub max_z: f64,
    /// minimum_z_position, mm.
    pub min_z: f64,
    /// Z above which the radius tapers, mm.
    pub limit_z: f64,
    /// Toolhead limits at start-up, mm/s and mm/s².
    pub max_velocity: f64,
    /// See `max_velocity`.
    pub max_accel: f64,
    /// max_z_velocity, mm/s.
    pub max_z_velocity: f64,
    /// How the towers home, if they can (set by the machine's reader).
    pub homing: Option<DeltaHoming>,
    need_home: bool,
}

impl DeltaLimits {
    /// Limits of a delta not yet homed.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        max_xy2: f64,
        slow_xy2: f64,
        very_slow_xy2: f64,
        max_z: f64,
        min_z: f64,
        limit_z: f64,
        max_velocity: f64,
        max_accel: f64,
        max_z_velocity: f64,
    ) -> Self {
        Self {
            limit_xy2: -1.0,
            max_xy2,
            slow_xy2,
            very_slow_xy2,
            max_z,
            min_z,
            limit_z,
            max_velocity,
            max_accel,
            max_z_velocity,
            homing: None,
            need_home: true,
        }
    }

    fn check_move(&mut self, m: &mut Move) -> Result<(), MoveError> {
        let end = m.end_pos;
        let end_xy2 = end[0] * end[0] + end[1] * end[1];
        if end_xy2 <= self.limit_xy2 && m.axes_d[2] == 0.0 {
            return Ok(());
        }
        if self.need_home {
            return Err(move_error(m, "Must home first"));
        }
        let end_z = end[2];
        let mut limit_xy2 = self.max_xy2;
        if end_z > self.limit_z {
            let above = self.max_z - end_z;
            limit_xy2 = limit_xy2.min(above * above);
        }
        if end_xy2 > limit_xy2 || end_z > self.max_z || end_z < self.min_z {
            // Out of range, unless it is the homing move: straight up to
            // the home position, which may lie above the lowest endstop.
            let homing = self.homing.is_some_and(|h| {
                end[0] == h.home[0]
                    && end[1] == h.home[1]
                    && end_z >= self.min_z
                    && end_z <= h.home[2]
            });
            if !homing {
                return Err(move_error(m, "Move out of range"));
            }
            limit_xy2 = -1.0;
        }
        if m.axes_d[2] != 0.0 {
            let z_ratio = m.move_d / m.axes_d[2].abs();
            m.limit_speed(self.max_z_velocity * z_ratio, m.accel);
            limit_xy2 = -1.0;
        }
        let start_xy2 = m.start_pos[0] * m.start_pos[0] + m.start_pos[1] * m.start_pos[1];
        let extreme_xy2 = end_xy2.max(start_xy2);
        if extreme_xy2 > self.slow_xy2 {
            let r = if extreme_xy2 > self.very_slow_xy2 {
                0.25
            } else {
                0.5
            };
            m.limit_speed(self.max_velocity * r, self.max_accel * r);
            limit_xy2 = -1.0;
        }
        self.limit_xy2 = limit_xy2.min(self.slow_xy2);
        Ok(())
    }
}

/// The machine's travel limits, by kinematics.
// One per machine and no heap to box into: the size difference is harmless.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Travel {
    /// Cartesian, CoreXY, CoreXZ.
    Cartesian(CartesianLimits),
    /// Linear delta.
    Delta(DeltaLimits),
}

impl Travel {
    /// Extra stepper `index` (engine slot `3 + index`): its axis and the
    /// number in its section's name.
    pub fn extra_stepper(&self, index: usize) -> Option<(u8, u8)> {
        match self {
            Self::Cartesian(c) => c.extra_steppers.get(index).copied().flatten(),
            _ => None,
        }
    }

    /// Checks a move and applies the kinematics' speed limits.
    pub fn check_move(&mut self, m: &mut Move) -> Result<(), MoveError> {
        match self {
            Self::Cartesian(c) => c.check_move(m),
            Self::Delta(d) => d.check_move(m),
        }
    }

    /// How `axis` homes on its own, where supported (cartesian-style
    /// machines; a delta's towers home together: [`Self::delta_homing`]).
    pub fn homing_info(&self, axis: usize) -> Option<HomingInfo> {
        match self {
            Self::Cartesian(c) => c.homing.get(axis).copied().flatten(),
            Self::Delta(_) => None,
        }
    }

    /// How a delta's towers home, if this is a delta.
    pub fn delta_homing(&self) -> Option<DeltaHoming> {
        match self {
            Self::Cartesian(_) => None,
            Self::Delta(d) => d.homing,
        }
    }

    /// Notes that `axis` has been homed (cartesian-style machines).
    pub fn set_axis_homed(&mut self, axis: usize) {
        if let Self::Cartesian(c) = self {
            c.set_homed(&[axis]);
        }
    }

    /// True once `axis` is homed (a delta: all or none).
    pub fn axis_homed(&self, axis: usize) -> bool {
        match self {
            Self::Cartesian(c) => c.range.get(axis).is_some_and(|r| r.0 <= r.1),
            Self::Delta(d) => !d.need_home,
        }
    }

    /// Forgets that `axis` is homed (cartesian-style machines).
    pub fn clear_axis_homed(&mut self, axis: usize) {
        if let Self::Cartesian(c) = self
            && let Some(r) = c.range.get_mut(axis)
        {
            *r = NOT_HOMED;
        }
    }

    /// Forgets homing (M84: the motors may move freely): every axis must
    /// be homed again before it moves.
    pub fn clear_homed(&mut self) {
        match self {
            Self::Cartesian(c) => c.range = [NOT_HOMED; 3],
            Self::Delta(d) => d.need_home = true,
        }
    }

    /// Notes that the position was set with every axis homed.
    pub fn set_homed(&mut self) {
        match self {
            Self::Cartesian(c) => c.set_homed(&[0, 1, 2]),
            Self::Delta(d) => {
                d.limit_xy2 = -1.0;
                d.need_home = false;
            }
        }
    }
}

/// The extruder's limits ([extruder] section).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExtruderLimits {
    /// nozzle_diameter, mm.
    pub nozzle_diameter: f64,
    /// Filament cross-section, mm².
    pub filament_area: f64,
    /// max_extrude_cross_section over the filament area.
    pub max_extrude_ratio: f64,
    /// max_extrude_only_velocity, mm/s.
    pub max_e_velocity: f64,
    /// max_extrude_only_accel, mm/s².
    pub max_e_accel: f64,
    /// max_extrude_only_distance, mm.
    pub max_e_dist: f64,
    /// instantaneous_corner_velocity, mm/s.
    pub instant_corner_v: f64,
}

impl ExtruderLimits {
    /// Klipper's extruder check of a move with E motion: refused while the
    /// extruder may not extrude (`can_extrude` false: below
    /// min_extrude_temp), when extrude-only (or retracting) further than
    /// max_extrude_only_distance, or wider than max_extrude_cross_section;
    /// extrude-only moves are slowed to the extrude-only limits.
    fn check_move(&self, m: &mut Move, can_extrude: bool) -> Result<(), MoveError> {
        let axis_r = m.axes_r[E];
        let axis_d = m.axes_d[E];
        let refuse = |reason, detail| MoveError {
            reason,
            end: m.end_pos,
            detail,
        };
        if !can_extrude {
            return Err(refuse(EXTRUDE_COLD, Detail::Nothing));
        }
        if (m.axes_d[0] == 0.0 && m.axes_d[1] == 0.0) || axis_r < 0.0 {
            // Extrude-only move or retraction.
            if axis_d.abs() > self.max_e_dist {
                return Err(refuse(
                    EXTRUDE_ONLY_TOO_LONG,
                    Detail::Limit {
                        value: axis_d,
                        limit: self.max_e_dist,
                        unit: "mm",
                    },
                ));
            }
            let inv_extrude_r = 1.0 / axis_r.abs();
            m.limit_speed(
                self.max_e_velocity * inv_extrude_r,
                self.max_e_accel * inv_extrude_r,
            );
        } else if axis_r > self.max_extrude_ratio
            && axis_d > self.nozzle_diameter * self.max_extrude_ratio
        {
            return Err(refuse(
                OVER_EXTRUSION,
                Detail::Limit {
                    value: axis_r * self.filament_area,
                    limit: self.max_extrude_ratio * self.filament_area,
                    unit: "mm^2",
                },
            ));
        }
        Ok(())
    }

    fn calc_junction(&self, prev: &Move, m: &Move) -> f64 {
        let diff_r = m.axes_r[E] - prev.axes_r[E];
        if diff_r != 0.0 {
            let v = self.instant_corner_v / diff_r.abs();
            v * v
        } else {
            m.max_cruise_v2
        }
    }
}

/// Where the queue stands (Klipper's "special queuing state").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum QueueState {
    /// Idle: the next flush re-anchors print time.
    NeedPrime,
    /// Moves queued since idle, none planned yet; a priming timeout
    /// flushes them all.
    Priming,
    /// Moves flowing.
    Main,
}

/// The toolhead with a lookahead queue of `N` moves.
#[derive(Debug, Clone)]
pub struct Toolhead<const N: usize> {
    /// Current limits (SET_VELOCITY_LIMIT and M204 change them).
    pub limits: Limits,
    /// Kinematic travel limits.
    pub kinematics: Travel,
    /// The extruder, if configured.
    pub extruder: Option<ExtruderLimits>,
    /// The extruder is hot enough to move (see [`Self::set_can_extrude`]).
    can_extrude: bool,
    lookahead: LookAhead<N>,
    commanded_pos: [f64; 4],
    print_time: f64,
    state: QueueState,
    /// The next released move starts no earlier than this, s
    /// ([`Self::hold_until`]).
    hold: f64,
    /// The MCU's print time when printing starts (0 in klippy's batch
    /// mode), s.
    time_origin: f64,
    /// Time up to which steps must be generated for the queued moves, s.
    need_step_gen_time: f64,
    /// Time up to which steps have been flushed through, s.
    last_step_gen_time: f64,
    /// Step-generation scan window (the later of SDS_CHECK_TIME and the
    /// machine's pressure advance / input shaper windows), s.
    kin_flush_delay: f64,
    /// The scan window of everything but the extruder steppers (the
    /// input shaper's), s.
    other_scan: f64,
    /// The last move released: its start print time (s) and the move
    /// (where a probing move was at its trigger).
    last_released: Option<(f64, Move)>,
}

impl<const N: usize> Toolhead<N> {
    /// A toolhead at rest at position 0; `scan_delay` is the largest
    /// step-generation scan window of the machine (pressure advance
    /// smoothing, input shaping), s.
    pub fn new(
        limits: Limits,
        kinematics: Travel,
        extruder: Option<ExtruderLimits>,
        scan_delay: f64,
    ) -> Self {
        let mut slot = core::mem::MaybeUninit::uninit();
        Self::init_in(&mut slot, limits, kinematics, extruder, scan_delay);
        // SAFETY: `init_in` initialised it.
        unsafe { slot.assume_init() }
    }

    /// [`Self::new`] built in place in `slot` (a long lookahead is too
    /// large to pass through a small stack); returns it.
    pub fn init_in(
        slot: &mut core::mem::MaybeUninit<Self>,
        limits: Limits,
        kinematics: Travel,
        extruder: Option<ExtruderLimits>,
        scan_delay: f64,
    ) -> &mut Self {
        use core::ptr::addr_of_mut;
        let p = slot.as_mut_ptr();
        // SAFETY: `p` is valid for writes; every field is written exactly
        // once (the empty lookahead straight into the slot: its storage is
        // uninitialised, so only its length is stored) before the slot is
        // taken as initialised.
        unsafe {
            addr_of_mut!((*p).lookahead).write(LookAhead::new());
            (*addr_of_mut!((*p).lookahead)).set_flush_time(BUFFER_TIME_HIGH);
            addr_of_mut!((*p).limits).write(limits);
            addr_of_mut!((*p).kinematics).write(kinematics);
            addr_of_mut!((*p).extruder).write(extruder);
            addr_of_mut!((*p).can_extrude).write(true);
            addr_of_mut!((*p).commanded_pos).write([0.0; 4]);
            addr_of_mut!((*p).print_time).write(0.0);
            addr_of_mut!((*p).state).write(QueueState::NeedPrime);
            addr_of_mut!((*p).time_origin).write(0.0);
            addr_of_mut!((*p).hold).write(f64::NEG_INFINITY);
            addr_of_mut!((*p).need_step_gen_time).write(0.0);
            addr_of_mut!((*p).last_step_gen_time).write(0.0);
            addr_of_mut!((*p).kin_flush_delay).write(scan_delay.max(SDS_CHECK_TIME));
            addr_of_mut!((*p).other_scan).write(scan_delay);
            addr_of_mut!((*p).last_released).write(None);
            slot.assume_init_mut()
        }
    }

    /// Whether moves with E motion may run: false while the extruder's
    /// heater is below its min_extrude_temp (they are then refused with
    /// Klipper's "Extrude below minimum temp"). True from the start: a
    /// toolhead alone plans as klippy's batch mode, which never refuses;
    /// the printer sets it from the heaters.
    pub fn set_can_extrude(&mut self, can_extrude: bool) {
        self.can_extrude = can_extrude;
    }

    /// Starts the clock at `origin` s instead of 0, as when printing begins
    /// long after the MCU started (print times then count from there).
    pub fn with_time_origin(mut self, origin: f64) -> Self {
        self.set_time_origin(origin);
        self
    }

    /// [`Self::with_time_origin`] in place (a toolhead with a long
    /// lookahead is large to move).
    pub fn set_time_origin(&mut self, origin: f64) {
        self.time_origin = origin;
        self.print_time = self.print_time.max(origin);
    }

    /// True while nothing is queued or flowing: the next move re-anchors
    /// print time.
    pub fn is_idle(&self) -> bool {
        self.state == QueueState::NeedPrime
    }

    /// True once moves flow (some have been released to step generation
    /// since the toolhead was last idle): their print times are fixed.
    pub fn is_flowing(&self) -> bool {
        self.state == QueueState::Main
    }

    /// The next move of an idle toolhead starts no earlier than print time
    /// `t` s (as klippy holds it back until its estimate of the MCU's
    /// print time lets it).
    pub fn hold_until(&mut self, t: f64) {
        if self.is_idle() {
            self.hold = t;
        }
    }

    /// If a priming timeout would plan moves now: how many of them are
    /// toolhead moves.
    pub fn priming_moves(&self) -> Option<usize> {
        let queued = self.lookahead.moves();
        (self.state == QueueState::Priming && !queued.is_empty())
            .then(|| queued.iter().filter(|m| m.is_kinematic).count())
    }

    /// What klippy's priming timer does when it expires (0.1 s after the
    /// first move of an idle queue, if no move has been planned since):
    /// plan and release every queued move. Hosts call it when that time has
    /// passed while reading input.
    pub fn priming_timeout(&mut self, sink: &mut impl MoveSink) {
        if self.state == QueueState::Priming {
            self.flush_lookahead(sink);
        }
    }

    /// What klippy's flush timer does while moves flow: once the moves
    /// released so far end within [`BUFFER_TIME_LOW`] of print time `now`
    /// (s, the MCU's clock), the input has stalled and every queued move
    /// is planned to a stop and released, so none is left waiting for
    /// lines that are not coming.
    pub fn flush_if_low(&mut self, now: f64, sink: &mut impl MoveSink) {
        if self.state == QueueState::Main && self.print_time - now < BUFFER_TIME_LOW {
            self.flush_lookahead(sink);
        }
    }

    /// The position of the last queued move, mm.
    pub fn position(&self) -> [f64; 4] {
        self.commanded_pos
    }

    /// The print time queued so far, s.
    pub fn print_time(&self) -> f64 {
        self.print_time
    }

    /// Queues a move to `new_pos` at `speed` mm/s.
    pub fn move_to(
        &mut self,
        new_pos: [f64; 4],
        speed: f64,
        sink: &mut impl MoveSink,
    ) -> Result<(), MoveError> {
        let Some(mut m) = Move::new(&self.limits, self.commanded_pos, new_pos, speed) else {
            return Ok(());
        };
        if m.is_kinematic {
            self.kinematics.check_move(&mut m)?;
        }
        if m.axes_d[E] != 0.0 {
            match &self.extruder {
                Some(e) => e.check_move(&mut m, self.can_extrude)?,
                None => return Err(move_error(&m, "Extrude when no extruder present")),
            }
        }
        self.commanded_pos = m.end_pos;
        if self.lookahead.is_full() {
            self.process_lookahead(true, sink);
            if self.lookahead.is_full() {
                self.process_lookahead(false, sink);
            }
        }
        let extruder = self.extruder;
        let want_flush = self.lookahead.add(m, |prev, next| match &extruder {
            Some(e) => e.calc_junction(prev, next),
            None => next.max_cruise_v2,
        });
        if want_flush {
            self.process_lookahead(true, sink);
        }
        if self.state == QueueState::NeedPrime {
            self.state = QueueState::Priming;
        }
        Ok(())
    }

    /// Limits the speed of the junction after the last queued move.
    pub fn limit_next_junction_speed(&mut self, speed: f64) {
        if let Some(m) = self.lookahead.last_mut() {
            m.limit_next_junction_speed(speed);
        }
    }

    /// Waits `delay` s after the queued moves (G4).
    pub fn dwell(&mut self, delay: f64, sink: &mut impl MoveSink) {
        let next = self.last_move_time(sink) + delay.max(0.0);
        self.print_time = self.print_time.max(next);
        self.state = QueueState::Priming;
    }

    /// Flushes every queued move (M400).
    pub fn wait_moves(&mut self, sink: &mut impl MoveSink) {
        self.flush_lookahead(sink);
    }

    /// Sets the position without moving (SET_KINEMATIC_POSITION, homing).
    pub fn set_position(&mut self, pos: [f64; 4], sink: &mut impl MoveSink) {
        self.flush_step_generation(sink);
        self.commanded_pos = pos;
        sink.set_position([pos[0], pos[1], pos[2]]);
    }

    /// Flushes the lookahead and returns the print time after the queued
    /// moves, s (re-anchoring it if the queue was idle).
    pub fn last_move_time(&mut self, sink: &mut impl MoveSink) -> f64 {
        if self.state == QueueState::Main {
            self.process_lookahead(false, sink);
        } else {
            self.flush_lookahead(sink);
            self.calc_print_time();
        }
        self.print_time
    }

    fn flush_lookahead(&mut self, sink: &mut impl MoveSink) {
        self.process_lookahead(false, sink);
        self.state = QueueState::NeedPrime;
        self.lookahead.set_flush_time(BUFFER_TIME_HIGH);
    }

    /// A move planned alone and run to its end (a homing move): it starts
    /// after the step generator's scan window and steps are flushed through
    /// its end before anything else moves.
    pub fn drip_move(
        &mut self,
        target: [f64; 4],
        speed: f64,
        sink: &mut impl MoveSink,
    ) -> Result<(), MoveError> {
        let mut target = target;
        target[E] = self.commanded_pos[E];
        let mut planned = Move::new(&self.limits, self.commanded_pos, target, speed);
        if let Some(m) = planned.as_mut() {
            self.kinematics.check_move(m)?;
        }
        self.dwell(self.kin_flush_delay, sink);
        self.process_lookahead(false, sink);
        if let Some(m) = planned {
            self.commanded_pos = m.end_pos;
            self.lookahead.add(m, |_, next| next.max_cruise_v2);
        }
        let count = self.lookahead.flush(false);
        self.calc_print_time();
        let end = self.release(count, sink);
        self.lookahead.reset();
        let through = end + self.kin_flush_delay;
        self.last_step_gen_time = self.last_step_gen_time.max(through);
        self.flush_step_generation(sink);
        Ok(())
    }

    /// Every queued move has run and the motion stopped at print time `t`
    /// s, before the planned end (a homing move cut short by its endstop):
    /// print time and step generation go on from `t`.
    pub(crate) fn rewind_to(&mut self, t: f64) {
        self.print_time = t;
        self.need_step_gen_time = t;
        self.last_step_gen_time = t;
    }

    /// Steps have been generated up to print time `t` s (klippy's
    /// `min_restart_time`): the first move after an idle queue starts no
    /// earlier than `t` plus the step generator's scan delay, so that it
    /// changes no step already generated (an input shaper's or pressure
    /// advance's look-back would otherwise see it start in the past).
    pub fn note_steps_generated(&mut self, t: f64) {
        if t.is_finite() {
            self.last_step_gen_time = self.last_step_gen_time.max(t);
        }
    }

    /// Where the last released move was at print time `t` (s), mm.
    pub(crate) fn released_position_at(&self, t: f64) -> Option<[f64; 4]> {
        let (start, m) = self.last_released.as_ref()?;
        let t = crate::math::clamp(t - start, 0.0, m.accel_t + m.cruise_t + m.decel_t);
        let accel_d = (m.start_v + 0.5 * m.accel * m.accel_t) * m.accel_t;
        let dist = if t < m.accel_t {
            (m.start_v + 0.5 * m.accel * t) * t
        } else if t < m.accel_t + m.cruise_t {
            accel_d + m.cruise_v * (t - m.accel_t)
        } else {
            let td = t - m.accel_t - m.cruise_t;
            accel_d + m.cruise_v * m.cruise_t + (m.cruise_v - 0.5 * m.accel * td) * td
        };
        Some(core::array::from_fn(|i| {
            m.start_pos[i] + m.axes_r[i] * dist
        }))
    }

    /// The scan window of everything but the extruder steppers (the input
    /// shaper's), s.
    pub fn note_other_scan(&mut self, other_scan: f64) {
        self.other_scan = other_scan;
    }

    /// Extruder stepper `stepper` (the machine's index) follows `motion`
    /// from after the moves so far (Klipper's SET_PRESSURE_ADVANCE,
    /// SET_EXTRUDER_ROTATION_DISTANCE, SYNC_EXTRUDER_MOTION): step
    /// generation is flushed and the sink told; `sync`: the stepper takes
    /// the extruder's position as its own. `extruder_scan` is the
    /// extruder steppers' scan window now (s), which the scan window
    /// follows.
    pub fn set_extruder_stepper(
        &mut self,
        stepper: usize,
        motion: &ExtruderStepperMotion,
        sync: bool,
        extruder_scan: f64,
        sink: &mut impl MoveSink,
    ) {
        self.flush_step_generation(sink);
        let position = sync.then_some(self.commanded_pos[E]);
        sink.extruder_stepper(stepper, motion, position);
        self.kin_flush_delay = self.other_scan.max(extruder_scan).max(SDS_CHECK_TIME);
    }

    pub(crate) fn flush_step_generation(&mut self, sink: &mut impl MoveSink) {
        self.flush_lookahead(sink);
        self.last_step_gen_time = self.last_step_gen_time.max(self.need_step_gen_time);
    }

    fn calc_print_time(&mut self) {
        let kin_time =
            (self.time_origin + MIN_KIN_TIME).max(self.last_step_gen_time) + self.kin_flush_delay;
        let min_print_time = (self.time_origin + BUFFER_TIME_START).max(kin_time);
        if min_print_time > self.print_time {
            self.print_time = min_print_time;
        }
    }

    fn process_lookahead(&mut self, lazy: bool, sink: &mut impl MoveSink) {
        let count = self.lookahead.flush(lazy);
        if count == 0 {
            return;
        }
        if self.state != QueueState::Main {
            self.state = QueueState::Main;
            self.calc_print_time();
        }
        self.release(count, sink);
    }

    /// Hands the `count` oldest planned moves to the sink, back to back from
    /// the current print time, and advances print time past them; returns
    /// the end of the last one, s.
    fn release(&mut self, count: usize, sink: &mut impl MoveSink) -> f64 {
        let mut next_move_time = self.print_time.max(self.hold);
        self.hold = f64::NEG_INFINITY;
        self.lookahead.take(count, |m| {
            emit(m, next_move_time, sink);
            self.last_released = Some((next_move_time, *m));
            // Same summation order as klippy, so times match to the last bit.
            next_move_time = next_move_time + m.accel_t + m.cruise_t + m.decel_t;
        });
        self.need_step_gen_time = self
            .need_step_gen_time
            .max(next_move_time + self.kin_flush_delay);
        self.print_time = self.print_time.max(next_move_time);
        next_move_time
    }
}

/// Hands one planned move to the sink's motion queues.
fn emit(m: &Move, print_time: f64, sink: &mut impl MoveSink) {
    let base = TrapqMove {
        print_time,
        accel_t: m.accel_t,
        cruise_t: m.cruise_t,
        decel_t: m.decel_t,
        start_pos: [m.start_pos[0], m.start_pos[1], m.start_pos[2]],
        axes_r: [m.axes_r[0], m.axes_r[1], m.axes_r[2]],
        start_v: m.start_v,
        cruise_v: m.cruise_v,
        accel: m.accel,
    };
    if m.is_kinematic {
        sink.toolhead(&base);
    }
    if m.axes_d[E] != 0.0 {
        let r = m.axes_r[E];
        let pressure_advance = r > 0.0 && (m.axes_d[0] != 0.0 || m.axes_d[1] != 0.0);
        sink.extruder(&TrapqMove {
            start_pos: [m.start_pos[E], 0.0, 0.0],
            axes_r: [1.0, if pressure_advance { 1.0 } else { 0.0 }, 0.0],
            start_v: m.start_v * r,
            cruise_v: m.cruise_v * r,
            accel: m.accel * r,
            ..base
        });
    }
}
