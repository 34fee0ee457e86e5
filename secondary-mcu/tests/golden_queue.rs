//! Klipper's own step command streams (golden `queue-*.txt`) through our
//! encoder: every command encodes to the message klippy sent (same text
//! when decoded by the generic codec), decodes back to the same command,
//! and the decoded stream expands to golden's step clocks (`steps-*.txt`,
//! as the MCU's 32-bit clock sees them).

use onechip_golden::{dict, dict_for, read_string};
use onechip_protocol::dictionary::Dictionary;
use onechip_secondary_mcu::step_commands::StepCommandEncoder;
use onechip_stepgen::compress::{StepCommand, expand};

/// Parses a `queue-*.txt` line: (oid, command).
fn parse_line(line: &str) -> (u8, StepCommand) {
    let f: Vec<&str> = line.split_whitespace().collect();
    let num = |i: usize| f[i].parse::<i64>().expect("number");
    let cmd = match f[0] {
        "set_next_step_dir" => StepCommand::Dir(num(2) == 1),
        "queue_step" => StepCommand::Steps {
            interval: u32::try_from(num(2)).expect("u32"),
            count: u16::try_from(num(3)).expect("u16"),
            add: i16::try_from(num(4)).expect("i16"),
        },
        other => panic!("unexpected command {other}"),
    };
    (u8::try_from(num(1)).expect("oid"), cmd)
}

fn check(case: &str, stepper: &str) {
    let dict_text = dict(dict_for(case));
    let dict = Dictionary::parse(&dict_text).expect("dictionary");
    let queue = read_string(format!("{case}/queue-{stepper}.txt"));
    let mut decoded = Vec::new();
    let mut encoder = None;
    for line in queue.lines().filter(|l| !l.starts_with('#')) {
        let (oid, cmd) = parse_line(line);
        let enc = *encoder
            .get_or_insert_with(|| StepCommandEncoder::new(&dict, oid, false).expect("known"));
        let mut buf = [0u8; 32];
        let len = enc.encode(&cmd, &mut buf).expect("fits");
        let (generic, used) = dict.decode(&buf[..len]).expect("decodes");
        assert_eq!(used, len);
        // Golden lines are positional; the generic text names parameters.
        let values: Vec<String> = generic
            .to_string()
            .split_whitespace()
            .skip(1)
            .map(|kv| kv.split_once('=').expect("name=value").1.to_string())
            .collect();
        let positional: Vec<&str> = line.split_whitespace().skip(1).collect();
        assert_eq!(values, positional, "{case} {stepper}: {line}");
        let (back, used) = enc.decode(&dict, &buf[..len]).expect("step command");
        assert_eq!((back, used), (cmd, len));
        decoded.push(back);
    }
    let mut expanded = Vec::new();
    expand(&decoded, |clock, dir| expanded.push((clock as u32, dir)));
    let golden: Vec<(u32, bool)> = onechip_golden::steps(case, stepper)
        .into_iter()
        .map(|(clock, dir)| (clock as u32, dir))
        .collect();
    assert_eq!(expanded, golden, "{case} {stepper}");
}

#[test]
fn stm32f446_streams_round_trip() {
    for stepper in ["stepper_x", "stepper_y", "stepper_z", "extruder"] {
        check("cart_extrude", stepper);
        check("cart_move_g28", stepper);
    }
}

#[test]
fn avr_and_h723_streams_round_trip() {
    for stepper in ["stepper_x", "stepper_y", "stepper_z", "extruder"] {
        check("avr_cart_extrude", stepper);
        check("h723_cart_extrude", stepper);
    }
}

#[test]
fn other_messages_and_oids_are_not_step_commands() {
    let dict_text = dict("stm32f446");
    let dict = Dictionary::parse(&dict_text).expect("dictionary");
    let ours = StepCommandEncoder::new(&dict, 3, true).expect("known");
    let other = StepCommandEncoder::new(&dict, 4, true).expect("known");
    let mut buf = [0u8; 32];
    let len = other
        .encode(&StepCommand::Dir(true), &mut buf)
        .expect("fits");
    assert_eq!(ours.decode(&dict, &buf[..len]), None);
    // An inverted direction pin sends the opposite level and reads back.
    let len = ours
        .encode(&StepCommand::Dir(true), &mut buf)
        .expect("fits");
    let text = dict.decode(&buf[..len]).expect("decodes").0.to_string();
    assert_eq!(text, "set_next_step_dir oid=3 dir=0");
    assert_eq!(
        ours.decode(&dict, &buf[..len]).map(|c| c.0),
        Some(StepCommand::Dir(true))
    );
    // A reset sends the whole 32-bit clock and reads back as such.
    let len = ours
        .encode(&StepCommand::ResetClock(u32::MAX), &mut buf)
        .expect("fits");
    let text = dict.decode(&buf[..len]).expect("decodes").0.to_string();
    assert_eq!(text, "reset_step_clock oid=3 clock=4294967295");
    assert_eq!(
        ours.decode(&dict, &buf[..len]).map(|c| c.0),
        Some(StepCommand::ResetClock(u32::MAX))
    );
    let len = dict.encode_text("get_clock", &mut buf).expect("encodes");
    assert_eq!(ours.decode(&dict, &buf[..len]), None);
    // Too small an output buffer is an error, not a panic.
    let big = StepCommand::Steps {
        interval: u32::MAX,
        count: u16::MAX,
        add: i16::MIN,
    };
    assert!(ours.encode(&big, &mut buf[..4]).is_err());
}
