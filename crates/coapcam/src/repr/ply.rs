//! Point clouds as binary little-endian PLY (written by `geometry`), with where they came
//! from in the comment line.

use geometry::Point3;

use super::codec::{Cloud, CloudSource, Decoders, EncodeError, Subject};

/// A point cloud as binary little-endian PLY, its origin in the comment line.
pub fn cloud_ply(
    points: &[Point3],
    timestamp_us: u64,
    source: CloudSource<'_>,
) -> Result<Vec<u8>, EncodeError> {
    let comment = match source {
        CloudSource::Camera { serial, frame } => {
            format!("coapcam camera {serial} frame {frame} timestamp_us {timestamp_us}")
        }
        CloudSource::Merged { serials } => format!(
            "coapcam merged cloud of {} cameras timestamp_us {timestamp_us}",
            serials.len()
        ),
    };
    Ok(geometry::encode_ply(points, Some(&comment))?)
}

/// PLY's encoder: point clouds.
pub fn encode(subject: &Subject<'_>) -> Result<Vec<u8>, EncodeError> {
    match *subject {
        Subject::Cloud {
            points,
            timestamp_us,
            source,
            ..
        } => cloud_ply(points, timestamp_us, source),
        _ => Err(subject.not_served("PLY")),
    }
}

/// PLY read back: a cloud (no cameras, no time).
pub const DECODERS: Decoders = Decoders {
    cloud: Some(|body| {
        Ok(Cloud {
            cloud: geometry::decode_ply(body)?,
            serials: Vec::new(),
            timestamp_us: 0,
            views: Vec::new(),
            frames: Vec::new(),
        })
    }),
    ..Decoders::NONE
};
