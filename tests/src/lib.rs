//! End-to-end tests of the host build live in `tests/`; here is what
//! they share for reading the golden data.

use std::path::PathBuf;

/// The golden data: `$ONECHIP_GOLDEN`, or `../shared/golden` beside the
/// checkout.
pub fn golden_dir() -> PathBuf {
    std::env::var_os("ONECHIP_GOLDEN").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/golden"),
        PathBuf::from,
    )
}

/// The number after `key` in golden case `case`'s `summary.txt`.
pub fn summary_value(case: &str, key: &str) -> f64 {
    let text =
        std::fs::read_to_string(golden_dir().join(case).join("summary.txt")).expect("summary");
    text.lines()
        .find_map(|l| l.strip_prefix(&format!("{key} ")))
        .expect("key")
        .trim()
        .parse()
        .expect("number")
}
