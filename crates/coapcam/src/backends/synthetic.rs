//! The synthetic cameras of a scene (`serve --scene`, and the default: the built-in
//! scene), the backend when no other is asked for.

use std::sync::Arc;

use rgbd::{Camera as _, CameraHub, Scene, Serial, SyntheticCamera};

use super::backend::{Backend, StartError};

/// The synthetic cameras of a scene.
pub struct Synthetic(pub Scene);

impl Backend for Synthetic {
    fn start(&mut self, hub: &Arc<CameraHub>) -> Result<Vec<Serial>, StartError> {
        let cameras = SyntheticCamera::all(&self.0).map_err(StartError::Scene)?;
        add(hub, cameras)
    }
}

/// Puts `cameras` (a scene's, built) into `hub`; returns their serials.
///
/// # Errors
///
/// When one of them is in the hub already.
pub fn add(hub: &CameraHub, cameras: Vec<Arc<SyntheticCamera>>) -> Result<Vec<Serial>, StartError> {
    let mut serials = Vec::new();
    for camera in cameras {
        serials.push(camera.serial());
        hub.add(camera).map_err(StartError::Add)?;
    }
    Ok(serials)
}
