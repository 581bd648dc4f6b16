//! The compact point cloud (coapcam's content format 65103, `application/x-depth-cloud+zstd`):
//! for each camera, the filtered depth image a cloud was computed from, as RVL, with
//! everything that turns it into exactly those points: the depth intrinsics, the 3D
//! transform into the common frame, the region of interest kept, and a correction applied
//! after the crop (the server's ICP registration).
//!
//! A cloud of 12 bytes a point becomes about 2 bytes a pixel before compression and well
//! under one after. The receiver deprojects the pixels with the same code and the same
//! f32 operations in the same order as the sender, so it gets the same bits (coapcam's
//! `repr::depth_cloud`; this crate only carries the numbers).
//!
//! The payload is one zstd frame of, little-endian:
//!
//! | bytes | field |
//! |---|---|
//! | 4 | `DCL1` |
//! | 1 | parts, 1-64; then per part: |
//! | 1 + n | camera serial: length, UTF-8 |
//! | 8 | frame number (u64) |
//! | 8 | microseconds since the UNIX epoch of the grab (u64) |
//! | 8 | width, height of the depth image (u32 each; equal to the RVL header's) |
//! | 16 | ppx, ppy, fx, fy (f32; fx and fy positive) |
//! | 1 | distortion model, librealsense's `rs2_distortion` number: 0 none, 1 modified Brown-Conrady, 2 inverse Brown-Conrady, 4 Brown-Conrady, 5 Kannala-Brandt 4 |
//! | 20 | five distortion coefficients (f32) |
//! | 48 | transform into the common frame: 3x3 linear part by rows, then the translation (f32) |
//! | 24 | region kept, in the common frame: min x, y, z, then max x, y, z (f32, min <= max) |
//! | 1 | 1 when a correction follows, else 0 |
//! | 48 | the correction, laid out as the transform (only when present) |
//! | 4 | length of the RVL payload (u32) |
//! | n | the depth image as RVL ([`crate::rvl`]) |
//!
//! Every f32 is finite, and the RVL image's metres per unit positive.

use std::io;

use crate::rvl::{self, DepthImage};
use crate::wire::{Reader, WireError, put_f32s, put_string, unzstd};

const MAGIC: &[u8; 4] = b"DCL1";
/// Most cameras in one payload.
pub const MAX_PARTS: usize = 64;
/// Most pixels of all parts together: 32 cameras of 1280 x 720.
const MAX_PIXELS: u64 = 1 << 25;
/// Most bytes decompressed: RVL takes at most 3 bytes a pixel.
const MAX_DECOMPRESSED: usize = 3 * (1 << 25) + MAX_PARTS * 512;
/// zstd level: RVL's output is already dense; level 1 gains most of what zstd can.
const ZSTD_LEVEL: i32 = 1;

/// Why a compact cloud payload could not be decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CloudError {
    /// The container: zstd, a field, or the layout.
    #[error("compact cloud: {0}")]
    Wire(#[from] WireError),
    /// A part's depth image.
    #[error("compact cloud, part {part}: {source}")]
    Depth {
        /// The part (0-based).
        part: usize,
        /// What RVL found.
        source: rvl::RvlError,
    },
}

/// Depth intrinsics as librealsense's `rs2_intrinsics`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Pixels per row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Principal point from the left edge, pixels.
    pub ppx: f32,
    /// Principal point from the top edge, pixels.
    pub ppy: f32,
    /// Focal length in pixel widths.
    pub fx: f32,
    /// Focal length in pixel heights.
    pub fy: f32,
    /// `rs2_distortion`: 0, 1, 2, 4 or 5 (see the module's table).
    pub model: u8,
    /// The model's coefficients.
    pub coeffs: [f32; 5],
}

/// Everything of one camera's part but its depth pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct Part {
    /// The camera's serial number.
    pub serial: String,
    /// The depth frame's number.
    pub frame_number: u64,
    /// Microseconds since the UNIX epoch of the grab.
    pub timestamp_us: u64,
    /// Intrinsics of the depth image as sent (after cropping and decimation).
    pub intrinsics: Intrinsics,
    /// Camera frame to common frame: 3x3 linear part by rows, then the translation.
    pub transform: [f32; 12],
    /// The box kept, in the common frame: min x, y, z, max x, y, z.
    pub roi: [f32; 6],
    /// Applied to the kept points after the crop, laid out as `transform`.
    pub correction: Option<[f32; 12]>,
}

