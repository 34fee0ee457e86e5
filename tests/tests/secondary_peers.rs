//! The secondary-MCU host role against stock Klipper MCU firmware
//! (`../shared/peers`): identify, the config phase with klippy's CRC,
//! clock synchronisation and step commands, checked on the peer's pins.

use onechip_host::secondary::{Heard, Secondary};
use onechip_secondary_mcu::clock_sync::{MAX_PENDING_QUERIES, QUERY_PERIOD};
use onechip_tests::peers::{Firmware, Peer};
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

/// One peer at a time: peers run in real time (the Linux MCU at real-time
/// priority), so two at once on a 2-core machine would measure each
/// other's load rather than our timing.
fn one_peer_at_a_time() -> MutexGuard<'static, ()> {
    static PEERS: Mutex<()> = Mutex::new(());
    PEERS.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Host time for these tests: seconds since the first call.
fn clock() -> impl Fn() -> f64 {
    let start = Instant::now();
    move || start.elapsed().as_secs_f64()
}

/// One stepper on the peer's `step`/`dir` pins.
fn one_stepper(step: &str, dir: &str, pulse_ticks: u32) -> Vec<String> {
    vec![
        "allocate_oids count=1".into(),
        format!(
            "config_stepper oid=0 step_pin={step} dir_pin={dir} invert_step=0 step_pulse_ticks={pulse_ticks}"
        ),
    ]
}

/// Services the link until `until` (host s), collecting what it heard.
fn run_until(mcu: &mut Secondary, now: &dyn Fn() -> f64, until: f64) -> Vec<Heard> {
    let mut heard = Vec::new();
    while now() < until {
        mcu.service(now(), Duration::from_millis(2), &mut heard)
            .expect("link");
    }
    heard
}

/// Connects to `firmware`, configures one stepper on `step`/`dir`, runs
/// 100 steps 1 ms apart and checks them on the MCU and on its pins.
fn hundred_steps(firmware: Firmware, step: &str, dir: &str, pulse_ticks: u32, freq: f64) {
    let _alone = one_peer_at_a_time();
    let peer = Peer::start(firmware, &format!("{firmware:?}-steps"));
    let now = clock();
    let config = one_stepper(step, dir, pulse_ticks);
    let start = Instant::now();
    let mut mcu = Secondary::connect(
        "ext",
        &peer.path,
        &|_| config.clone(),
        &now,
        Duration::from_secs(10),
    )
    .unwrap_or_else(|e| panic!("connect: {e}"));
    println!(
        "{firmware:?}: connected in {:.3} s, move_count {}",
        start.elapsed().as_secs_f64(),
        mcu.move_count
    );
    // get_config said is_config=1 with our CRC, or connect would have failed.
    assert!(mcu.move_count > 100, "{}", mcu.move_count);
    let sync = *mcu.connection().clock().expect("synced");
    assert_eq!(sync.mcu_freq(), freq);
    println!(
        "{firmware:?}: clock estimate {:.1} Hz ({:+.1} ppm)",
        sync.estimated_freq(),
        (sync.estimated_freq() / freq - 1.0) * 1e6
    );

    // 100 steps at 1 ms, the first 0.3 s from now.
    let first = sync.clock_at(now() + 0.3);
    let interval = (freq / 1000.0) as u32;
    let conn = mcu.connection();
    for line in [
        "set_next_step_dir oid=0 dir=1".to_string(),
        format!(
            "queue_step oid=0 interval={} count=1 add=0",
            first & 0xffff_ffff
        ),
        format!("queue_step oid=0 interval={interval} count=99 add=0"),
    ] {
        conn.send_text(&line, 0).expect("queued");
    }
    let t = now();
    run_until(&mut mcu, &now, t + 0.6);
    mcu.connection()
        .send_text("stepper_get_position oid=0", 0)
        .expect("queued");
    let t = now();
    let heard = run_until(&mut mcu, &now, t + 0.3);
    assert!(
        heard.contains(&Heard::Response("stepper_position oid=0 pos=100".into())),
        "{heard:?}"
    );
    let edges = peer.rising_edges(step);
    assert_eq!(edges.len(), 100, "step edges on the pin");
    let gaps: Vec<f64> = edges.windows(2).map(|w| w[1] - w[0]).collect();
    let worst = gaps.iter().map(|g| (g - 0.001).abs()).fold(0.0, f64::max);
    println!(
        "{firmware:?}: 100 steps, worst interval error {:.0} µs",
        worst * 1e6
    );
    assert!(worst < 0.001, "{gaps:?}");
}

#[test]
fn linux_mcu_identifies_configures_and_steps_on_its_pins() {
    hundred_steps(
        Firmware::Linux,
        "gpiochip0/gpio1",
        "gpiochip0/gpio2",
        100,
        50e6,
    );
}

#[test]
fn atmega2560_identifies_configures_and_steps_on_its_pins() {
    hundred_steps(Firmware::Avr, "PA4", "PA6", 32, 16e6);
}

