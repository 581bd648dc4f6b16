//! Representations of grabbed frames: the thesis packets (DESIGN.md §5, header in
//! network byte order), PNG / JPEG images, CBOR maps (the packet's header fields plus
//! serial, frame number, microsecond timestamp and intrinsics, the data as a byte string;
//! the keys are listed in README.md) and binary PLY point clouds.

use ciborium::Value;
use coap::ContentFormat;
use geometry::Point3;
use image::ExtendedColorType;
use image::ImageEncoder as _;
use image::codecs::jpeg::JpegEncoder;
use image::codecs::png::PngEncoder;
use rgbd::{ColorFormat, ColorFrame, DepthFrame, Extrinsics, Intrinsics, Serial};

/// Packet type of a color image.
const TYPE_COLOR: u8 = 1;
/// Packet type of a depth image.
const TYPE_DEPTH: u8 = 2;
/// Packet type of a point cloud.
const TYPE_CLOUD: u8 = 3;
/// Bytes per point of a point-cloud packet: x, y, z as f32.
const POINT_SIZE: u8 = 12;
/// Quality of JPEG color images.
const JPEG_QUALITY: u8 = 90;

/// A representation could not be encoded.
#[derive(Debug, thiserror::Error)]
pub(crate) enum EncodeError {
    #[error("encoding {format}: {source}")]
    Image {
        format: &'static str,
        source: image::ImageError,
    },
    #[error("encoding CBOR: {0}")]
    Cbor(#[from] ciborium::ser::Error<std::io::Error>),
    #[error("encoding PLY: {0}")]
    Ply(#[from] geometry::PlyError),
}

fn image_error(format: &'static str) -> impl FnOnce(image::ImageError) -> EncodeError {
    move |source| EncodeError::Image { format, source }
}

/// Seconds since the UNIX epoch of a frame timestamp in microseconds, as the 32-bit
/// field of the packets holds them.
pub(crate) fn unix_seconds(timestamp_us: u64) -> u32 {
    u32::try_from(timestamp_us / 1_000_000).unwrap_or(u32::MAX)
}

fn dimension(v: u32) -> [u8; 2] {
    u16::try_from(v).unwrap_or(u16::MAX).to_be_bytes()
}

/// The rows of a color frame without stride padding.
fn compact_pixels(frame: &ColorFrame) -> impl Iterator<Item = &[u8]> {
    let row = frame.width as usize * frame.format.bytes_per_pixel();
    (0..frame.height as usize).filter_map(move |y| {
        let start = y * frame.stride;
        frame.data.get(start..start + row)
    })
}

/// Color packet: type 1, width, height, pixel size, timestamp, then the pixels
/// row-major in the frame's format.
pub(crate) fn color_packet(frame: &ColorFrame) -> Vec<u8> {
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
fn append_depth_values(frame: &DepthFrame, out: &mut Vec<u8>) {
    for row in depth_rows(frame) {
        for v in row {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
}

/// Appends x, y, z of every point as f32 little-endian.
fn append_points(points: &[Point3], out: &mut Vec<u8>) {
    for p in points {
        for c in [p.x, p.y, p.z] {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
}

/// Depth packet: type 2, width, height, pixel size 2, timestamp, depth scale (f32),
/// then Z16 values little-endian.
pub(crate) fn depth_packet(frame: &DepthFrame) -> Vec<u8> {
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

fn depth_rows(frame: &DepthFrame) -> impl Iterator<Item = &[u16]> {
    let width = frame.width as usize;
    (0..frame.height as usize).filter_map(move |y| {
        let start = y * frame.stride;
        frame.data.get(start..start + width)
    })
}

/// Point-cloud packet: type 3, point size 12, reserved 0, number of points (u32),
/// timestamp, then x, y, z as f32 little-endian in metres.
pub(crate) fn cloud_packet(points: &[Point3], timestamp_s: u32) -> Vec<u8> {
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

/// Where a point cloud came from, for its CBOR map and PLY comment.
#[derive(Debug, Clone, Copy)]
pub(crate) enum CloudSource<'a> {
    /// One camera's grab.
    Camera { serial: &'a Serial, frame: u64 },
    /// `/cams/pointclouds`: the cameras whose clouds were merged.
    Merged { serials: &'a [Serial] },
}

fn text(key: &str) -> Value {
    Value::Text(key.to_owned())
}

fn uint(v: impl Into<u64>) -> Value {
    Value::Integer(v.into().into())
}

fn float(v: f32) -> Value {
    Value::Float(f64::from(v))
}

fn floats(values: &[f32]) -> Value {
    Value::Array(values.iter().map(|v| float(*v)).collect())
}

fn intrinsics_value(k: &Intrinsics) -> Value {
    Value::Map(vec![
        (text("width"), uint(k.width)),
        (text("height"), uint(k.height)),
        (text("ppx"), float(k.ppx)),
        (text("ppy"), float(k.ppy)),
        (text("fx"), float(k.fx)),
        (text("fy"), float(k.fy)),
        (text("model"), text(k.model.name())),
        (text("coeffs"), floats(&k.coeffs)),
    ])
}

fn cbor(entries: Vec<(Value, Value)>) -> Result<Vec<u8>, EncodeError> {
    let mut out = Vec::new();
    ciborium::into_writer(&Value::Map(entries), &mut out)?;
    Ok(out)
}

/// Color as a CBOR map: `type` 1, `width`, `height`, `pixel_size`, `format`, `timestamp`,
/// `timestamp_us`, `frame`, `serial`, `intrinsics`, `depth_to_color` (`rotation`, 9
/// floats column-major, and `translation` in metres: where a point of the depth frame,
/// the frame of the 3d-transformation, lies in this image's camera), `data` (compact
/// rows).
pub(crate) fn color_cbor(
    frame: &ColorFrame,
    intrinsics: &Intrinsics,
    depth_to_color: &Extrinsics,
    serial: &Serial,
) -> Result<Vec<u8>, EncodeError> {
    let bpp = frame.format.bytes_per_pixel();
    let mut data = Vec::with_capacity(frame.width as usize * frame.height as usize * bpp);
    for row in compact_pixels(frame) {
        data.extend_from_slice(row);
    }
    cbor(vec![
        (text("type"), uint(TYPE_COLOR)),
        (text("width"), uint(frame.width)),
        (text("height"), uint(frame.height)),
        (text("pixel_size"), uint(bpp as u64)),
        (text("format"), text(frame.format.name())),
        (text("timestamp"), uint(unix_seconds(frame.timestamp_us))),
        (text("timestamp_us"), uint(frame.timestamp_us)),
        (text("frame"), uint(frame.frame_number)),
        (text("serial"), text(serial.as_str())),
        (text("intrinsics"), intrinsics_value(intrinsics)),
        (
            text("depth_to_color"),
            Value::Map(vec![
                (text("rotation"), floats(&depth_to_color.rotation)),
                (text("translation"), floats(&depth_to_color.translation)),
            ]),
        ),
        (text("data"), Value::Bytes(data)),
    ])
}

/// Depth as a CBOR map: `type` 2, `width`, `height`, `pixel_size` 2, `timestamp`,
/// `timestamp_us`, `frame`, `serial`, `depth_scale`, `intrinsics`, `data` (Z16
/// little-endian).
pub(crate) fn depth_cbor(
    frame: &DepthFrame,
    intrinsics: &Intrinsics,
    serial: &Serial,
) -> Result<Vec<u8>, EncodeError> {
    let mut data = Vec::with_capacity(frame.width as usize * frame.height as usize * 2);
    append_depth_values(frame, &mut data);
    cbor(vec![
        (text("type"), uint(TYPE_DEPTH)),
        (text("width"), uint(frame.width)),
        (text("height"), uint(frame.height)),
        (text("pixel_size"), uint(2u8)),
        (text("timestamp"), uint(unix_seconds(frame.timestamp_us))),
        (text("timestamp_us"), uint(frame.timestamp_us)),
        (text("frame"), uint(frame.frame_number)),
        (text("serial"), text(serial.as_str())),
        (text("depth_scale"), float(frame.depth_scale)),
        (text("intrinsics"), intrinsics_value(intrinsics)),
        (text("data"), Value::Bytes(data)),
    ])
}

/// A point cloud as a CBOR map: `type` 3, `point_size` 12, `points`, `timestamp`,
/// `timestamp_us`, then `serial` and `frame` of one camera's grab or `serials` of a merged
/// cloud, and `data` (x, y, z as f32 little-endian, metres).
pub(crate) fn cloud_cbor(
    points: &[Point3],
    timestamp_us: u64,
    source: CloudSource<'_>,
) -> Result<Vec<u8>, EncodeError> {
    let mut data = Vec::with_capacity(points.len() * usize::from(POINT_SIZE));
    append_points(points, &mut data);
    let mut entries = vec![
        (text("type"), uint(TYPE_CLOUD)),
        (text("point_size"), uint(POINT_SIZE)),
        (text("points"), uint(points.len() as u64)),
        (text("timestamp"), uint(unix_seconds(timestamp_us))),
        (text("timestamp_us"), uint(timestamp_us)),
    ];
    match source {
        CloudSource::Camera { serial, frame } => {
            entries.push((text("serial"), text(serial.as_str())));
            entries.push((text("frame"), uint(frame)));
        }
        CloudSource::Merged { serials } => entries.push((
            text("serials"),
            Value::Array(serials.iter().map(|s| text(s.as_str())).collect()),
        )),
    }
    entries.push((text("data"), Value::Bytes(data)));
    cbor(entries)
}

/// A point cloud in content format `cf`: CBOR, PLY, else the thesis packet.
pub(crate) fn cloud(
    cf: ContentFormat,
    points: &[Point3],
    timestamp_us: u64,
    source: CloudSource<'_>,
) -> Result<Vec<u8>, EncodeError> {
    match cf {
        ContentFormat::CBOR => cloud_cbor(points, timestamp_us, source),
        ContentFormat::PLY => cloud_ply(points, timestamp_us, source),
        _ => Ok(cloud_packet(points, unix_seconds(timestamp_us))),
    }
}

/// A point cloud as binary little-endian PLY, its origin in the comment line.
pub(crate) fn cloud_ply(
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

/// The pixels as RGB (or RGBA when the frame has alpha), compact rows.
fn rgb_pixels(frame: &ColorFrame) -> (Vec<u8>, ExtendedColorType) {
    let (alpha, swap) = match frame.format {
        ColorFormat::Rgb8 => (false, false),
        ColorFormat::Bgr8 => (false, true),
        ColorFormat::Rgba8 => (true, false),
        ColorFormat::Bgra8 => (true, true),
    };
    let bpp = frame.format.bytes_per_pixel();
    let mut out = Vec::with_capacity(frame.width as usize * frame.height as usize * bpp);
    for row in compact_pixels(frame) {
        for px in row.chunks_exact(bpp) {
            let (r, b) = if swap { (px[2], px[0]) } else { (px[0], px[2]) };
            out.extend_from_slice(&[r, px[1], b]);
            if alpha {
                out.push(px[3]);
            }
        }
    }
    let ty = if alpha {
        ExtendedColorType::Rgba8
    } else {
        ExtendedColorType::Rgb8
    };
    (out, ty)
}

/// Color as an 8-bit RGB(A) PNG.
pub(crate) fn color_png(frame: &ColorFrame) -> Result<Vec<u8>, EncodeError> {
    let (pixels, ty) = rgb_pixels(frame);
    let mut out = Vec::new();
    PngEncoder::new(&mut out)
        .write_image(&pixels, frame.width, frame.height, ty)
        .map_err(image_error("PNG"))?;
    Ok(out)
}

/// Color as a JPEG (alpha dropped).
pub(crate) fn color_jpeg(frame: &ColorFrame) -> Result<Vec<u8>, EncodeError> {
    let (pixels, ty) = rgb_pixels(frame);
    let rgb: Vec<u8> = if ty == ExtendedColorType::Rgba8 {
        pixels
            .chunks_exact(4)
            .flat_map(|p| [p[0], p[1], p[2]])
            .collect()
    } else {
        pixels
    };
    let mut out = Vec::new();
    JpegEncoder::new_with_quality(&mut out, JPEG_QUALITY)
        .write_image(&rgb, frame.width, frame.height, ExtendedColorType::Rgb8)
        .map_err(image_error("JPEG"))?;
    Ok(out)
}

/// Depth as a 16-bit grayscale PNG of the raw units.
pub(crate) fn depth_png(frame: &DepthFrame) -> Result<Vec<u8>, EncodeError> {
    let mut pixels = Vec::with_capacity(frame.width as usize * frame.height as usize * 2);
    for row in depth_rows(frame) {
        for v in row {
            pixels.extend_from_slice(&v.to_ne_bytes());
        }
    }
    let mut out = Vec::new();
    PngEncoder::new(&mut out)
        .write_image(&pixels, frame.width, frame.height, ExtendedColorType::L16)
        .map_err(image_error("PNG"))?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn color(format: ColorFormat, width: u32, height: u32, stride: usize) -> ColorFrame {
        ColorFrame {
            format,
            width,
            height,
            stride,
            timestamp_us: 1_700_000_000_500_000,
            frame_number: 1,
            data: vec![7; stride * height as usize],
        }
    }

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

    #[test]
    fn images_encode() {
        let frame = color(ColorFormat::Bgra8, 4, 2, 16);
        assert!(color_png(&frame).is_ok_and(|p| p.starts_with(b"\x89PNG")));
        assert!(color_jpeg(&frame).is_ok_and(|p| p.starts_with(&[0xff, 0xd8])));
    }
}
