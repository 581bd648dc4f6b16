//! A recording decoded: the events both readers ([`super::bag`], [`super::db3`]) turn
//! messages into, the limits they enforce, and [`DeviceBuilder`], which assembles the
//! events into [`RecordedDevice`]s.

use std::collections::BTreeMap;

use crate::camera::{Serial, SerialError};
use crate::frame::{ColorFormat, DepthFormat};
use crate::intrinsics::{DistortionModel, Extrinsics, Intrinsics};
use crate::mode::{ModeTable, ResolutionModes};
use crate::settings::{ColorSettings, DepthSettings};

/// Most decoded pixel bytes a recording may hold (1 GiB, about 200 depth+color frame
/// pairs at 1280x720).
pub const MAX_RECORDING_BYTES: usize = 1 << 30;

/// Largest width or height of a recorded image, pixels.
pub const MAX_IMAGE_SIDE: u32 = 4096;

/// Longest text (info value, option, stream info) a recording may carry, bytes.
const MAX_TEXT_BYTES: usize = 64 * 1024;

/// Why a recording cannot be played.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PlaybackError {
    /// The file cannot be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// What the OS said.
        source: std::io::Error,
    },
    /// Neither a ROS 1 bag nor a ROS 2 SQLite recording.
    #[error("{path}: not a librealsense recording (neither \"#ROSBAG V2.0\" nor SQLite)")]
    UnknownFormat {
        /// The file.
        path: String,
    },
    /// The ROS 1 bag container is damaged.
    #[error("bag: {0}")]
    Bag(String),
    /// The SQLite database cannot be read.
    #[error("db3: {0}")]
    Sqlite(String),
    /// A message does not decode as its type.
    #[error("topic {topic}: {reason}")]
    Message {
        /// The message's topic.
        topic: String,
        /// What is wrong.
        reason: String,
    },
    /// Something the camera needs is not in the recording.
    #[error("recording has no {0}")]
    Missing(String),
    /// The recording uses something this reader does not support.
    #[error("unsupported: {0}")]
    Unsupported(String),
    /// A size beyond the reader's bounds.
    #[error("{what}: {size} exceeds the limit of {limit}")]
    TooLarge {
        /// What is too large.
        what: String,
        /// Its size.
        size: u64,
        /// The limit.
        limit: u64,
    },
    /// The recorded serial number is not a valid [`Serial`].
    #[error("recorded serial number: {0}")]
    Serial(#[from] SerialError),
}

impl PlaybackError {
    pub(crate) fn message(topic: &str, reason: impl Into<String>) -> Self {
        Self::Message {
            topic: crate::clip(topic, crate::MESSAGE_CHARS).into_owned(),
            reason: reason.into(),
        }
    }
}

/// The stream of a topic this reader plays (`Depth_0` or `Color_0`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub(crate) enum Kind {
    Depth,
    Color,
}

/// Where a topic belongs: `/device_<d>/sensor_<s>/<Stream>_<i>/<rest>`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct TopicPath<'a> {
    pub(crate) device: u32,
    pub(crate) sensor: Option<u32>,
    /// The stream, if the topic is under `Depth_0` or `Color_0`.
    pub(crate) stream: Option<Kind>,
    /// The segments after the device, sensor and stream segments.
    pub(crate) rest: Vec<&'a str>,
}

impl<'a> TopicPath<'a> {
    /// Splits a librealsense topic; `None` for topics outside `/device_<d>`.
    pub(crate) fn parse(topic: &'a str) -> Option<Self> {
        let mut parts = topic.strip_prefix('/')?.split('/').peekable();
        let device = parts.next()?.strip_prefix("device_")?.parse().ok()?;
        let sensor = match parts.peek().and_then(|p| p.strip_prefix("sensor_")) {
            Some(s) => {
                let s = s.parse().ok()?;
                parts.next();
                Some(s)
            }
            None => None,
        };
        let stream = match parts.peek() {
            Some(&"Depth_0") => Some(Kind::Depth),
            Some(&"Color_0") => Some(Kind::Color),
            _ => None,
        };
        if stream.is_some() {
            parts.next();
        }
        Some(Self {
            device,
            sensor,
            stream,
            rest: parts.collect(),
        })
    }
}

