//! A D400 camera served through librealsense: the [`Camera`] implementation.

use std::ffi::c_int;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use super::ffi::{
    self, CameraInfo, Device, DeviceList, Frame, FrameQueue, Lib, Profile, ProfileData, RsError,
    RsIntrinsics, Sensor,
};
use super::{D400, GrabMode};
use crate::advanced::{AdvancedConfig, AdvancedError};
use crate::backend::FrameClock;
use crate::camera::{AdvancedMode, Camera, CameraError, Serial};
use crate::frame::{ColorFormat, ColorFrame, DepthFrame};
use crate::intrinsics::{DistortionModel, Extrinsics, Intrinsics, Pose};
use crate::mode::{ModeTable, Stream};
use crate::settings::{ColorSettings, DepthSettings};

/// The librealsense format of a color format.
pub(super) fn rs_color_format(format: ColorFormat) -> c_int {
    match format {
        ColorFormat::Rgb8 => ffi::FORMAT_RGB8,
        ColorFormat::Bgr8 => ffi::FORMAT_BGR8,
        ColorFormat::Rgba8 => ffi::FORMAT_RGBA8,
        ColorFormat::Bgra8 => ffi::FORMAT_BGRA8,
    }
}

/// A stream profile as the settings ask for it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Wanted {
    stream: c_int,
    format: c_int,
    width: u32,
    height: u32,
    fps: u32,
}

impl Wanted {
    fn depth(s: &DepthSettings) -> Self {
        Self {
            stream: ffi::STREAM_DEPTH,
            format: ffi::FORMAT_Z16,
            width: s.width,
            height: s.height,
            fps: s.fps,
        }
    }

    fn color(s: &ColorSettings) -> Self {
        Self {
            stream: ffi::STREAM_COLOR,
            format: rs_color_format(s.format),
            width: s.width,
            height: s.height,
            fps: s.fps,
        }
    }

    fn matches(&self, d: &ProfileData) -> bool {
        d.stream == self.stream
            && d.format == self.format
            && i64::from(d.width) == i64::from(self.width)
            && i64::from(d.height) == i64::from(self.height)
            && i64::from(d.fps) == i64::from(self.fps)
    }
}

/// A sensor streaming into a queue (continuous mode).
struct Session {
    queue: FrameQueue,
    /// The profile the sensor was opened with.
    want: Wanted,
}

/// One sensor and its streaming session, behind one lock: the open/start/stop/close
/// of a sensor never interleave.
struct Slot {
    name: &'static str,
    sensor: Sensor,
    session: Mutex<Option<Session>>,
}

