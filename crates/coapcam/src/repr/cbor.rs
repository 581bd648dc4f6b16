//! CBOR maps (docs/design.md §5): the packet's header fields by name, plus the camera's
//! serial, frame number, microsecond timestamp and intrinsics, the data as a byte string.
//! Each map is one serde type ([`ColorMap`], [`DepthMap`], [`CloudMap`]) that the server
//! encodes and the client decodes, with typed errors ([`CborError`]); the typed values a
//! client wants ([`ColorCapture`], [`DepthCapture`], [`Cloud`]) are read from them. A
//! decoder ignores keys it does not know, so a map may gain keys.

use geometry::Point3;
use rgbd::{ColorFrame, DepthFrame, DistortionModel, Extrinsics, Intrinsics, Serial};
use serde::{Deserialize, Serialize};

pub use super::codec::{CborError, Cloud};
use super::codec::{Decoders, Subject, checked_len};
use super::packet::unix_seconds;
use super::packet::{
    self, POINT_SIZE, TYPE_CLOUD, TYPE_COLOR, TYPE_DEPTH, append_depth_values, append_points,
    compact_pixels,
};
use super::{CloudSource, EncodeError};

/// A CBOR byte string (major type 2), not an array of numbers.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct ByteString(pub Vec<u8>);

impl Serialize for ByteString {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(&self.0)
    }
}

impl<'de> Deserialize<'de> for ByteString {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl serde::de::Visitor<'_> for Visitor {
            type Value = ByteString;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("a byte string")
            }
            fn visit_bytes<E: serde::de::Error>(self, v: &[u8]) -> Result<ByteString, E> {
                Ok(ByteString(v.to_vec()))
            }
            fn visit_byte_buf<E: serde::de::Error>(self, v: Vec<u8>) -> Result<ByteString, E> {
                Ok(ByteString(v))
            }
        }
        d.deserialize_byte_buf(Visitor)
    }
}

/// Intrinsics as the maps carry them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct IntrinsicsMap {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Principal point, x.
    pub ppx: f32,
    /// Principal point, y.
    pub ppy: f32,
    /// Focal length, x, pixels.
    pub fx: f32,
    /// Focal length, y, pixels.
    pub fy: f32,
    /// The distortion model's name.
    pub model: String,
    /// Its five coefficients.
    pub coeffs: [f32; 5],
}

impl From<&Intrinsics> for IntrinsicsMap {
    fn from(k: &Intrinsics) -> Self {
        Self {
            width: k.width,
            height: k.height,
            ppx: k.ppx,
            ppy: k.ppy,
            fx: k.fx,
            fy: k.fy,
            model: k.model.name().to_owned(),
            coeffs: k.coeffs,
        }
    }
}

impl TryFrom<&IntrinsicsMap> for Intrinsics {
    type Error = CborError;

    fn try_from(k: &IntrinsicsMap) -> Result<Self, CborError> {
        Ok(Self {
            width: k.width,
            height: k.height,
            ppx: k.ppx,
            ppy: k.ppy,
            fx: k.fx,
            fy: k.fy,
            model: DistortionModel::from_name(&k.model)
                .ok_or_else(|| CborError::Model(k.model.clone()))?,
            coeffs: k.coeffs,
        })
    }
}

/// Depth->color extrinsics as the color map carries them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ExtrinsicsMap {
    /// 9 floats, column-major.
    pub rotation: [f32; 9],
    /// Metres.
    pub translation: [f32; 3],
}

/// The color map: `type` 1, `width`, `height`, `pixel_size`, `format`, `timestamp`,
/// `timestamp_us`, `frame`, `serial`, `intrinsics`, `depth_to_color` (`rotation`, 9
/// floats column-major, and `translation` in metres: where a point of the depth frame,
/// the frame of the 3d-transformation, lies in this image's camera), `data` (compact
/// rows).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ColorMap {
    /// 1.
    #[serde(rename = "type")]
    pub kind: u8,
    /// Pixels.
    pub width: u32,
    /// Pixels.
    pub height: u32,
    /// Bytes per pixel.
    pub pixel_size: u32,
    /// The camera's pixel format (RGB8, BGR8, RGBA8, BGRA8).
    pub format: String,
    /// Whole seconds since the UNIX epoch.
    pub timestamp: u32,
    /// Microseconds since the UNIX epoch.
    pub timestamp_us: u64,
    /// The camera's frame number.
    pub frame: u64,
    /// The camera's serial.
    pub serial: String,
    /// The color camera's intrinsics.
    pub intrinsics: IntrinsicsMap,
    /// Where a point of the depth camera lies in the color camera's frame.
    pub depth_to_color: ExtrinsicsMap,
    /// The pixels, compact rows.
    pub data: ByteString,
}

