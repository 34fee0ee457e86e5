//! The console as Marlin-family hosts drive it, on the simulated shipped
//! printer in virtual time: numbered lines with checksums and resends,
//! `ok T:` temperatures and auto-reports, printing from the card (list,
//! select, print, progress, done; upload and delete), M112 at once and a
//! restart after it.

use onechip_host::console_printer::ConsolePrinter;
use onechip_host::{Options, Start};
use onechip_tests::sd_folder;
use std::path::{Path, PathBuf};

/// A short job: home while the hot end heats, then a square with
/// extrusion.
const JOB: &str = "M104 S200\nG28\nM109 S200\nG90\nG1 Z5 F600\nG1 X20 Y20 F6000\nG1 X60 Y20 E2\nG1 X60 Y60 E4\nG1 X20 Y60 E6\nG1 X20 Y20 E8\nM400\n";

/// A fresh SD folder with the shipped printer.cfg.
fn sd(name: &str) -> PathBuf {
    sd_folder::new(&format!("protocol-{name}"), &sd_folder::shipped_cfg(), None)
}

fn printer(dir: &Path) -> ConsolePrinter {
    let options = Options {
        start: Start::At([50.0, 80.0, 30.0]),
        ..Options::default()
    };
    ConsolePrinter::new(dir, &options).expect("printer")
}

/// `line` numbered `n` with its checksum, as OctoPrint and Printrun send.
fn numbered(n: u32, line: &str) -> String {
    let body = format!("N{n} {line}");
    let sum = body.bytes().fold(0u8, |a, b| a ^ b);
    format!("{body}*{sum}")
}

/// Steps and final position of every stepper.
fn steps(p: &ConsolePrinter) -> Vec<(usize, i64)> {
    p.steps().map(|l| (l.count, l.position)).collect()
}

/// Runs until the card's print is done (at most `limit` s).
fn print_to_end(p: &mut ConsolePrinter, limit: f64) -> String {
    let mut out = String::new();
    let mut waited = 0.0;
    while !out.contains("Done printing file") {
        assert!(waited < limit, "not done after {limit} s:\n{out}");
        out += &p.run_for(1.0);
        waited += 1.0;
    }
    out + &p.run_for(1.0)
}

