//! The README's main command, on the shipped default SD folder, works end to
//! end through the host build.

use std::path::PathBuf;

fn shipped_default() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../sdcard-configs/octopus-pro-h723")
}

#[test]
fn the_shipped_default_runs_clean() {
    let summary = onechip_host::run(&shipped_default(), None).expect("runs");
    assert!(summary.gcode_path.ends_with("first-layer-square.gcode"));
    for section in [
        "mcu",
        "printer",
        "stepper_x",
        "stepper_y",
        "stepper_z",
        "extruder",
    ] {
        assert!(
            summary.sections.iter().any(|s| s == section),
            "missing [{section}]"
        );
    }
    assert_eq!(summary.errors, []);
    assert_eq!(summary.acks, summary.lines);
    assert_eq!(summary.lines, 19);
}

#[test]
fn a_folder_without_gcode_is_a_clear_error() {
    let dir = std::env::temp_dir().join(format!("onechip-empty-sd-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    std::fs::write(dir.join("printer.cfg"), "[printer]\n").expect("write");
    let err = onechip_host::run(&dir, None).expect_err("no gcode");
    assert!(
        err.to_string()
            .contains("expected exactly one *.gcode file"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
