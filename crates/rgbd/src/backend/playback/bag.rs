//! ROS 1 bag v2.0 recordings (`.bag`, librealsense up to 2.56).
//!
//! Topics read (d = device, s = sensor, `<S>` = `Depth_0` or `Color_0`):
//!
//! | topic | type | use |
//! |---|---|---|
//! | `/device_d/info` | diagnostic_msgs/KeyValue | serial number, name |
//! | `/device_d/sensor_s/<S>/info` | realsense_msgs/StreamInfo | fps, encoding |
//! | `/device_d/sensor_s/<S>/info/camera_info` | sensor_msgs/CameraInfo | intrinsics |
//! | `/device_d/sensor_s/<S>/image/data` | sensor_msgs/Image | frames |
//! | `/device_d/sensor_s/<S>/tf/<ref>` | geometry_msgs/Transform | extrinsics |
//! | `/device_d/sensor_s/option/Depth_Units/value` | std_msgs/Float32 | depth units |
//!
//! librealsense's quirks: its `Image` header writes the string `"1"` in the
//! `frame_id` slot and then appends a float32 with the frame's depth units after the
//! pixel data (older files have neither: the `Depth_Units` option is used); the
//! CameraInfo's `distortion_model` holds librealsense's model name ("Brown
//! Conrady"). The Transform is the one from the reference stream to this stream;
//! its quaternion is converted with the usual formula into librealsense's
//! column-major rotation, which reproduces what librealsense 2.56.5's own playback
//! returns (the tests compare a recording with a rotated depth -> color transform).
//!
//! The container is parsed by the `rosbag` crate. Before handing it the file, the
//! record headers are walked here once (without reading chunk data) so that damage
//! the crate would not survive is refused with an error: an index position beyond
//! the end of the file, chunks larger than [`MAX_CHUNK_BYTES`], or compression other
//! than `none` and `lz4` (librealsense writes no other). A crafted LZ4 chunk can
//! still make the crate inflate up to about 255 times its compressed size before it
//! compares the result with the recorded size.

use std::collections::HashMap;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

use rosbag::{ChunkRecord, MessageRecord, RosBag};

use super::recording::{
    DeviceBuilder, Event, Image, Kind, Pixels, PlaybackError, TopicPath, camera_matrix_intrinsics,
    check_image, check_text,
};
use crate::intrinsics::{DistortionModel, Extrinsics, Intrinsics};

/// The first bytes of a ROS 1 bag v2.0.
pub(crate) const MAGIC: &[u8] = b"#ROSBAG V2.0\n";

/// Largest (decompressed) chunk accepted, bytes.
pub const MAX_CHUNK_BYTES: u64 = 256 << 20;

/// Largest record header accepted, bytes (librealsense's are under 200).
const MAX_HEADER_BYTES: u32 = 64 * 1024;

fn bag_error(e: impl std::fmt::Display) -> PlaybackError {
    PlaybackError::Bag(e.to_string())
}

/// The fields of a record header: `name=value` entries, each prefixed by its length.
fn header_fields(header: &[u8]) -> Result<HashMap<&str, &[u8]>, PlaybackError> {
    let mut fields = HashMap::new();
    let mut rest = header;
    while !rest.is_empty() {
        let (len, tail) = rest
            .split_first_chunk::<4>()
            .ok_or_else(|| bag_error("truncated record header field"))?;
        let len = u32::from_le_bytes(*len) as usize;
        let field = tail
            .get(..len)
            .ok_or_else(|| bag_error("record header field runs past its header"))?;
        rest = &tail[len..];
        let eq = field
            .iter()
            .position(|&b| b == b'=')
            .ok_or_else(|| bag_error("record header field without '='"))?;
        let name = std::str::from_utf8(&field[..eq])
            .map_err(|_| bag_error("record header field name is not UTF-8"))?;
        fields.insert(name, &field[eq + 1..]);
    }
    Ok(fields)
}

fn read_u32(file: &mut std::fs::File) -> Result<u32, PlaybackError> {
    let mut b = [0u8; 4];
    file.read_exact(&mut b).map_err(bag_error)?;
    Ok(u32::from_le_bytes(b))
}