/// The payload of `parts` (1 to [`MAX_PARTS`]), each with its depth image as RVL
/// ([`rvl::encode`]); other counts are refused (`InvalidInput`), as the decoder would.
pub fn encode<'a>(parts: impl IntoIterator<Item = (&'a Part, &'a [u8])>) -> io::Result<Vec<u8>> {
    let mut out = MAGIC.to_vec();
    out.push(0);
    let mut count = 0usize;
    for (part, depth) in parts {
        count += 1;
        if count > MAX_PARTS {
            let why = format!("a compact cloud holds at most {MAX_PARTS} cameras");
            return Err(io::Error::new(io::ErrorKind::InvalidInput, why));
        }
        put_string(&mut out, &part.serial);
        out.extend_from_slice(&part.frame_number.to_le_bytes());
        out.extend_from_slice(&part.timestamp_us.to_le_bytes());
        let k = &part.intrinsics;
        out.extend_from_slice(&k.width.to_le_bytes());
        out.extend_from_slice(&k.height.to_le_bytes());
        put_f32s(&mut out, &[k.ppx, k.ppy, k.fx, k.fy]);
        out.push(k.model);
        put_f32s(&mut out, &k.coeffs);
        put_f32s(&mut out, &part.transform);
        put_f32s(&mut out, &part.roi);
        match &part.correction {
            Some(c) => {
                out.push(1);
                put_f32s(&mut out, c);
            }
            None => out.push(0),
        }
        out.extend_from_slice(&(depth.len() as u32).to_le_bytes());
        out.extend_from_slice(depth);
    }
    if count == 0 {
        let why = "a compact cloud holds at least one camera's depth";
        return Err(io::Error::new(io::ErrorKind::InvalidInput, why));
    }
    out[MAGIC.len()] = count as u8;
    zstd::bulk::compress(&out, ZSTD_LEVEL)
}