/// The depth map: `type` 2, `width`, `height`, `pixel_size` 2, `timestamp`,
/// `timestamp_us`, `frame`, `serial`, `depth_scale`, `intrinsics`, `data` (Z16
/// little-endian).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DepthMap {
    /// 2.
    #[serde(rename = "type")]
    pub kind: u8,
    /// Pixels.
    pub width: u32,
    /// Pixels.
    pub height: u32,
    /// 2.
    pub pixel_size: u32,
    /// Whole seconds since the UNIX epoch.
    pub timestamp: u32,
    /// Microseconds since the UNIX epoch.
    pub timestamp_us: u64,
    /// The camera's frame number.
    pub frame: u64,
    /// The camera's serial.
    pub serial: String,
    /// Metres per depth unit.
    pub depth_scale: f32,
    /// The depth camera's intrinsics.
    pub intrinsics: IntrinsicsMap,
    /// Z16 little-endian, compact rows.
    pub data: ByteString,
}

/// The point-cloud map: `type` 3, `point_size` 12, `points`, `timestamp`,
/// `timestamp_us`, then `serial` and `frame` of one camera's grab or `serials` of a merged
/// cloud, and `data` (x, y, z as f32 little-endian, metres).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CloudMap {
    /// 3.
    #[serde(rename = "type")]
    pub kind: u8,
    /// 12.
    pub point_size: u32,
    /// How many points `data` holds.
    pub points: u64,
    /// Whole seconds since the UNIX epoch.
    pub timestamp: u32,
    /// Microseconds since the UNIX epoch.
    pub timestamp_us: u64,
    /// One camera's cloud: its serial.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub serial: Option<String>,
    /// One camera's cloud: its frame number.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame: Option<u64>,
    /// A merged cloud: its cameras' serials, in merge order.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub serials: Option<Vec<String>>,
    /// The points.
    pub data: ByteString,
}

fn decode<T: serde::de::DeserializeOwned>(
    body: &[u8],
    what: &'static str,
    expected: u8,
    kind: impl Fn(&T) -> u8,
) -> Result<T, CborError> {
    let map: T =
        ciborium::from_reader(body).map_err(|source| CborError::Decode { what, source })?;
    match kind(&map) {
        found if found == expected => Ok(map),
        found => Err(CborError::Type {
            what,
            expected,
            found,
        }),
    }
}

fn cbor(map: &impl Serialize) -> Result<Vec<u8>, EncodeError> {
    let mut out = Vec::new();
    ciborium::into_writer(map, &mut out)?;
    Ok(out)
}

/// Color as a [`ColorMap`].
pub fn color_cbor(
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
    cbor(&ColorMap {
        kind: TYPE_COLOR,
        width: frame.width,
        height: frame.height,
        pixel_size: bpp as u32,
        format: frame.format.name().to_owned(),
        timestamp: unix_seconds(frame.timestamp_us),
        timestamp_us: frame.timestamp_us,
        frame: frame.frame_number,
        serial: serial.as_str().to_owned(),
        intrinsics: intrinsics.into(),
        depth_to_color: ExtrinsicsMap {
            rotation: depth_to_color.rotation,
            translation: depth_to_color.translation,
        },
        data: ByteString(data),
    })
}

/// Depth as a [`DepthMap`].
pub fn depth_cbor(
    frame: &DepthFrame,
    intrinsics: &Intrinsics,
    serial: &Serial,
) -> Result<Vec<u8>, EncodeError> {
    let mut data = Vec::with_capacity(frame.width as usize * frame.height as usize * 2);
    append_depth_values(frame, &mut data);
    cbor(&DepthMap {
        kind: TYPE_DEPTH,
        width: frame.width,
        height: frame.height,
        pixel_size: 2,
        timestamp: unix_seconds(frame.timestamp_us),
        timestamp_us: frame.timestamp_us,
        frame: frame.frame_number,
        serial: serial.as_str().to_owned(),
        depth_scale: frame.depth_scale,
        intrinsics: intrinsics.into(),
        data: ByteString(data),
    })
}