#[test]
fn a_corrupt_line_is_resent_and_every_line_runs_exactly_once() {
    let dir = sd("resend");
    let lines: Vec<&str> = JOB.lines().collect();
    // Clean: every line numbered, each answered `ok`.
    let mut clean = printer(&dir);
    assert!(clean.send(&numbered(0, "M110 N0")).ends_with("ok\n"));
    for (i, line) in lines.iter().enumerate() {
        let reply = clean.send(&numbered(i as u32 + 1, line));
        assert!(reply.ends_with("ok\n"), "{reply}");
        assert!(!reply.contains("Error"), "{reply}");
    }
    clean.run_for(2.0);
    // Line 4 arrives corrupted: refused with a resend request, not run;
    // line 5, already on its way, is refused too; the host resends from
    // 4, and then (as a host whose resend crossed a second request does)
    // sends 4 once more, which is acknowledged without running again.
    let mut lossy = printer(&dir);
    lossy.send(&numbered(0, "M110 N0"));
    for (i, line) in lines.iter().enumerate().take(3) {
        lossy.send(&numbered(i as u32 + 1, line));
    }
    let mut corrupt = numbered(4, lines[3]).into_bytes();
    corrupt[5] ^= 0x04;
    corrupt.push(b'\n');
    let refused = lossy.receive(&corrupt);
    assert_eq!(
        refused,
        "Error:checksum mismatch, Last Line: 3\nResend: 4\nok\n"
    );
    let skipped = lossy.send(&numbered(5, lines[4]));
    assert_eq!(
        skipped,
        "Error:Line Number is not Last Line Number+1, Last Line: 3\nResend: 4\nok\n"
    );
    let unnumbered_sum = lossy.send(&numbered(4, lines[3]).replace("N4 ", "N4  "));
    assert!(
        unnumbered_sum.contains("checksum mismatch"),
        "{unnumbered_sum}"
    );
    for (i, line) in lines.iter().enumerate().skip(3) {
        let reply = lossy.send(&numbered(i as u32 + 1, line));
        assert!(
            reply.ends_with("ok\n") && !reply.contains("Error"),
            "{reply}"
        );
        if i == 3 {
            assert_eq!(
                lossy.send(&numbered(4, line)),
                "ok\n",
                "repeat acknowledged"
            );
        }
    }
    lossy.run_for(2.0);
    assert_eq!(steps(&lossy), steps(&clean));
    assert_eq!(lossy.position(), clean.position());
    assert_eq!(clean.position(), [20.0, 20.0, 5.0, 8.0]);
    let missing = lossy.send("N12 G1 X1");
    assert!(
        missing.starts_with("Error:No Checksum with line number, Last Line: 11\nResend: 12\n"),
        "{missing}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn temperatures_come_on_the_ok_and_as_auto_reports() {
    let dir = sd("m105");
    let mut p = printer(&dir);
    let m115 = p.send("M115");
    assert!(m115.starts_with("FIRMWARE_NAME:onechip"), "{m115}");
    for cap in [
        "AUTOREPORT_TEMP:1",
        "EMERGENCY_PARSER:1",
        "AUTOREPORT_SD_STATUS:1",
        "EXTENDED_M20:1",
    ] {
        assert!(m115.contains(&format!("Cap:{cap}\n")), "{cap}: {m115}");
    }
    p.run_for(1.0);
    let m105 = p.send("M105");
    assert!(m105.starts_with("ok T:"), "{m105}");
    assert!(
        m105.contains(" B:") && m105.contains(" @:") && m105.contains(" B@:"),
        "{m105}"
    );
    // Heating: the hot end's power shows.
    p.send("M104 S200");
    p.run_for(2.0);
    let heating = p.send("M105");
    assert!(
        heating.contains(" @:127 "),
        "full power while far below: {heating}"
    );
    assert_eq!(m105.lines().count(), 1, "{m105}");
    assert_eq!(p.send("M155 S1"), "ok\n");
    let reports = p.run_for(3.05);
    let n = reports.lines().filter(|l| l.starts_with("T:")).count();
    assert_eq!(n, 3, "{reports}");
    p.send("M155 S0");
    assert!(!p.run_for(3.0).contains("T:"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_file_prints_from_the_card_as_hosts_drive_it() {
    let dir = sd("sdprint");
    std::fs::write(dir.join("cube.gcode"), JOB).expect("job");
    std::fs::create_dir_all(dir.join("parts")).expect("folder");
    std::fs::write(dir.join("parts/ring.gcode"), "G28\n").expect("job");
    // The same lines from the console: what the card's print must equal.
    let mut streamed = printer(&dir);
    for line in JOB.lines() {
        streamed.send(line);
    }
    streamed.run_for(2.0);

    let mut p = printer(&dir);
    let list = p.send("M20 L");
    assert!(list.starts_with("Begin file list\n"), "{list}");
    assert!(
        list.contains(&format!("cube.gcode {} cube.gcode\n", JOB.len())),
        "{list}"
    );
    assert!(list.contains("parts/ring.gcode 4 ring.gcode\n"), "{list}");
    assert!(list.ends_with("End file list\nok\n"), "{list}");
    assert_eq!(p.send("M27"), "Not SD printing.\nok\n");
    assert_eq!(
        p.send("M23 /CUBE.GCODE"),
        format!(
            "File opened: cube.gcode Size: {}\nFile selected\nok\n",
            JOB.len()
        )
    );
    assert_eq!(
        p.send("M23 nothing.gcode"),
        "open failed, File: nothing.gcode.\nok\n"
    );
    assert_eq!(p.send("M24"), "ok\n");
    p.run_for(3.0);
    let progress = p.send("M27");
    assert!(progress.starts_with("SD printing byte "), "{progress}");
    // Console commands still work during the print.
    assert!(p.send("M105").starts_with("ok T:"));
    let rest = print_to_end(&mut p, 300.0);
    assert!(!rest.contains("!!"), "{rest}");
    assert_eq!(p.send("M27"), "Not SD printing.\nok\n");
    assert_eq!(steps(&p), steps(&streamed));
    assert_eq!(p.position(), streamed.position());
    // Klipper's command does the same in one line.
    let mut again = printer(&dir);
    assert!(
        again
            .send("SDCARD_PRINT_FILE FILENAME=cube.gcode")
            .contains("File selected")
    );
    print_to_end(&mut again, 300.0);
    assert_eq!(steps(&again), steps(&streamed));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_file_is_uploaded_printed_paused_resumed_and_deleted() {
    let dir = sd("upload");
    let mut p = printer(&dir);
    assert_eq!(p.send("M28 up.gcode"), "Writing to file: up.gcode\nok\n");
    for (i, line) in JOB.lines().enumerate() {
        // Numbered lines go to the file without their envelope.
        assert_eq!(p.send(&numbered(i as u32 + 1, line)), "ok\n");
    }
    assert_eq!(p.send("M29"), "Done saving file.\nok\n");
    assert_eq!(
        std::fs::read_to_string(dir.join("up.gcode")).expect("written"),
        JOB
    );
    p.send("M23 up.gcode");
    p.send("M24");
    p.run_for(2.0);
    assert_eq!(p.send("PAUSE"), "ok\n");
    let paused = p.send("M27");
    p.run_for(2.0);
    assert_eq!(p.send("M27"), paused, "no line runs while paused");
    assert_eq!(p.send("PAUSE"), "!! Print already paused\nok\n");
    assert_eq!(p.send("RESUME"), "ok\n");
    print_to_end(&mut p, 300.0);
    assert_eq!(p.position(), [20.0, 20.0, 5.0, 8.0]);
    assert_eq!(p.send("M30 up.gcode"), "File deleted:up.gcode\nok\n");
    assert!(!dir.join("up.gcode").exists());
    assert_eq!(p.send("M30 up.gcode"), "open failed, File: up.gcode.\nok\n");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn autostart_files_print_at_boot_in_order() {
    let dir = sd("autostart");
    std::fs::write(dir.join("auto0.g"), "G28\nG1 X10 Y10 Z10 F6000\n").expect("auto0");
    std::fs::write(dir.join("auto1.g"), "G1 X30 F6000\n").expect("auto1");
    std::fs::write(dir.join("auto3.g"), "G1 X90 F6000\n").expect("auto3, after a gap");
    let mut p = printer(&dir);
    p.autostart();
    // Homing from mid-travel takes about 34 s.
    let out = p.run_for(60.0);
    assert_eq!(out.matches("Done printing file").count(), 2, "{out}");
    assert_eq!(out.matches("File selected").count(), 2, "{out}");
    assert_eq!(p.position()[..3], [30.0, 10.0, 10.0]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn m112_stops_at_once_and_a_restart_prints_again() {
    let dir = sd("m112");
    std::fs::write(dir.join("cube.gcode"), JOB).expect("job");
    let mut p = printer(&dir);
    p.send("M140 S60");
    p.send("SDCARD_PRINT_FILE FILENAME=cube.gcode");
    p.run_for(12.0);
    assert!(p.heaters_on().iter().any(|&on| on), "the bed heats");
    let before: usize = p.steps().map(|l| l.count).sum();
    assert!(before > 0);
    // Mid-line: the emergency parser acts on the byte after `M112`, before
    // the line ends.
    let at = p.now();
    p.receive(b"M112 ");
    let last_step = p.steps().filter_map(|l| l.last).max();
    assert!(last_step.is_some_and(|c| c <= at), "no step after M112");
    assert_eq!(p.heaters_on(), [false, false]);
    let reply = p.receive(b"\n");
    assert!(reply.contains("!! Shutdown due to M112 command"), "{reply}");
    let stopped: usize = p.steps().map(|l| l.count).sum();
    p.run_for(2.0);
    let after: usize = p.steps().map(|l| l.count).sum();
    assert_eq!(after, stopped, "nothing moves after the shutdown");
    let refused = p.send("G1 X10");
    assert!(
        refused.starts_with("!! MCU shutdown: Shutdown due to M112 command"),
        "{refused}"
    );
    // FIRMWARE_RESTART: a fresh printer that homes and prints again.
    assert_eq!(p.send("FIRMWARE_RESTART"), "ok\n");
    let restarted = p.send("SDCARD_PRINT_FILE FILENAME=cube.gcode");
    assert!(restarted.contains("File selected"), "{restarted}");
    let rest = print_to_end(&mut p, 300.0);
    assert!(!rest.contains("!!"), "{rest}");
    assert_eq!(p.position(), [20.0, 20.0, 5.0, 8.0]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_host_that_stops_mid_stream_leaves_no_move_queued_and_no_heater_on() {
    let dir = sd("stall");
    let stream = |p: &mut ConsolePrinter| {
        for line in ["M140 S60", "M104 S200", "G28", "M109 S200", "G1 Z2 F600"] {
            p.send(line);
        }
        for i in 0..1000 {
            let (x, y) = (10 + i % 50, 10 + i / 20);
            p.send(&format!("G1 X{x} Y{y} E{} F6000", i as f64 * 0.02));
        }
    };
    let mut finished = printer(&dir);
    stream(&mut finished);
    finished.send("M400");
    finished.run_for(30.0);
    // The host goes silent after its last move: the lookahead is flushed
    // when the moves sent run low (Klipper's flush timer), so every move
    // runs, and the heaters stay on until the idle timeout (600 s after
    // the last move ended) turns them off.
    let mut silent = printer(&dir);
    stream(&mut silent);
    silent.run_for(30.0);
    assert_eq!(steps(&silent), steps(&finished));
    let targets = |p: &mut ConsolePrinter| {
        let m105 = p.send("M105");
        assert!(m105.starts_with("ok T:"), "{m105}");
        (m105.contains(" /200.0 "), m105.contains(" /60.0 "))
    };
    assert_eq!(targets(&mut silent), (true, true));
    // The last move ends after the host went silent and within 30 s; the
    // M105 queries do not count as activity.
    silent.run_for(569.0);
    assert_eq!(targets(&mut silent), (true, true), "not before the timeout");
    silent.run_for(32.0);
    assert_eq!(
        targets(&mut silent),
        (false, false),
        "off after the timeout"
    );
    // M84 in the idle G-code: homing is forgotten.
    let refused = silent.send("G1 X20");
    assert!(refused.contains("Must home axis first"), "{refused}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn m119_reads_the_endstops() {
    let dir = sd("m119");
    let mut p = printer(&dir);
    assert_eq!(p.send("M119"), "x:open y:open z:open\nok\n");
    p.send("G28");
    p.run_for(1.0);
    // Homed: each axis rests where its endstop triggered.
    let homed = p.send("QUERY_ENDSTOPS");
    assert_eq!(homed, "x:TRIGGERED y:TRIGGERED z:TRIGGERED\nok\n");
    p.send("G1 X50 Y50 Z20 F6000");
    p.run_for(5.0);
    assert_eq!(p.send("M119"), "x:open y:open z:open\nok\n");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_host_slower_than_its_moves_does_not_starve_the_steppers() {
    let dir = sd("slowhost");
    let mut p = printer(&dir);
    p.send("G28");
    p.send("G1 X10 Y10 Z5 F6000");
    p.run_for(2.0);
    // 1 mm moves at 100 mm/s (10 ms each) sent every 30 ms: the steppers
    // run each move's steps and wait for the next, never behind their
    // clock (Klipper: print time is fixed when moves are released, and a
    // stalled queue is flushed).
    let mut replies = String::new();
    for i in 0..200 {
        replies += &p.send(&format!("G1 X{} F6000", 11 + i % 100));
        replies += &p.run_for(0.030);
    }
    replies += &p.run_for(3.0);
    assert!(!replies.contains("!!"), "{replies}");
    let m114 = p.send("M114");
    assert!(m114.starts_with("X:110.000 "), "{m114}");
    // Where the steppers really are: the last target, X 110 (from the
    // start at X 50, 0.0125 mm per step).
    let x_steps = p.steps().next().map(|l| l.position);
    assert_eq!(x_steps, Some(((110.0 - 50.0) / 0.0125) as i64));
    let _ = std::fs::remove_dir_all(&dir);
}