fn field_u64(fields: &HashMap<&str, &[u8]>, name: &str) -> Result<Option<u64>, PlaybackError> {
    match fields.get(name) {
        None => Ok(None),
        Some(v) if v.len() == 8 => {
            let mut b = [0u8; 8];
            b.copy_from_slice(v);
            Ok(Some(u64::from_le_bytes(b)))
        }
        Some(v) if v.len() == 4 => {
            let mut b = [0u8; 4];
            b.copy_from_slice(v);
            Ok(Some(u64::from(u32::from_le_bytes(b))))
        }
        Some(_) => Err(bag_error(format!("header field {name} has a bad length"))),
    }
}

/// Reads one record's header (bounded); its data length follows it.
fn record_header(file: &mut std::fs::File) -> Result<Vec<u8>, PlaybackError> {
    let len = read_u32(file)?;
    if len > MAX_HEADER_BYTES {
        return Err(PlaybackError::TooLarge {
            what: "bag record header".into(),
            size: u64::from(len),
            limit: u64::from(MAX_HEADER_BYTES),
        });
    }
    let mut header = vec![0u8; len as usize];
    file.read_exact(&mut header).map_err(bag_error)?;
    Ok(header)
}

/// Walks the record headers of the whole file (see the module documentation).
fn check_container(path: &Path) -> Result<(), PlaybackError> {
    let mut file = std::fs::File::open(path).map_err(|source| PlaybackError::Io {
        path: path.display().to_string(),
        source,
    })?;
    let file_len = file.metadata().map_err(bag_error)?.len();
    file.seek(SeekFrom::Start(MAGIC.len() as u64))
        .map_err(bag_error)?;
    let header = record_header(&mut file)?;
    let fields = header_fields(&header)?;
    let data_len = read_u32(&mut file)?;
    if fields.get("op").copied() != Some(&[0x03][..]) {
        return Err(bag_error("the first record is not the bag header"));
    }
    let index_pos = field_u64(&fields, "index_pos")?
        .ok_or_else(|| bag_error("bag header without index_pos"))?;
    let mut pos = file
        .stream_position()
        .map_err(bag_error)?
        .saturating_add(u64::from(data_len));
    if index_pos < pos || index_pos > file_len {
        return Err(bag_error(format!(
            "index position {index_pos} outside the file ({file_len} bytes): truncated?"
        )));
    }
    while pos < index_pos {
        file.seek(SeekFrom::Start(pos)).map_err(bag_error)?;
        let header = record_header(&mut file)?;
        let fields = header_fields(&header)?;
        let data_len = read_u32(&mut file)?;
        let end = file
            .stream_position()
            .map_err(bag_error)?
            .saturating_add(u64::from(data_len));
        if end > index_pos {
            return Err(bag_error(format!(
                "record at {pos} runs past the index position: truncated?"
            )));
        }
        if fields.get("op").copied() == Some(&[0x05][..]) {
            let compression = fields.get("compression").copied();
            if !matches!(compression, Some(b"none" | b"lz4")) {
                return Err(PlaybackError::Unsupported(format!(
                    "bag chunk compression {:?} (librealsense writes none or lz4)",
                    compression.map(String::from_utf8_lossy)
                )));
            }
            let size =
                field_u64(&fields, "size")?.ok_or_else(|| bag_error("chunk without size"))?;
            if size > MAX_CHUNK_BYTES {
                return Err(PlaybackError::TooLarge {
                    what: "bag chunk".into(),
                    size,
                    limit: MAX_CHUNK_BYTES,
                });
            }
        }
        pos = end;
    }
    Ok(())
}

/// Reads a `.bag` recording into `builder`.
pub(crate) fn read(path: &Path, builder: &mut DeviceBuilder) -> Result<(), PlaybackError> {
    check_container(path)?;
    let bag = RosBag::new(path).map_err(bag_error)?;
    let mut connections: HashMap<u32, (String, String)> = HashMap::new();
    for record in bag.chunk_records() {
        let ChunkRecord::Chunk(chunk) = record.map_err(bag_error)? else {
            continue;
        };
        for message in chunk.messages() {
            match message.map_err(bag_error)? {
                MessageRecord::Connection(c) => {
                    connections.insert(c.id, (c.topic.to_owned(), c.tp.to_owned()));
                }
                MessageRecord::MessageData(m) => {
                    let (topic, tp) = connections.get(&m.conn_id).ok_or_else(|| {
                        bag_error(format!("message on unknown connection {}", m.conn_id))
                    })?;
                    if let Some(event) = decode(topic, tp, m.data)? {
                        builder.add(event)?;
                    }
                }
            }
        }
    }
    Ok(())
}