/// A point cloud as a [`CloudMap`].
pub fn cloud_cbor(
    points: &[Point3],
    timestamp_us: u64,
    source: CloudSource<'_>,
) -> Result<Vec<u8>, EncodeError> {
    let mut data = Vec::with_capacity(points.len() * usize::from(POINT_SIZE));
    append_points(points, &mut data);
    let (serial, frame, serials) = match source {
        CloudSource::Camera { serial, frame } => {
            (Some(serial.as_str().to_owned()), Some(frame), None)
        }
        CloudSource::Merged { serials } => (
            None,
            None,
            Some(serials.iter().map(|s| s.as_str().to_owned()).collect()),
        ),
    };
    cbor(&CloudMap {
        kind: TYPE_CLOUD,
        point_size: u32::from(POINT_SIZE),
        points: points.len() as u64,
        timestamp: unix_seconds(timestamp_us),
        timestamp_us,
        serial,
        frame,
        serials,
        data: ByteString(data),
    })
}

// ---- reading

impl Cloud {
    /// Reads the CBOR point-cloud map, checking `points` against the data.
    pub fn from_cbor(body: &[u8]) -> Result<Self, CborError> {
        let what = "point cloud";
        let map: CloudMap = decode(body, what, TYPE_CLOUD, |m: &CloudMap| m.kind)?;
        let count = map.points;
        let bytes = map.data.0.len();
        if checked_len(&[count, u64::from(POINT_SIZE)]) != Some(bytes as u64) {
            return Err(CborError::Data {
                what,
                why: format!("{count} points announced, {bytes} bytes of points arrived"),
            });
        }
        let serials = match (map.serials, map.serial) {
            (Some(list), _) => list,
            (None, Some(one)) => vec![one],
            (None, None) => return Err(CborError::NoCamera),
        };
        Ok(Self {
            cloud: packet::points(&map.data.0),
            serials,
            timestamp_us: map.timestamp_us,
            views: Vec::new(),
            frames: Vec::new(),
        })
    }
}

/// A color frame as the server's CBOR representation carries it: RGB pixels, the color
/// intrinsics and the depth->color extrinsics.
pub struct ColorCapture {
    /// The pixels.
    pub image: image::RgbImage,
    /// The color camera's intrinsics.
    pub intrinsics: Intrinsics,
    /// Where a point of the depth camera lies in the color camera's frame.
    pub depth_to_color: Extrinsics,
}

impl ColorCapture {
    /// Reads the CBOR color representation (docs/design.md §5).
    pub fn from_cbor(body: &[u8]) -> Result<Self, CborError> {
        let what = "color frame";
        let map: ColorMap = decode(body, what, TYPE_COLOR, |m: &ColorMap| m.kind)?;
        let image = packet::rgb_image(
            &map.data.0,
            map.width,
            map.height,
            map.pixel_size as usize,
            &map.format,
        )
        .map_err(|why| CborError::Data { what, why })?;
        Ok(Self {
            image,
            intrinsics: Intrinsics::try_from(&map.intrinsics)?,
            depth_to_color: Extrinsics {
                rotation: map.depth_to_color.rotation,
                translation: map.depth_to_color.translation,
            },
        })
    }
}

/// A depth frame as the server's CBOR representation carries it, with its intrinsics and
/// the camera's serial.
pub struct DepthCapture {
    /// The frame (compact rows).
    pub frame: DepthFrame,
    /// The depth camera's intrinsics.
    pub intrinsics: Intrinsics,
    /// The camera's serial.
    pub serial: String,
}

