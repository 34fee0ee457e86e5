//! Arbitrary text as a data dictionary: parsing must never panic, and a
//! dictionary that parses must answer every lookup and round-trip what it
//! encodes.
#![no_main]

use libfuzzer_sys::fuzz_target;
use onechip_protocol::dictionary::Dictionary;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let Ok(dict) = Dictionary::parse(text) else { return };
    let _ = (dict.constant_int("CLOCK_FREQ"), dict.constant_str("MCU"), dict.version());
    for message in dict.messages() {
        let _ = dict.by_id(message.id);
        let mut line = String::from(message.name());
        for (name, ty) in message.params() {
            if let Some(e) = dict.enumeration_for(name) {
                let mut symbol = String::new();
                let _ = e.write_name(0, &mut symbol);
                let _ = e.value_of(&symbol);
            }
            line.push_str(&format!(" {name}={}", if ty.is_bytes() { "00" } else { "1" }));
        }
        let mut out = [0u8; 256];
        if let Ok(n) = dict.encode_text(&line, &mut out) {
            let (decoded, used) = dict.decode(&out[..n]).expect("what we encode decodes");
            assert_eq!(used, n);
            let _ = decoded.to_string();
        }
    }
});
