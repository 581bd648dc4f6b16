//! ROS 2 SQLite recordings (`.db3`, librealsense 2.57 and later).
//!
//! The file is an SQLite database with the tables `topics (id, name, type,
//! serialization_format, ...)` and `messages (id, topic_id, timestamp, data)`; every
//! message is CDR (little-endian encapsulation, decoded with `cdr-encoding`). Topics
//! read (d = device, s = sensor, `<S>` = `Depth_0` or `Color_0`):
//!
//! | topic | type | use |
//! |---|---|---|
//! | `/device_d/info` | std_msgs/msg/String | `key=value;...`: serial number, name |
//! | `/device_d/sensor_s/<S>/info` | std_msgs/msg/String | `encoding=Z16;fps=30` |
//! | `/device_d/sensor_s/<S>/camera_info` | std_msgs/msg/String | the distortion model (`model=...`) |
//! | `/device_d/sensor_s/<S>/image/camera_info` | sensor_msgs/msg/CameraInfo | size, K, D |
//! | `/device_d/sensor_s/<S>/image/data/compressedDepth` | sensor_msgs/msg/CompressedImage | depth: `16UC1; compressedDepth png` |
//! | `/device_d/sensor_s/<S>/image/data/compressed` | sensor_msgs/msg/CompressedImage | color: `rgb8; png compressed bgr8` |
//! | `/device_d/sensor_s/<S>/image/data` | sensor_msgs/msg/Image | uncompressed frames |
//! | `/device_d/sensor_s/<S>/image/metadata` | std_msgs/msg/String | `Frame number=...;depth_units=...` |
//! | `/device_d/sensor_s/<S>/tf/<ref>` | std_msgs/msg/String | `rotation=9 values;translation=3 values` |
//! | `/device_d/sensor_s/option/Depth_Units/value` | std_msgs/msg/String | depth units |
//!
//! The CameraInfo's `distortion_model` is ROS's ("plumb_bob" for every Brown
//! variant), so the model comes from the stream's `camera_info` string when the
//! recording has one. A `compressedDepth` message's data is a 12-byte header
//! (format and two depth-quantisation parameters, unused for 16-bit depth) followed
//! by a 16-bit grayscale PNG; color PNGs are 8-bit RGB (RGBA with alpha). Image
//! metadata shares its message's timestamp; it gives the recorded frame number and
//! the frame's depth units.

use std::collections::HashMap;
use std::path::Path;

use byteorder::LittleEndian;
use rusqlite::{Connection, OpenFlags};
use serde::Deserialize;

use super::recording::{
    DeviceBuilder, Event, Image, Kind, Pixels, PlaybackError, TopicPath, camera_matrix_intrinsics,
    check_image, check_text,
};
use crate::frame::ColorFormat;
use crate::intrinsics::{DistortionModel, Extrinsics};

/// The first bytes of an SQLite 3 database.
pub(crate) const MAGIC: &[u8] = b"SQLite format 3\0";

/// Largest message accepted, bytes.
pub const MAX_MESSAGE_BYTES: i64 = 64 << 20;

/// Length of the compressed-depth header before the PNG.
const COMPRESSED_DEPTH_HEADER: usize = 12;

fn sql_error(e: impl std::fmt::Display) -> PlaybackError {
    PlaybackError::Sqlite(e.to_string())
}

#[derive(Deserialize)]
struct StringMsg {
    data: String,
}

#[derive(Deserialize)]
struct Time {
    _sec: i32,
    _nanosec: u32,
}

#[derive(Deserialize)]
struct Header {
    _stamp: Time,
    _frame_id: String,
}

#[derive(Deserialize)]
struct CompressedImage<'a> {
    _header: Header,
    format: String,
    #[serde(borrow)]
    data: &'a [u8],
}

#[derive(Deserialize)]
struct RawImage<'a> {
    _header: Header,
    height: u32,
    width: u32,
    encoding: String,
    is_bigendian: u8,
    step: u32,
    #[serde(borrow)]
    data: &'a [u8],
}

