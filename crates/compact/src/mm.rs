//! The quantized point cloud (coapcam's content format 65104, `application/x-cloud-mm+zstd`):
//! points rounded to whole millimetres in the frame they are given in, each coordinate
//! as the zig-zag coded difference to the previous point's, in LEB128, in one zstd frame.
//! For clouds that do not come from one depth image; a coordinate moves by at most 0.5 mm
//! and the f32 rounding of its metres (4 µm at 50 m).
//!
//! Little-endian, inside the zstd frame:
//!
//! | bytes | field |
//! |---|---|
//! | 4 | `QMM1` |
//! | 8 | microseconds since the UNIX epoch of the newest grab (u64) |
//! | 1 | cameras that made the cloud, 0-255; then each serial: length, UTF-8 |
//! | 4 | points (u32, at most 8,388,608) |
//! | ... | per point x, y, z: LEB128 of zig-zag(mm - previous point's mm), the first point's differences to 0; every coordinate within ±1,000,000 mm |

use std::io;

use crate::wire::{Reader, WireError, put_string, put_varint, unzstd};

const MAGIC: &[u8; 4] = b"QMM1";
/// Most points in one payload.
pub const MAX_POINTS: usize = 1 << 23;
/// Most bytes decompressed: 5 bytes for each of three coordinates, and the header.
const MAX_DECOMPRESSED: usize = MAX_POINTS * 15 + 17 + 255 * 256;
/// zstd level: the differences are small and repetitive; level 3 is zstd's default.
const ZSTD_LEVEL: i32 = 3;

/// A quantized cloud.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct MmCloud {
    /// Microseconds since the UNIX epoch of the newest grab.
    pub timestamp_us: u64,
    /// Cameras that made the cloud.
    pub serials: Vec<String>,
    /// Points, metres (whole millimetres).
    pub points: Vec<[f32; 3]>,
}

/// Most millimetres from the origin on any axis: a kilometre. Within it, whole
/// millimetres survive the trip through f32 metres exactly.
pub const MAX_MM: i32 = 1_000_000;

/// Whole millimetres of `metres`; `None` beyond [`MAX_MM`] (or not a number).
fn mm(metres: f32) -> Option<i32> {
    let v = (metres * 1000.0).round();
    (v.abs() <= MAX_MM as f32).then_some(v as i32)
}

fn zigzag(delta: i32) -> u32 {
    ((delta << 1) ^ (delta >> 31)) as u32
}

fn unzigzag(value: u32) -> i32 {
    (value >> 1) as i32 ^ -((value & 1) as i32)
}

/// The payload of `points` (metres, within a kilometre of the origin on each axis; at most
/// [`MAX_POINTS`], at most 255 serials); anything else is refused (`InvalidInput`), as the
/// decoder would.
pub fn encode(timestamp_us: u64, serials: &[&str], points: &[[f32; 3]]) -> io::Result<Vec<u8>> {
    let refuse = |why: String| Err(io::Error::new(io::ErrorKind::InvalidInput, why));
    if points.len() > MAX_POINTS {
        return refuse(format!("{} points, at most {MAX_POINTS}", points.len()));
    }
    let Ok(cameras) = u8::try_from(serials.len()) else {
        return refuse(format!("{} cameras, at most 255", serials.len()));
    };
    let mut out = Vec::with_capacity(32 + points.len() * 4);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&timestamp_us.to_le_bytes());
    out.push(cameras);
    for sn in serials {
        put_string(&mut out, sn);
    }
    out.extend_from_slice(&(points.len() as u32).to_le_bytes());
    let mut previous = [0i32; 3];
    for p in points {
        for (axis, v) in p.iter().enumerate() {
            let Some(v) = mm(*v) else {
                return refuse(format!("{v} m is not within {MAX_MM} mm of the origin"));
            };
            put_varint(&mut out, zigzag(v.wrapping_sub(previous[axis])));
            previous[axis] = v;
        }
    }
    zstd::bulk::compress(&out, ZSTD_LEVEL)
}

