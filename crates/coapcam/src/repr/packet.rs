//! Reading the thesis packets (DESIGN.md §5) on the client side: the inverse of
//! `cams::repr`'s encoders, checked against the lengths their headers announce.

use geometry::{Point3, PointCloud};

/// Packet type of a depth image.
const TYPE_DEPTH: u8 = 2;
/// Packet type of a point cloud.
const TYPE_CLOUD: u8 = 3;

/// A packet that does not hold what its header says.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{what} packet: {problem}")]
pub(crate) struct PacketError {
    what: &'static str,
    problem: String,
}

fn error(what: &'static str, problem: impl Into<String>) -> PacketError {
    PacketError {
        what,
        problem: problem.into(),
    }
}

/// A depth image: Z16 values in raw units and the metres per unit.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct DepthImage {
    pub(crate) width: u32,
    pub(crate) height: u32,
    /// Seconds since the UNIX epoch.
    pub(crate) timestamp_s: u32,
    pub(crate) depth_scale: f32,
    /// Row-major, `width * height` values; 0 = no depth.
    pub(crate) values: Vec<u16>,
}

/// A point cloud in metres and the second it was grabbed.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct CloudPacket {
    /// Seconds since the UNIX epoch.
    pub(crate) timestamp_s: u32,
    pub(crate) cloud: PointCloud,
}

fn be_u16(b: &[u8], at: usize) -> u16 {
    u16::from_be_bytes([b[at], b[at + 1]])
}

fn be_u32(b: &[u8], at: usize) -> u32 {
    u32::from_be_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

/// Checks what every packet begins with: at least `header` bytes, the packet type `kind`
/// first, and the element size `(name, at byte, expected)`.
fn check_header(
    packet: &[u8],
    what: &'static str,
    header: usize,
    kind: u8,
    (size_name, size_at, size): (&str, usize, u8),
) -> Result<(), PacketError> {
    if packet.len() < header {
        return Err(error(
            what,
            format!("{} bytes, the header alone is {header}", packet.len()),
        ));
    }
    if packet[0] != kind {
        return Err(error(what, format!("type {}, expected {kind}", packet[0])));
    }
    if packet[size_at] != size {
        return Err(error(
            what,
            format!("{size_name} {}, expected {size}", packet[size_at]),
        ));
    }
    Ok(())
}

/// Reads a depth packet: type 2, width, height, pixel size 2, timestamp, depth scale,
/// then Z16 values little-endian.
pub(crate) fn depth(packet: &[u8]) -> Result<DepthImage, PacketError> {
    const HEADER: usize = 14;
    let what = "depth";
    check_header(packet, what, HEADER, TYPE_DEPTH, ("pixel size", 5, 2))?;
    let (width, height) = (u32::from(be_u16(packet, 1)), u32::from(be_u16(packet, 3)));
    let expected = HEADER + width as usize * height as usize * 2;
    if packet.len() != expected {
        return Err(error(
            what,
            format!(
                "{width}x{height} needs {expected} bytes, {} arrived",
                packet.len()
            ),
        ));
    }
    let depth_scale = f32::from_bits(be_u32(packet, 10));
    if !(depth_scale.is_finite() && depth_scale > 0.0) {
        return Err(error(
            what,
            format!("depth scale {depth_scale} is not positive"),
        ));
    }
    Ok(DepthImage {
        width,
        height,
        timestamp_s: be_u32(packet, 6),
        depth_scale,
        values: packet[HEADER..]
            .chunks_exact(2)
            .map(|v| u16::from_le_bytes([v[0], v[1]]))
            .collect(),
    })
}

/// Reads a point-cloud packet: type 3, point size 12, reserved, number of points (u32),
/// timestamp, then x, y, z as f32 little-endian.
pub(crate) fn cloud(packet: &[u8]) -> Result<CloudPacket, PacketError> {
    const HEADER: usize = 12;
    let what = "point-cloud";
    check_header(packet, what, HEADER, TYPE_CLOUD, ("point size", 1, 12))?;
    let count = be_u32(packet, 4) as usize;
    let body = &packet[HEADER..];
    if count.checked_mul(12) != Some(body.len()) {
        return Err(error(
            what,
            format!(
                "{count} points announced, {} bytes of points arrived",
                body.len()
            ),
        ));
    }
    Ok(CloudPacket {
        timestamp_s: be_u32(packet, 8),
        cloud: points(body),
    })
}

/// Points stored as x, y, z f32 little-endian (12 bytes each; a partial point is
/// ignored: callers check the length).
pub(crate) fn points(data: &[u8]) -> PointCloud {
    let f = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    data.chunks_exact(12)
        .map(|p| Point3::new(f(&p[0..4]), f(&p[4..8]), f(&p[8..12])))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud_packet(points: &[[f32; 3]], announced: u32) -> Vec<u8> {
        let mut p = vec![3, 12, 0, 0];
        p.extend_from_slice(&announced.to_be_bytes());
        p.extend_from_slice(&1_700_000_000u32.to_be_bytes());
        for q in points {
            for c in q {
                p.extend_from_slice(&c.to_le_bytes());
            }
        }
        p
    }

    #[test]
    fn a_cloud_packet_reads_back_its_points_and_timestamp() {
        let got = cloud(&cloud_packet(&[[1.0, -2.0, 0.5], [0.0, 0.25, 3.0]], 2)).unwrap();
        assert_eq!(got.timestamp_s, 1_700_000_000);
        assert_eq!(
            got.cloud.points,
            vec![Point3::new(1.0, -2.0, 0.5), Point3::new(0.0, 0.25, 3.0)]
        );
        assert!(cloud(&cloud_packet(&[], 0)).unwrap().cloud.is_empty());
    }

    #[test]
    fn a_cloud_packet_whose_count_disagrees_is_refused() {
        let err = cloud(&cloud_packet(&[[1.0, 2.0, 3.0]], 2)).unwrap_err();
        assert!(
            err.to_string().contains("2 points announced, 12 bytes"),
            "{err}"
        );
        let mut short = cloud_packet(&[[1.0, 2.0, 3.0]], 1);
        short.pop();
        assert!(cloud(&short).is_err());
        assert!(cloud(&[3, 12]).is_err());
    }

    #[test]
    fn a_depth_packet_reads_back_values_and_scale() {
        let mut p = vec![2, 0, 2, 0, 1, 2];
        p.extend_from_slice(&5u32.to_be_bytes());
        p.extend_from_slice(&0.001f32.to_be_bytes());
        p.extend_from_slice(&[0x34, 0x12, 0, 0]);
        let d = depth(&p).unwrap();
        assert_eq!((d.width, d.height, d.timestamp_s), (2, 1, 5));
        assert_eq!(d.depth_scale, 0.001);
        assert_eq!(d.values, vec![0x1234, 0]);
        p.push(0);
        assert!(
            depth(&p)
                .unwrap_err()
                .to_string()
                .contains("needs 18 bytes")
        );
    }
}