/// The leading fields of sensor_msgs/msg/CameraInfo (the rest is not needed).
#[derive(Deserialize)]
struct CameraInfo {
    _header: Header,
    height: u32,
    width: u32,
    distortion_model: String,
    d: Vec<f64>,
    k: [f64; 9],
}

/// Decodes a CDR message: a 4-byte encapsulation header (little-endian CDR only),
/// then the body, whose alignment counts from after the header.
fn cdr<'a, T: Deserialize<'a>>(topic: &str, data: &'a [u8]) -> Result<T, PlaybackError> {
    let body = match data {
        [0x00, 0x01, _, _, body @ ..] => body,
        [a, b, _, _, ..] => {
            return Err(PlaybackError::Unsupported(format!(
                "{topic}: CDR encapsulation {a:#04x}{b:02x} (only little-endian CDR)"
            )));
        }
        _ => return Err(PlaybackError::message(topic, "shorter than its CDR header")),
    };
    cdr_encoding::from_bytes::<T, LittleEndian>(body)
        .map(|(value, _)| value)
        .map_err(|e| PlaybackError::message(topic, format!("CDR: {e}")))
}

fn string(topic: &str, data: &[u8]) -> Result<String, PlaybackError> {
    let s = cdr::<StringMsg>(topic, data)?.data;
    check_text(topic, &s)?;
    Ok(s)
}

/// `key=value;key=value;` pairs, in order.
fn pairs(text: &str) -> impl Iterator<Item = (&str, &str)> {
    text.split(';')
        .filter(|p| !p.is_empty())
        .filter_map(|p| p.split_once('='))
}

fn number<T: std::str::FromStr>(topic: &str, what: &str, text: &str) -> Result<T, PlaybackError> {
    text.trim().parse().map_err(|_| {
        PlaybackError::message(
            topic,
            format!("{what} {:?} is not a number", crate::echo(text)),
        )
    })
}

fn numbers<const N: usize>(topic: &str, what: &str, text: &str) -> Result<[f32; N], PlaybackError> {
    let mut out = [0.0f32; N];
    let mut parts = text.split(',');
    for slot in &mut out {
        let part = parts.next().ok_or_else(|| {
            PlaybackError::message(topic, format!("{what} has fewer than {N} values"))
        })?;
        *slot = number(topic, what, part)?;
    }
    if parts.next().is_some() {
        return Err(PlaybackError::message(
            topic,
            format!("{what} has more than {N} values"),
        ));
    }
    Ok(out)
}

/// Per-frame metadata: recorded frame number and depth units.
#[derive(Debug, Default, Clone, Copy)]
struct Metadata {
    frame_number: Option<u64>,
    depth_units: Option<f32>,
}

