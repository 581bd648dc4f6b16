//! The synthetic D415: renders a [`Scene`] as a D415 would see it.
//!
//! Depth is rendered from the left imager (the depth origin) with D415 intrinsics for
//! the current depth mode. With noise `"d415"` each pixel goes through this model:
//!
//! 1. exact depth z along the camera's z axis at the pixel centre (ray casting);
//! 2. 0 if the surface point is hidden from the right imager (55 mm along +x): the
//!    occlusion shadow beside depth edges;
//! 3. 0 for about 1 % of pixels at random (dropout);
//! 4. at a depth discontinuity (a 4-neighbour differs by more than 2 % of z) the
//!    pixel takes the mean depth of 4x4 sub-pixel rays seen by both imagers, so
//!    pixels straddling an edge "fly" between the two surfaces;
//! 5. 0 nearer than the minimum range fx * 55 mm / 126 px (0.39 m at 1280x720,
//!    scaling with the mode's fx) or beyond 10 m;
//! 6. stereo noise added in disparity: d = fx B / z plus a zero-mean sample of
//!    standard deviation 0.08 px, z = fx B / d; to first order the depth error has
//!    sigma = z^2 * 0.08 / (fx * 0.055 m), Intel's RMS formula;
//! 7. rounded to depth units (0 if it does not fit in 16 bits).
//!
//! An object's finish (see [`scene::Finish`]) adds, with noise `"d415"`, a chance that the
//! pixel loses its depth, decided after step 3 and growing the noise of step 6 by
//! (1 + 1.5 x that chance):
//!
//! - reflectivity r < 1: the light coming back, s = r cos(incidence) / distance^2
//!   (metres), is too weak to match below s = 0.02 (every pixel lost) and enough from
//!   s = 0.15 on (none lost), a smoothstep between: r = 0.1 at 1 m loses a third of its
//!   pixels, r = 0.05 at 1.2 m nearly all;
//! - gloss g > 0: the projector (taken midway between the imagers) glares where the
//!   surface mirrors it into either imager; the chance is min(1, 1.5 g (n.h)^600), h the
//!   half-vector between the directions to the projector and to the imager: a patch
//!   a few centimetres wide at 1 m where a glossy face looks straight at the camera.
//!
//! Losses cluster in 4 x 4 pixel patches (each patch draws one number, each pixel adds a
//! little of its own) and change from frame to frame, as the holes of a real D415 on
//! black or shiny parcels do. Reflectivity does not change the color image (the object's
//! `color` says how it looks); gloss adds a highlight of the fixed light (Blinn-Phong).
//!
//! Every random choice comes from a counter-based hash of (scene seed, serial, frame
//! number, pixel index), so a frame's bytes depend on nothing else (not on threads).
//!
//! Noise `"ideal"` means: step 1 and step 7 only: the exact depth at every pixel centre
//! where a ray hits a surface, rounded to the nearest depth unit; no shadows, no
//! dropout, no flying pixels, no range limits, no noise. 0 only where the ray hits
//! nothing or the depth does not fit in 16 bits.
//!
//! Color is rendered from the color camera (15 mm from the left imager, see
//! [`d415::DEPTH_TO_COLOR_X_M`]) with its own intrinsics: flat colors shaded by one
//! fixed directional light (ambient + Lambert), labels as black and white modules on
//! the box's top face, a highlight on glossy surfaces. A camera's `color_sensor` (off by
//! default) then blurs it (Gaussian, `blur_px`), multiplies it by `exposure` and adds
//! noise of standard deviation `noise * sqrt((level + 16) / 144)` per channel (photon
//! noise over a read-noise floor; `noise` at mid grey), new each frame, clipping at 0
//! and 255.
//!
//! A scene may have a timeline (objects that appear, slide in and are removed; see
//! [`scene`]): a grab renders the scene as it stands at the frame's capture, in scene
//! time since the cameras were made ([`SyntheticCamera::scene_time`]; all cameras of
//! [`SyntheticCamera::all`] share one). The scene is prepared once; the world of a
//! moment is rebuilt from the prepared objects only when something moved, appeared or
//! left since the frame before.
//!
//! A scene camera with `stall_s` stalls at that scene time: from then on every grab
//! returns the frame of that moment again (its number, capture time and pixels), as a
//! camera whose driver keeps serving its last frame.
//!
//! Grabs deliver frames at once unless a frame delay is set
//! ([`SyntheticCamera::set_frame_delay`]); a grab whose timeout is shorter than the
//! delay fails with [`CameraError::Timeout`] after waiting the timeout. A camera set
//! disconnected ([`SyntheticCamera::set_connected`]) fails grabs with
//! [`CameraError::Disconnected`].