impl DepthCapture {
    /// Reads the CBOR depth representation (docs/design.md §5).
    pub fn from_cbor(body: &[u8]) -> Result<Self, CborError> {
        let what = "depth frame";
        let map: DepthMap = decode(body, what, TYPE_DEPTH, |m: &DepthMap| m.kind)?;
        let needed = checked_len(&[map.width.into(), map.height.into(), 2]);
        if map.pixel_size != 2 || needed != Some(map.data.0.len() as u64) {
            return Err(CborError::Data {
                what,
                why: format!(
                    "{} bytes are not {}x{} pixels of {} bytes (2)",
                    map.data.0.len(),
                    map.width,
                    map.height,
                    map.pixel_size
                ),
            });
        }
        Ok(Self {
            frame: DepthFrame {
                width: map.width,
                height: map.height,
                stride: map.width as usize,
                depth_scale: map.depth_scale,
                timestamp_us: map.timestamp_us,
                frame_number: map.frame,
                data: map
                    .data
                    .0
                    .chunks_exact(2)
                    .map(|b| u16::from_le_bytes([b[0], b[1]]))
                    .collect(),
            },
            intrinsics: Intrinsics::try_from(&map.intrinsics)?,
            serial: map.serial,
        })
    }
}

// ---- the row of the table

/// CBOR's encoder: every stream, with its camera, intrinsics and time.
pub fn encode(subject: &Subject<'_>) -> Result<Vec<u8>, EncodeError> {
    match *subject {
        Subject::Color {
            frame,
            intrinsics,
            depth_to_color,
            serial,
            ..
        } => color_cbor(frame, intrinsics, depth_to_color, serial),
        Subject::Depth {
            frame,
            intrinsics,
            serial,
        } => depth_cbor(frame, intrinsics, serial),
        Subject::Cloud {
            points,
            timestamp_us,
            source,
            ..
        } => cloud_cbor(points, timestamp_us, source),
    }
}

/// CBOR read back: a cloud (color and depth maps are read by [`ColorCapture`] and
/// [`DepthCapture`]).
pub const DECODERS: Decoders = Decoders {
    cloud: Some(|body| Ok(Cloud::from_cbor(body)?)),
    ..Decoders::NONE
};

#[cfg(test)]
mod tests {
    use ciborium::Value;
    use rgbd::{ColorFormat, d415};

    use super::*;

    fn serial() -> Serial {
        Serial::parse("840412060746").expect("a serial")
    }

    fn keys(body: &[u8]) -> Vec<String> {
        let value: Value = ciborium::from_reader(body).expect("CBOR");
        let map = value.as_map().expect("a map");
        assert!(
            map.iter()
                .any(|(k, v)| k.as_text() == Some("data") && v.is_bytes()),
            "data is a byte string"
        );
        map.iter()
            .map(|(k, _)| k.as_text().expect("text keys").to_owned())
            .collect()
    }

    #[test]
    fn a_color_frame_round_trips_with_its_geometry() {
        // 2x2 BGR8 with a padded stride: the map carries compact rows.
        let frame = ColorFrame {
            format: ColorFormat::Bgr8,
            width: 2,
            height: 2,
            stride: 7,
            timestamp_us: 1_700_000_000_250_000,
            frame_number: 9,
            data: vec![1, 2, 3, 4, 5, 6, 0, 7, 8, 9, 10, 11, 12, 0],
        };
        let k = d415::color_intrinsics(2, 2);
        let e = d415::depth_to_color();
        let body = color_cbor(&frame, &k, &e, &serial()).expect("encodes");
        assert_eq!(
            keys(&body),
            [
                "type",
                "width",
                "height",
                "pixel_size",
                "format",
                "timestamp",
                "timestamp_us",
                "frame",
                "serial",
                "intrinsics",
                "depth_to_color",
                "data"
            ]
        );
        let got = ColorCapture::from_cbor(&body).expect("decodes");
        assert_eq!(got.image.as_raw(), &[3, 2, 1, 6, 5, 4, 9, 8, 7, 12, 11, 10]);
        assert_eq!(got.intrinsics, k);
        assert_eq!(got.depth_to_color, e);
    }

    #[test]
    fn a_depth_frame_round_trips() {
        let frame = DepthFrame {
            width: 2,
            height: 2,
            stride: 3,
            depth_scale: 0.000_25,
            timestamp_us: 1_700_000_000_500_000,
            frame_number: 7,
            data: vec![5, 6, 99, 0, 65535, 99],
        };
        let k = d415::depth_intrinsics(2, 2);
        let body = depth_cbor(&frame, &k, &serial()).expect("encodes");
        assert_eq!(keys(&body).last().map(String::as_str), Some("data"));
        let got = DepthCapture::from_cbor(&body).expect("decodes");
        assert_eq!(got.frame.data, [5, 6, 0, 65535]);
        assert_eq!(
            (
                got.frame.depth_scale,
                got.frame.frame_number,
                got.frame.stride
            ),
            (0.000_25, 7, 2)
        );
        assert_eq!(got.intrinsics, k);
        assert_eq!(got.serial, "840412060746");
    }

