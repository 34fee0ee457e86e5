//! The protocol against real Klipper output (`../shared/golden`): every
//! dictionary parses, every wire stream decodes to klippy's own decoded
//! command log line for line, and re-encoding that log reproduces the wire
//! bytes exactly (framing, sequence numbers and CRCs included).
//!
//! Which messages share a block depends on klippy's serial-queue timing, not
//! on the commands, so the re-encoding takes each block's message count from
//! the golden stream; everything inside the blocks is ours.
//!
//! klippy sends absolute clocks as 64-bit values, but the log prints the 32
//! bits the MCU keeps. [`HostClock`] rebuilds the 64-bit value the way a host
//! knows it: the congruent clock nearest to the latest time the stream has
//! reached (step clocks and earlier absolute clocks).

use onechip_golden::{dict, dict_for, read, read_string};
use onechip_protocol::block;
use onechip_protocol::codec::is_absolute_clock;
use onechip_protocol::dictionary::Dictionary;
use std::collections::HashMap;

/// The host's 64-bit view of MCU time, rebuilt from a command log.
#[derive(Default)]
struct HostClock {
    /// Latest 64-bit clock the stream has reached.
    now: i64,
    /// 64-bit clock of each stepper's last queued step, by oid.
    steps: HashMap<i64, i64>,
}

impl HostClock {
    /// Rewrites the line's absolute clocks as 64-bit values and advances time.
    fn extend_line(&mut self, line: &str) -> String {
        let mut out = Vec::new();
        let mut args = HashMap::new();
        for word in line.split_ascii_whitespace() {
            let Some((key, value)) = word.split_once('=') else {
                out.push(word.to_string());
                continue;
            };
            let mut value: i64 = value.parse().unwrap_or(-1);
            // A zero clock is a literal ("stop now"), not a time.
            if is_absolute_clock(key) && value > 0 {
                let base = self.now - (1 << 31);
                value = base + (value - base).rem_euclid(1 << 32);
                self.now = self.now.max(value);
            }
            args.insert(key, value);
            out.push(if value < 0 {
                word.to_string()
            } else {
                format!("{key}={value}")
            });
        }
        match line.split_ascii_whitespace().next() {
            Some("queue_step") => {
                let (count, add) = (args["count"], args["add"]);
                let start = self.steps.entry(args["oid"]).or_insert(0);
                *start += args["interval"] * count + add * count * (count - 1) / 2;
                self.now = self.now.max(*start);
            }
            Some("reset_step_clock") => {
                self.steps.insert(args["oid"], args["clock"]);
            }
            _ => {}
        }
        out.join(" ")
    }
}

/// One golden session: its dictionary's text, the wire bytes and the log.
struct Session {
    case: String,
    dictionary: String,
    wire: Vec<u8>,
    log: String,
}

/// Every golden case's session, with the dictionary it ran against.
fn sessions() -> impl Iterator<Item = Session> {
    let cases = onechip_golden::cases();
    assert_eq!(cases.len(), 15, "expected the 15 golden cases: {cases:?}");
    cases.into_iter().map(|case| Session {
        dictionary: dict(dict_for(&case)),
        wire: read(format!("{case}/klippy.serial")),
        log: read_string(format!("{case}/mcu-commands.txt")),
        case,
    })
}

/// The golden blocks of a wire stream, each as its decoded messages.
fn golden_blocks(dict: &Dictionary<'_>, case: &str, wire: &[u8]) -> Vec<(usize, Vec<String>)> {
    let mut blocks = Vec::new();
    let mut at = 0;
    while at < wire.len() {
        let frame =
            block::parse(&wire[at..]).unwrap_or_else(|e| panic!("{case}: block at {at}: {e:?}"));
        let mut messages = Vec::new();
        let mut rest = frame.payload;
        while !rest.is_empty() {
            let (msg, used) = dict
                .decode(rest)
                .unwrap_or_else(|e| panic!("{case}: at {at}: {e}"));
            messages.push(msg.to_string());
            rest = &rest[used..];
        }
        blocks.push((at, messages));
        at += frame.wire_len();
    }
    blocks
}

#[test]
fn every_golden_dictionary_parses_with_its_constants() {
    for (name, mcu, clock) in [
        ("atmega2560", "atmega2560", 16_000_000),
        ("stm32f446", "stm32f446xx", 180_000_000),
        ("stm32h723", "stm32h723xx", 520_000_000),
        ("lpc176x", "lpc1768", 100_000_000),
    ] {
        let text = dict(name);
        let dict = Dictionary::parse(&text).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(dict.constant_int("CLOCK_FREQ"), Some(clock), "{name}");
        assert_eq!(dict.constant_str("MCU"), Some(mcu), "{name}");
        assert!(dict.messages().len() > 100, "{name}");
        assert!(
            dict.version().is_some_and(|v| v.starts_with("v0.13")),
            "{name}"
        );
        for step_cmd in [
            "queue_step",
            "set_next_step_dir",
            "reset_step_clock",
            "identify",
        ] {
            assert!(dict.by_name(step_cmd).is_some(), "{name}: {step_cmd}");
        }
    }
}

#[test]
fn decoding_each_wire_stream_gives_the_command_log_line_for_line() {
    for session in sessions() {
        let case = &session.case;
        let dict = Dictionary::parse(&session.dictionary).expect("dictionary");
        let decoded: Vec<String> = golden_blocks(&dict, case, &session.wire)
            .into_iter()
            .flat_map(|(_, m)| m)
            .collect();
        let expected: Vec<&str> = session.log.lines().collect();
        assert!(
            decoded.len() > 100,
            "{case}: only {} messages",
            decoded.len()
        );
        assert_eq!(decoded.len(), expected.len(), "{case}: message count");
        for (i, (got, want)) in decoded.iter().zip(&expected).enumerate() {
            assert_eq!(got, want, "{case}: message {i}");
        }
    }
}

#[test]
fn encoding_each_command_log_gives_the_wire_bytes_exactly() {
    for session in sessions() {
        let case = &session.case;
        let dict = Dictionary::parse(&session.dictionary).expect("dictionary");
        let mut lines = session.log.lines();
        let mut clock = HostClock::default();
        let mut seq = 1u8;
        // How many messages klippy put in each block (see module doc).
        for (at, messages) in golden_blocks(&dict, case, &session.wire) {
            let mut payload = [0u8; block::MAX_PAYLOAD];
            let mut len = 0;
            for _ in &messages {
                let line = clock.extend_line(
                    lines
                        .next()
                        .unwrap_or_else(|| panic!("{case}: log too short")),
                );
                len += dict
                    .encode_text(&line, &mut payload[len..])
                    .unwrap_or_else(|e| panic!("{case}: {line}: {e}"));
            }
            let mut frame = [0u8; block::MAX_LEN];
            let n = block::encode(seq, &payload[..len], &mut frame).expect("fits");
            assert_eq!(
                &frame[..n],
                &session.wire[at..at + n],
                "{case}: block at byte {at}"
            );
            seq = seq.wrapping_add(1);
        }
        assert_eq!(lines.next(), None, "{case}: log has lines the wire lacks");
    }
}