/// A little-endian ROS 1 message reader: no alignment, strings and arrays prefixed
/// by a u32 length. Every read is bounded by the message.
struct Ros1<'a> {
    topic: &'a str,
    data: &'a [u8],
}

impl<'a> Ros1<'a> {
    fn short(&self) -> PlaybackError {
        PlaybackError::message(self.topic, "message ends early")
    }

    fn bytes(&mut self, n: usize) -> Result<&'a [u8], PlaybackError> {
        if n > self.data.len() {
            return Err(self.short());
        }
        let (head, tail) = self.data.split_at(n);
        self.data = tail;
        Ok(head)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], PlaybackError> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.bytes(N)?);
        Ok(out)
    }

    fn u8(&mut self) -> Result<u8, PlaybackError> {
        Ok(self.array::<1>()?[0])
    }

    fn u32(&mut self) -> Result<u32, PlaybackError> {
        self.array().map(u32::from_le_bytes)
    }

    fn f32(&mut self) -> Result<f32, PlaybackError> {
        self.array().map(f32::from_le_bytes)
    }

    fn f64(&mut self) -> Result<f64, PlaybackError> {
        self.array().map(f64::from_le_bytes)
    }

    fn blob(&mut self) -> Result<&'a [u8], PlaybackError> {
        let n = self.u32()? as usize;
        self.bytes(n)
    }

    fn string(&mut self) -> Result<&'a str, PlaybackError> {
        let topic = self.topic;
        let s = std::str::from_utf8(self.blob()?)
            .map_err(|_| PlaybackError::message(topic, "string is not UTF-8"))?;
        check_text(topic, s)?;
        Ok(s)
    }

    /// std_msgs/Header: seq, stamp, frame_id. Returns (seq, frame_id).
    fn header(&mut self) -> Result<(u32, &'a str), PlaybackError> {
        let seq = self.u32()?;
        self.bytes(8)?;
        Ok((seq, self.string()?))
    }
}

fn decode(topic: &str, tp: &str, data: &[u8]) -> Result<Option<Event>, PlaybackError> {
    let Some(path) = TopicPath::parse(topic) else {
        return Ok(None);
    };
    let expect = |wanted: &str| {
        if tp == wanted {
            Ok(())
        } else {
            Err(PlaybackError::message(
                topic,
                format!("type {tp}, expected {wanted}"),
            ))
        }
    };
    let mut m = Ros1 { topic, data };
    let device = path.device;
    let rest = path.rest.as_slice();
    let event = match (path.sensor, path.stream, rest) {
        (None, None, ["info"]) => {
            expect("diagnostic_msgs/KeyValue")?;
            let key = m.string()?.to_owned();
            let value = m.string()?.to_owned();
            Event::DeviceInfo { device, key, value }
        }
        (Some(sensor), Some(stream), ["info"]) => {
            expect("realsense_msgs/StreamInfo")?;
            let fps = m.u32()?;
            let encoding = m.string()?;
            let pixels = Pixels::from_name(encoding).ok_or_else(|| {
                PlaybackError::Unsupported(format!("{topic}: encoding {encoding:?}"))
            })?;
            builder_sensor(device, stream, sensor, fps, pixels)
        }
        (Some(_), Some(stream), ["info", "camera_info"]) => {
            expect("sensor_msgs/CameraInfo")?;
            Event::Intrinsics {
                device,
                stream,
                intrinsics: camera_info(&mut m)?,
            }
        }
        (Some(sensor), None, ["option", name, "value"]) => {
            expect("std_msgs/Float32")?;
            Event::OptionValue {
                device,
                sensor,
                name: (*name).to_owned(),
                value: m.f32()?,
            }
        }
        (Some(_), Some(stream), ["image", "data"]) => {
            expect("sensor_msgs/Image")?;
            Event::Frame {
                device,
                stream,
                image: image(&mut m)?,
            }
        }
        (Some(_), Some(stream), ["tf", reference]) => {
            expect("geometry_msgs/Transform")?;
            Event::FromReference {
                device,
                stream,
                reference: (*reference).to_owned(),
                extrinsics: transform(&mut m)?,
            }
        }
        _ => return Ok(None),
    };
    Ok(Some(event))
}

