//! Host throughput of the protocol on a real stream: klippy's own
//! `cart_extrude` session (../shared/golden), decoded from wire bytes to
//! messages, and encoded from its command log back to framed blocks.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use onechip_protocol::block;
use onechip_protocol::codec::Encoder;
use onechip_protocol::dictionary::Dictionary;
use std::hint::black_box;
use std::path::PathBuf;

fn golden(path: &str) -> Vec<u8> {
    let dir = std::env::var_os("ONECHIP_GOLDEN").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/golden"),
        PathBuf::from,
    );
    std::fs::read(dir.join(path)).expect("golden data (set ONECHIP_GOLDEN)")
}

fn codec(c: &mut Criterion) {
    let dict_text = String::from_utf8(golden("dicts/stm32f446.dict")).expect("UTF-8");
    let dict = Dictionary::parse(&dict_text).expect("dictionary");
    let wire = golden("cart_extrude/klippy.serial");
    let log = String::from_utf8(golden("cart_extrude/mcu-commands.txt")).expect("UTF-8");

    let mut group = c.benchmark_group("cart_extrude");
    group.throughput(Throughput::Bytes(wire.len() as u64));
    group.bench_function("decode wire bytes", |b| {
        b.iter(|| {
            let (mut at, mut messages) = (0, 0);
            while at < wire.len() {
                let frame = block::parse(&wire[at..]).expect("valid block");
                let mut rest = frame.payload;
                while !rest.is_empty() {
                    let (msg, used) = dict.decode(rest).expect("valid message");
                    black_box(&msg);
                    rest = &rest[used..];
                    messages += 1;
                }
                at += frame.wire_len();
            }
            messages
        })
    });
    group.bench_function("encode command log to blocks", |b| {
        b.iter(|| {
            let mut payload = [0u8; block::MAX_PAYLOAD];
            let mut frame = [0u8; block::MAX_LEN];
            let (mut len, mut seq, mut bytes) = (0, 0u8, 0);
            for line in log.lines() {
                let mut msg = [0u8; 64];
                let n = dict.encode_text(line, &mut msg).expect("valid line");
                if len + n > block::MAX_PAYLOAD {
                    bytes += block::encode(seq, &payload[..len], &mut frame).expect("fits");
                    seq = seq.wrapping_add(1);
                    len = 0;
                }
                payload[len..len + n].copy_from_slice(&msg[..n]);
                len += n;
            }
            bytes + block::encode(seq, &payload[..len], &mut frame).expect("fits")
        })
    });
    // The firmware's path: queue_step arguments straight to bytes.
    let steps: Vec<[i64; 4]> = log
        .lines()
        .filter(|l| l.starts_with("queue_step "))
        .map(|l| {
            let mut v = l
                .split_ascii_whitespace()
                .skip(1)
                .map(|w| w.split_once('=').map_or(0, |(_, x)| x.parse().unwrap_or(0)));
            [(); 4].map(|()| v.next().unwrap_or(0))
        })
        .collect();
    let encoder = Encoder::new(&dict, "queue_step").expect("queue_step");
    let mut sizes = [0u8; 64];
    let wire_bytes: usize = steps
        .iter()
        .map(|a| encoder.encode_ints(a, &mut sizes).expect("valid"))
        .sum();
    group.throughput(Throughput::Bytes(wire_bytes as u64));
    group.bench_function("encode queue_step arguments", |b| {
        b.iter(|| {
            let mut out = [0u8; 64];
            steps
                .iter()
                .map(|a| encoder.encode_ints(black_box(a), &mut out).expect("valid"))
                .sum::<usize>()
        })
    });
    group.finish();
}

criterion_group!(benches, codec);
criterion_main!(benches);
