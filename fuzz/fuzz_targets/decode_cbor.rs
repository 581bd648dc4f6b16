//! coapcam's CBOR maps (the color, depth and point-cloud representations): the decoders
//! never panic on any bytes, and a cloud that decodes encodes back to the same points and
//! timestamp.

#![no_main]

use coapcam::repr::CloudSource;
use coapcam::repr::cbor::{Cloud, ColorCapture, DepthCapture, cloud_cbor};
use libfuzzer_sys::fuzz_target;
use rgbd::Serial;

fuzz_target!(|data: &[u8]| {
    let _ = ColorCapture::from_cbor(data);
    let _ = DepthCapture::from_cbor(data);
    let Ok(cloud) = Cloud::from_cbor(data) else {
        return;
    };
    // Only serials a server could send are encoded again.
    let Ok(serials) = cloud
        .serials
        .iter()
        .map(|s| s.parse::<Serial>())
        .collect::<Result<Vec<_>, _>>()
    else {
        return;
    };
    let source = CloudSource::Merged { serials: &serials };
    let again = cloud_cbor(&cloud.cloud.points, cloud.timestamp_us, source)
        .expect("CBOR encodes in memory");
    let back = Cloud::from_cbor(&again).expect("our own encoding decodes");
    let bits = |c: &Cloud| -> Vec<[u32; 3]> {
        c.cloud
            .points
            .iter()
            .map(|p| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
            .collect()
    };
    assert_eq!(bits(&back), bits(&cloud));
    assert_eq!(back.timestamp_us, cloud.timestamp_us);
    assert_eq!(back.serials, cloud.serials);
});
