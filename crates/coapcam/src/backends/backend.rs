//! The [`Backend`] trait every camera backend implements.

use std::path::PathBuf;
use std::sync::Arc;

use rgbd::backend::playback::PlaybackError;
use rgbd::backend::realsense::RealSenseError;
use rgbd::{CameraHub, HubError, SceneError, Serial};

/// A source of cameras for a camera server: started once with the server's hub, it puts
/// its cameras into it (and adds and removes them as they come and go), and serves them
/// until it is dropped.
pub trait Backend: Send + Sync {
    /// Puts the cameras present now into `hub` and returns their serials; the server
    /// answers once each of them is routed.
    ///
    /// # Errors
    ///
    /// When the backend cannot start (a library or a file it needs, a camera it cannot
    /// add); the server does not start then.
    fn start(&mut self, hub: &Arc<CameraHub>) -> Result<Vec<Serial>, StartError>;
}

/// A backend could not start: what it was doing, and why.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StartError {
    /// The scene's synthetic cameras could not be built.
    #[error("building the scene's cameras")]
    Scene(#[source] SceneError),
    /// A camera could not go into the hub (a camera of its serial is there already).
    #[error("adding a camera")]
    Add(#[source] HubError),
    /// A recording could not be opened or read.
    #[error("opening recording {}", path.display())]
    Recording {
        /// The recording's file.
        path: PathBuf,
        /// Why.
        source: PlaybackError,
    },
    /// A recorded camera could not go into the hub.
    #[error("adding the camera of {}", path.display())]
    AddRecorded {
        /// The recording's file.
        path: PathBuf,
        /// Why.
        source: HubError,
    },
    /// librealsense could not be loaded, or its cameras did not come.
    #[error(transparent)]
    RealSense(#[from] RealSenseError),
    /// librealsense did not start.
    #[error("starting librealsense {version}")]
    StartRealSense {
        /// The library's version.
        version: String,
        /// Why.
        source: RealSenseError,
    },
    /// A scene's camera could not be added to librealsense as a virtual D415.
    #[error("adding a virtual D415 to librealsense")]
    Software(#[source] RealSenseError),
}
