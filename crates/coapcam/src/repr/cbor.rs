//! CBOR maps (docs/design.md §5): the packet's header fields by name, plus the camera's
//! serial, frame number, microsecond timestamp and intrinsics, the data as a byte string.
//! Encoders (the server) and decoders (the client) side by side.

use anyhow::{Context as _, bail};
use ciborium::Value;
use geometry::{Point3, PointCloud};
use rgbd::{ColorFrame, DepthFrame, Extrinsics, Intrinsics, Serial};

use super::packet::unix_seconds;
use super::packet::{
    self, POINT_SIZE, TYPE_CLOUD, TYPE_COLOR, TYPE_DEPTH, append_depth_values, append_points,
    compact_pixels,
};
use super::{CloudSource, EncodeError};

fn text(key: &str) -> Value {
    Value::Text(key.to_owned())
}

fn uint(v: impl Into<u64>) -> Value {
    Value::Integer(v.into().into())
}

fn float(v: f32) -> Value {
    Value::Float(f64::from(v))
}

fn float_array(values: &[f32]) -> Value {
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
        (text("coeffs"), float_array(&k.coeffs)),
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
                (text("rotation"), float_array(&depth_to_color.rotation)),
                (
                    text("translation"),
                    float_array(&depth_to_color.translation),
                ),
            ]),
        ),
        (text("data"), Value::Bytes(data)),
    ])
}

/// Depth as a CBOR map: `type` 2, `width`, `height`, `pixel_size` 2, `timestamp`,
/// `timestamp_us`, `frame`, `serial`, `depth_scale`, `intrinsics`, `data` (Z16
/// little-endian).
pub fn depth_cbor(
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
pub fn cloud_cbor(
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

// ---- reading

/// A CBOR map's entries.
type Map = [(Value, Value)];

/// A field of a CBOR map.
pub fn field<'a>(map: &'a Map, key: &str) -> anyhow::Result<&'a Value> {
    map.iter()
        .find(|(k, _)| k.as_text() == Some(key))
        .map(|(_, v)| v)
        .with_context(|| format!("the CBOR map has no {key:?}"))
}

/// An array of exactly `N` numbers.
pub fn floats<const N: usize>(value: &Value) -> anyhow::Result<[f32; N]> {
    let items = value.as_array().context("expected an array of numbers")?;
    let mut out = [0.0; N];
    if items.len() != N {
        bail!("expected {N} numbers, found {}", items.len());
    }
    for (o, v) in out.iter_mut().zip(items) {
        *o = v.as_float().context("expected a number")? as f32;
    }
    Ok(out)
}

/// An integer field that fits in 32 bits.
pub fn u32_of(map: &Map, key: &str) -> anyhow::Result<u32> {
    let v = field(map, key)?
        .as_integer()
        .with_context(|| format!("{key} is not an integer"))?;
    u32::try_from(v).with_context(|| format!("{key} is out of range"))
}

/// A point cloud from its CBOR map, with the cameras that made it (`serial`, or
/// `serials` of a merged cloud) and its timestamp.
pub struct Cloud {
    /// The points, metres.
    pub cloud: PointCloud,
    /// Serials of the cameras that made it.
    pub serials: Vec<String>,
    /// When it was grabbed, microseconds since the UNIX epoch.
    pub timestamp_us: u64,
}

impl Cloud {
    /// Reads the CBOR point-cloud map, checking `points` against the data.
    pub fn from_cbor(body: &[u8]) -> anyhow::Result<Self> {
        let value: Value = ciborium::from_reader(body).context("decoding the CBOR point cloud")?;
        let map = value
            .as_map()
            .context("the CBOR point cloud is not a map")?;
        let data = field(map, "data")?
            .as_bytes()
            .context("data is not bytes")?;
        let count = u32_of(map, "points")? as usize;
        if count.checked_mul(12) != Some(data.len()) {
            bail!(
                "{count} points announced, {} bytes of points arrived",
                data.len()
            );
        }
        let text = |v: &Value| {
            v.as_text()
                .map(str::to_owned)
                .context("a serial is not text")
        };
        let serials = match field(map, "serials") {
            Ok(list) => list
                .as_array()
                .context("serials is not an array")?
                .iter()
                .map(text)
                .collect::<anyhow::Result<_>>()?,
            Err(_) => vec![text(field(map, "serial")?)?],
        };
        let timestamp_us = field(map, "timestamp_us")?
            .as_integer()
            .and_then(|v| u64::try_from(v).ok())
            .context("timestamp_us is not a count of microseconds")?;
        Ok(Self {
            cloud: packet::points(data),
            serials,
            timestamp_us,
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
    pub fn from_cbor(body: &[u8]) -> anyhow::Result<Self> {
        let value: Value = ciborium::from_reader(body).context("decoding the CBOR color frame")?;
        let map = value
            .as_map()
            .context("the CBOR color frame is not a map")?;
        let (width, height) = (u32_of(map, "width")?, u32_of(map, "height")?);
        let bpp = u32_of(map, "pixel_size")? as usize;
        let format = field(map, "format")?
            .as_text()
            .context("format is not text")?;
        let data = field(map, "data")?
            .as_bytes()
            .context("data is not bytes")?;
        let image = packet::rgb_image(data, width, height, bpp, format)
            .map_err(|e| anyhow::anyhow!("the CBOR color frame: {e}"))?;
        let k = field(map, "intrinsics")?
            .as_map()
            .context("intrinsics is not a map")?;
        let model_name = field(k, "model")?.as_text().context("model is not text")?;
        let f = |key: &str| -> anyhow::Result<f32> {
            Ok(field(k, key)?
                .as_float()
                .with_context(|| format!("{key} is not a number"))? as f32)
        };
        let intrinsics = Intrinsics {
            width: u32_of(k, "width")?,
            height: u32_of(k, "height")?,
            ppx: f("ppx")?,
            ppy: f("ppy")?,
            fx: f("fx")?,
            fy: f("fy")?,
            model: rgbd::DistortionModel::from_name(model_name)
                .with_context(|| format!("unknown distortion model {model_name:?}"))?,
            coeffs: floats(field(k, "coeffs")?)?,
        };
        let e = field(map, "depth_to_color")?
            .as_map()
            .context("depth_to_color is not a map")?;
        let depth_to_color = Extrinsics {
            rotation: floats(field(e, "rotation")?)?,
            translation: floats(field(e, "translation")?)?,
        };
        Ok(Self {
            image,
            intrinsics,
            depth_to_color,
        })
    }
}
