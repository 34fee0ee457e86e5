//! Arbitrary bytes through the block deframer and into both link ends, and
//! every block found through the message decoder of a real dictionary.
//! Must never panic; every block reported must re-encode to itself.
#![no_main]

use libfuzzer_sys::fuzz_target;
use onechip_protocol::block;
use onechip_protocol::dictionary::Dictionary;
use onechip_protocol::mcu;
use onechip_protocol::transport::{Deframer, Frame, HostLink, McuLink};

fuzz_target!(|data: &[u8]| {
    let Ok(dict) = Dictionary::parse(mcu::DICTIONARY_JSON) else { return };
    let mut deframer = Deframer::new();
    deframer.push(data, |frame| {
        if let Frame::Block { seq, payload } = frame {
            let mut out = [0u8; block::MAX_LEN];
            let n = block::encode(seq, payload, &mut out).expect("a parsed payload fits a block");
            assert_eq!(block::parse(&out[..n]).map(|b| b.payload), Ok(payload));
            let mut rest = payload;
            while let Ok((msg, used)) = dict.decode(rest) {
                let _ = msg.to_string();
                rest = &rest[used..];
            }
        }
    });
    let _ = block::parse(data);
    McuLink::new().receive(data, |_| {});
    let mut host = HostLink::default();
    let _ = host.send(b"abc", 0);
    host.receive(data, 1, |_| {});
    let mut retransmit = [0u8; 1024];
    let _ = host.poll(u64::MAX, &mut retransmit);
});
