//! Playback of recordings made by librealsense (realsense-viewer, `rs.recorder`): one
//! [`PlaybackCamera`] per recorded device.
//!
//! Two file formats, told apart by their first bytes:
//!
//! - ROS 1 bag v2.0 (`.bag`, librealsense up to 2.56): read with the `rosbag` crate;
//!   see [`bag`] for the topics and librealsense's quirks.
//! - ROS 2 SQLite (`.db3`, librealsense 2.57 and later): tables `topics` and
//!   `messages` of CDR-serialized messages; see [`db3`].
//!
//! Both share librealsense's topic grammar `/device_<d>/sensor_<s>/<Stream>_<i>/...`;
//! the readers turn messages into `Event`s and `DeviceBuilder` assembles them.
//!
//! Playback: the whole recording is decoded when it is opened (at most
//! [`MAX_RECORDING_BYTES`] of pixels; a longer recording is refused, not truncated).
//! Each grab returns the next recorded frame of that stream, in recording order, and
//! wraps to the first after the last: a grab never waits, and every recorded frame is
//! served in turn however fast or slowly clients grab. Grabbed frames are numbered
//! from 1 by the camera and stamped with the wall clock, as live frames are; the
//! recorded frame numbers are in [`PlaybackCamera::recorded_frame_numbers`].
//!
//! Settings: the recorded mode is the only mode of each stream; a settings document
//! asking for anything else is refused with the mode table's error (4.00 on the wire).
//! Depth and color streams are both required (the `/cams` resources need both); other
//! streams (infrared, motion) are ignored.

pub mod bag;
pub mod db3;

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use crate::advanced::{AdvancedConfig, AdvancedError};
use crate::backend::FrameClock;
use crate::camera::{Camera, CameraError, Serial, SerialError};
use crate::frame::{ColorFormat, ColorFrame, DepthFormat, DepthFrame};
use crate::intrinsics::{DistortionModel, Extrinsics, Intrinsics, Pose};
use crate::mode::{ModeTable, ResolutionModes, Stream};
use crate::settings::{ColorSettings, DepthSettings};

/// Most decoded pixel bytes a recording may hold (1 GiB, about 200 depth+color frame
/// pairs at 1280x720).
pub const MAX_RECORDING_BYTES: usize = 1 << 30;

/// Largest width or height of a recorded image, pixels.
pub const MAX_IMAGE_SIDE: u32 = 4096;

