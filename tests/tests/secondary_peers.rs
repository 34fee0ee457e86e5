//! The secondary-MCU host role against stock Klipper MCU firmware
//! (`../shared/peers`): identify, the config phase with klippy's CRC,
//! clock synchronisation and step commands, checked on the peer's pins.

use onechip_host::secondary::{Heard, Secondary};
use onechip_tests::peers::{Firmware, Peer};
use std::time::{Duration, Instant};

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
    let peer = Peer::start(firmware, &format!("{firmware:?}-steps"));
    let now = clock();
    let config = one_stepper(step, dir, pulse_ticks);
    let start = Instant::now();
    let mut mcu = Secondary::connect(
        "ext",
        &peer.path,
        &config,
        &[],
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
