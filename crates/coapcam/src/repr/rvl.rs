//! Depth as RVL (65101) and as RVL in a zstd frame (65102), lossless. The codec and the
//! payload's layout are the `compact` crate's ([`compact::rvl`]); here a grabbed frame
//! becomes a payload, and a payload a [`DepthImage`].

use compact::rvl;
use rgbd::DepthFrame;

use super::codec::{Decoders, DepthImage, EncodeError, Subject};
use super::packet::{depth_rows, unix_seconds};

pub use compact::rvl::RvlError;

/// A depth frame as RVL (65101). Frames are at most 65,535 pixels wide and high (a
/// D400's largest is 1280 x 720).
pub fn depth_rvl(frame: &DepthFrame) -> Vec<u8> {
    let width = frame.width as usize;
    let packed;
    let pixels = if frame.stride == width {
        &frame.data[..(width * frame.height as usize).min(frame.data.len())]
    } else {
        packed = depth_rows(frame).flatten().copied().collect::<Vec<u16>>();
        &packed[..]
    };
    rvl::encode(
        frame.width as u16,
        frame.height as u16,
        frame.depth_scale,
        unix_seconds(frame.timestamp_us),
        pixels,
    )
}

/// A depth frame as RVL in a zstd frame (65102).
pub fn depth_rvl_zstd(frame: &DepthFrame) -> Result<Vec<u8>, EncodeError> {
    Ok(rvl::compress(&depth_rvl(frame))?)
}

/// An RVL payload (65101) as a depth image.
pub fn depth_from_rvl(payload: &[u8]) -> Result<DepthImage, RvlError> {
    rvl::decode(payload).map(image)
}

/// An RVL+zstd payload (65102) as a depth image.
pub fn depth_from_rvl_zstd(payload: &[u8]) -> Result<DepthImage, RvlError> {
    rvl::decode_zstd(payload).map(image)
}

fn image(d: rvl::DepthImage) -> DepthImage {
    DepthImage {
        width: u32::from(d.width),
        height: u32::from(d.height),
        timestamp_s: d.timestamp_s,
        depth_scale: d.depth_scale,
        values: d.values,
    }
}

// ---- the rows of the table

/// RVL's encoder: depth.
pub fn encode_rvl(subject: &Subject<'_>) -> Result<Vec<u8>, EncodeError> {
    match *subject {
        Subject::Depth { frame, .. } => Ok(depth_rvl(frame)),
        _ => Err(subject.not_served("RVL")),
    }
}

/// RVL+zstd's encoder: depth.
pub fn encode_rvl_zstd(subject: &Subject<'_>) -> Result<Vec<u8>, EncodeError> {
    match *subject {
        Subject::Depth { frame, .. } => depth_rvl_zstd(frame),
        _ => Err(subject.not_served("RVL+zstd")),
    }
}

/// RVL read back: depth.
pub const RVL_DECODERS: Decoders = Decoders {
    depth: Some(|body| Ok(depth_from_rvl(body)?)),
    ..Decoders::NONE
};

/// RVL+zstd read back: depth.
pub const RVL_ZSTD_DECODERS: Decoders = Decoders {
    depth: Some(|body| Ok(depth_from_rvl_zstd(body)?)),
    ..Decoders::NONE
};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_round_trips_without_its_row_padding() {
        let frame = DepthFrame {
            width: 2,
            height: 2,
            stride: 3,
            depth_scale: 0.000_25,
            timestamp_us: 1_700_000_000_500_000,
            frame_number: 7,
            data: vec![5, 6, 99, 0, 8, 99],
        };
        for payload in [depth_rvl(&frame), depth_rvl_zstd(&frame).expect("zstd")] {
            let image = depth_from_rvl(&payload).or_else(|_| depth_from_rvl_zstd(&payload));
            let image = image.expect("decodes");
            assert_eq!(image.values, [5, 6, 0, 8]);
            assert_eq!((image.width, image.height), (2, 2));
            assert_eq!(image.depth_scale, 0.000_25);
            assert_eq!(image.timestamp_s, 1_700_000_000);
        }
    }
}
