//! Instructions per `queue_step` on a Cortex-M7: encoding the message, then
//! encoding plus its share of block framing (CRC16), then decoding it.
//! Uses the real STM32F446 data dictionary of the golden runs.
#![no_std]
#![no_main]

use cortex_m_rt::entry;
use onechip_m7bench::{Inputs, exit, measure, report};
use onechip_protocol::block;
use onechip_protocol::codec::Encoder;
use onechip_protocol::dictionary::Dictionary;

const DICTIONARY: &str = include_str!("../../../../shared/golden/dicts/stm32f446.dict");
const STEPS: usize = 1000;

#[entry]
fn main() -> ! {
    let Ok(dict) = Dictionary::parse(DICTIONARY) else {
        panic!("dictionary")
    };
    let Ok(queue_step) = Encoder::new(&dict, "queue_step") else {
        panic!("queue_step")
    };
    let mut inputs = Inputs(0x1234_5678);
    let args: [[i64; 4]; STEPS] = core::array::from_fn(|_| {
        [
            inputs.between(2, 8),
            inputs.between(20_000, 200_000),
            inputs.between(1, 1500),
            inputs.between(-3000, 6000),
        ]
    });

    measure(0, || 0u32);

    let mut payload = [0u8; block::MAX_PAYLOAD];
    let encoded_bytes = measure(1, || {
        let mut total = 0;
        for a in &args {
            let n = queue_step
                .encode_ints(core::hint::black_box(a), &mut payload)
                .unwrap_or(0);
            total += n;
        }
        total
    });

    let mut frame = [0u8; block::MAX_LEN];
    let blocks = measure(2, || {
        let (mut len, mut blocks) = (0, 0u32);
        for a in &args {
            if len + 9 > block::MAX_PAYLOAD {
                let _ = block::encode(blocks as u8, &payload[..len], &mut frame);
                blocks += 1;
                len = 0;
            }
            len += queue_step
                .encode_ints(core::hint::black_box(a), &mut payload[len..])
                .unwrap_or(0);
        }
        let _ = block::encode(blocks as u8, &payload[..len], &mut frame);
        blocks + 1
    });

    let mut wire = [0u8; 9];
    let n = queue_step.encode_ints(&args[0], &mut wire).unwrap_or(0);
    let decoded_sum = measure(3, || {
        let mut sum = 0i64;
        for _ in 0..STEPS {
            if let Ok((msg, _)) = dict.decode(core::hint::black_box(&wire[..n])) {
                sum += msg.int("count").unwrap_or(0);
            }
        }
        sum
    });

    report(format_args!(
        "queue_step x{STEPS}: region 1 encode ({encoded_bytes} bytes), region 2 encode+frame ({blocks} blocks), region 3 decode (sum {decoded_sum})"
    ));
    exit()
}