/// The pixel layout of a recorded stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Pixels {
    Z16,
    Color(ColorFormat),
}

impl Pixels {
    /// From librealsense's format names ("Z16", "RGB8") or ROS encodings ("mono16",
    /// "16UC1", "rgb8", ...).
    pub(crate) fn from_name(name: &str) -> Option<Self> {
        Some(match name {
            "Z16" | "mono16" | "16UC1" => Self::Z16,
            "RGB8" | "rgb8" => Self::Color(ColorFormat::Rgb8),
            "BGR8" | "bgr8" => Self::Color(ColorFormat::Bgr8),
            "RGBA8" | "rgba8" => Self::Color(ColorFormat::Rgba8),
            "BGRA8" | "bgra8" => Self::Color(ColorFormat::Bgra8),
            _ => return None,
        })
    }

    pub(crate) fn bytes_per_pixel(self) -> usize {
        match self {
            Self::Z16 => 2,
            Self::Color(f) => f.bytes_per_pixel(),
        }
    }
}

/// A recorded image, decoded: `width * height * bpp` bytes, rows packed, Z16 little-endian.
#[derive(Debug, Clone)]
pub(crate) struct Image {
    pub(crate) frame_number: u64,
    pub(crate) width: u32,
    pub(crate) height: u32,
    pub(crate) pixels: Pixels,
    pub(crate) data: Vec<u8>,
    /// Metres per depth unit carried by the frame itself.
    pub(crate) depth_units: Option<f32>,
}

/// What a reader found in one message.
#[derive(Debug)]
pub(crate) enum Event {
    /// A device information key and value ("Serial Number", "Name", ...).
    DeviceInfo {
        device: u32,
        key: String,
        value: String,
    },
    /// Stream information: frame rate, format, and the stream's sensor.
    StreamInfo {
        device: u32,
        stream: Kind,
        fps: u32,
        pixels: Pixels,
        sensor: Option<u32>,
    },
    /// Stream intrinsics.
    Intrinsics {
        device: u32,
        stream: Kind,
        intrinsics: Intrinsics,
    },
    /// A sensor option's value.
    OptionValue {
        device: u32,
        sensor: u32,
        name: String,
        value: f32,
    },
    /// The transform from a reference frame (a group name) to the stream:
    /// `p_stream = R * p_reference + t`.
    FromReference {
        device: u32,
        stream: Kind,
        reference: String,
        extrinsics: Extrinsics,
    },
    /// One frame.
    Frame {
        device: u32,
        stream: Kind,
        image: Image,
    },
}

#[derive(Debug, Default)]
struct StreamBuilder {
    fps: Option<u32>,
    pixels: Option<Pixels>,
    intrinsics: Option<Intrinsics>,
    model: Option<DistortionModel>,
    sensor: Option<u32>,
    from_reference: Option<(String, Extrinsics)>,
    frames: Vec<Image>,
}

/// Collects the events of one recording into devices, bounding the pixel bytes.
#[derive(Debug, Default)]
pub(crate) struct DeviceBuilder {
    devices: BTreeMap<u32, DeviceParts>,
    bytes: usize,
}

#[derive(Debug, Default)]
struct DeviceParts {
    info: BTreeMap<String, String>,
    options: BTreeMap<(u32, String), f32>,
    streams: BTreeMap<Kind, StreamBuilder>,
}

impl DeviceBuilder {
    pub(crate) fn add(&mut self, event: Event) -> Result<(), PlaybackError> {
        match event {
            Event::DeviceInfo { device, key, value } => {
                self.device(device).info.insert(key, value);
            }
            Event::StreamInfo {
                device,
                stream,
                fps,
                pixels,
                sensor,
            } => {
                let s = self.stream(device, stream);
                s.fps = Some(fps);
                s.pixels = Some(pixels);
                s.sensor = sensor;
            }
            Event::Intrinsics {
                device,
                stream,
                intrinsics,
            } => self.stream(device, stream).intrinsics = Some(intrinsics),
            Event::OptionValue {
                device,
                sensor,
                name,
                value,
            } => {
                self.device(device).options.insert((sensor, name), value);
            }
            Event::FromReference {
                device,
                stream,
                reference,
                extrinsics,
            } => self.stream(device, stream).from_reference = Some((reference, extrinsics)),
            Event::Frame {
                device,
                stream,
                image,
            } => {
                self.bytes = self.bytes.saturating_add(image.data.len());
                if self.bytes > MAX_RECORDING_BYTES {
                    return Err(PlaybackError::TooLarge {
                        what: "decoded frames of the recording".to_owned(),
                        size: self.bytes as u64,
                        limit: MAX_RECORDING_BYTES as u64,
                    });
                }
                self.stream(device, stream).frames.push(image);
            }
        }
        Ok(())
    }

