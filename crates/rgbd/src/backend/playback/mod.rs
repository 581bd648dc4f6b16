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
//! streams (infrared, motion) are ignored. A recording has the recorded stereo baseline
//! but no advanced mode ([`Camera::advanced_mode`] is `None`).

pub mod bag;
pub mod db3;
mod recording;

pub use recording::{MAX_IMAGE_SIDE, MAX_RECORDING_BYTES, PlaybackError};

use std::path::Path;
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use crate::backend::FrameClock;
use crate::camera::{Camera, CameraError, Serial};
use crate::frame::{ColorFrame, DepthFrame};
use crate::intrinsics::{Extrinsics, Intrinsics, Pose};
use crate::mode::{ModeTable, Stream};
use crate::settings::{ColorSettings, DepthSettings};
use recording::{DeviceBuilder, RecordedDevice};

#[derive(Debug, Default)]
struct State {
    color: usize,
    depth: usize,
    clock: FrameClock,
}

/// One recorded device played back as a camera (see the module documentation).
#[derive(Debug)]
pub struct PlaybackCamera {
    recorded: RecordedDevice,
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
        Ok(builder.finish()?.into_iter().map(Self::play).collect())
    }

    /// A camera playing `device`'s frames.
    fn play(recorded: RecordedDevice) -> Self {
        Self {
            recorded,
            state: Mutex::new(State::default()),
        }
    }

    /// The recorded frame numbers of a stream, in playback order.
    pub fn recorded_frame_numbers(&self, stream: Stream) -> Vec<u64> {
        match stream {
            Stream::Depth => self.recorded.depth_frames.iter().map(|f| f.0).collect(),
            Stream::Color => self.recorded.color_frames.iter().map(|f| f.0).collect(),
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
            Stream::Depth => (&mut s.depth, self.recorded.depth_frames.len()),
            Stream::Color => (&mut s.color, self.recorded.color_frames.len()),
        };
        let index = *cursor;
        *cursor = (index + 1) % len.max(1);
        let (grab, timestamp_us) = s.clock.stamp(stream);
        (index, grab, timestamp_us)
    }
}

impl Camera for PlaybackCamera {
    fn serial(&self) -> Serial {
        self.recorded.serial
    }

    fn model(&self) -> &str {
        &self.recorded.model
    }

    fn stream_modes(&self) -> &ModeTable {
        &self.recorded.modes
    }

    fn color_settings(&self) -> ColorSettings {
        self.recorded.color_settings
    }

    fn set_color_settings(&self, settings: ColorSettings) -> Result<(), CameraError> {
        settings.validate(&self.recorded.modes)?;
        Ok(())
    }

    fn depth_settings(&self) -> DepthSettings {
        self.recorded.depth_settings
    }

    fn set_depth_settings(&self, settings: DepthSettings) -> Result<(), CameraError> {
        settings.validate(&self.recorded.modes)?;
        Ok(())
    }

    fn grab_color(&self, _timeout: Duration) -> Result<ColorFrame, CameraError> {
        let (index, frame_number, timestamp_us) = self.next(Stream::Color);
        let s = &self.recorded.color_settings;
        let data = self
            .recorded
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
        let s = &self.recorded.depth_settings;
        let (depth_scale, data) = self
            .recorded
            .depth_frames
            .get(index)
            .map_or((self.recorded.depth_scale, Vec::new()), |f| {
                (f.1, f.2.clone())
            });
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
        Ok(self.recorded.depth_intrinsics)
    }

    fn color_intrinsics(&self) -> Result<Intrinsics, CameraError> {
        Ok(self.recorded.color_intrinsics)
    }

    fn depth_to_color(&self) -> Result<Extrinsics, CameraError> {
        Ok(self.recorded.depth_to_color)
    }

    fn depth_scale(&self) -> f32 {
        self.recorded.depth_scale
    }

    fn stereo_baseline_m(&self) -> Option<f32> {
        // A recording without the option (librealsense records it): the D415's nominal,
        // as librealsense records D400 cameras only.
        Some(self.recorded.baseline_m.unwrap_or(crate::d415::BASELINE_M))
    }

    fn true_pose(&self) -> Option<Pose> {
        None
    }
}
