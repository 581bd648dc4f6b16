//! The [`Backend`] trait every camera backend implements.

use std::sync::Arc;

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

/// A backend could not start: what it was doing, and why. What every backend may meet is
/// a variant here; what one backend alone meets (a recording it cannot open, a library it
/// cannot load) is that backend's own error, in its file, carried by
/// [`StartError::Backend`]: a new backend needs no variant here.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StartError {
    /// The scene's synthetic cameras could not be built.
    #[error("building the scene's cameras")]
    Scene(#[source] SceneError),
    /// A camera could not go into the hub (a camera of its serial is there already).
    #[error("adding a camera")]
    Add(#[source] HubError),
    /// A backend's own error ([`StartError::backend`]).
    #[error(transparent)]
    Backend(Box<dyn std::error::Error + Send + Sync>),
}

impl StartError {
    /// A backend's own error `e`, said as it says it.
    pub fn backend(e: impl std::error::Error + Send + Sync + 'static) -> Self {
        Self::Backend(Box::new(e))
    }
}
