//! SET_PRESSURE_ADVANCE on the simulated shipped printer, over the
//! console: Klipper's reply, its refusals, and extrusion with the new
//! advance (golden_end_to_end.rs shows its steps equal klippy's when the
//! G-code sets what printer.cfg would).

use onechip_host::console_printer::ConsolePrinter;
use onechip_host::{Options, Start};
use onechip_tests::sd_folder;

#[test]
fn set_pressure_advance_reports_changes_and_refuses_as_klipper() {
    let cfg = sd_folder::shipped_cfg();
    // Extruding cold, as the simulated hot end is not heated here.
    let cfg = cfg.replace("[extruder]\n", "[extruder]\nmin_extrude_temp: 0\n");
    let dir = sd_folder::new("pa", &cfg, None);
    let options = Options {
        start: Start::At([50.0, 80.0, 30.0]),
        ..Options::default()
    };
    let mut p = ConsolePrinter::new(&dir, &options).expect("printer");
    // The shipped printer.cfg's.
    assert_eq!(
        p.send("SET_PRESSURE_ADVANCE"),
        "// pressure_advance: 0.040000\n// pressure_advance_smooth_time: 0.040000\nok\n"
    );
    assert_eq!(
        p.send("SET_PRESSURE_ADVANCE ADVANCE=0.05 SMOOTH_TIME=0.03"),
        "// pressure_advance: 0.050000\n// pressure_advance_smooth_time: 0.030000\nok\n"
    );
    // What is not given stays.
    assert!(
        p.send("SET_PRESSURE_ADVANCE EXTRUDER=extruder ADVANCE=0.06")
            .starts_with(
                "// pressure_advance: 0.060000\n// pressure_advance_smooth_time: 0.030000"
            )
    );
    for line in [
        "SET_PRESSURE_ADVANCE EXTRUDER=extruder1 ADVANCE=0.1",
        "SET_PRESSURE_ADVANCE ADVANCE=-1",
        "SET_PRESSURE_ADVANCE SMOOTH_TIME=0.3",
    ] {
        assert!(p.send(line).starts_with("!! "), "{line}");
    }
    assert!(
        p.send("SET_PRESSURE_ADVANCE")
            .starts_with("// pressure_advance: 0.060000")
    );
    // Extrusion with the advance: every step made, none lost.
    p.send("G28");
    p.send("M83");
    p.send("G1 X100 Y100 E10 F3000");
    p.send("SET_PRESSURE_ADVANCE ADVANCE=0");
    p.send("G1 X50 Y50 E5 F3000");
    p.send("M400");
    // The extruder (stepper 3: 200 × 16 steps per 33.5 mm) made every
    // step of the 15 mm, with and without the advance.
    let extruder = p.steps().nth(3).expect("the extruder's steps").position;
    let want = 15.0 * 200.0 * 16.0 / 33.5;
    assert!(
        (extruder as f64 - want).abs() <= 1.0,
        "{extruder} steps, not {want}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
