//! Every block klippy wrote in the golden runs is well framed, and our encoder
//! rebuilds it byte for byte from its sequence number and payload.

use onechip_protocol::block;
use std::path::PathBuf;

fn golden_dir() -> PathBuf {
    std::env::var_os("ONECHIP_GOLDEN").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/golden"),
        PathBuf::from,
    )
}

#[test]
fn golden_serial_streams_reframe_byte_for_byte() {
    let dir = golden_dir();
    let mut cases = 0;
    for entry in std::fs::read_dir(&dir).expect("golden folder (set ONECHIP_GOLDEN)") {
        let path = entry.expect("dir entry").path().join("klippy.serial");
        let Ok(bytes) = std::fs::read(&path) else {
            continue;
        };
        cases += 1;
        let (mut at, mut blocks, mut expected_seq) = (0, 0, None);
        while at < bytes.len() {
            let found = block::parse(&bytes[at..])
                .unwrap_or_else(|e| panic!("{}: offset {at}: {e:?}", path.display()));
            if let Some(seq) = expected_seq {
                assert_eq!(found.seq, seq, "{}: sequence gap at {at}", path.display());
            }
            expected_seq = Some((found.seq + 1) & block::SEQ_MASK);
            let mut rebuilt = [0u8; block::MAX_LEN];
            let n = block::encode(found.seq, found.payload, &mut rebuilt).expect("fits");
            assert_eq!(
                &rebuilt[..n],
                &bytes[at..at + n],
                "{}: block at {at}",
                path.display()
            );
            at += n;
            blocks += 1;
        }
        assert!(blocks > 10, "{}: only {blocks} blocks", path.display());
    }
    assert_eq!(
        cases,
        15,
        "expected the 15 golden cases in {}",
        dir.display()
    );
}