impl Slot {
    fn lock(&self) -> MutexGuard<'_, Option<Session>> {
        // The session is replaced whole; a panicking holder leaves a usable value.
        self.session.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Calls `f` with the sensor's profile that matches `want`.
    fn with_profile<R>(
        &self,
        want: Wanted,
        f: impl FnOnce(&Profile<'_>, ProfileData) -> Result<R, RsError>,
    ) -> Result<R, CameraError> {
        let list = self.sensor.profiles()?;
        for i in 0..list.len()? {
            let profile = list.get(i)?;
            let data = profile.data()?;
            if want.matches(&data) {
                return Ok(f(&profile, data)?);
            }
        }
        Err(CameraError::Device(format!(
            "the {} sensor offers no {}x{} at {} fps in format {}",
            self.name, want.width, want.height, want.fps, want.format
        )))
    }

    /// Opens the sensor with profile `want` and starts it into a new queue.
    fn start(&self, lib: &Arc<Lib>, want: Wanted) -> Result<FrameQueue, CameraError> {
        let queue = FrameQueue::new(lib, 1)?;
        self.with_profile(want, |p, _| self.sensor.open(p))?;
        if let Err(e) = self.sensor.start(&queue) {
            let _ = self.sensor.close();
            return Err(e.into());
        }
        Ok(queue)
    }

    fn stop_session(&self, session: &mut Option<Session>) -> Result<(), RsError> {
        if session.take().is_some() {
            let stopped = self.sensor.stop();
            let closed = self.sensor.close();
            stopped?;
            closed?;
        }
        Ok(())
    }

    /// One frame with profile `want`, as `mode` says.
    fn grab(
        &self,
        lib: &Arc<Lib>,
        want: Wanted,
        mode: GrabMode,
        timeout: Duration,
    ) -> Result<Frame, CameraError> {
        let timeout_ms = u32::try_from(timeout.as_millis()).unwrap_or(u32::MAX);
        let timed_out = CameraError::Timeout {
            timeout_ms: u64::from(timeout_ms),
        };
        let mut session = self.lock();
        match mode {
            GrabMode::PerRequest => {
                // The mode is fixed per camera: no session was started.
                let queue = self.start(lib, want)?;
                let waited = wait_wanted(&queue, &want, timeout);
                let stopped = self.sensor.stop();
                let closed = self.sensor.close();
                let frame = waited?;
                stopped?;
                closed?;
                frame.ok_or(timed_out)
            }
            GrabMode::Streaming => {
                if session.as_ref().map(|s| s.want) != Some(want) {
                    self.stop_session(&mut session)?;
                    let queue = self.start(lib, want)?;
                    *session = Some(Session { queue, want });
                }
                let Some(s) = session.as_ref() else {
                    return Err(timed_out);
                };
                let mut newest = None;
                while let Some(frame) = s.queue.poll()? {
                    if is_wanted(&frame, &want)? {
                        newest = Some(frame);
                    }
                }
                match newest {
                    Some(frame) => Ok(frame),
                    None => wait_wanted(&s.queue, &want, timeout)?.ok_or(timed_out),
                }
            }
        }
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        let mut session = self.lock();
        // Nothing to report to on drop; the sensor is released right after.
        let _ = self.stop_session(&mut session);
    }
}

#[derive(Debug)]
struct State {
    color: ColorSettings,
    depth: DepthSettings,
    depth_scale: f32,
    clock: FrameClock,
}

/// An Intel RealSense D400 camera reached through librealsense.
pub struct RealSenseCamera {
    lib: Arc<Lib>,
    serial: Serial,
    model: String,
    /// The depth sensor's stereo baseline, read once (a device's calibration).
    baseline_m: f32,
    modes: ModeTable,
    mode: GrabMode,
    depth: Slot,
    color: Slot,
    state: Mutex<State>,
    connected: AtomicBool,
    // Last: the sensors above belong to it.
    device: Device,
}

impl std::fmt::Debug for RealSenseCamera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RealSenseCamera")
            .field("serial", &self.serial)
            .field("model", &self.model)
            .field("mode", &self.mode)
            .finish()
    }
}

