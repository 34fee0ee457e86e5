//! Resetting secondary MCUs as klippy does, against stock Klipper
//! firmware (`../shared/peers`): its automated firmware restart when an
//! MCU holds another config, and FIRMWARE_RESTART after a shutdown, each
//! by the firmware's own means (the Linux MCU's `config_reset`, which
//! re-executes it behind a new pseudo-terminal; the AVR's `reset`, a
//! watchdog reboot).

use onechip_host::Options;
use onechip_host::console_printer::ConsolePrinter;
use onechip_host::secondary;
use onechip_planner::mcu_section::RestartMethod;
use onechip_tests::peers::{Firmware, Peer, extruder_pins, printer_with_extruder_on};
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

/// One peer at a time (they run in real time).
fn one_peer_at_a_time() -> MutexGuard<'static, ()> {
    static PEERS: Mutex<()> = Mutex::new(());
    PEERS.lock().unwrap_or_else(PoisonError::into_inner)
}

/// How long a connection may take here.
const CONNECT: Duration = Duration::from_secs(10);

/// One stepper on `firmware`'s extruder pins, its pulse `pulse_ticks`
/// long: two configs that differ only in that have different CRCs.
fn one_stepper(firmware: Firmware, pulse_ticks: u32) -> Vec<String> {
    let pins = extruder_pins(firmware);
    vec![
        "allocate_oids count=1".into(),
        format!(
            "config_stepper oid=0 step_pin={} dir_pin={} invert_step=0 step_pulse_ticks={pulse_ticks}",
            pins.step, pins.dir
        ),
    ]
}

/// The peer holds one config; another is refused as klippy refuses it,
/// then taken after the reset klippy's automated firmware restart does.
fn holding_another_config(firmware: Firmware) {
    let _alone = one_peer_at_a_time();
    let peer = Peer::start(firmware, &format!("{firmware:?}-crc"));
    let start = Instant::now();
    let now = move || start.elapsed().as_secs_f64();
    let old = one_stepper(firmware, 32);
    let first = secondary::connect("ext", &peer.path, &|_| old.clone(), &now, CONNECT);
    drop(first.unwrap_or_else(|e| panic!("first config: {e}")));
    let new = one_stepper(firmware, 40);
    let refused = secondary::connect("ext", &peer.path, &|_| new.clone(), &now, CONNECT);
    assert_eq!(
        refused.err().map(|e| e.to_string()).as_deref(),
        Some("MCU 'ext' CRC does not match config")
    );
    // A pseudo-terminal has no DTR line to reset an Arduino by.
    let by_dtr = secondary::connect_or_restart(
        "ext",
        &peer.path,
        RestartMethod::Arduino,
        &|_| new.clone(),
        &now,
        CONNECT,
    );
    assert_eq!(
        by_dtr.err().map(|e| e.to_string()).as_deref(),
        Some(
            "MCU 'ext': unable to reset by the serial line: Inappropriate ioctl for device (os error 25)"
        )
    );
    let asked = now();
    let mcu = secondary::connect_or_restart(
        "ext",
        &peer.path,
        RestartMethod::Command,
        &|_| new.clone(),
        &now,
        CONNECT,
    )
    .unwrap_or_else(|e| panic!("restarted: {e}"));
    println!(
        "{firmware:?}: reset and configured anew in {:.2} s, move_count {}",
        now() - asked,
        mcu.move_count
    );
    // Connected: get_config said is_config=1 with the new config's CRC.
    assert!(mcu.move_count > 0);
    drop(mcu);
    // It holds the new config now: connecting with it needs no reset.
    let again = secondary::connect("ext", &peer.path, &|_| new.clone(), &now, CONNECT);
    assert!(again.is_ok(), "{:?}", again.err().map(|e| e.to_string()));
}

#[test]
fn a_linux_mcu_holding_another_config_is_reset_by_config_reset_and_configured_anew() {
    holding_another_config(Firmware::Linux);
}

#[test]
fn an_atmega2560_holding_another_config_is_reset_by_its_reset_command_and_configured_anew() {
    holding_another_config(Firmware::Avr);
}