/// Decodes a payload.
pub fn decode(payload: &[u8]) -> Result<MmCloud, WireError> {
    let data = unzstd(payload, MAX_DECOMPRESSED)?;
    let mut r = Reader::new(&data);
    if r.bytes(4, "magic")? != MAGIC {
        return Err(r.invalid(0, "magic", "not QMM1".into()));
    }
    let timestamp_us = r.u64("timestamp")?;
    let serials = (0..r.u8("serials")?)
        .map(|_| r.string("serial"))
        .collect::<Result<_, _>>()?;
    let at = r.at();
    let count = r.u32("points")? as usize;
    // Each point takes at least three bytes.
    if count > MAX_POINTS || count > (data.len() - r.at()) / 3 {
        let why = format!("{count} points do not fit the data or the limit of {MAX_POINTS}");
        return Err(r.invalid(at, "points", why));
    }
    let mut points = Vec::with_capacity(count);
    let mut previous = [0i32; 3];
    for _ in 0..count {
        let mut p = [0.0; 3];
        for (axis, v) in p.iter_mut().enumerate() {
            let at = r.at();
            previous[axis] = previous[axis].wrapping_add(unzigzag(r.varint("coordinate")?));
            if previous[axis].unsigned_abs() > MAX_MM as u32 {
                let why = format!("{} mm is beyond {MAX_MM} mm", previous[axis]);
                return Err(r.invalid(at, "coordinate", why));
            }
            *v = previous[axis] as f32 / 1000.0;
        }
        points.push(p);
    }
    r.finish()?;
    Ok(MmCloud {
        timestamp_us,
        serials,
        points,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn a_known_cloud_gives_known_bytes() {
        let payload =
            encode(7, &["ab"], &[[0.001, -0.002, 1.0], [0.0015, -0.002, 1.0]]).expect("zstd");
        let raw = unzstd(&payload, 1 << 10).expect("unzstd");
        let mut expected = b"QMM1".to_vec();
        expected.extend_from_slice(&7u64.to_le_bytes());
        expected.extend_from_slice(&[1, 2, b'a', b'b']);
        expected.extend_from_slice(&2u32.to_le_bytes());
        // (1, -2, 1000) mm: zig-zag 2, 3, 2000 = 0xd0 0x0f; then (+1, 0, 0): 0.0015 rounds
        // to 2 mm.
        expected.extend_from_slice(&[2, 3, 0xd0, 0x0f, 2, 0, 0]);
        assert_eq!(raw, expected);
        let back = decode(&payload).expect("decodes");
        assert_eq!(back.points, [[0.001, -0.002, 1.0], [0.002, -0.002, 1.0]]);
        assert_eq!(
            (back.timestamp_us, &back.serials[..]),
            (7, &["ab".to_owned()][..])
        );
    }

    #[test]
    fn the_encoder_refuses_what_the_decoder_would() {
        for bad in [f32::NAN, f32::INFINITY, 1000.001, -1000.001] {
            assert!(encode(0, &[], &[[0.0, bad, 0.0]]).is_err(), "{bad} m");
        }
        assert!(
            encode(0, &[], &[[1000.0, -1000.0, 0.0]]).is_ok(),
            "a kilometre"
        );
        assert!(encode(0, &["a"; 256], &[]).is_err(), "256 cameras");
    }

    #[test]
    fn malformed_payloads_give_typed_errors() {
        let raw = |edit: fn(&mut Vec<u8>)| {
            let payload = encode(7, &["ab"], &[[0.001, 0.0, 1.0]]).expect("zstd");
            let mut data = unzstd(&payload, 1 << 10).expect("unzstd");
            edit(&mut data);
            decode(&zstd::bulk::compress(&data, 1).expect("zstd"))
        };
        assert!(matches!(decode(b"QMM1"), Err(WireError::Zstd(_))));
        assert!(matches!(
            raw(|d| d[3] = b'0'),
            Err(WireError::Invalid { field: "magic", .. })
        ));
        assert!(matches!(
            raw(|d| d[16..20].copy_from_slice(&9u32.to_le_bytes())),
            Err(WireError::Invalid {
                field: "points",
                ..
            })
        ));
        assert!(matches!(
            raw(|d| d.truncate(22)),
            Err(WireError::Invalid { .. })
        ));
        assert!(matches!(
            raw(|d| d.extend_from_slice(&[0x80, 0x80, 0x80, 0x80, 0x80, 1])),
            Err(WireError::Trailing(_) | WireError::Invalid { .. })
        ));
        assert!(matches!(
            raw(|d| {
                let n = d.len();
                d[n - 1] = 0x80;
            }),
            Err(WireError::Truncated {
                field: "coordinate",
                ..
            })
        ));
        assert!(matches!(raw(|d| d.push(0)), Err(WireError::Trailing(1))));
    }

    proptest! {
        #[test]
        fn points_come_back_within_half_a_millimetre(
            points in prop::collection::vec(prop::array::uniform3(-50.0f32..50.0), 0..300),
        ) {
            let back = decode(&encode(1, &[], &points).expect("zstd")).expect("decodes");
            prop_assert_eq!(back.points.len(), points.len());
            for (a, b) in points.iter().zip(&back.points) {
                for axis in 0..3 {
                    prop_assert!((a[axis] - b[axis]).abs() <= 0.000_51, "{a:?} {b:?}");
                }
            }
        }
    }
}