    /// The distortion model of a stream, overriding the one its intrinsics came with.
    pub(crate) fn set_model(&mut self, device: u32, stream: Kind, model: DistortionModel) {
        self.stream(device, stream).model = Some(model);
    }

    fn device(&mut self, device: u32) -> &mut DeviceParts {
        self.devices.entry(device).or_default()
    }

    fn stream(&mut self, device: u32, stream: Kind) -> &mut StreamBuilder {
        self.device(device).streams.entry(stream).or_default()
    }

    /// Every recorded device, each ready to be played.
    pub(crate) fn finish(self) -> Result<Vec<RecordedDevice>, PlaybackError> {
        if self.devices.is_empty() {
            return Err(PlaybackError::Missing(
                "device (no /device_<n> topics)".into(),
            ));
        }
        self.devices
            .into_iter()
            .map(|(index, parts)| parts.finish(index))
            .collect()
    }
}

struct Played {
    intrinsics: Intrinsics,
    fps: u32,
    pixels: Pixels,
    frames: Vec<Image>,
    sensor: Option<u32>,
    from_reference: Option<(String, Extrinsics)>,
}

fn finish_stream(
    device: u32,
    kind: Kind,
    s: Option<StreamBuilder>,
) -> Result<Played, PlaybackError> {
    let name = match kind {
        Kind::Depth => "Depth_0",
        Kind::Color => "Color_0",
    };
    let what = |x: &str| PlaybackError::Missing(format!("{x} for /device_{device}/.../{name}"));
    let s = s.ok_or_else(|| what("stream"))?;
    let mut intrinsics = s.intrinsics.ok_or_else(|| what("intrinsics"))?;
    if let Some(model) = s.model {
        intrinsics.model = model;
    }
    let fps = s.fps.ok_or_else(|| what("stream info (fps, format)"))?;
    let pixels = s.pixels.ok_or_else(|| what("stream info (fps, format)"))?;
    if s.frames.is_empty() {
        return Err(what("frames"));
    }
    match (kind, pixels) {
        (Kind::Depth, Pixels::Z16) | (Kind::Color, Pixels::Color(_)) => {}
        _ => {
            return Err(PlaybackError::Unsupported(format!(
                "{name} recorded as {pixels:?}"
            )));
        }
    }
    for f in &s.frames {
        if (f.width, f.height, f.pixels) != (intrinsics.width, intrinsics.height, pixels) {
            return Err(PlaybackError::message(
                name,
                format!(
                    "frame {} is {}x{} {:?}, the stream {}x{} {:?}",
                    f.frame_number,
                    f.width,
                    f.height,
                    f.pixels,
                    intrinsics.width,
                    intrinsics.height,
                    pixels
                ),
            ));
        }
    }
    Ok(Played {
        intrinsics,
        fps,
        pixels,
        frames: s.frames,
        sensor: s.sensor,
        from_reference: s.from_reference,
    })
}

