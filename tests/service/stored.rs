//! The wire answers a stored result byte for byte as the JSON the store keeps: every
//! localization of the golden store (written by the pre-refactor code, whose API answered with
//! the stored bytes) is answered today with exactly those bytes.

/// Every localization in the golden store (written by the pre-refactor code, whose API
/// answered with the stored bytes) is answered today with exactly those bytes.
#[test]
fn stored_localizations_are_answered_byte_for_byte() {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/store-layout4.golden");
    let text = std::fs::read_to_string(path).unwrap();
    let unhex = |h: &str| -> Vec<u8> {
        (0..h.len())
            .step_by(2)
            .map(|k| u8::from_str_radix(&h[k..k + 2], 16).unwrap())
            .collect()
    };
    let mut seen = 0;
    for line in text.lines().filter(|l| l.starts_with("4c")) {
        let (k, v) = line.split_once(' ').unwrap();
        let (k, v) = (unhex(k), unhex(v));
        let record = seasonloc_store::sled::codec::decode_localization(&k, &v).unwrap();
        let wire = serde_json::to_vec(&seasonloc_server::api::LocalizationResponse::from(&record))
            .unwrap();
        // format byte, id, map id, created, length prefix, then the stored JSON
        assert_eq!(wire, &v[1 + 8 + 8 + 8 + 4..]);
        seen += 1;
    }
    assert_eq!(seen, 2);
}
