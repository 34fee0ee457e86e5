//! The expensive half of the host role: itersolve and stepcompress over the
//! planner's moves, producing `(interval, count, add)` step queues for the
//! local stepper engine and `queue_step` commands for secondary MCUs (issue #4).
//!
//! Available now:
//! - [`motion`]: the whole pipeline for a machine: planned moves in, each
//!   stepper's commands out, with back-pressure;
//! - [`profile`]: the pipeline at the firmware's queue sizes, not generic
//!   (compiled here, whoever drives it);
//! - [`trapq`]: the bounded motion queue the planner fills and step
//!   generation reads, pruned as generation passes;
//! - [`segment`]: planned moves split into constant-acceleration segments,
//!   time gaps filled with stationary ones;
//! - [`solver`]: step times of one stepper (half-step crossings of its
//!   position), with Klipper's direction-change rules, over a whole
//!   segment queue as Klipper's itersolve walks its trapq;
//! - [`extruder`]: the extruder's position with smoothed pressure advance;
//! - [`shaper`]: input shaping of the X and Y positions a stepper follows;
//! - [`compress`]: step clocks to `(interval, count, add)` sequences within
//!   `max_error`, with the step+dir+step filter and far steps.
#![cfg_attr(not(feature = "std"), no_std)]

pub mod compress;
pub mod extruder;
pub mod motion;
pub mod profile;
pub mod segment;
pub mod shaper;
pub mod solver;
pub mod trapq;
