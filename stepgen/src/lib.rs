//! The expensive half of the host role: itersolve and stepcompress over the
//! planner's moves, producing `(interval, count, add)` step queues for the
//! local stepper engine and `queue_step` commands for secondary MCUs (issue #4).
#![cfg_attr(not(feature = "std"), no_std)]
