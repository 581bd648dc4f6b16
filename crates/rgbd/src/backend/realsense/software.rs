//! A virtual D415 inside librealsense: a software device fed by the synthetic camera.

use std::ffi::c_int;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use super::D400;
use super::RealSenseError;
use super::camera::rs_color_format;
use super::ffi::{
    self, CameraInfo, Context, InjectedFrame, Lib, RsExtrinsics, RsIntrinsics, RsVideoStream,
    SoftwareDevice, SoftwareSensor,
};
use crate::backend::synthetic::SyntheticCamera;
use crate::camera::{Camera, Serial};
use crate::d415;
use crate::intrinsics::Intrinsics;
use crate::mode::ModeTable;
use crate::settings::{ColorSettings, DepthSettings};

/// How often an idle injector looks whether its sensor was started.
const IDLE_POLL: Duration = Duration::from_millis(2);

/// What one added profile is, in our terms.
#[derive(Debug, Clone, Copy)]
enum Mode {
    Depth(DepthSettings),
    Color(ColorSettings),
}

impl Mode {
    fn fps(&self) -> u32 {
        match self {
            Self::Depth(s) => s.fps,
            Self::Color(s) => s.fps,
        }
    }
}

/// A software sensor, the mode of each profile added to it, by unique id.
struct Injected {
    sensor: SoftwareSensor,
    modes: Vec<(c_int, Mode)>,
}

/// A librealsense software device presenting a D415 (name "Intel RealSense D415",
/// product line D400, the synthetic camera's serial) with a depth sensor offering
/// every Z16 mode and a color sensor offering every color mode of the D415 table,
/// with the synthetic D415's intrinsics, depth->color extrinsics and depth units.
///
/// While a sensor streams, a thread renders frames of the open profile with the
/// synthetic camera and injects them with `rs2_software_sensor_on_video_frame`, one
/// per frame period. Dropping the value stops the threads; the device stays in the
/// context (librealsense cannot remove it) and delivers no more frames.
pub struct SoftwareD415 {
    serial: Serial,
    running: Arc<AtomicBool>,
    threads: Vec<JoinHandle<()>>,
    injected: Arc<Mutex<u64>>,
}

impl std::fmt::Debug for SoftwareD415 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SoftwareD415")
            .field("serial", &self.serial)
            .field("frames_injected", &self.frames_injected())
            .finish()
    }
}

fn rs_intrinsics(k: &Intrinsics) -> RsIntrinsics {
    RsIntrinsics {
        width: c_int::try_from(k.width).unwrap_or(c_int::MAX),
        height: c_int::try_from(k.height).unwrap_or(c_int::MAX),
        ppx: k.ppx,
        ppy: k.ppy,
        fx: k.fx,
        fy: k.fy,
        model: match k.model {
            crate::DistortionModel::None => 0,
            crate::DistortionModel::ModifiedBrownConrady => 1,
            crate::DistortionModel::InverseBrownConrady => 2,
            crate::DistortionModel::BrownConrady => 4,
            crate::DistortionModel::KannalaBrandt4 => 5,
        },
        coeffs: k.coeffs,
    }
}

fn stream(
    kind: c_int,
    uid: c_int,
    format: c_int,
    bpp: usize,
    k: &Intrinsics,
    fps: u32,
) -> RsVideoStream {
    let int = |v: u32| c_int::try_from(v).unwrap_or(c_int::MAX);
    RsVideoStream {
        stream: kind,
        index: 0,
        uid,
        width: int(k.width),
        height: int(k.height),
        fps: int(fps),
        bpp: c_int::try_from(bpp).unwrap_or(c_int::MAX),
        format,
        intrinsics: rs_intrinsics(k),
    }
}

impl SoftwareD415 {
    pub(super) fn new(
        lib: &Arc<Lib>,
        context: &Context,
        synthetic: Arc<SyntheticCamera>,
    ) -> Result<Self, RealSenseError> {
        let serial = synthetic.serial();
        let device = SoftwareDevice::new(lib)?;
        let table = ModeTable::d415();
        let mut uid: c_int = 0;
        let mut next_uid = || {
            uid += 1;
            uid
        };
        let mut depth = Injected {
            sensor: device.add_sensor("Stereo Module")?,
            modes: Vec::new(),
        };
        for res in &table.depth {
            for &fps in &res.fps {
                let settings = DepthSettings {
                    fps,
                    width: res.width,
                    height: res.height,
                    ..DepthSettings::default()
                };
                let k = d415::depth_intrinsics(res.width, res.height);
                let id = next_uid();
                depth.sensor.add_video_stream(stream(
                    ffi::STREAM_DEPTH,
                    id,
                    ffi::FORMAT_Z16,
                    2,
                    &k,
                    fps,
                ))?;
                depth.modes.push((id, Mode::Depth(settings)));
            }
        }
        depth
            .sensor
            .add_read_only_option(ffi::OPTION_DEPTH_UNITS, synthetic.depth_scale())?;
        depth
            .sensor
            .add_read_only_option(ffi::OPTION_STEREO_BASELINE, d415::BASELINE_M * 1000.0)?;
        let mut color = Injected {
            sensor: device.add_sensor("RGB Camera")?,
            modes: Vec::new(),
        };
        for &format in &table.color_formats {
            for res in &table.color {
                for &fps in &res.fps {
                    let settings = ColorSettings {
                        format,
                        fps,
                        width: res.width,
                        height: res.height,
                    };
                    let k = d415::color_intrinsics(res.width, res.height);
                    let id = next_uid();
                    color.sensor.add_video_stream(stream(
                        ffi::STREAM_COLOR,
                        id,
                        rs_color_format(format),
                        format.bytes_per_pixel(),
                        &k,
                        fps,
                    ))?;
                    color.modes.push((id, Mode::Color(settings)));
                }
            }
        }
        register_extrinsics(&depth.sensor, &color.sensor)?;
        for (info, value) in [
            (CameraInfo::Name, d415::MODEL_NAME),
            (CameraInfo::SerialNumber, serial.as_str()),
            (CameraInfo::ProductLine, D400),
        ] {
            device.register_info(info, value)?;
        }
        context.add_software_device(device.device())?;
        let running = Arc::new(AtomicBool::new(true));
        let injected = Arc::new(Mutex::new(0));
        let device = Arc::new(device);
        let threads = [depth, color]
            .into_iter()
            .map(|sensor| {
                let running = Arc::clone(&running);
                let synthetic = Arc::clone(&synthetic);
                let injected = Arc::clone(&injected);
                let device = Arc::clone(&device);
                std::thread::spawn(move || {
                    inject_while(&running, &sensor, &synthetic, &injected);
                    drop(device);
                })
            })
            .collect();
        Ok(Self {
            serial,
            running,
            threads,
            injected,
        })
    }