/// 1 mm of extrusion, waited for.
const EXTRUDE_1MM: &str = "G1 E1 F300\nM400";

/// Sends each line of `lines`; returns the replies. The peer's last
/// steps after an M400 may reach its pin log a little after the main
/// MCU's clock has passed them: some time is left for them.
fn send_all(p: &mut ConsolePrinter, lines: &str) -> String {
    let replies = lines.lines().map(|l| p.send(l)).collect();
    std::thread::sleep(Duration::from_millis(200));
    replies
}

/// A printer with its extruder on `firmware` extrudes, is stopped by M112
/// (which stops the secondary too), and after FIRMWARE_RESTART extrudes
/// again on the reset and reconfigured secondary.
fn restart_after_m112(firmware: Firmware) {
    let _alone = one_peer_at_a_time();
    let peer = Peer::start(firmware, &format!("{firmware:?}-m112"));
    let sd = peer.path.with_file_name("sd");
    printer_with_extruder_on(firmware, &sd, &peer.path, "command", "");
    let mut p = ConsolePrinter::new(&sd, &Options::default()).unwrap_or_else(|e| panic!("{e}"));
    let step = extruder_pins(firmware).step;
    let replies = send_all(&mut p, &format!("M83\n{EXTRUDE_1MM}"));
    assert!(!replies.contains("!!"), "{replies}");
    let per_mm = peer.rising_edges(step).len();
    assert!(per_mm > 10, "{per_mm} steps for 1 mm");
    let stopped = p.send("M112");
    assert!(
        stopped.contains("Shutdown due to M112 command"),
        "{stopped}"
    );
    let refused = send_all(&mut p, EXTRUDE_1MM);
    assert!(refused.contains("M112"), "{refused}");
    assert_eq!(
        peer.rising_edges(step).len(),
        per_mm,
        "moved while shut down"
    );
    let asked = Instant::now();
    assert_eq!(p.send("FIRMWARE_RESTART"), "ok\n");
    println!(
        "{firmware:?}: FIRMWARE_RESTART took {:.2} s; {per_mm} steps a mm",
        asked.elapsed().as_secs_f64()
    );
    let replies = send_all(&mut p, &format!("M83\n{EXTRUDE_1MM}\n{EXTRUDE_1MM}"));
    assert!(!replies.contains("!!"), "{replies}");
    // The pin log goes on across the reset: 1 mm before, 2 mm after (a
    // mm is not a whole number of steps: 1 mm made the nearest whole).
    let after = peer.rising_edges(step).len() - per_mm;
    assert!(after.abs_diff(2 * per_mm) <= 1, "{after} steps for 2 mm");
}

#[test]
fn firmware_restart_resets_and_reconfigures_a_stock_linux_mcu_after_m112() {
    restart_after_m112(Firmware::Linux);
}

#[test]
fn firmware_restart_resets_and_reconfigures_a_stock_atmega2560_after_m112() {
    restart_after_m112(Firmware::Avr);
}

#[test]
fn a_secondary_that_cannot_be_reset_keeps_the_printer_shut_down_with_klippers_message() {
    let _alone = one_peer_at_a_time();
    let peer = Peer::start(Firmware::Linux, "no-reset");
    let sd = peer.path.with_file_name("sd");
    // Klipper's default restart_method: the serial line's DTR, which a
    // pseudo-terminal does not have.
    printer_with_extruder_on(Firmware::Linux, &sd, &peer.path, "arduino", "");
    let mut p = ConsolePrinter::new(&sd, &Options::default()).unwrap_or_else(|e| panic!("{e}"));
    p.send("M112");
    assert_eq!(p.send("FIRMWARE_RESTART"), "ok\n");
    let replies = send_all(&mut p, &format!("M83\n{EXTRUDE_1MM}"));
    assert!(
        replies.contains(
            "MCU 'ext': unable to reset by the serial line: Inappropriate ioctl for device"
        ),
        "{replies}"
    );
    assert!(
        peer.rising_edges(extruder_pins(Firmware::Linux).step)
            .is_empty()
    );
}