impl RealSenseCamera {
    /// The camera of `device`, or why it cannot be served.
    pub(super) fn new(lib: Arc<Lib>, device: Device, mode: GrabMode) -> Result<Self, String> {
        let text = |what| device.info(what).map_err(|e| e.to_string());
        let name = text(CameraInfo::Name)?.unwrap_or_else(|| "unnamed device".to_owned());
        let line = text(CameraInfo::ProductLine)?;
        if line.as_deref() != Some(D400) {
            return Err(format!(
                "{name}: product line {} is not {D400}",
                line.as_deref().unwrap_or("(none)")
            ));
        }
        let serial_text =
            text(CameraInfo::SerialNumber)?.ok_or_else(|| format!("{name}: no serial number"))?;
        let serial = Serial::parse(&serial_text).map_err(|e| format!("{name}: {e}"))?;
        let mut depth = None;
        let mut color = None;
        for sensor in device.sensors().map_err(|e| e.to_string())? {
            let kind = sensor_kind(&sensor).map_err(|e| e.to_string())?;
            match kind {
                Some(ffi::STREAM_DEPTH) if depth.is_none() => depth = Some(sensor),
                Some(ffi::STREAM_COLOR) if color.is_none() => color = Some(sensor),
                _ => {}
            }
        }
        let slot = |name, sensor: Option<Sensor>| {
            sensor
                .map(|sensor| Slot {
                    name,
                    sensor,
                    session: Mutex::new(None),
                })
                .ok_or_else(|| format!("{serial}: no {name} sensor"))
        };
        let depth = slot("depth", depth)?;
        let color = slot("color", color)?;
        let depth_scale = depth
            .sensor
            .option(ffi::OPTION_DEPTH_UNITS)
            .map_err(|e| format!("{serial}: {e}"))?;
        let baseline_mm = depth
            .sensor
            .option(ffi::OPTION_STEREO_BASELINE)
            .map_err(|e| format!("{serial}: the stereo baseline: {e}"))?;
        if !(baseline_mm.is_finite() && baseline_mm > 0.0) {
            return Err(format!(
                "{serial}: the stereo baseline is {baseline_mm} mm, not a positive length"
            ));
        }
        Ok(Self {
            lib,
            serial,
            model: name,
            baseline_m: baseline_mm / 1000.0,
            modes: ModeTable::d415(),
            mode,
            depth,
            color,
            state: Mutex::new(State {
                color: ColorSettings::default(),
                depth: DepthSettings::default(),
                depth_scale,
                clock: FrameClock::default(),
            }),
            connected: AtomicBool::new(true),
            device,
        })
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // Single-assignment updates: consistent after a panic.
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// How this camera grabs.
    pub fn grab_mode(&self) -> GrabMode {
        self.mode
    }

    pub(super) fn is_in(&self, list: &DeviceList) -> Result<bool, RsError> {
        list.contains(&self.device)
    }

    pub(super) fn set_disconnected(&self) {
        self.connected.store(false, Ordering::SeqCst);
    }

    fn check_connected(&self) -> Result<(), CameraError> {
        if self.connected.load(Ordering::SeqCst) {
            Ok(())
        } else {
            Err(CameraError::Disconnected {
                serial: self.serial,
            })
        }
    }

    fn require_advanced(&self) -> Result<(), CameraError> {
        if self.device.advanced_mode_enabled()? {
            Ok(())
        } else {
            Err(CameraError::AdvancedModeUnavailable {
                serial: self.serial,
            })
        }
    }

    fn refresh_depth_scale(&self) -> Result<f32, CameraError> {
        let scale = self.depth.sensor.option(ffi::OPTION_DEPTH_UNITS)?;
        self.lock().depth_scale = scale;
        Ok(scale)
    }
}

/// Which stream a sensor serves: depth if it offers Z16 depth, else color if it offers
/// color, else `None`.
fn sensor_kind(sensor: &Sensor) -> Result<Option<c_int>, RsError> {
    let list = sensor.profiles()?;
    let mut kind = None;
    for i in 0..list.len()? {
        let d = list.get(i)?.data()?;
        if d.stream == ffi::STREAM_DEPTH && d.format == ffi::FORMAT_Z16 {
            return Ok(Some(ffi::STREAM_DEPTH));
        }
        if d.stream == ffi::STREAM_COLOR {
            kind = Some(ffi::STREAM_COLOR);
        }
    }
    Ok(kind)
}

/// Whether `frame` has the format and size `want` asks for. A frame of the stream's
/// previous profile can still arrive after the stream restarts with another (the
/// software device's injector may be rendering one just then); grabs pass it over.
fn is_wanted(frame: &Frame, want: &Wanted) -> Result<bool, RsError> {
    let format = frame.profile()?.data()?.format;
    let (width, height, _) = frame.geometry()?;
    Ok(format == want.format
        && u32::try_from(width).ok() == Some(want.width)
        && u32::try_from(height).ok() == Some(want.height))
}

/// The first frame of `queue` that [`is_wanted`], waiting up to `timeout` in all.
fn wait_wanted(
    queue: &FrameQueue,
    want: &Wanted,
    timeout: Duration,
) -> Result<Option<Frame>, RsError> {
    let deadline = Instant::now() + timeout;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let left_ms = u32::try_from(left.as_millis()).unwrap_or(u32::MAX);
        match queue.wait(left_ms)? {
            Some(frame) if is_wanted(&frame, want)? => return Ok(Some(frame)),
            Some(_) if !left.is_zero() => {}
            _ => return Ok(None),
        }
    }
}