/// An SD folder: the shipped printer with its extruder on the secondary
/// MCU at `serial` (Linux MCU pins), cold extrusion allowed, and `gcode`.
fn extruder_on_secondary(dir: &std::path::Path, serial: &std::path::Path, gcode: &str) {
    let shipped = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../sdcard-configs/octopus-pro-h723/printer.cfg");
    let cfg = std::fs::read_to_string(shipped).expect("shipped printer.cfg");
    let cfg = cfg
        .replace(
            "[extruder]\nstep_pin: PF9\ndir_pin: PF10\nenable_pin: !PG2\n",
            "[extruder]\nstep_pin: ext:gpiochip0/gpio10\ndir_pin: ext:gpiochip0/gpio11\n\
             enable_pin: !ext:gpiochip0/gpio12\nmin_extrude_temp: 0\n",
        )
        .replace(
            "[printer]",
            &format!(
                "[mcu ext]\nserial: {}\nrestart_method: command\n\n[printer]",
                serial.display()
            ),
        );
    assert!(
        cfg.contains("ext:gpiochip0/gpio10"),
        "extruder section moved"
    );
    std::fs::create_dir_all(dir).expect("sd folder");
    std::fs::write(dir.join("printer.cfg"), cfg).expect("printer.cfg");
    std::fs::write(dir.join("job.gcode"), gcode).expect("gcode");
}

/// p50, p99 and max of `values`' magnitudes.
fn percentiles(values: &[f64]) -> (f64, f64, f64) {
    let mut v: Vec<f64> = values.iter().map(|x| x.abs()).collect();
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q) as usize];
    (at(0.5), at(0.99), at(1.0))
}

#[test]
fn a_print_with_the_extruder_on_a_stock_linux_mcu_steps_as_planned() {
    let _alone = one_peer_at_a_time();
    let peer = Peer::start(Firmware::Linux, "extruder");
    let sd = peer.path.with_file_name("sd");
    // Extrusion and retraction, through direction changes and a dwell.
    let gcode =
        "M83\nG1 E5 F300\nG1 E-2 F1800\nG1 E4 F600\nG4 P200\nG1 E-1 F1200\nG1 E3 F240\nM400\n";
    extruder_on_secondary(&sd, &peer.path, gcode);
    let summary = onechip_host::run(&sd, None).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(summary.shutdown, None, "{}", summary.transcript);
    assert!(summary.errors.is_empty(), "{:?}", summary.errors);
    let extruder = summary
        .steppers
        .iter()
        .find(|s| s.name == "extruder")
        .expect("extruder");
    // 9 mm forward net at 16 × 200 / 33.5 steps per mm.
    let per_mm: f64 = 16.0 * 200.0 / 33.5;
    assert_eq!(extruder.position, (9.0 * per_mm).round() as i64);
    let (_, clocks) = &summary.secondary_steps[0];
    assert_eq!(clocks.len(), extruder.steps);
    // What the peer's pin did: every step, nothing more.
    std::thread::sleep(Duration::from_millis(100));
    let edges = peer.rising_edges("gpiochip0/gpio10");
    assert_eq!(edges.len(), clocks.len(), "step edges on the peer's pin");
    // When: each edge against its planned clock (50 MHz), less the
    // constant offset between the peer's clock and CLOCK_MONOTONIC.
    let offsets: Vec<f64> = edges
        .iter()
        .zip(clocks)
        .map(|(&t, &c)| t - (c & 0xffff_ffff) as f64 / 50e6)
        .collect();
    let mut sorted = offsets.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[sorted.len() / 2];
    let late: Vec<f64> = offsets.iter().map(|o| o - median).collect();
    let (p50, p99, max) = percentiles(&late);
    println!(
        "extruder on the Linux MCU: {} steps, final position {}; edge vs plan p50 {:.0} µs, p99 {:.0} µs, max {:.0} µs",
        clocks.len(),
        extruder.position,
        p50 * 1e6,
        p99 * 1e6,
        max * 1e6
    );
    // The Linux MCU is as punctual as the kernel lets it be: nearly every
    // edge within a tenth of a millisecond, the odd one a few ms late.
    assert!(p99 < 0.000_500, "p99 {p99} s");
    assert!(max < 0.010, "an edge {max} s away from its planned time");
}

/// klippy's limit for a silent MCU, s: it is lost once more than
/// `MAX_PENDING_QUERIES` of its clock queries (one every `QUERY_PERIOD`)
/// are unanswered, as its once-a-second stats check notices.
fn klippy_timeout() -> f64 {
    f64::from(MAX_PENDING_QUERIES + 1) * QUERY_PERIOD + 1.0
}

/// The extruder's step pin on the Linux MCU (see [`extruder_on_secondary`]).
const EXTRUDER_STEP: &str = "gpiochip0/gpio10";

