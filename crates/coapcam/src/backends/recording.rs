//! `serve --bag`: librealsense recordings (`.bag`, `.db3`) played as cameras, one per
//! recorded device.

use std::path::PathBuf;
use std::sync::Arc;

use rgbd::backend::playback::PlaybackCamera;
use rgbd::{Camera as _, CameraHub, Scene, Serial};

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
            let cameras = PlaybackCamera::open(path).map_err(|source| StartError::Recording {
                path: path.clone(),
                source,
            })?;
            for camera in cameras {
                serials.push(camera.serial());
                hub.add(Arc::new(camera))
                    .map_err(|source| StartError::AddRecorded {
                        path: path.clone(),
                        source,
                    })?;
            }
        }
        Ok(serials)
    }
}