/// The rows of a frame with `row_bytes` of pixels per row, without padding.
fn packed_rows(frame: &Frame, want: &Wanted, bpp: usize) -> Result<Vec<u8>, CameraError> {
    let profile = frame.profile()?.data()?;
    let (width, height, stride) = frame.geometry()?;
    let mismatch = || {
        CameraError::Device(format!(
            "frame is {width}x{height} (format {}), settings ask for {}x{} (format {})",
            profile.format, want.width, want.height, want.format
        ))
    };
    if !is_wanted(frame, want)? {
        return Err(mismatch());
    }
    let row = want.width as usize * bpp;
    let stride = usize::try_from(stride).map_err(|_| mismatch())?;
    let rows = want.height as usize;
    let data = frame.data()?;
    if stride < row || rows > 0 && data.len() < stride * (rows - 1) + row {
        return Err(CameraError::Device(format!(
            "frame holds {} bytes, {rows} rows of {row} bytes with stride {stride} need more",
            data.len()
        )));
    }
    let mut out = Vec::with_capacity(row * rows);
    for r in 0..rows {
        out.extend_from_slice(&data[r * stride..r * stride + row]);
    }
    Ok(out)
}

fn intrinsics(k: RsIntrinsics) -> Result<Intrinsics, CameraError> {
    let model = match k.model {
        0 => DistortionModel::None,
        1 => DistortionModel::ModifiedBrownConrady,
        2 => DistortionModel::InverseBrownConrady,
        4 => DistortionModel::BrownConrady,
        5 => DistortionModel::KannalaBrandt4,
        other => {
            return Err(CameraError::Device(format!(
                "distortion model {other} is not supported"
            )));
        }
    };
    let size = |v: c_int| {
        u32::try_from(v).map_err(|_| CameraError::Device(format!("image size {v} in intrinsics")))
    };
    Ok(Intrinsics {
        width: size(k.width)?,
        height: size(k.height)?,
        ppx: k.ppx,
        ppy: k.ppy,
        fx: k.fx,
        fy: k.fy,
        model,
        coeffs: k.coeffs,
    })
}

/// A device's advanced-mode JSON as our document: keys of this crate's D400 key set
/// are kept (and checked), keys it does not know are left out.
fn device_config(json: &str) -> Result<AdvancedConfig, CameraError> {
    let bad = |e: String| CameraError::Device(format!("advanced-mode JSON from the device: {e}"));
    let doc: serde_json::Value = serde_json::from_str(json).map_err(|e| bad(e.to_string()))?;
    let map = match doc {
        serde_json::Value::Object(mut map) => match map.remove("parameters") {
            Some(serde_json::Value::Object(params)) => params,
            Some(_) => return Err(bad("\"parameters\" is not an object".to_owned())),
            None => map,
        },
        _ => return Err(bad("not an object".to_owned())),
    };
    let mut config = AdvancedConfig::default();
    for (key, value) in map {
        let value = match value {
            serde_json::Value::String(s) => s,
            other => other.to_string(),
        };
        match config.set(&key, &value) {
            Ok(_) | Err(AdvancedError::UnknownKey(_)) => {}
            Err(e) => return Err(bad(e.to_string())),
        }
    }
    Ok(config)
}