/// Reads a `.db3` recording into `builder`.
pub(crate) fn read(path: &Path, builder: &mut DeviceBuilder) -> Result<(), PlaybackError> {
    let db = Connection::open_with_flags(
        path,
        OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
    )
    .map_err(sql_error)?;
    // Pass 1: everything but the frames (small messages, metadata first so that the
    // frames of pass 2 can be numbered); pass 2: the frames, in recording order.
    let mut metadata: HashMap<(String, i64), Metadata> = HashMap::new();
    let mut models: HashMap<(u32, Kind), DistortionModel> = HashMap::new();
    let mut counters: HashMap<(u32, Kind), u64> = HashMap::new();
    for frames in [false, true] {
        let mut statement = db
            .prepare(
                "SELECT t.name, t.type, t.serialization_format, m.timestamp, length(m.data), m.data \
                 FROM messages m JOIN topics t ON t.id = m.topic_id \
                 WHERE (instr(t.name, '/image/data') > 0) = ?1 \
                 ORDER BY m.timestamp, m.id",
            )
            .map_err(sql_error)?;
        let mut rows = statement.query([frames]).map_err(sql_error)?;
        while let Some(row) = rows.next().map_err(sql_error)? {
            let topic: String = row.get(0).map_err(sql_error)?;
            let tp: String = row.get(1).map_err(sql_error)?;
            let format: String = row.get(2).map_err(sql_error)?;
            let timestamp: i64 = row.get(3).map_err(sql_error)?;
            let len: i64 = row.get(4).map_err(sql_error)?;
            if len > MAX_MESSAGE_BYTES {
                return Err(PlaybackError::TooLarge {
                    what: format!("message on {}", crate::clip(&topic, crate::MESSAGE_CHARS)),
                    size: u64::try_from(len).unwrap_or(u64::MAX),
                    limit: MAX_MESSAGE_BYTES as u64,
                });
            }
            let Some(path) = TopicPath::parse(&topic) else {
                continue;
            };
            if format != "cdr" {
                return Err(PlaybackError::Unsupported(format!(
                    "{topic}: serialization format {:?}",
                    crate::echo(&format)
                )));
            }
            let data = row
                .get_ref(5)
                .map_err(sql_error)?
                .as_blob()
                .map_err(sql_error)?;
            let message = Message {
                topic: &topic,
                tp: &tp,
                data,
                path: &path,
            };
            if frames {
                let (Some(stream), Some(image)) = (path.stream, message.frame()?) else {
                    continue;
                };
                let mut image = image;
                let prefix = stream_prefix(&topic);
                let meta = metadata
                    .get(&(prefix.to_owned(), timestamp))
                    .copied()
                    .unwrap_or_default();
                let counter = counters.entry((path.device, stream)).or_default();
                *counter += 1;
                image.frame_number = meta.frame_number.unwrap_or(*counter);
                image.depth_units = meta.depth_units;
                builder.add(Event::Frame {
                    device: path.device,
                    stream,
                    image,
                })?;
            } else if path.rest.as_slice() == ["image", "metadata"] {
                message.expect("std_msgs/msg/String")?;
                let text = string(&topic, data)?;
                let mut meta = Metadata::default();
                for (key, value) in pairs(&text) {
                    match key {
                        "Frame number" => meta.frame_number = Some(number(&topic, key, value)?),
                        "depth_units" => meta.depth_units = Some(number(&topic, key, value)?),
                        _ => {}
                    }
                }
                metadata.insert((stream_prefix(&topic).to_owned(), timestamp), meta);
            } else {
                for event in message.static_events(&mut models)? {
                    builder.add(event)?;
                }
            }
        }
    }
    for ((device, stream), model) in models {
        builder.set_model(device, stream, model);
    }
    Ok(())
}

/// The topic up to and including the stream segment (`/device_0/sensor_0/Depth_0`).
fn stream_prefix(topic: &str) -> &str {
    topic.find("/image/").map_or(topic, |i| &topic[..i])
}

struct Message<'a> {
    topic: &'a str,
    tp: &'a str,
    data: &'a [u8],
    path: &'a TopicPath<'a>,
}