pub mod cert;
pub mod d415;
mod fields;
mod kinds;
mod label;
pub mod lane;
mod ray;
mod raycast;
mod render;
pub mod scene;
mod scene_file;

use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use crate::advanced::{AdvancedConfig, VisualPreset};
use crate::backend::FrameClock;
use crate::camera::{AdvancedMode, Camera, CameraError, Serial};
use crate::frame::{ColorFrame, DepthFrame};
use crate::intrinsics::{Extrinsics, Intrinsics, Pose};
use crate::mode::{ModeTable, Stream};
use crate::settings::{ColorSettings, DepthSettings};
use raycast::{Stage, View};
use render::DepthJob;
use scene::{ColorSensor, Noise, Scene, SceneError};

#[derive(Debug)]
struct State {
    color: ColorSettings,
    depth: DepthSettings,
    advanced: AdvancedConfig,
    clock: FrameClock,
    connected: bool,
    frame_delay: Duration,
    /// Once stalled: the frame served again, per stream (depth, color): its number and
    /// capture time.
    frozen: [Option<(u64, u64)>; 2],
}

/// A synthetic Intel RealSense D415 looking at a scene.
#[derive(Debug)]
pub struct SyntheticCamera {
    serial: Serial,
    noise: Noise,
    seed: u64,
    pose: Pose,
    calibrated: bool,
    stage: Arc<Stage>,
    /// Scene time 0: when the scene's cameras were made.
    epoch: Instant,
    /// The same moment on the system's clock, µs since the UNIX epoch.
    epoch_unix_us: u64,
    /// From this scene time on the camera serves its frame of that moment again.
    stall: Option<Duration>,
    modes: ModeTable,
    state: Mutex<State>,
    /// What the color sensor adds to the color image.
    color_sensor: ColorSensor,
}

impl SyntheticCamera {
    /// The scene's camera with this serial; its scene time starts now.
    pub fn new(scene: &Scene, serial: &Serial) -> Result<Self, SceneError> {
        let stage = Arc::new(Stage::new(scene)?);
        Self::on_stage(scene, serial, stage, Instant::now())
    }

    /// Every camera of the scene, sharing one prepared scene and one scene time, which
    /// starts now.
    pub fn all(scene: &Scene) -> Result<Vec<Arc<Self>>, SceneError> {
        Self::all_since(scene, Instant::now())
    }

    /// Every camera of the scene, sharing one prepared scene, with scene time 0 at
    /// `epoch`.
    pub fn all_since(scene: &Scene, epoch: Instant) -> Result<Vec<Arc<Self>>, SceneError> {
        let stage = Arc::new(Stage::new(scene)?);
        scene
            .cameras
            .iter()
            .map(|c| Self::on_stage(scene, &c.serial, Arc::clone(&stage), epoch).map(Arc::new))
            .collect()
    }

