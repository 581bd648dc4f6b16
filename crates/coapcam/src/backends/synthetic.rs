//! The synthetic cameras of a scene (`serve --scene`, and the default: the built-in
//! scene), the backend when no other is asked for.

use std::sync::Arc;

use anyhow::Context as _;
use rgbd::{Camera as _, CameraHub, Scene, Serial, SyntheticCamera};

use super::backend::Backend;

/// The synthetic cameras of a scene.
pub struct Synthetic(pub Scene);

impl Backend for Synthetic {
    fn start(&mut self, hub: &Arc<CameraHub>) -> anyhow::Result<Vec<Serial>> {
        add(hub, &self.0)
    }
}

/// Puts the synthetic cameras of `scene` into `hub`; returns their serials.
///
/// # Errors
///
/// When the scene's cameras cannot be built, or one of them is in the hub already.
pub fn add(hub: &CameraHub, scene: &Scene) -> anyhow::Result<Vec<Serial>> {
    let cameras = SyntheticCamera::all(scene).context("building the scene's cameras")?;
    let mut serials = Vec::new();
    for camera in cameras {
        serials.push(camera.serial());
        hub.add(camera).context("adding a camera")?;
    }
    Ok(serials)
}
