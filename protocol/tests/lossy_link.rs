//! Property: over links that insert, drop and corrupt bytes in both
//! directions, every payload the host sends is delivered to the MCU exactly
//! once and in order, and the host sees every block acknowledged.
//! Deterministic: each run is a fixed seed of a small xorshift generator.

use onechip_protocol::block::{MAX_LEN, MAX_PAYLOAD};
use onechip_protocol::transport::{HostLink, MAX_PENDING_BLOCKS, McuLink, Reply};
use std::collections::VecDeque;

struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    fn chance(&mut self, per_million: u64) -> bool {
        self.next() % 1_000_000 < per_million
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// Fault rates per byte, in parts per million.
#[derive(Clone, Copy)]
struct Faults {
    drop: u64,
    corrupt: u64,
    insert: u64,
}

/// One direction of a serial line: 250 kbaud (40 µs a byte), 1 ms latency.
struct Wire {
    in_flight: VecDeque<(u64, u8)>,
    free_at: u64,
    faults: Faults,
    damaged: u64,
}

impl Wire {
    fn new(faults: Faults) -> Self {
        Self {
            in_flight: VecDeque::new(),
            free_at: 0,
            faults,
            damaged: 0,
        }
    }

    fn write(&mut self, bytes: &[u8], now: u64, rng: &mut Rng) {
        for &byte in bytes {
            self.free_at = self.free_at.max(now) + 40;
            let arrive = self.free_at + 1_000;
            if rng.chance(self.faults.insert) {
                self.in_flight.push_back((arrive, rng.next() as u8));
                self.damaged += 1;
            }
            if rng.chance(self.faults.drop) {
                self.damaged += 1;
                continue;
            }
            let mut b = byte;
            if rng.chance(self.faults.corrupt) {
                b ^= 1 << rng.below(8);
                self.damaged += 1;
            }
            self.in_flight.push_back((arrive, b));
        }
    }

    fn read(&mut self, now: u64) -> Vec<u8> {
        let mut out = Vec::new();
        while self.in_flight.front().is_some_and(|&(t, _)| t <= now) {
            out.extend(self.in_flight.pop_front().map(|(_, b)| b));
        }
        out
    }
}

/// Runs one seeded session; returns (virtual µs taken, bytes damaged).
fn run(seed: u64, messages: usize, faults: Faults) -> (u64, u64) {
    let mut rng = Rng(seed);
    let (mut to_mcu, mut to_host) = (Wire::new(faults), Wire::new(faults));
    let (mut host, mut mcu) = (HostLink::default(), McuLink::new());
    let payloads: Vec<Vec<u8>> = (0..messages)
        .map(|i| {
            let len = 2 + rng.below(MAX_PAYLOAD as u64 - 1) as usize;
            let mut p: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
            p[..2].copy_from_slice(&(i as u16).to_le_bytes());
            p
        })
        .collect();
    let mut delivered: Vec<Vec<u8>> = Vec::new();
    let mut next = 0;
    let mut retransmit = vec![0u8; 1 + MAX_PENDING_BLOCKS * MAX_LEN];
    let mut now = 0u64;
    let limit = 600_000_000; // ten virtual minutes
    while (next < messages || host.unacknowledged() > 0) && now < limit {
        while next < messages && host.can_send(payloads[next].len()) {
            let frame = host
                .send(&payloads[next], now)
                .expect("can_send said yes")
                .to_vec();
            to_mcu.write(&frame, now, &mut rng);
            next += 1;
        }
        if let Some(n) = host.poll(now, &mut retransmit) {
            to_mcu.write(&retransmit[..n], now, &mut rng);
        }
        let arrived = to_mcu.read(now);
        if !arrived.is_empty()
            && let Reply::Ack(_) = mcu.receive(&arrived, |p| delivered.push(p.to_vec()))
        {
            let mut ack = [0u8; MAX_LEN];
            let n = mcu.frame_reply(&[], &mut ack).expect("empty payload fits");
            to_host.write(&ack[..n], now, &mut rng);
        }
        let acks = to_host.read(now);
        host.receive(&acks, now, |_| panic!("the MCU sent no data"));
        now += 100;
    }
    assert!(
        now < limit,
        "seed {seed}: stalled with {} unacknowledged",
        host.unacknowledged()
    );
    assert_eq!(delivered.len(), messages, "seed {seed}: delivered count");
    for (i, (got, sent)) in delivered.iter().zip(&payloads).enumerate() {
        assert_eq!(got, sent, "seed {seed}: payload {i}");
    }
    (now, to_mcu.damaged + to_host.damaged)
}

#[test]
fn a_clean_link_delivers_everything_without_retransmission() {
    let (took, damaged) = run(
        1,
        300,
        Faults {
            drop: 0,
            corrupt: 0,
            insert: 0,
        },
    );
    assert_eq!(damaged, 0);
    // 300 blocks of ~33 bytes at 40 µs a byte take about 0.4 s of wire time.
    assert!(took < 1_000_000, "took {took} µs");
}

#[test]
fn damaged_links_still_deliver_every_block_once_in_order() {
    let faults = Faults {
        drop: 2_000,
        corrupt: 2_000,
        insert: 2_000,
    };
    let mut total_damage = 0;
    for seed in 1..=20 {
        let (_, damaged) = run(0x9e37_79b9 * seed, 300, faults);
        total_damage += damaged;
    }
    assert!(total_damage > 1_000, "faults were injected: {total_damage}");
}

#[test]
fn heavy_damage_only_slows_delivery_down() {
    // 2 % of bytes damaged: a full block survives about one try in three,
    // and timeouts back off towards 5 s.
    let faults = Faults {
        drop: 10_000,
        corrupt: 5_000,
        insert: 5_000,
    };
    for seed in 1..=5 {
        let (took, _) = run(0x1234_5678 + seed, 100, faults);
        eprintln!(
            "seed {seed}: 100 blocks in {:.1} virtual s",
            took as f64 / 1e6
        );
    }
}