/// The parts of a payload with their depth images.
pub fn decode(payload: &[u8]) -> Result<Vec<(Part, DepthImage)>, CloudError> {
    let data = unzstd(payload, MAX_DECOMPRESSED)?;
    let mut r = Reader::new(&data);
    if r.bytes(4, "magic")? != MAGIC {
        return Err(r.invalid(0, "magic", "not DCL1".into()).into());
    }
    let at = r.at();
    let count = usize::from(r.u8("parts")?);
    if count == 0 || count > MAX_PARTS {
        let why = format!("{count} parts; 1-{MAX_PARTS} allowed");
        return Err(r.invalid(at, "parts", why).into());
    }
    let mut parts = Vec::with_capacity(count);
    let mut pixels = 0u64;
    for index in 0..count {
        let serial = r.string("serial")?;
        let frame_number = r.u64("frame number")?;
        let timestamp_us = r.u64("timestamp")?;
        let at = r.at();
        let width = r.u32("width")?;
        let height = r.u32("height")?;
        pixels += u64::from(width) * u64::from(height);
        if pixels > MAX_PIXELS {
            let why = format!("more than {MAX_PIXELS} pixels in all parts");
            return Err(r.invalid(at, "width", why).into());
        }
        let at = r.at();
        let [ppx, ppy, fx, fy] = r.finite("ppx, ppy, fx, fy")?;
        if fx <= 0.0 || fy <= 0.0 {
            let why = format!("focal lengths {fx}, {fy} must be positive");
            return Err(r.invalid(at, "fx, fy", why).into());
        }
        let at = r.at();
        let model = r.u8("distortion model")?;
        if !matches!(model, 0 | 1 | 2 | 4 | 5) {
            let why = format!("{model} is not 0, 1, 2, 4 or 5");
            return Err(r.invalid(at, "distortion model", why).into());
        }
        let coeffs = r.finite("coefficients")?;
        let transform = r.finite("transform")?;
        let at = r.at();
        let roi: [f32; 6] = r.finite("region")?;
        if (0..3).any(|i| roi[i] > roi[i + 3]) {
            let why = format!("{roi:?}: a minimum above its maximum");
            return Err(r.invalid(at, "region", why).into());
        }
        let at = r.at();
        let correction = match r.u8("correction flag")? {
            0 => None,
            1 => Some(r.finite("correction")?),
            other => {
                let why = format!("{other} is neither 0 nor 1");
                return Err(r.invalid(at, "correction flag", why).into());
            }
        };
        let len = r.u32("RVL length")? as usize;
        let depth =
            rvl::decode(r.bytes(len, "RVL payload")?).map_err(|source| CloudError::Depth {
                part: index,
                source,
            })?;
        if !(depth.depth_scale.is_finite() && depth.depth_scale > 0.0) {
            let why = format!("metres per unit {} must be positive", depth.depth_scale);
            return Err(r.invalid(at, "RVL payload", why).into());
        }
        if (u32::from(depth.width), u32::from(depth.height)) != (width, height) {
            let why = format!(
                "the intrinsics are {width}x{height}, the RVL image {}x{}",
                depth.width, depth.height
            );
            return Err(r.invalid(at, "RVL payload", why).into());
        }
        let intrinsics = Intrinsics {
            width,
            height,
            ppx,
            ppy,
            fx,
            fy,
            model,
            coeffs,
        };
        let part = Part {
            serial,
            frame_number,
            timestamp_us,
            intrinsics,
            transform,
            roi,
            correction,
        };
        parts.push((part, depth));
    }
    r.finish()?;
    Ok(parts)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn part(serial: &str) -> Part {
        Part {
            serial: serial.into(),
            frame_number: 42,
            timestamp_us: 1_700_000_000_123_456,
            intrinsics: Intrinsics {
                width: 3,
                height: 2,
                ppx: 1.5,
                ppy: 1.0,
                fx: 600.0,
                fy: 601.0,
                model: 4,
                coeffs: [0.1, -0.2, 0.0, 0.0, 0.01],
            },
            transform: [1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.1, 0.2, 1.3],
            roi: [-1.0, -1.0, 0.005, 1.0, 1.0, 3.0],
            correction: None,
        }
    }

    fn depth() -> Vec<u8> {
        rvl::encode(3, 2, 0.001, 1_700_000_000, &[0, 900, 901, 0, 0, 1200])
    }

    #[test]
    fn parts_round_trip() {
        let a = part("840412060746");
        let mut b = part("f0000002");
        b.correction = Some([1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.002, 0.0, 0.0]);
        let d = depth();
        let back = decode(&encode([(&a, &d[..]), (&b, &d[..])]).expect("zstd")).expect("decodes");
        assert_eq!(back.len(), 2);
        assert_eq!(back[0].0, a);
        assert_eq!(back[1].0, b);
        assert_eq!(back[1].1.values, [0, 900, 901, 0, 0, 1200]);
    }

    #[test]
    fn the_encoder_refuses_what_the_decoder_would() {
        let d = depth();
        assert!(encode([]).is_err(), "no part");
        let many = vec![part("a"); MAX_PARTS + 1];
        assert!(
            encode(many.iter().map(|p| (p, &d[..]))).is_err(),
            "65 parts"
        );
        let most = &many[..MAX_PARTS];
        let payload = encode(most.iter().map(|p| (p, &d[..]))).expect("64 parts");
        assert_eq!(decode(&payload).expect("decodes").len(), MAX_PARTS);
    }

    /// The uncompressed layout with one field changed by `edit`.
    fn mangled(edit: impl FnOnce(&mut Vec<u8>)) -> Result<Vec<(Part, DepthImage)>, CloudError> {
        let d = depth();
        let mut raw =
            unzstd(&encode([(&part("a"), &d[..])]).expect("zstd"), 1 << 20).expect("unzstd");
        edit(&mut raw);
        decode(&zstd::bulk::compress(&raw, 1).expect("zstd"))
    }

    #[test]
    fn malformed_payloads_give_typed_errors() {
        assert!(matches!(
            decode(b"not zstd"),
            Err(CloudError::Wire(WireError::Zstd(_)))
        ));
        // Offsets: magic 0-3, parts 4, serial 5-6, frame 7-14, time 15-22, width 23,
        // height 27, ppx 31, ppy 35, fx 39, fy 43, model 47, coefficients 48, transform 68,
        // region 116, flag 140, RVL length 141, RVL 145.
        let invalid = |r: Result<_, CloudError>| match r {
            Err(CloudError::Wire(WireError::Invalid { field, .. })) => field,
            other => panic!("{other:?}"),
        };
        assert_eq!(invalid(mangled(|d| d[0] = b'X')), "magic");
        assert_eq!(invalid(mangled(|d| d[4] = 0)), "parts");
        assert_eq!(invalid(mangled(|d| d[47] = 3)), "distortion model");
        assert_eq!(
            invalid(mangled(|d| d[39..43].copy_from_slice(&0f32.to_le_bytes()))),
            "fx, fy"
        );
        assert_eq!(
            invalid(mangled(
                |d| d[68..72].copy_from_slice(&f32::NAN.to_le_bytes())
            )),
            "transform"
        );
        assert_eq!(
            invalid(mangled(|d| d[116..120].copy_from_slice(&5f32.to_le_bytes()))),
            "region"
        );
        assert_eq!(invalid(mangled(|d| d[140] = 2)), "correction flag");
        assert_eq!(invalid(mangled(|d| d[23] = 4)), "RVL payload");
        assert_eq!(
            invalid(mangled(
                |d| d[23..31].copy_from_slice(&[0, 0, 0, 1, 0, 0, 0, 1])
            )),
            "width"
        );
        assert!(matches!(
            mangled(|d| d.truncate(150)),
            Err(CloudError::Wire(WireError::Truncated {
                field: "RVL payload",
                ..
            }))
        ));
        assert!(matches!(
            mangled(|d| d.push(0)),
            Err(CloudError::Wire(WireError::Trailing(1)))
        ));
        assert!(matches!(
            mangled(|d| {
                let end = d.len() - 4;
                d[end..].copy_from_slice(&[0xff; 4]);
            }),
            Err(CloudError::Depth { part: 0, .. })
        ));
    }
}