impl DeviceParts {
    fn finish(mut self, index: u32) -> Result<RecordedDevice, PlaybackError> {
        let serial_text = self
            .info
            .get("Serial Number")
            .ok_or_else(|| PlaybackError::Missing(format!("serial number for /device_{index}")))?;
        let serial = Serial::parse(serial_text)?;
        let model = self
            .info
            .get("Name")
            .cloned()
            .unwrap_or_else(|| "Intel RealSense (recording)".to_owned());
        let mut depth = finish_stream(index, Kind::Depth, self.streams.remove(&Kind::Depth))?;
        let mut color = finish_stream(index, Kind::Color, self.streams.remove(&Kind::Color))?;
        let depth_sensor = depth.sensor;
        let option_units = self
            .options
            .iter()
            .find(|((sensor, name), _)| {
                name == "Depth_Units" && depth_sensor.is_none_or(|d| d == *sensor)
            })
            .map(|(_, v)| *v);
        let baseline_m = self
            .options
            .iter()
            .find(|((sensor, name), _)| {
                name == "Stereo_Baseline" && depth_sensor.is_none_or(|d| d == *sensor)
            })
            .map(|(_, mm)| *mm / 1000.0)
            .filter(|m| m.is_finite() && *m > 0.0);
        let depth_scale = option_units
            .or_else(|| depth.frames.iter().find_map(|f| f.depth_units))
            .ok_or_else(|| PlaybackError::Missing("depth units (option Depth_Units)".into()))?;
        if !(depth_scale.is_finite() && depth_scale > 0.0) {
            return Err(PlaybackError::message(
                "Depth_Units",
                format!("{depth_scale} is not a positive number of metres"),
            ));
        }
        let depth_to_color = match (depth.from_reference.take(), color.from_reference.take()) {
            (Some((a, from_a_to_depth)), Some((b, from_b_to_color))) if a == b => {
                compose(&from_b_to_color, &invert(&from_a_to_depth))
            }
            (Some((a, _)), Some((b, _))) => {
                return Err(PlaybackError::Unsupported(format!(
                    "depth and color extrinsics against different references ({a}, {b})"
                )));
            }
            _ => return Err(PlaybackError::Missing("depth or color extrinsics".into())),
        };
        let Pixels::Color(color_format) = color.pixels else {
            return Err(PlaybackError::Unsupported(
                "color stream is not color".into(),
            ));
        };
        let modes = ModeTable {
            color_formats: vec![color_format],
            color: vec![ResolutionModes {
                width: color.intrinsics.width,
                height: color.intrinsics.height,
                fps: vec![color.fps],
            }],
            depth_formats: vec![DepthFormat::Z16],
            depth: vec![ResolutionModes {
                width: depth.intrinsics.width,
                height: depth.intrinsics.height,
                fps: vec![depth.fps],
            }],
        };
        let color_settings = ColorSettings {
            format: color_format,
            fps: color.fps,
            width: color.intrinsics.width,
            height: color.intrinsics.height,
        };
        let depth_settings = DepthSettings {
            format: DepthFormat::Z16,
            fps: depth.fps,
            width: depth.intrinsics.width,
            height: depth.intrinsics.height,
        };
        let depth_frames = depth
            .frames
            .into_iter()
            .map(|f| {
                let scale = f.depth_units.unwrap_or(depth_scale);
                let values = f
                    .data
                    .chunks_exact(2)
                    .map(|b| u16::from_le_bytes([b[0], b[1]]))
                    .collect();
                (f.frame_number, scale, values)
            })
            .collect();
        let color_frames = color
            .frames
            .into_iter()
            .map(|f| (f.frame_number, f.data))
            .collect();
        Ok(RecordedDevice {
            serial,
            model,
            modes,
            color_settings,
            depth_settings,
            color_intrinsics: color.intrinsics,
            depth_intrinsics: depth.intrinsics,
            depth_to_color,
            depth_scale,
            baseline_m,
            depth_frames,
            color_frames,
        })
    }
}

/// `a` after `b`: p -> a(b(p)).
fn compose(a: &Extrinsics, b: &Extrinsics) -> Extrinsics {
    let mut rotation = [0.0; 9];
    for col in 0..3 {
        for row in 0..3 {
            rotation[col * 3 + row] = (0..3)
                .map(|k| a.rotation[k * 3 + row] * b.rotation[col * 3 + k])
                .sum();
        }
    }
    Extrinsics {
        rotation,
        translation: a.transform(b.translation),
    }
}

/// The inverse rigid transform.
fn invert(e: &Extrinsics) -> Extrinsics {
    let r = &e.rotation;
    // The transpose of a column-major matrix.
    let rotation = [r[0], r[3], r[6], r[1], r[4], r[7], r[2], r[5], r[8]];
    let t = e.translation;
    let back = Extrinsics {
        rotation,
        translation: [0.0; 3],
    }
    .transform(t);
    Extrinsics {
        rotation,
        translation: [-back[0], -back[1], -back[2]],
    }
}

