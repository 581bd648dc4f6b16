//! Quantized cloud decoding: `mm::decode` never panics, on any bytes and on any bytes in a
//! zstd frame, and every payload that decodes encodes back to the same cloud.

#![no_main]

use compact::mm;
use libfuzzer_sys::fuzz_target;

fn check(payload: &[u8]) {
    let Ok(cloud) = mm::decode(payload) else {
        return;
    };
    let serials: Vec<&str> = cloud.serials.iter().map(String::as_str).collect();
    let again = mm::encode(cloud.timestamp_us, &serials, &cloud.points)
        .expect("zstd compresses in memory");
    let back = mm::decode(&again).expect("our own encoding decodes");
    assert_eq!(back, cloud);
}

fuzz_target!(|data: &[u8]| {
    check(data);
    if let Ok(wrapped) = zstd::bulk::compress(data, 1) {
        check(&wrapped);
    }
});