/// A StreamInfo carries the stream's sensor too; the sensor event is implied.
fn builder_sensor(device: u32, stream: Kind, sensor: u32, fps: u32, pixels: Pixels) -> Event {
    Event::StreamInfo {
        device,
        stream,
        fps,
        pixels,
        sensor: Some(sensor),
    }
}

fn camera_info(m: &mut Ros1<'_>) -> Result<Intrinsics, PlaybackError> {
    m.header()?;
    let height = m.u32()?;
    let width = m.u32()?;
    let model_name = m.string()?;
    let model = DistortionModel::from_name(model_name).ok_or_else(|| {
        PlaybackError::Unsupported(format!("{}: distortion model {model_name:?}", m.topic))
    })?;
    let n = m.u32()? as usize;
    if n > 16 {
        return Err(PlaybackError::message(
            m.topic,
            format!("{n} distortion coefficients"),
        ));
    }
    let mut coeffs = [0.0f32; 5];
    for i in 0..n {
        let c = m.f64()?;
        if let Some(slot) = coeffs.get_mut(i) {
            *slot = c as f32;
        }
    }
    let mut k = [0.0f64; 9];
    for v in &mut k {
        *v = m.f64()?;
    }
    Ok(camera_matrix_intrinsics(width, height, &k, model, coeffs))
}

fn image(m: &mut Ros1<'_>) -> Result<Image, PlaybackError> {
    let (seq, frame_id) = m.header()?;
    let height = m.u32()?;
    let width = m.u32()?;
    let encoding = m.string()?;
    let pixels = Pixels::from_name(encoding)
        .ok_or_else(|| PlaybackError::Unsupported(format!("{}: encoding {encoding:?}", m.topic)))?;
    let big_endian = m.u8()? != 0;
    let step = m.u32()?;
    let data = m.blob()?;
    check_image(m.topic, width, height, pixels, data.len())?;
    if step as usize != width as usize * pixels.bytes_per_pixel() {
        return Err(PlaybackError::message(
            m.topic,
            format!("row step {step} for {width} pixels of {pixels:?}"),
        ));
    }
    let mut data = data.to_vec();
    if big_endian && pixels == Pixels::Z16 {
        for px in data.chunks_exact_mut(2) {
            px.swap(0, 1);
        }
    }
    // librealsense's header version "1" announces the trailing depth units.
    let depth_units = if frame_id == "1" && m.data.len() >= 4 {
        Some(m.f32()?)
    } else {
        None
    };
    Ok(Image {
        frame_number: u64::from(seq),
        width,
        height,
        pixels,
        data,
        depth_units,
    })
}

/// geometry_msgs/Transform: translation (x, y, z), rotation quaternion (x, y, z, w).
fn transform(m: &mut Ros1<'_>) -> Result<Extrinsics, PlaybackError> {
    let mut t = [0.0f64; 3];
    for v in &mut t {
        *v = m.f64()?;
    }
    let mut q = [0.0f64; 4];
    for v in &mut q {
        *v = m.f64()?;
    }
    let [x, y, z, w] = q;
    let norm = (x * x + y * y + z * z + w * w).sqrt();
    if !(norm.is_finite() && (norm - 1.0).abs() < 1e-3) {
        return Err(PlaybackError::message(
            m.topic,
            format!("rotation quaternion of norm {norm}"),
        ));
    }
    // The rotation matrix of (x, y, z, w), row-major, into librealsense's
    // column-major slots.
    let r = [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - z * w),
            2.0 * (x * z + y * w),
        ],
        [
            2.0 * (x * y + z * w),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - x * w),
        ],
        [
            2.0 * (x * z - y * w),
            2.0 * (y * z + x * w),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ];
    let mut rotation = [0.0f32; 9];
    for (row, values) in r.iter().enumerate() {
        for (col, v) in values.iter().enumerate() {
            rotation[col * 3 + row] = *v as f32;
        }
    }
    Ok(Extrinsics {
        rotation,
        translation: [t[0] as f32, t[1] as f32, t[2] as f32],
    })
}
