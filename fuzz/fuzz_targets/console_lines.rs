//! The console's line protocol against a host that numbers its lines and
//! resends on request, over a link that corrupts bytes: the fuzzer picks
//! which byte of which transmission is corrupted and how (at most one per
//! transmission: the XOR checksum is meant to catch single-byte errors).
//! Every line must run exactly once, in order, intact; nothing may panic
//! (the emergency parser reads the same bytes).
#![no_main]

use libfuzzer_sys::fuzz_target;
use onechip_app::emergency::EmergencyParser;
use onechip_app::line::{LineAssembler, LineEvent};
use onechip_app::line_protocol::{Checked, LineNumbers};

/// The host's job.
const JOB: [&str; 6] = ["G28", "G1 X10 Y10 F3000", "M104 S200", "G1 Z0.2", "M117 Hi*there", "G1 X0"];

fuzz_target!(|data: &[u8]| {
    let mut corruptions = data.chunks_exact(3);
    let mut numbers = LineNumbers::new();
    let mut lines = LineAssembler::<256>::new();
    let mut emergency = EmergencyParser::new();
    let mut ran: Vec<Vec<u8>> = Vec::new();
    let mut next = 1i64;
    let mut transmissions = 0;
    while (next as usize) <= JOB.len() {
        transmissions += 1;
        assert!(transmissions < 10_000, "the host never gets through");
        let body = format!("N{next} {}", JOB[next as usize - 1]);
        let sum = body.bytes().fold(0u8, |a, b| a ^ b);
        let mut wire = format!("{body}*{sum}\n").into_bytes();
        if let Some(&[at, xor, on]) = corruptions.next()
            && on & 1 == 1
            && xor != 0
        {
            let at = usize::from(at) % wire.len();
            wire[at] ^= xor;
        }
        let mut resend = None;
        let mut acked = false;
        // A corrupted line end leaves the line pending: the host's
        // timeout sends a bare line end, as OctoPrint's and Printrun's do.
        for &byte in wire.iter().chain(b"\n") {
            let _ = emergency.push(byte);
            let checked = match lines.push(byte) {
                Some(LineEvent::Complete(line)) => numbers.check(line),
                Some(LineEvent::TooLong { len }) => numbers.too_long(len),
                None => continue,
            };
            acked = true;
            match checked {
                Checked::Run(command) => ran.push(command.to_vec()),
                Checked::Repeat => {}
                Checked::Resend { resend: n, .. } => resend = Some(n),
            }
        }
        assert!(acked, "every transmission is answered");
        next = resend.unwrap_or(numbers.last() + 1);
    }
    let expected: Vec<Vec<u8>> = JOB.iter().map(|l| l.as_bytes().to_vec()).collect();
    // A line split by a corrupted line end: its head is numbered without a
    // checksum and its tail has a checksum without a number, both refused,
    // unless the corrupted byte was the `*` or a checksum digit (then the
    // tail is only digits) or the line number's first digit (then the
    // head is a bare `N`): those run, and are no G-code command.
    let (numbered, fragments): (Vec<_>, Vec<_>) =
        ran.into_iter().partition(|l| expected.contains(l));
    assert_eq!(numbered, expected);
    for fragment in fragments {
        let digits = fragment.strip_prefix(b"N").unwrap_or(&fragment);
        assert!(digits.iter().all(u8::is_ascii_digit), "{fragment:?} ran");
    }
});