const NO_ADVANCED_MODE: &str = "a recording has no advanced mode";

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
    /// The recorded serial number is not 12 digits.
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

    /// One camera per device.
    pub(crate) fn finish(self) -> Result<Vec<PlaybackCamera>, PlaybackError> {
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
    fn finish(mut self, index: u32) -> Result<PlaybackCamera, PlaybackError> {
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
        Ok(PlaybackCamera {
            serial,
            model,
            modes,
            color_settings,
            depth_settings,
            color_intrinsics: color.intrinsics,
            depth_intrinsics: depth.intrinsics,
            depth_to_color,
            depth_scale,
            depth_frames,
            color_frames,
            state: Mutex::new(State::default()),
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

#[derive(Debug, Default)]
struct State {
    color: usize,
    depth: usize,
    clock: FrameClock,
}

/// One recorded device played back as a camera (see the module documentation).
#[derive(Debug)]
pub struct PlaybackCamera {
    serial: Serial,
    model: String,
    modes: ModeTable,
    color_settings: ColorSettings,
    depth_settings: DepthSettings,
    color_intrinsics: Intrinsics,
    depth_intrinsics: Intrinsics,
    depth_to_color: Extrinsics,
    depth_scale: f32,
    /// (recorded frame number, metres per unit, values).
    depth_frames: Vec<(u64, f32, Vec<u16>)>,
    /// (recorded frame number, pixels).
    color_frames: Vec<(u64, Vec<u8>)>,
    state: Mutex<State>,
}

impl PlaybackCamera {
    /// Opens a `.bag` or `.db3` recording (told apart by content, not by name) and
    /// returns one camera per recorded device.
    pub fn open(path: &Path) -> Result<Vec<Self>, PlaybackError> {
        let io = |source| PlaybackError::Io {
            path: path.display().to_string(),
            source,
        };
        let mut magic = [0u8; 16];
        let n = {
            use std::io::Read;
            let mut file = std::fs::File::open(path).map_err(io)?;
            let mut n = 0;
            while n < magic.len() {
                match file.read(&mut magic[n..]).map_err(io)? {
                    0 => break,
                    k => n += k,
                }
            }
            n
        };
        let magic = &magic[..n];
        let mut builder = DeviceBuilder::default();
        if magic.starts_with(bag::MAGIC) {
            bag::read(path, &mut builder)?;
        } else if magic.starts_with(db3::MAGIC) {
            db3::read(path, &mut builder)?;
        } else {
            return Err(PlaybackError::UnknownFormat {
                path: path.display().to_string(),
            });
        }
        builder.finish()
    }

    /// The recorded frame numbers of a stream, in playback order.
    pub fn recorded_frame_numbers(&self, stream: Stream) -> Vec<u64> {
        match stream {
            Stream::Depth => self.depth_frames.iter().map(|f| f.0).collect(),
            Stream::Color => self.color_frames.iter().map(|f| f.0).collect(),
        }
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // Every update is a few assignments; a panicking holder leaves it consistent.
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Advances a stream's cursor; returns (recording index, grab number, timestamp).
    fn next(&self, stream: Stream) -> (usize, u64, u64) {
        let mut guard = self.lock();
        let s = &mut *guard;
        let (cursor, len) = match stream {
            Stream::Depth => (&mut s.depth, self.depth_frames.len()),
            Stream::Color => (&mut s.color, self.color_frames.len()),
        };
        let index = *cursor;
        *cursor = (index + 1) % len.max(1);
        let (grab, timestamp_us) = s.clock.stamp(stream);
        (index, grab, timestamp_us)
    }
}

impl Camera for PlaybackCamera {
    fn serial(&self) -> Serial {
        self.serial
    }

    fn model(&self) -> &str {
        &self.model
    }

    fn stream_modes(&self) -> &ModeTable {
        &self.modes
    }

    fn color_settings(&self) -> ColorSettings {
        self.color_settings
    }

    fn set_color_settings(&self, settings: ColorSettings) -> Result<(), CameraError> {
        settings.validate(&self.modes)?;
        Ok(())
    }

    fn depth_settings(&self) -> DepthSettings {
        self.depth_settings
    }

    fn set_depth_settings(&self, settings: DepthSettings) -> Result<(), CameraError> {
        settings.validate(&self.modes)?;
        Ok(())
    }

    fn grab_color(&self, _timeout: Duration) -> Result<ColorFrame, CameraError> {
        let (index, frame_number, timestamp_us) = self.next(Stream::Color);
        let s = &self.color_settings;
        let data = self
            .color_frames
            .get(index)
            .map(|f| f.1.clone())
            .unwrap_or_default();
        Ok(ColorFrame {
            format: s.format,
            width: s.width,
            height: s.height,
            stride: s.width as usize * s.format.bytes_per_pixel(),
            timestamp_us,
            frame_number,
            data,
        })
    }

    fn grab_depth(&self, _timeout: Duration) -> Result<DepthFrame, CameraError> {
        let (index, frame_number, timestamp_us) = self.next(Stream::Depth);
        let s = &self.depth_settings;
        let (depth_scale, data) = self
            .depth_frames
            .get(index)
            .map_or((self.depth_scale, Vec::new()), |f| (f.1, f.2.clone()));
        Ok(DepthFrame {
            width: s.width,
            height: s.height,
            stride: s.width as usize,
            depth_scale,
            timestamp_us,
            frame_number,
            data,
        })
    }

    fn depth_intrinsics(&self) -> Result<Intrinsics, CameraError> {
        Ok(self.depth_intrinsics)
    }

    fn color_intrinsics(&self) -> Result<Intrinsics, CameraError> {
        Ok(self.color_intrinsics)
    }

    fn depth_to_color(&self) -> Result<Extrinsics, CameraError> {
        Ok(self.depth_to_color)
    }

    fn depth_scale(&self) -> f32 {
        self.depth_scale
    }

    fn advanced_config(&self) -> Result<AdvancedConfig, CameraError> {
        Err(AdvancedError::NotSupported(NO_ADVANCED_MODE.into()).into())
    }

    fn set_advanced_config(&self, _config: &AdvancedConfig) -> Result<(), CameraError> {
        Err(AdvancedError::NotSupported(NO_ADVANCED_MODE.into()).into())
    }

    fn true_pose(&self) -> Option<Pose> {
        None
    }
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