/// A print with the extruder on a fresh Linux MCU and its hot end heating
/// on the main MCU; once the peer has made `edges` extruder steps,
/// `fault` does something to it and says when. Returns the run, when
/// the fault came and the peer (still running, for its pin log).
fn print_with_fault(
    test: &str,
    edges: usize,
    fault: impl FnOnce(&Peer) + Send,
) -> (onechip_host::Summary, Instant, Peer) {
    let peer = Peer::start(Firmware::Linux, test);
    let sd = peer.path.with_file_name("sd");
    // 30 mm at 5 mm/s: 6 s of extrusion, 2866 steps.
    extruder_on_secondary(&sd, &peer.path, "M104 S200\nM83\nG1 E30 F300\nM400\n");
    let (summary, at) = std::thread::scope(|s| {
        let injector = s.spawn(|| {
            let started = peer.wait_for_edges(EXTRUDER_STEP, edges, Duration::from_secs(20));
            assert!(started, "the peer never stepped");
            fault(&peer);
            Instant::now()
        });
        let summary = onechip_host::run(&sd, None).unwrap_or_else(|e| panic!("{e}"));
        (summary, injector.join().expect("fault injected"))
    });
    (summary, at, peer)
}

/// The extruder heater was heating, and is off now.
fn assert_heater_was_on_and_is_off(summary: &onechip_host::Summary) {
    let hot_end = summary
        .heaters
        .iter()
        .find(|h| h.name == "extruder")
        .expect("extruder heater");
    assert!(hot_end.duty > 0.0, "the hot end never heated: {hot_end:?}");
    assert!(!hot_end.on_at_end, "the hot end is still on: {hot_end:?}");
}

/// The console's `!!` line for `message`, and the printer stopped with it.
fn assert_shut_down_with(summary: &onechip_host::Summary, message: &str) {
    assert_eq!(summary.shutdown.as_deref(), Some(message));
    assert!(
        summary.transcript.contains(&format!("!! {message}\n")),
        "{}",
        summary.transcript
    );
}

#[test]
fn killing_the_peer_mid_print_loses_communication_and_turns_heaters_off() {
    let _alone = one_peer_at_a_time();
    let (summary, killed, peer) = print_with_fault("killed", 300, |peer| {
        peer.signal_mcu(libc::SIGKILL);
    });
    assert_shut_down_with(&summary, "Lost communication with MCU 'ext'");
    let noticed = summary.secondary_fault_at.expect("fault noticed");
    let detection = noticed.saturating_duration_since(killed).as_secs_f64();
    println!(
        "killed peer: Lost communication noticed {:.1} ms after the kill (klippy: within {:.1} s)",
        detection * 1e3,
        klippy_timeout()
    );
    assert!(detection < klippy_timeout(), "{detection} s");
    assert_heater_was_on_and_is_off(&summary);
    // It died mid-print: fewer steps than planned.
    let made = peer.rising_edges(EXTRUDER_STEP).len();
    assert!(made >= 300 && made < 2866, "{made} steps");
}

#[test]
fn a_frozen_peer_is_lost_after_klippys_clock_query_timeout() {
    let _alone = one_peer_at_a_time();
    let (summary, frozen, _peer) = print_with_fault("frozen", 300, |peer| {
        peer.signal_mcu(libc::SIGSTOP);
    });
    assert_shut_down_with(&summary, "Lost communication with MCU 'ext'");
    let noticed = summary.secondary_fault_at.expect("fault noticed");
    let detection = noticed.saturating_duration_since(frozen).as_secs_f64();
    println!(
        "frozen peer: Lost communication noticed {detection:.2} s after it froze (klippy: {:.1}..{:.1} s)",
        f64::from(MAX_PENDING_QUERIES - 1) * QUERY_PERIOD,
        klippy_timeout()
    );
    // Four or five queries unanswered (one may have been on its way).
    let earliest = f64::from(MAX_PENDING_QUERIES - 1) * QUERY_PERIOD;
    assert!(
        (earliest..klippy_timeout()).contains(&detection),
        "{detection} s"
    );
    assert_heater_was_on_and_is_off(&summary);
}

#[test]
fn a_shutdown_of_the_peer_reaches_the_console_and_stops_the_printer() {
    let _alone = one_peer_at_a_time();
    // Frozen for 0.3 s while stepping: its next step timers are far in
    // the past when it runs again, and the firmware shuts itself down.
    let (summary, _, peer) = print_with_fault("shutdown", 300, |peer| {
        peer.signal_mcu(libc::SIGSTOP);
        std::thread::sleep(Duration::from_millis(300));
        peer.signal_mcu(libc::SIGCONT);
    });
    let message = summary.shutdown.clone().expect("shut down");
    println!("peer shutdown: {message}");
    let reason = message
        .strip_prefix("MCU 'ext' shutdown: ")
        .unwrap_or_else(|| panic!("{message}"));
    // The reason is one of the firmware's own shutdown strings.
    let dict =
        std::fs::read_to_string(onechip_tests::peers::peers_dir().join("linux/klipper.dict"))
            .expect("dictionary");
    assert!(
        !reason.is_empty() && dict.contains(&format!("\"{reason}\"")),
        "{reason}"
    );
    assert_shut_down_with(&summary, &message);
    assert_heater_was_on_and_is_off(&summary);
    let made = peer.rising_edges(EXTRUDER_STEP).len();
    assert!(made < 2866, "{made} steps");
}
