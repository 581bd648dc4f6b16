//! The [`Backend`] trait every camera backend implements.

use std::sync::Arc;

use rgbd::{CameraHub, Serial};

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
    fn start(&mut self, hub: &Arc<CameraHub>) -> anyhow::Result<Vec<Serial>>;
}