    fn on_stage(
        scene: &Scene,
        serial: &Serial,
        stage: Arc<Stage>,
        epoch: Instant,
    ) -> Result<Self, SceneError> {
        let invalid = |reason: &str| SceneError::Invalid {
            field: format!("camera {serial}"),
            reason: reason.to_owned(),
        };
        let cam = scene
            .camera(serial)
            .ok_or_else(|| invalid("no camera with this serial in the scene"))?;
        let pose = cam
            .pose()
            .ok_or_else(|| invalid("look_at and up do not define a pose"))?;
        Ok(Self {
            serial: *serial,
            noise: cam.noise,
            seed: scene.seed,
            pose,
            calibrated: cam.calibrated,
            stage,
            epoch,
            epoch_unix_us: unix_us_at(epoch),
            stall: cam.stall_s.map(Duration::from_secs_f64),
            color_sensor: cam.color_sensor,
            modes: ModeTable::d415(),
            state: Mutex::new(State {
                color: ColorSettings::default(),
                depth: DepthSettings::default(),
                advanced: AdvancedConfig::preset(VisualPreset::Default),
                clock: FrameClock::default(),
                connected: true,
                frame_delay: Duration::ZERO,
                frozen: [None; 2],
            }),
        })
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // State updates are single assignments; a panicking holder leaves it consistent.
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Simulates plugging the camera in (`true`) or pulling it out (`false`).
    pub fn set_connected(&self, connected: bool) {
        self.lock().connected = connected;
    }

    /// Time a frame takes to arrive after a grab starts (default zero).
    pub fn set_frame_delay(&self, delay: Duration) {
        self.lock().frame_delay = delay;
    }

    fn depth_scale_of(state: &State) -> f32 {
        state
            .advanced
            .depth_units_um()
            .map_or(DepthFrame::DEFAULT_DEPTH_SCALE, |um| um as f32 * 1e-6)
    }

    /// Scene time now: how long ago the scene's cameras were made. The scene's
    /// timelines (appear, slide, remove) are in this time.
    pub fn scene_time(&self) -> Duration {
        self.epoch.elapsed()
    }

    /// Renders depth frame `frame_number` with the current settings at the current
    /// scene time ([`SyntheticCamera::render_depth_at`]).
    pub fn render_depth(&self, frame_number: u64) -> DepthFrame {
        self.render_depth_at(frame_number, self.scene_time())
    }

    /// Renders depth frame `frame_number` with the current settings as the scene stands
    /// at `scene_time`, without touching the frame counter. `timestamp_us` is the device
    /// clock: microseconds since stream start at the mode's frame rate. Same scene seed,
    /// serial, settings, frame number and scene (as it stands then) give identical data.
    pub fn render_depth_at(&self, frame_number: u64, scene_time: Duration) -> DepthFrame {
        let (settings, depth_scale) = {
            let s = self.lock();
            (s.depth, Self::depth_scale_of(&s))
        };
        let k = d415::depth_intrinsics(settings.width, settings.height);
        let view = View::new(&self.pose, [0.0; 3], k);
        let job = DepthJob {
            noise: self.noise,
            key: render::frame_key(self.seed, self.serial.as_u64(), frame_number),
            depth_scale,
        };
        DepthFrame {
            width: settings.width,
            height: settings.height,
            stride: settings.width as usize,
            depth_scale,
            timestamp_us: device_time_us(frame_number, settings.fps),
            frame_number,
            data: render::render_depth(&self.stage.world_at(scene_time.as_secs_f64()), &view, &job),
        }
    }

    /// Renders color frame `frame_number` with the current settings at the current
    /// scene time ([`SyntheticCamera::render_color_at`]).
    pub fn render_color(&self, frame_number: u64) -> ColorFrame {
        self.render_color_at(frame_number, self.scene_time())
    }

    /// Renders color frame `frame_number` with the current settings as the scene stands
    /// at `scene_time`, without touching the frame counter (timestamps as
    /// [`SyntheticCamera::render_depth_at`]).
    pub fn render_color_at(&self, frame_number: u64, scene_time: Duration) -> ColorFrame {
        let settings = self.lock().color;
        let k = d415::color_intrinsics(settings.width, settings.height);
        let view = View::new(&self.pose, color_offset(), k);
        ColorFrame {
            format: settings.format,
            width: settings.width,
            height: settings.height,
            stride: settings.width as usize * settings.format.bytes_per_pixel(),
            timestamp_us: device_time_us(frame_number, settings.fps),
            frame_number,
            data: {
                let world = self.stage.world_at(scene_time.as_secs_f64());
                let mut data = render::render_color(&world, &view, settings.format);
                if !self.color_sensor.is_off() {
                    render::apply_color_sensor(
                        &mut data,
                        settings.width as usize,
                        settings.height as usize,
                        settings.format,
                        &self.color_sensor,
                        render::frame_key(self.seed, self.serial.as_u64(), frame_number),
                    );
                }
                data
            },
        }
    }

    /// Waits for the next frame (frame delay vs timeout) and returns (frame number,
    /// wall-clock timestamp in µs, the scene time to render). A stalled camera returns
    /// the frame of its stall again.
    fn next_frame(
        &self,
        stream: Stream,
        timeout: Duration,
    ) -> Result<(u64, u64, Duration), CameraError> {
        let delay = {
            let s = self.lock();
            if !s.connected {
                return Err(CameraError::Disconnected {
                    serial: self.serial,
                });
            }
            s.frame_delay
        };
        if delay > timeout {
            std::thread::sleep(timeout);
            return Err(CameraError::Timeout {
                timeout_ms: timeout.as_millis().try_into().unwrap_or(u64::MAX),
            });
        }
        std::thread::sleep(delay);
        let scene_time = self.scene_time();
        let mut s = self.lock();
        if !s.connected {
            return Err(CameraError::Disconnected {
                serial: self.serial,
            });
        }
        match self.stall.filter(|stall| scene_time >= *stall) {
            Some(stall) => {
                let slot = usize::from(stream == Stream::Color);
                let (frame_number, timestamp_us) = match s.frozen[slot] {
                    Some(frozen) => frozen,
                    None => {
                        // The frame of the stall's moment, stamped then.
                        let (n, now_us) = s.clock.stamp(stream);
                        let at_us = self.epoch_unix_us + stall.as_micros() as u64;
                        let frozen = (n, at_us.min(now_us));
                        s.frozen[slot] = Some(frozen);
                        frozen
                    }
                };
                Ok((frame_number, timestamp_us, stall))
            }
            None => {
                let (frame_number, timestamp_us) = s.clock.stamp(stream);
                Ok((frame_number, timestamp_us, scene_time))
            }
        }
    }
}

/// The system's clock at `instant` (read now, moved back by the time since), µs since
/// the UNIX epoch.
fn unix_us_at(instant: Instant) -> u64 {
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap_or_default();
    now.saturating_sub(instant.elapsed()).as_micros() as u64
}

/// Optical centre of the color camera in the depth frame.
fn color_offset() -> [f32; 3] {
    let t = d415::depth_to_color().translation;
    [-t[0], -t[1], -t[2]]
}

fn device_time_us(frame_number: u64, fps: u32) -> u64 {
    frame_number.saturating_mul(1_000_000) / u64::from(fps.max(1))
}

impl Camera for SyntheticCamera {
    fn serial(&self) -> Serial {
        self.serial
    }

