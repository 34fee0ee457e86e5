//! A host fetches the MCU role's data dictionary through the whole stack:
//! codec -> HostLink -> bytes -> McuLink -> Dispatcher (identify) -> reply
//! block -> HostLink -> Fetcher (inflate) -> Dictionary.

use onechip_protocol::codec::{Decoded, Field};
use onechip_protocol::dictionary::Dictionary;
use onechip_protocol::identify::{CHUNK, Fetcher, Progress};
use onechip_protocol::mcu::{self, DispatchError, Dispatcher, Handler, Responses};
use onechip_protocol::transport::{HostLink, McuLink, Reply};

/// An MCU role that implements nothing beyond identify.
struct Bare;

impl Handler for Bare {
    fn command<'d>(
        &mut self,
        _: &Decoded<'_, '_, '_>,
        _: &mut Responses<'d, '_>,
    ) -> Result<(), DispatchError<'d>> {
        Err(DispatchError::Handler("not implemented"))
    }
}

#[test]
fn host_fetches_the_mcu_dictionary_over_the_link() {
    let mcu_dict = Dictionary::parse(mcu::DICTIONARY_JSON).expect("built-in dictionary");
    let dispatcher = Dispatcher::new(&mcu_dict, mcu::DICTIONARY_ZLIB);
    let (mut host, mut link) = (HostLink::default(), McuLink::new());
    // Before identify the host knows only the built-in messages, which every
    // dictionary shares; the MCU's own parse of its dictionary serves here.
    let bootstrap = &mcu_dict;
    let mut out = vec![0u8; 16 * 1024];
    let mut fetcher = Fetcher::new(&mut out);
    let mut now = 0;
    let json_len = loop {
        let mut request = [0u8; 16];
        let line = format!("identify offset={} count={CHUNK}", fetcher.offset());
        let n = bootstrap.encode_text(&line, &mut request).expect("encodes");
        let wire = host.send(&request[..n], now).expect("window open").to_vec();

        let mut reply_payload = [0u8; 64];
        let mut reply_len = 0;
        let reply = link.receive(&wire, |payload| {
            reply_len = dispatcher
                .dispatch(payload, &mut Bare, &mut reply_payload)
                .expect("dispatches");
        });
        assert!(matches!(reply, Reply::Ack(_)));
        let mut frame = [0u8; 64];
        let m = link
            .frame_reply(&reply_payload[..reply_len], &mut frame)
            .expect("fits");

        now += 1_000;
        let mut answer = None;
        host.receive(&frame[..m], now, |payload| {
            let (msg, _) = bootstrap.decode(payload).expect("identify_response");
            let (Some(offset), Some(Field::Bytes(data))) =
                (msg.int("offset"), msg.fields.get(1).copied())
            else {
                panic!("malformed identify_response");
            };
            answer = Some(
                fetcher
                    .on_response(offset as u32, data)
                    .expect("valid chunk"),
            );
        });
        assert_eq!(
            host.unacknowledged(),
            0,
            "the reply acknowledged the request"
        );
        if let Some(Progress::Done(n)) = answer {
            break n;
        }
    };
    let json = std::str::from_utf8(&out[..json_len]).expect("UTF-8");
    assert_eq!(json, mcu::DICTIONARY_JSON);
    let fetched = Dictionary::parse(json).expect("parses");
    assert_eq!(fetched.constant_int("RECEIVE_WINDOW"), Some(192));
    assert!(fetched.by_name("get_clock").is_some());
}
