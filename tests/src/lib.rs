//! End-to-end tests of the host build live in `tests/`; the golden data
//! they read comes from `onechip-golden`, re-exported here.

pub mod peers;

pub use onechip_golden::{golden_dir, summary_value};
