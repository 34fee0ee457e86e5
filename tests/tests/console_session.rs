//! One scripted console session through the printer session as the board
//! runs it (lines arriving on the console in USB packets, the console's
//! priming timeout looking at the clock after each) and through the
//! simulator reading the same lines from the SD card: the same replies,
//! the same printer. printer.cfg is only an `[include]` of the machine.

use onechip_host::Options;
use onechip_tests::sd_folder;
use std::path::PathBuf;

const SCRIPT: &str = "M115\n\
G28\n\
G1 X20 Y30 Z5 F6000\n\
M104 S200\n\
M106 S128\n\
M109 S200\n\
M105\n\
G1 X1.2.3\n\
G1 X60 Y40 E2 F3000\n\
M114\n";

fn sd() -> PathBuf {
    let dir = sd_folder::new("console", "[include machine/*.cfg]\n", None);
    std::fs::create_dir_all(dir.join("machine")).expect("temp dir");
    std::fs::write(dir.join("machine/octopus.cfg"), sd_folder::shipped_cfg()).expect("cfg");
    std::fs::write(dir.join("session.gcode"), SCRIPT).expect("gcode");
    dir
}

#[test]
fn the_board_console_and_the_simulator_give_the_same_replies() {
    let dir = sd();
    let run = |console| {
        onechip_host::run_with(
            &dir,
            &Options {
                console,
                ..Options::default()
            },
        )
        .expect("runs")
    };
    let (board, simulator) = (run(true), run(false));
    assert_eq!(board.transcript, simulator.transcript);
    assert_eq!(board.print_time, simulator.print_time);
    let t = &board.transcript;
    // Every line is acknowledged exactly once (M105 on its `ok` line,
    // as Marlin: `ok T:200.0 /200.0 ...`).
    assert_eq!(
        t.lines()
            .filter(|l| *l == "ok" || l.starts_with("ok "))
            .count(),
        SCRIPT.lines().count()
    );
    assert!(t.lines().any(|l| l.starts_with("ok T:")), "{t}");
    assert!(
        t.starts_with("FIRMWARE_NAME:onechip FIRMWARE_VERSION:"),
        "{t}"
    );
    // The included config has a fan and heaters: M106 and M109 work,
    // M109 reports temperatures while it waits, M105 once more.
    assert!(board.errors.len() == 1, "{:?}", board.errors);
    assert!(
        board.errors[0].1.contains("unable to parse"),
        "{:?}",
        board.errors
    );
    assert_eq!(board.errors[0].0, 8);
    assert!(board.temperatures.len() >= 2, "{t}");
    assert!(board.temperatures.iter().any(|(line, _)| *line == 7));
    assert!(board.heat_wait > 0.0);
    assert_eq!(board.endstops.len(), 6);
    assert_eq!(
        board.replies.last().map(|r| r.1.as_str()),
        Some("X:60.000 Y:40.000 Z:5.000 E:2.000")
    );
    std::fs::remove_dir_all(&dir).ok();
}
