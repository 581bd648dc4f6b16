//! Compact cloud decoding: `cloud::decode` never panics, on any bytes and on any bytes in a
//! zstd frame (so that the fuzzer reaches the layout inside), and every payload that
//! decodes encodes back to the same parts.

#![no_main]

use compact::{cloud, rvl};
use libfuzzer_sys::fuzz_target;

fn check(payload: &[u8]) {
    let Ok(parts) = cloud::decode(payload) else {
        return;
    };
    let depths: Vec<Vec<u8>> = parts
        .iter()
        .map(|(_, d)| rvl::encode(d.width, d.height, d.depth_scale, d.timestamp_s, &d.values))
        .collect();
    let again = cloud::encode(parts.iter().zip(&depths).map(|((p, _), d)| (p, &d[..])))
        .expect("zstd compresses in memory");
    let back = cloud::decode(&again).expect("our own encoding decodes");
    assert_eq!(back, parts);
}

fuzz_target!(|data: &[u8]| {
    check(data);
    if let Ok(wrapped) = zstd::bulk::compress(data, 1) {
        check(&wrapped);
    }
});
