//! A move that arrives once the toolhead has gone idle, while the last
//! moves still run, starts after the steps already generated for their
//! shaped tail (klippy's `min_restart_time`): with input shaping the
//! steps near the end of a move depend on the next one, and a move
//! starting before the generated steps would move the shaped position at
//! once, a burst of steps at one clock.

use onechip_host::console_printer::ConsolePrinter;
use onechip_host::{Options, Start};
use onechip_tests::sd_folder;

#[test]
fn a_move_after_the_queue_went_idle_starts_after_the_generated_steps() {
    let cfg = sd_folder::shipped_cfg();
    let shaped = format!(
        "{cfg}\n[input_shaper]\nshaper_type_x: mzv\nshaper_freq_x: 40\n\
         shaper_type_y: ei\nshaper_freq_y: 35\n"
    );
    let dir = sd_folder::new("restart", &shaped, None);
    let options = Options {
        start: Start::At([50.0, 80.0, 30.0]),
        ..Options::default()
    };
    let mut p = ConsolePrinter::new(&dir, &options).expect("printer");
    for line in ["G28", "G90", "G1 Z5 F600", "G1 X20 Y20 F6000", "M400"] {
        p.send(line);
    }
    // 130 mm at 100 mm/s: 1.3 s. Below 1 s of queued motion the input
    // has stalled, the queue is flushed and the toolhead is idle.
    p.send("G1 X150 Y20 F6000");
    p.run_for(0.8);
    // The move still runs for about half a second: the next one follows
    // it, but after its generated shaped tail.
    p.send("G1 X150 Y150 F6000");
    p.send("M400");
    p.run_for(1.0);
    let freq = options.mcu_freq;
    for (i, log) in p.steps().enumerate().take(2) {
        let shortest = log.min_interval.expect("stepped") as f64 / freq;
        // 80 steps/mm at 100 mm/s: 125 µs; shaping smooths, never bursts.
        assert!(shortest > 50e-6, "stepper {i}: steps {shortest:e} s apart");
    }
    let at = p.position();
    assert_eq!([at[0], at[1]], [150.0, 150.0], "final position");
    std::fs::remove_dir_all(&dir).ok();
}
