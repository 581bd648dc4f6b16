//! RGB-D cameras for coapcam: frames, D415 stream modes, settings documents, the
//! `Camera` trait with its hot-plug `CameraHub`, and the backends: the synthetic D415,
//! Intel RealSense D400 cameras through librealsense (loaded at run time), and playback
//! of librealsense recordings (`.bag`, `.db3`; [`backend::playback`]).
//!
//! Owns: color/depth frame types, intrinsics/extrinsics and deprojection, the depth
//! post-processing filters (librealsense's blocks, [`filter`]), the
//! D415 mode tables and camera model, the depth-settings / color-settings /
//! advanced-config JSON documents (thesis Listings A.1, A.2, A.5), scene files
//! (docs/design.md §7) and the camera backends. The only unsafe code is librealsense's FFI
//! (`backend::realsense::ffi`, allowed there alone).
//!
//! Must not: know CoAP or networking, use async runtimes (the crate is synchronous;
//! callers move grabs off their executors), or read clocks anywhere but in a backend (its grab path,
//! librealsense's wait for a first camera, the software D415's frame pacing).

#![deny(unsafe_code)]

pub mod advanced;
pub mod backend;
pub mod camera;
pub mod deproject;
pub mod filter;
pub mod frame;
pub mod intrinsics;
pub mod mode;
pub mod settings;

/// Longest client string, in characters, that an error message echoes (docs/design.md §2.3: a
/// short diagnostic).
const ECHO_CHARS: usize = 64;

/// Longest parser description, in characters, that an error message carries.
const MESSAGE_CHARS: usize = 200;

/// `s` as an error message echoes it: at most [`ECHO_CHARS`] characters, then "…".
pub(crate) fn echo(s: &str) -> std::borrow::Cow<'_, str> {
    clip(s, ECHO_CHARS)
}

/// At most `max` characters of `s`, then "…" when anything was cut.
fn clip(s: &str, max: usize) -> std::borrow::Cow<'_, str> {
    match s.char_indices().nth(max) {
        None => std::borrow::Cow::Borrowed(s),
        Some((end, _)) => std::borrow::Cow::Owned(format!("{}…", &s[..end])),
    }
}

pub use advanced::{AdvancedConfig, AdvancedError, VisualPreset};
pub use backend::synthetic::{SyntheticCamera, cert, d415, lane, scene};
pub use camera::{
    AdvancedMode, Camera, CameraError, CameraHub, HubError, HubEvent, Serial, SerialError,
    SettingError,
};
pub use deproject::{Deprojector, deproject_frame};
pub use filter::{FilterError, FrameFilter, PostProcessing, PostProcessingConfig};
pub use frame::{ColorFormat, ColorFrame, DepthFormat, DepthFrame};
pub use intrinsics::{DistortionModel, Extrinsics, Intrinsics, Pose, ProjectError};
pub use mode::{ModeError, ModeTable, ResolutionModes, Stream};
pub use scene::{Scene, SceneError};
pub use settings::{ColorSettings, DepthSettings, SensorFormat, Settings, SettingsError};
