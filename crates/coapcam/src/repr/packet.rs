//! The thesis packets (docs/design.md §5): a header in network byte order, then the data.
//! Encoders (the server) and decoders (the client) side by side; the decoders check the
//! lengths the headers announce.
//!
//! | type | header | data |
//! |---|---|---|
//! | 1 color | type, width, height (u16), pixel size (u8), timestamp (u32 s) | pixels, compact rows, the camera's format |
//! | 2 depth | as color with pixel size 2, then the depth scale (f32) | Z16 values little-endian |
//! | 3 point cloud | type, point size 12, reserved (u16), points (u32), timestamp (u32 s) | x, y, z as f32 little-endian, metres |

use geometry::{Point3, PointCloud};
use image::RgbImage;
use rgbd::{ColorFrame, DepthFrame};

pub use super::codec::DepthImage;
pub use super::codec::PacketError;
use super::codec::{Cloud, ColorDecoder, DecodeError, Decoders, EncodeError, Subject, checked_len};

/// Packet type of a color image.
pub const TYPE_COLOR: u8 = 1;
/// Packet type of a depth image.
pub const TYPE_DEPTH: u8 = 2;
/// Packet type of a point cloud.
pub const TYPE_CLOUD: u8 = 3;
/// Bytes per point of a point-cloud packet: x, y, z as f32.
pub const POINT_SIZE: u8 = 12;

/// Seconds since the UNIX epoch of a frame timestamp in microseconds, as the 32-bit
/// field of the packets holds them.
pub fn unix_seconds(timestamp_us: u64) -> u32 {
    u32::try_from(timestamp_us / 1_000_000).unwrap_or(u32::MAX)
}

fn dimension(v: u32) -> [u8; 2] {
    u16::try_from(v).unwrap_or(u16::MAX).to_be_bytes()
}

/// The rows of a color frame without stride padding.
pub(super) fn compact_pixels(frame: &ColorFrame) -> impl Iterator<Item = &[u8]> {
    let row = frame.width as usize * frame.format.bytes_per_pixel();
    (0..frame.height as usize).filter_map(move |y| {
        let start = y * frame.stride;
        frame.data.get(start..start + row)
    })
}

/// Color packet: type 1, width, height, pixel size, timestamp, then the pixels
/// row-major in the frame's format.
pub fn color_packet(frame: &ColorFrame) -> Vec<u8> {
    let bpp = frame.format.bytes_per_pixel();
    let mut out = Vec::with_capacity(10 + frame.width as usize * frame.height as usize * bpp);
    out.push(TYPE_COLOR);
    out.extend_from_slice(&dimension(frame.width));
    out.extend_from_slice(&dimension(frame.height));
    out.push(u8::try_from(bpp).unwrap_or(u8::MAX));
    out.extend_from_slice(&unix_seconds(frame.timestamp_us).to_be_bytes());
    for row in compact_pixels(frame) {
        out.extend_from_slice(row);
    }
    out
}