impl Message<'_> {
    fn expect(&self, wanted: &str) -> Result<(), PlaybackError> {
        if self.tp == wanted {
            Ok(())
        } else {
            Err(PlaybackError::message(
                self.topic,
                format!("type {}, expected {wanted}", self.tp),
            ))
        }
    }

    /// Events of the non-frame topics; distortion models go to `models`.
    fn static_events(
        &self,
        models: &mut HashMap<(u32, Kind), DistortionModel>,
    ) -> Result<Vec<Event>, PlaybackError> {
        let topic = self.topic;
        let device = self.path.device;
        let mut events = Vec::new();
        match (
            self.path.sensor,
            self.path.stream,
            self.path.rest.as_slice(),
        ) {
            (None, None, ["info"]) => {
                self.expect("std_msgs/msg/String")?;
                for (key, value) in pairs(&string(topic, self.data)?) {
                    events.push(Event::DeviceInfo {
                        device,
                        key: key.to_owned(),
                        value: value.to_owned(),
                    });
                }
            }
            (Some(sensor), Some(stream), ["info"]) => {
                self.expect("std_msgs/msg/String")?;
                let text = string(topic, self.data)?;
                let mut fps = None;
                let mut pixels = None;
                for (key, value) in pairs(&text) {
                    match key {
                        "fps" => fps = Some(number(topic, key, value)?),
                        "encoding" => {
                            pixels = Some(Pixels::from_name(value).ok_or_else(|| {
                                PlaybackError::Unsupported(format!(
                                    "{topic}: encoding {:?}",
                                    crate::echo(value)
                                ))
                            })?);
                        }
                        _ => {}
                    }
                }
                let (Some(fps), Some(pixels)) = (fps, pixels) else {
                    return Err(PlaybackError::message(
                        topic,
                        "stream info without fps or encoding",
                    ));
                };
                events.push(Event::StreamInfo {
                    device,
                    stream,
                    fps,
                    pixels,
                    sensor: Some(sensor),
                });
            }
            (Some(_), Some(stream), ["camera_info"]) => {
                self.expect("std_msgs/msg/String")?;
                let text = string(topic, self.data)?;
                if let Some((_, name)) = pairs(&text).find(|(k, _)| *k == "model") {
                    let model = DistortionModel::from_name(name).ok_or_else(|| {
                        PlaybackError::Unsupported(format!(
                            "{topic}: distortion model {:?}",
                            crate::echo(name)
                        ))
                    })?;
                    models.insert((device, stream), model);
                }
            }
            (Some(_), Some(stream), ["image", "camera_info"]) => {
                self.expect("sensor_msgs/msg/CameraInfo")?;
                let info: CameraInfo = cdr(topic, self.data)?;
                let mut coeffs = [0.0f32; 5];
                for (slot, c) in coeffs.iter_mut().zip(&info.d) {
                    *slot = *c as f32;
                }
                let model = match info.distortion_model.as_str() {
                    "plumb_bob" | "rational_polynomial" => DistortionModel::BrownConrady,
                    "equidistant" => DistortionModel::KannalaBrandt4,
                    _ => DistortionModel::None,
                };
                events.push(Event::Intrinsics {
                    device,
                    stream,
                    intrinsics: camera_matrix_intrinsics(
                        info.width,
                        info.height,
                        &info.k,
                        model,
                        coeffs,
                    ),
                });
            }
            (Some(sensor), None, ["option", name, "value"]) => {
                self.expect("std_msgs/msg/String")?;
                let text = string(topic, self.data)?;
                events.push(Event::OptionValue {
                    device,
                    sensor,
                    name: (*name).to_owned(),
                    value: number(topic, name, &text)?,
                });
            }
            (Some(_), Some(stream), ["tf", reference]) => {
                self.expect("std_msgs/msg/String")?;
                let text = string(topic, self.data)?;
                let mut rotation = None;
                let mut translation = None;
                for (key, value) in pairs(&text) {
                    match key {
                        "rotation" => rotation = Some(numbers::<9>(topic, key, value)?),
                        "translation" => translation = Some(numbers::<3>(topic, key, value)?),
                        _ => {}
                    }
                }
                let (Some(rotation), Some(translation)) = (rotation, translation) else {
                    return Err(PlaybackError::message(
                        topic,
                        "transform without rotation or translation",
                    ));
                };
                events.push(Event::FromReference {
                    device,
                    stream,
                    reference: (*reference).to_owned(),
                    extrinsics: Extrinsics {
                        rotation,
                        translation,
                    },
                });
            }
            _ => {}
        }
        Ok(events)
    }

    /// The image of a frame topic, or `None` for topics under `image/data` this reader
    /// does not play.
    fn frame(&self) -> Result<Option<Image>, PlaybackError> {
        let topic = self.topic;
        let image = match self.path.rest.as_slice() {
            ["image", "data", "compressedDepth"] => {
                self.expect("sensor_msgs/msg/CompressedImage")?;
                let m: CompressedImage<'_> = cdr(topic, self.data)?;
                if !m.format.contains("compressedDepth png") {
                    return Err(PlaybackError::Unsupported(format!(
                        "{topic}: compressed depth format {:?}",
                        crate::echo(&m.format)
                    )));
                }
                let png = m.data.get(COMPRESSED_DEPTH_HEADER..).ok_or_else(|| {
                    PlaybackError::message(topic, "compressed depth shorter than its header")
                })?;
                decode_png(topic, png, Pixels::Z16)?
            }
            ["image", "data", "compressed"] => {
                self.expect("sensor_msgs/msg/CompressedImage")?;
                let m: CompressedImage<'_> = cdr(topic, self.data)?;
                let original = m.format.split(';').next().unwrap_or_default().trim();
                if !m.format.contains("png") {
                    return Err(PlaybackError::Unsupported(format!(
                        "{topic}: compressed format {:?} (only PNG)",
                        crate::echo(&m.format)
                    )));
                }
                let pixels = Pixels::from_name(original).ok_or_else(|| {
                    PlaybackError::Unsupported(format!(
                        "{topic}: encoding {:?}",
                        crate::echo(original)
                    ))
                })?;
                decode_png(topic, m.data, pixels)?
            }
            ["image", "data"] => {
                self.expect("sensor_msgs/msg/Image")?;
                let m: RawImage<'_> = cdr(topic, self.data)?;
                let pixels = Pixels::from_name(&m.encoding).ok_or_else(|| {
                    PlaybackError::Unsupported(format!(
                        "{topic}: encoding {:?}",
                        crate::echo(&m.encoding)
                    ))
                })?;
                check_image(topic, m.width, m.height, pixels, m.data.len())?;
                if m.step as usize != m.width as usize * pixels.bytes_per_pixel() {
                    return Err(PlaybackError::message(
                        topic,
                        format!("row step {}", m.step),
                    ));
                }
                let mut data = m.data.to_vec();
                if m.is_bigendian != 0 && pixels == Pixels::Z16 {
                    for px in data.chunks_exact_mut(2) {
                        px.swap(0, 1);
                    }
                }
                Image {
                    frame_number: 0,
                    width: m.width,
                    height: m.height,
                    pixels,
                    data,
                    depth_units: None,
                }
            }
            _ => return Ok(None),
        };
        Ok(Some(image))
    }
}