impl Camera for RealSenseCamera {
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
        self.lock().color
    }

    fn set_color_settings(&self, settings: ColorSettings) -> Result<(), CameraError> {
        settings.validate(&self.modes)?;
        self.color
            .with_profile(Wanted::color(&settings), |_, _| Ok(()))?;
        self.lock().color = settings;
        Ok(())
    }

    fn depth_settings(&self) -> DepthSettings {
        self.lock().depth
    }

    fn set_depth_settings(&self, settings: DepthSettings) -> Result<(), CameraError> {
        settings.validate(&self.modes)?;
        self.depth
            .with_profile(Wanted::depth(&settings), |_, _| Ok(()))?;
        self.lock().depth = settings;
        Ok(())
    }

    fn grab_color(&self, timeout: Duration) -> Result<ColorFrame, CameraError> {
        self.check_connected()?;
        let settings = self.lock().color;
        let want = Wanted::color(&settings);
        let frame = self.color.grab(&self.lib, want, self.mode, timeout)?;
        let bpp = settings.format.bytes_per_pixel();
        let data = packed_rows(&frame, &want, bpp)?;
        let captured_us = frame.host_time_us()?;
        drop(frame);
        let (frame_number, arrived_us) = self.lock().clock.stamp(Stream::Color);
        let timestamp_us = captured_us.unwrap_or(arrived_us);
        Ok(ColorFrame {
            format: settings.format,
            width: settings.width,
            height: settings.height,
            stride: settings.width as usize * bpp,
            timestamp_us,
            frame_number,
            data,
        })
    }

    fn grab_depth(&self, timeout: Duration) -> Result<DepthFrame, CameraError> {
        self.check_connected()?;
        let settings = self.lock().depth;
        let want = Wanted::depth(&settings);
        let frame = self.depth.grab(&self.lib, want, self.mode, timeout)?;
        let bytes = packed_rows(&frame, &want, 2)?;
        let captured_us = frame.host_time_us()?;
        drop(frame);
        let depth_scale = self.refresh_depth_scale()?;
        let (frame_number, arrived_us) = self.lock().clock.stamp(Stream::Depth);
        let timestamp_us = captured_us.unwrap_or(arrived_us);
        Ok(DepthFrame {
            width: settings.width,
            height: settings.height,
            stride: settings.width as usize,
            depth_scale,
            timestamp_us,
            frame_number,
            data: bytes
                .chunks_exact(2)
                .map(|b| u16::from_le_bytes([b[0], b[1]]))
                .collect(),
        })
    }

    fn depth_intrinsics(&self) -> Result<Intrinsics, CameraError> {
        let want = Wanted::depth(&self.lock().depth);
        intrinsics(self.depth.with_profile(want, |p, _| p.intrinsics())?)
    }

    fn color_intrinsics(&self) -> Result<Intrinsics, CameraError> {
        let want = Wanted::color(&self.lock().color);
        intrinsics(self.color.with_profile(want, |p, _| p.intrinsics())?)
    }

    fn depth_to_color(&self) -> Result<Extrinsics, CameraError> {
        let (depth, color) = {
            let s = self.lock();
            (Wanted::depth(&s.depth), Wanted::color(&s.color))
        };
        let color_list = self.color.sensor.profiles()?;
        for i in 0..color_list.len()? {
            let c = color_list.get(i)?;
            if color.matches(&c.data()?) {
                let e = self.depth.with_profile(depth, |d, _| d.extrinsics_to(&c))?;
                return Ok(Extrinsics {
                    rotation: e.rotation,
                    translation: e.translation,
                });
            }
        }
        Err(CameraError::Device(format!(
            "the color sensor offers no {}x{} at {} fps",
            color.width, color.height, color.fps
        )))
    }

    fn stereo_baseline_m(&self) -> Option<f32> {
        Some(self.baseline_m)
    }

    fn depth_scale(&self) -> f32 {
        // The last value read from the device (at start, each depth grab, each
        // advanced-config load); the trait cannot report a failed read.
        self.lock().depth_scale
    }

    fn advanced_mode(&self) -> Option<&dyn AdvancedMode> {
        Some(self)
    }

    fn true_pose(&self) -> Option<Pose> {
        None
    }
}

/// Every D400 has the advanced mode; while it is disabled on the device, both calls
/// answer [`CameraError::AdvancedModeUnavailable`].
impl AdvancedMode for RealSenseCamera {
    fn advanced_config(&self) -> Result<AdvancedConfig, CameraError> {
        self.require_advanced()?;
        let mut doc = device_config(&self.device.serialize_json()?)?;
        let depth = self.lock().depth;
        doc.set_depth_mode(&depth)?;
        Ok(doc)
    }

    fn set_advanced_config(&self, config: &AdvancedConfig) -> Result<(), CameraError> {
        self.require_advanced()?;
        let depth = config.depth_mode(self.lock().depth);
        depth.validate(&self.modes)?;
        self.depth
            .with_profile(Wanted::depth(&depth), |_, _| Ok(()))?;
        self.device.load_json(&config.to_json())?;
        self.lock().depth = depth;
        self.refresh_depth_scale()?;
        Ok(())
    }
}