/// Appends the depth values of `frame` little-endian, compact rows.
pub(super) fn append_depth_values(frame: &DepthFrame, out: &mut Vec<u8>) {
    for row in depth_rows(frame) {
        for v in row {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
}

/// Appends x, y, z of every point as f32 little-endian.
pub(super) fn append_points(points: &[Point3], out: &mut Vec<u8>) {
    for p in points {
        for c in [p.x, p.y, p.z] {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
}

/// Depth packet: type 2, width, height, pixel size 2, timestamp, depth scale (f32),
/// then Z16 values little-endian.
pub fn depth_packet(frame: &DepthFrame) -> Vec<u8> {
    let mut out = Vec::with_capacity(14 + frame.width as usize * frame.height as usize * 2);
    out.push(TYPE_DEPTH);
    out.extend_from_slice(&dimension(frame.width));
    out.extend_from_slice(&dimension(frame.height));
    out.push(2);
    out.extend_from_slice(&unix_seconds(frame.timestamp_us).to_be_bytes());
    out.extend_from_slice(&frame.depth_scale.to_be_bytes());
    append_depth_values(frame, &mut out);
    out
}

pub(super) fn depth_rows(frame: &DepthFrame) -> impl Iterator<Item = &[u16]> {
    let width = frame.width as usize;
    (0..frame.height as usize).filter_map(move |y| {
        let start = y * frame.stride;
        frame.data.get(start..start + width)
    })
}

/// Point-cloud packet: type 3, point size 12, reserved 0, number of points (u32),
/// timestamp, then x, y, z as f32 little-endian in metres.
pub fn cloud_packet(points: &[Point3], timestamp_s: u32) -> Vec<u8> {
    let mut out = Vec::with_capacity(12 + points.len() * usize::from(POINT_SIZE));
    out.push(TYPE_CLOUD);
    out.push(POINT_SIZE);
    out.extend_from_slice(&0u16.to_be_bytes());
    out.extend_from_slice(
        &u32::try_from(points.len())
            .unwrap_or(u32::MAX)
            .to_be_bytes(),
    );
    out.extend_from_slice(&timestamp_s.to_be_bytes());
    append_points(points, &mut out);
    out
}

// ---- reading

fn error(what: &'static str, problem: impl Into<String>) -> PacketError {
    PacketError {
        what,
        problem: problem.into(),
    }
}

/// A point cloud in metres and the second it was grabbed.
#[derive(Debug, Clone, PartialEq)]
pub struct CloudPacket {
    /// Seconds since the UNIX epoch.
    pub timestamp_s: u32,
    /// The points, metres.
    pub cloud: PointCloud,
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
pub fn depth(packet: &[u8]) -> Result<DepthImage, PacketError> {
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
pub fn cloud(packet: &[u8]) -> Result<CloudPacket, PacketError> {
    const HEADER: usize = 12;
    let what = "point-cloud";
    check_header(packet, what, HEADER, TYPE_CLOUD, ("point size", 1, 12))?;
    let count = be_u32(packet, 4) as usize;
    let body = &packet[HEADER..];
    if checked_len(&[count as u64, 12]) != Some(body.len() as u64) {
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
pub fn points(data: &[u8]) -> PointCloud {
    let f = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    data.chunks_exact(12)
        .map(|p| Point3::new(f(&p[0..4]), f(&p[4..8]), f(&p[8..12])))
        .collect()
}

/// Color pixels of `width` x `height`, `bytes_per_pixel` (3 or 4) each, in the camera's
/// `format` (RGB8, BGR8, RGBA8, BGRA8), as an RGB image.
pub fn rgb_image(
    pixels: &[u8],
    width: u32,
    height: u32,
    bytes_per_pixel: usize,
    format: &str,
) -> Result<RgbImage, String> {
    let needed = checked_len(&[width.into(), height.into(), bytes_per_pixel as u64]);
    if !(3..=4).contains(&bytes_per_pixel) || needed != Some(pixels.len() as u64) {
        return Err(format!(
            "{} bytes are not {width}x{height} pixels of {bytes_per_pixel} bytes",
            pixels.len()
        ));
    }
    let bgr = format.to_ascii_uppercase().starts_with("BGR");
    let rgb = pixels
        .chunks_exact(bytes_per_pixel)
        .flat_map(|p| {
            if bgr {
                [p[2], p[1], p[0]]
            } else {
                [p[0], p[1], p[2]]
            }
        })
        .collect();
    RgbImage::from_raw(width, height, rgb).ok_or_else(|| "the image's size".to_owned())
}

/// Reads a color packet whose pixels are in the camera's `format` (its color-settings:
/// RGB8, BGR8, RGBA8 or BGRA8) as an RGB image.
pub fn color(packet: &[u8], format: &str) -> Result<RgbImage, PacketError> {
    const HEADER: usize = 10;
    let what = "color";
    if packet.len() < HEADER {
        return Err(error(
            what,
            format!("{} bytes, the header alone is {HEADER}", packet.len()),
        ));
    }
    if packet[0] != TYPE_COLOR {
        return Err(error(
            what,
            format!("type {}, expected {TYPE_COLOR}", packet[0]),
        ));
    }
    let (width, height) = (u32::from(be_u16(packet, 1)), u32::from(be_u16(packet, 3)));
    rgb_image(
        &packet[HEADER..],
        width,
        height,
        usize::from(packet[5]),
        format,
    )
    .map_err(|problem| error(what, problem))
}

// ---- the row of the table

fn read_error(what: &'static str) -> impl FnOnce(PacketError) -> DecodeError {
    move |source| DecodeError::Packet { what, source }
}

/// The thesis packet's encoder: every stream.
pub fn encode(subject: &Subject<'_>) -> Result<Vec<u8>, EncodeError> {
    Ok(match *subject {
        Subject::Color { frame, .. } => color_packet(frame),
        Subject::Depth { frame, .. } => depth_packet(frame),
        Subject::Cloud {
            points,
            timestamp_us,
            ..
        } => cloud_packet(points, unix_seconds(timestamp_us)),
    })
}

/// The thesis packet read back: color with the camera's pixel format, depth, and a cloud
/// (no cameras, whole seconds).
pub const DECODERS: Decoders = Decoders {
    color: Some(ColorDecoder::WithPixelFormat(|body, pixel_format| {
        color(body, pixel_format).map_err(read_error("color"))
    })),
    depth: Some(|body| depth(body).map_err(read_error("depth"))),
    cloud: Some(|body| {
        let p = cloud(body).map_err(read_error("point-cloud"))?;
        Ok(Cloud {
            cloud: p.cloud,
            serials: Vec::new(),
            timestamp_us: u64::from(p.timestamp_s) * 1_000_000,
            views: Vec::new(),
            frames: Vec::new(),
        })
    }),
};

#[cfg(test)]
mod tests {
    use super::*;
    use crate::repr::tests::color;
    use rgbd::ColorFormat;

    #[test]
    fn color_packet_is_ten_bytes_of_header_and_compact_pixels() {
        let p = color_packet(&color(ColorFormat::Bgr8, 640, 480, 640 * 3 + 8));
        assert_eq!(p.len(), 921_610);
        assert_eq!(&p[..6], &[1, 0x02, 0x80, 0x01, 0xe0, 3]);
        assert_eq!(&p[6..10], &1_700_000_000u32.to_be_bytes());
    }

    #[test]
    fn depth_packet_has_scale_and_little_endian_values() {
        let frame = DepthFrame {
            width: 2,
            height: 1,
            stride: 2,
            depth_scale: 0.001,
            timestamp_us: 3_000_000,
            frame_number: 1,
            data: vec![0x0102, 0x0304],
        };
        let p = depth_packet(&frame);
        assert_eq!(p.len(), 14 + 4);
        assert_eq!(&p[..6], &[2, 0, 2, 0, 1, 2]);
        assert_eq!(&p[6..10], &3u32.to_be_bytes());
        assert_eq!(&p[10..14], &0.001f32.to_be_bytes());
        assert_eq!(&p[14..], &[0x02, 0x01, 0x04, 0x03]);
    }

    #[test]
    fn cloud_packet_counts_points_in_32_bits() {
        let p = cloud_packet(&[Point3::new(1.0, 2.0, 3.0)], 9);
        assert_eq!(p.len(), 24);
        assert_eq!(&p[..4], &[3, 12, 0, 0]);
        assert_eq!(&p[4..8], &1u32.to_be_bytes());
        assert_eq!(&p[8..12], &9u32.to_be_bytes());
        assert_eq!(&p[12..16], &1.0f32.to_le_bytes());
        assert_eq!(cloud_packet(&[], 0).len(), 12);
    }

    fn raw_cloud_packet(points: &[[f32; 3]], announced: u32) -> Vec<u8> {
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
        let got = cloud(&raw_cloud_packet(&[[1.0, -2.0, 0.5], [0.0, 0.25, 3.0]], 2)).unwrap();
        assert_eq!(got.timestamp_s, 1_700_000_000);
        assert_eq!(
            got.cloud.points,
            vec![Point3::new(1.0, -2.0, 0.5), Point3::new(0.0, 0.25, 3.0)]
        );
        assert!(cloud(&raw_cloud_packet(&[], 0)).unwrap().cloud.is_empty());
    }

    #[test]
    fn a_cloud_packet_whose_count_disagrees_is_refused() {
        let err = cloud(&raw_cloud_packet(&[[1.0, 2.0, 3.0]], 2)).unwrap_err();
        assert!(
            err.to_string().contains("2 points announced, 12 bytes"),
            "{err}"
        );
        let mut short = raw_cloud_packet(&[[1.0, 2.0, 3.0]], 1);
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
