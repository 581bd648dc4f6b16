//! RVL depth decoding: `rvl::decode` and `rvl::decode_zstd` never panic on any bytes, and
//! every payload that decodes encodes back to the same image.

#![no_main]

use compact::rvl;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(image) = rvl::decode(data) {
        assert_eq!(image.values.len(), usize::from(image.width) * usize::from(image.height));
        let again = rvl::encode(
            image.width,
            image.height,
            image.depth_scale,
            image.timestamp_s,
            &image.values,
        );
        let back = rvl::decode(&again).expect("our own encoding decodes");
        assert_eq!(back.values, image.values);
    }
    let _ = rvl::decode_zstd(data);
});