    fn model(&self) -> &str {
        d415::MODEL_NAME
    }

    fn stream_modes(&self) -> &ModeTable {
        &self.modes
    }

    fn color_settings(&self) -> ColorSettings {
        self.lock().color
    }

    fn set_color_settings(&self, settings: ColorSettings) -> Result<(), CameraError> {
        settings.validate(&self.modes)?;
        self.lock().color = settings;
        Ok(())
    }

    fn depth_settings(&self) -> DepthSettings {
        self.lock().depth
    }

    fn set_depth_settings(&self, settings: DepthSettings) -> Result<(), CameraError> {
        settings.validate(&self.modes)?;
        self.lock().depth = settings;
        Ok(())
    }

    fn grab_color(&self, timeout: Duration) -> Result<ColorFrame, CameraError> {
        let (frame_number, timestamp_us, at) = self.next_frame(Stream::Color, timeout)?;
        let mut frame = self.render_color_at(frame_number, at);
        frame.timestamp_us = timestamp_us;
        Ok(frame)
    }

    fn grab_depth(&self, timeout: Duration) -> Result<DepthFrame, CameraError> {
        let (frame_number, timestamp_us, at) = self.next_frame(Stream::Depth, timeout)?;
        let mut frame = self.render_depth_at(frame_number, at);
        frame.timestamp_us = timestamp_us;
        Ok(frame)
    }

    fn depth_intrinsics(&self) -> Result<Intrinsics, CameraError> {
        let s = self.lock().depth;
        Ok(d415::depth_intrinsics(s.width, s.height))
    }

    fn color_intrinsics(&self) -> Result<Intrinsics, CameraError> {
        let s = self.lock().color;
        Ok(d415::color_intrinsics(s.width, s.height))
    }

    fn depth_to_color(&self) -> Result<Extrinsics, CameraError> {
        Ok(d415::depth_to_color())
    }

    fn depth_scale(&self) -> f32 {
        Self::depth_scale_of(&self.lock())
    }

    fn stereo_baseline_m(&self) -> Option<f32> {
        Some(d415::BASELINE_M)
    }

    fn advanced_mode(&self) -> Option<&dyn AdvancedMode> {
        Some(self)
    }

    fn true_pose(&self) -> Option<Pose> {
        self.calibrated.then_some(self.pose)
    }
}

/// A D415's advanced mode, as a model: the document is kept, and its depth mode is the
/// camera's.
impl AdvancedMode for SyntheticCamera {
    fn advanced_config(&self) -> Result<AdvancedConfig, CameraError> {
        let s = self.lock();
        let mut doc = s.advanced.clone();
        // The stream keys describe the current depth mode.
        doc.set_depth_mode(&s.depth)?;
        Ok(doc)
    }

    fn set_advanced_config(&self, config: &AdvancedConfig) -> Result<(), CameraError> {
        let mut s = self.lock();
        let depth = config.depth_mode(s.depth);
        depth.validate(&self.modes)?;
        s.advanced.merge(config);
        s.depth = depth;
        Ok(())
    }
}