    #[test]
    fn clouds_name_their_camera_or_cameras() {
        let points = [Point3::new(0.5, -0.25, 1.0), Point3::new(0.0, 0.0, 0.125)];
        let sn = serial();
        let one = cloud_cbor(
            &points,
            42,
            CloudSource::Camera {
                serial: &sn,
                frame: 3,
            },
        )
        .expect("encodes");
        assert!(keys(&one).contains(&"frame".to_owned()));
        let got = Cloud::from_cbor(&one).expect("decodes");
        assert_eq!(got.cloud.points, points);
        assert_eq!((got.serials, got.timestamp_us), (vec![sn.to_string()], 42));
        let serials = [sn, Serial::parse("000000000007").expect("a serial")];
        let merged =
            cloud_cbor(&points, 43, CloudSource::Merged { serials: &serials }).expect("encodes");
        assert!(!keys(&merged).contains(&"serial".to_owned()));
        let got = Cloud::from_cbor(&merged).expect("decodes");
        assert_eq!(got.serials, ["840412060746", "000000000007"]);
    }

    #[test]
    fn what_does_not_fit_is_a_typed_error() {
        let sn = serial();
        let points = [Point3::new(1.0, 2.0, 3.0)];
        let body = cloud_cbor(
            &points,
            1,
            CloudSource::Camera {
                serial: &sn,
                frame: 1,
            },
        )
        .expect("encodes");
        assert!(matches!(
            ColorCapture::from_cbor(&body),
            Err(CborError::Decode { .. })
        ));
        assert!(matches!(
            Cloud::from_cbor(&body[..body.len() - 1]),
            Err(CborError::Decode { .. })
        ));
        let mut map: CloudMap = ciborium::from_reader(&body[..]).expect("a cloud map");
        let encode = |map: &CloudMap| cbor(map).expect("encodes");
        map.points = 2;
        assert!(matches!(
            Cloud::from_cbor(&encode(&map)),
            Err(CborError::Data { .. })
        ));
        map.points = u64::MAX;
        assert!(matches!(
            Cloud::from_cbor(&encode(&map)),
            Err(CborError::Data { .. })
        ));
        map.points = 1;
        map.serial = None;
        assert!(matches!(
            Cloud::from_cbor(&encode(&map)),
            Err(CborError::NoCamera)
        ));
        map.kind = TYPE_DEPTH;
        assert!(matches!(
            Cloud::from_cbor(&encode(&map)),
            Err(CborError::Type { found: 2, .. })
        ));

        let k = d415::depth_intrinsics(1, 1);
        let frame = DepthFrame {
            width: 1,
            height: 1,
            stride: 1,
            depth_scale: 0.001,
            timestamp_us: 1,
            frame_number: 1,
            data: vec![1],
        };
        let body = depth_cbor(&frame, &k, &sn).expect("encodes");
        let mut map: DepthMap = ciborium::from_reader(&body[..]).expect("a depth map");
        map.intrinsics.model = "fisheye of the future".into();
        assert!(matches!(
            DepthCapture::from_cbor(&cbor(&map).expect("encodes")),
            Err(CborError::Model(_))
        ));
        map.intrinsics.model = k.model.name().into();
        map.data.0.push(0);
        assert!(matches!(
            DepthCapture::from_cbor(&cbor(&map).expect("encodes")),
            Err(CborError::Data { .. })
        ));
        // Pixels as an array of numbers instead of a byte string.
        let mut value: Value = ciborium::from_reader(&body[..]).expect("CBOR");
        if let Value::Map(entries) = &mut value {
            for (key, v) in entries.iter_mut() {
                if key.as_text() == Some("data") {
                    *v = Value::Array(vec![Value::Integer(1.into()), Value::Integer(0.into())]);
                }
            }
        }
        let mut array = Vec::new();
        ciborium::into_writer(&value, &mut array).expect("encodes");
        assert!(matches!(
            DepthCapture::from_cbor(&array),
            Err(CborError::Decode { .. })
        ));
    }
}