/// Intrinsics from a ROS CameraInfo: its row-major camera matrix `k`
/// (`[fx 0 ppx; 0 fy ppy; 0 0 1]`), distortion model and coefficients.
pub(crate) fn camera_matrix_intrinsics(
    width: u32,
    height: u32,
    k: &[f64; 9],
    model: DistortionModel,
    coeffs: [f32; 5],
) -> Intrinsics {
    Intrinsics {
        width,
        height,
        fx: k[0] as f32,
        ppx: k[2] as f32,
        fy: k[4] as f32,
        ppy: k[5] as f32,
        model,
        coeffs,
    }
}

/// Checks an image's size against the bounds and the data length against
/// `width * height * bpp`.
pub(crate) fn check_image(
    topic: &str,
    width: u32,
    height: u32,
    pixels: Pixels,
    data_len: usize,
) -> Result<(), PlaybackError> {
    for side in [width, height] {
        if side == 0 || side > MAX_IMAGE_SIDE {
            return Err(PlaybackError::TooLarge {
                what: format!("{topic}: image side"),
                size: u64::from(side),
                limit: u64::from(MAX_IMAGE_SIDE),
            });
        }
    }
    let expected = width as usize * height as usize * pixels.bytes_per_pixel();
    if data_len != expected {
        return Err(PlaybackError::message(
            topic,
            format!("{data_len} pixel bytes for {width}x{height} {pixels:?} (expected {expected})"),
        ));
    }
    Ok(())
}

/// Text of a message, bounded.
pub(crate) fn check_text(topic: &str, text: &str) -> Result<(), PlaybackError> {
    if text.len() > MAX_TEXT_BYTES {
        return Err(PlaybackError::TooLarge {
            what: format!("{topic}: text"),
            size: text.len() as u64,
            limit: MAX_TEXT_BYTES as u64,
        });
    }
    Ok(())
}

/// One recorded device, decoded: what a [`super::PlaybackCamera`] plays.
#[derive(Debug)]
pub(crate) struct RecordedDevice {
    pub(crate) serial: Serial,
    pub(crate) model: String,
    pub(crate) modes: ModeTable,
    pub(crate) color_settings: ColorSettings,
    pub(crate) depth_settings: DepthSettings,
    pub(crate) color_intrinsics: Intrinsics,
    pub(crate) depth_intrinsics: Intrinsics,
    pub(crate) depth_to_color: Extrinsics,
    pub(crate) depth_scale: f32,
    /// The option `Stereo_Baseline` (mm) in metres, when recorded.
    pub(crate) baseline_m: Option<f32>,
    /// (recorded frame number, metres per unit, values).
    pub(crate) depth_frames: Vec<(u64, f32, Vec<u16>)>,
    /// (recorded frame number, pixels).
    pub(crate) color_frames: Vec<(u64, Vec<u8>)>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topics_split_into_device_sensor_stream() {
        let t = TopicPath::parse("/device_0/sensor_1/Color_0/image/data").unwrap();
        assert_eq!(
            (t.device, t.sensor, t.stream, t.rest),
            (0, Some(1), Some(Kind::Color), vec!["image", "data"])
        );
        let t = TopicPath::parse("/device_2/info").unwrap();
        assert_eq!((t.device, t.sensor, t.stream), (2, None, None));
        let t = TopicPath::parse("/device_0/sensor_0/Infrared_1/info").unwrap();
        assert_eq!(t.stream, None);
        assert_eq!(TopicPath::parse("/file_version"), None);
        assert_eq!(TopicPath::parse("/device_x/info"), None);
    }

    #[test]
    fn extrinsics_compose_and_invert() {
        let e = Extrinsics {
            rotation: [0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            translation: [0.5, 0.25, -1.0],
        };
        let p = [0.3, -0.7, 2.0];
        let back = invert(&e).transform(e.transform(p));
        for i in 0..3 {
            assert!((back[i] - p[i]).abs() < 1e-6, "{back:?}");
        }
        let twice = compose(&e, &e).transform(p);
        let step = e.transform(e.transform(p));
        for i in 0..3 {
            assert!((twice[i] - step[i]).abs() < 1e-6, "{twice:?} {step:?}");
        }
    }
}