    /// The serial the device reports.
    pub fn serial(&self) -> Serial {
        self.serial
    }

    /// Frames handed to librealsense so far (both sensors), counted before it takes
    /// them; it drops those that arrive while their sensor is not streaming.
    pub fn frames_injected(&self) -> u64 {
        *self.injected.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

impl Drop for SoftwareD415 {
    fn drop(&mut self) {
        self.running.store(false, Ordering::SeqCst);
        for thread in self.threads.drain(..) {
            // A panicked injector has nothing left to clean up.
            let _ = thread.join();
        }
    }
}

/// Registers the D415's depth->color transform between every depth and every color
/// profile: each depth profile to the first color profile, and the first depth profile
/// to each color profile (librealsense chains the rest through its extrinsics graph).
fn register_extrinsics(
    depth: &SoftwareSensor,
    color: &SoftwareSensor,
) -> Result<(), RealSenseError> {
    let e = d415::depth_to_color();
    let e = RsExtrinsics {
        rotation: e.rotation,
        translation: e.translation,
    };
    let missing = || ffi::RsError {
        function: "rs2_software_sensor_add_video_stream".to_owned(),
        message: "a sensor has no profile".to_owned(),
    };
    let first_depth = depth.profile(0).ok_or_else(missing)?;
    let first_color = color.profile(0).ok_or_else(missing)?;
    for i in 0..depth.profile_count() {
        if let Some(d) = depth.profile(i) {
            d.register_extrinsics(&first_color, e)?;
        }
    }
    for j in 1..color.profile_count() {
        if let Some(c) = color.profile(j) {
            first_depth.register_extrinsics(&c, e)?;
        }
    }
    Ok(())
}

/// Injects frames of the sensor's open profile while `running`.
fn inject_while(
    running: &AtomicBool,
    injected: &Injected,
    synthetic: &SyntheticCamera,
    count: &Mutex<u64>,
) {
    let mut frame_number: u64 = 0;
    while running.load(Ordering::SeqCst) {
        let Some((index, mode)) = active_mode(injected) else {
            std::thread::sleep(IDLE_POLL);
            continue;
        };
        frame_number += 1;
        // A refused frame is dropped like one that arrives while the sensor is closed.
        let _ = inject(injected, index, mode, synthetic, frame_number, count);
        std::thread::sleep(Duration::from_secs(1) / mode.fps().max(1));
    }
}

/// The index and mode of the profile the sensor is open with, if any.
fn active_mode(injected: &Injected) -> Option<(usize, Mode)> {
    let active = injected.sensor.sensor().active_profiles().ok()?;
    if active.len().ok()? == 0 {
        return None;
    }
    let uid = active.get(0).ok()?.data().ok()?.uid;
    injected
        .modes
        .iter()
        .enumerate()
        .find(|(_, (id, _))| *id == uid)
        .map(|(i, (_, mode))| (i, *mode))
}

/// Renders frame `frame_number` of `mode` and hands it to librealsense, counting it in
/// `count` first: the grab that receives it may return before this call does.
fn inject(
    injected: &Injected,
    index: usize,
    mode: Mode,
    synthetic: &SyntheticCamera,
    frame_number: u64,
    count: &Mutex<u64>,
) -> Result<(), RealSenseError> {
    let invalid = |e: crate::CameraError| ffi::RsError {
        function: "SoftwareD415".to_owned(),
        message: e.to_string(),
    };
    let (bytes, stride, bpp, timestamp_us, depth_units) = match mode {
        Mode::Depth(settings) => {
            synthetic.set_depth_settings(settings).map_err(invalid)?;
            let frame = synthetic.render_depth(frame_number);
            let bytes: Vec<u8> = frame.data.iter().flat_map(|v| v.to_le_bytes()).collect();
            let (stride, time, scale) = (frame.stride * 2, frame.timestamp_us, frame.depth_scale);
            (bytes, stride, 2, time, scale)
        }
        Mode::Color(settings) => {
            synthetic.set_color_settings(settings).map_err(invalid)?;
            let frame = synthetic.render_color(frame_number);
            let bpp = frame.format.bytes_per_pixel();
            (frame.data, frame.stride, bpp, frame.timestamp_us, 0.0)
        }
    };
    *count.lock().unwrap_or_else(PoisonError::into_inner) += 1;
    injected.sensor.inject(
        index,
        &InjectedFrame {
            bytes: &bytes,
            stride,
            bpp,
            number: frame_number,
            timestamp_ms: timestamp_us as f64 / 1000.0,
            depth_units,
        },
    )?;
    Ok(())
}
