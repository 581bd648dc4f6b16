//! `serve --bag`: librealsense recordings (`.bag`, `.db3`) played as cameras, one per
//! recorded device.

use std::path::PathBuf;
use std::sync::Arc;

use rgbd::backend::playback::{PlaybackCamera, PlaybackError};
use rgbd::{Camera as _, CameraHub, HubError, Scene, Serial};

use super::backend::{Backend, StartError};

/// The flags of the recordings.
#[derive(Debug, Clone, Default, clap::Args)]
#[group(skip)]
pub struct Args {
    /// Play a librealsense recording (.bag or .db3) as cameras, one per recorded
    /// device, instead of synthetic ones; repeatable.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["scene", "no_cameras", "realsense"])]
    bag: Vec<PathBuf>,
}

impl Args {
    /// Whether recordings are asked for.
    pub fn configured(&self) -> bool {
        !self.bag.is_empty()
    }

    /// The recordings as a backend, when asked for.
    pub fn backend(&self, _scene: &Scene) -> Option<Box<dyn Backend>> {
        self.configured()
            .then(|| Box::new(Recordings(self.bag.clone())) as Box<dyn Backend>)
    }
}

/// The recordings at these paths.
pub struct Recordings(pub Vec<PathBuf>);

impl Backend for Recordings {
    fn start(&mut self, hub: &Arc<CameraHub>) -> Result<Vec<Serial>, StartError> {
        let mut serials = Vec::new();
        for path in &self.0 {
            let cameras = PlaybackCamera::open(path).map_err(|source| {
                StartError::backend(RecordingError::Open {
                    path: path.clone(),
                    source,
                })
            })?;
            for camera in cameras {
                serials.push(camera.serial());
                hub.add(Arc::new(camera)).map_err(|source| {
                    StartError::backend(RecordingError::Add {
                        path: path.clone(),
                        source,
                    })
                })?;
            }
        }
        Ok(serials)
    }
}

/// A recording could not be served.
#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    /// It could not be opened or read.
    #[error("opening recording {}", path.display())]
    Open {
        /// The recording's file.
        path: PathBuf,
        /// Why.
        source: PlaybackError,
    },
    /// A recorded camera could not go into the hub.
    #[error("adding the camera of {}", path.display())]
    Add {
        /// The recording's file.
        path: PathBuf,
        /// Why.
        source: HubError,
    },
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A recording that cannot be opened fails the backend's start naming it, and the
    /// playback's reason once, though `StartError` has no variant of its own for it.
    #[test]
    fn a_recording_that_cannot_be_opened_is_named() {
        let dir = crate::ScratchDir::new("recording-missing");
        let path = dir.path().join("none.bag");
        let hub = Arc::new(CameraHub::new());
        let e = Recordings(vec![path.clone()])
            .start(&hub)
            .expect_err("no such recording");
        assert!(matches!(e, StartError::Backend(_)), "{e:?}");
        let text = crate::error_text(&e);
        let named = format!("opening recording {}: ", path.display());
        assert!(text.starts_with(&named), "{text}");
        assert_eq!(text.matches("opening recording").count(), 1, "{text}");
        assert!(text.len() > named.len(), "{text}");
    }
}