/// Decodes a PNG into `pixels`' layout, checking its size before allocating.
fn decode_png(topic: &str, png_data: &[u8], pixels: Pixels) -> Result<Image, PlaybackError> {
    let png_error = |e: png::DecodingError| PlaybackError::message(topic, format!("PNG: {e}"));
    let mut decoder = png::Decoder::new(std::io::Cursor::new(png_data));
    decoder.set_transformations(png::Transformations::IDENTITY);
    let mut reader = decoder.read_info().map_err(png_error)?;
    let (width, height, color_type, bit_depth) = {
        let info = reader.info();
        (info.width, info.height, info.color_type, info.bit_depth)
    };
    let wanted = match pixels {
        Pixels::Z16 => (png::ColorType::Grayscale, png::BitDepth::Sixteen),
        Pixels::Color(ColorFormat::Rgb8 | ColorFormat::Bgr8) => {
            (png::ColorType::Rgb, png::BitDepth::Eight)
        }
        Pixels::Color(ColorFormat::Rgba8 | ColorFormat::Bgra8) => {
            (png::ColorType::Rgba, png::BitDepth::Eight)
        }
    };
    if (color_type, bit_depth) != wanted {
        return Err(PlaybackError::message(
            topic,
            format!("PNG is {color_type:?} {bit_depth:?}, expected {wanted:?} for {pixels:?}"),
        ));
    }
    let len = width as usize * height as usize * pixels.bytes_per_pixel();
    check_image(topic, width, height, pixels, len)?;
    let mut data = vec![0u8; len];
    reader.next_frame(&mut data).map_err(png_error)?;
    match pixels {
        // PNG stores 16-bit samples big-endian.
        Pixels::Z16 => data.chunks_exact_mut(2).for_each(|px| px.swap(0, 1)),
        // PNG stores red first.
        Pixels::Color(ColorFormat::Bgr8 | ColorFormat::Bgra8) => {
            let bpp = pixels.bytes_per_pixel();
            data.chunks_exact_mut(bpp).for_each(|px| px.swap(0, 2));
        }
        Pixels::Color(ColorFormat::Rgb8 | ColorFormat::Rgba8) => {}
    }
    Ok(Image {
        frame_number: 0,
        width,
        height,
        pixels,
        data,
        depth_units: None,
    })
}
