//! `serve --realsense`: the Intel RealSense D400 cameras librealsense2 finds (loaded at
//! run time, hot-plug followed), and with `--realsense-software` virtual D415s of the
//! scene put into librealsense.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use rgbd::backend::realsense::{
    GrabMode, LibrarySearch, RealSense, RealSenseError, RealSenseLibrary, SoftwareD415,
};
use rgbd::{CameraHub, Scene, Serial, SyntheticCamera};

use super::backend::{Backend, StartError};

/// How long librealsense gets to announce the first camera.
const FIRST_CAMERA: Duration = Duration::from_secs(3);

/// The flags of librealsense's cameras.
#[derive(Debug, Clone, Default, clap::Args)]
#[group(skip)]
pub struct Args {
    /// Serve the Intel RealSense D400 cameras librealsense2 finds (loaded at run time;
    /// hot-plug followed) instead of synthetic ones.
    #[arg(long, conflicts_with = "no_cameras")]
    realsense: bool,
    /// The librealsense2 library for --realsense (default: $LIBREALSENSE2_PATH, then
    /// librealsense2.so.2.* / librealsense2.so on the system library path).
    #[arg(long, value_name = "PATH", requires = "realsense")]
    librealsense: Option<PathBuf>,
    /// A library to load globally before librealsense2 (repeatable), e.g. the libpython
    /// a pyrealsense2 wheel's module needs when that module is --librealsense.
    #[arg(long, value_name = "PATH", requires = "realsense")]
    librealsense_preload: Vec<PathBuf>,
    /// With --realsense: keep the sensors streaming and serve the newest frame, instead
    /// of opening and closing a sensor per grab.
    #[arg(long, requires = "realsense")]
    realsense_streaming: bool,
    /// With --realsense: also put a virtual D415 per camera of the scene into
    /// librealsense (a software device fed by the synthetic renderer), served through
    /// the same librealsense code path as a real camera. For testing without hardware.
    #[arg(long, requires = "realsense")]
    realsense_software: bool,
}

impl Args {
    /// Whether librealsense's cameras are asked for.
    pub fn configured(&self) -> bool {
        self.realsense
    }

    /// librealsense's cameras as a backend, when asked for; `scene` gives the virtual
    /// cameras of `--realsense-software`.
    pub fn backend(&self, scene: &Scene) -> Option<Box<dyn Backend>> {
        self.realsense.then(|| {
            Box::new(RealSenseCameras::new(RealSenseOptions {
                library: LibrarySearch {
                    explicit: self.librealsense.clone(),
                    preload: self.librealsense_preload.clone(),
                },
                streaming: self.realsense_streaming,
                software: self.realsense_software.then(|| scene.clone()),
            })) as Box<dyn Backend>
        })
    }
}

/// How the RealSense cameras are served.
pub struct RealSenseOptions {
    /// Where librealsense2 is loaded from.
    pub library: LibrarySearch,
    /// Keep the sensors streaming and serve the newest frame, instead of opening and
    /// closing a sensor per grab.
    pub streaming: bool,
    /// Also put a virtual D415 per camera of this scene into librealsense (a software
    /// device fed by the synthetic renderer).
    pub software: Option<Scene>,
}

/// The cameras librealsense finds, served from [`Backend::start`] until dropped.
pub struct RealSenseCameras {
    options: RealSenseOptions,
    running: Option<Running>,
}

impl RealSenseCameras {
    /// The backend of `options`, not started.
    pub fn new(options: RealSenseOptions) -> Self {
        Self {
            options,
            running: None,
        }
    }
}

/// A started librealsense and its virtual cameras.
struct Running {
    // Dropped before the context: stops injecting.
    _software: Vec<SoftwareD415>,
    _realsense: RealSense,
}

impl Backend for RealSenseCameras {
    fn start(&mut self, hub: &Arc<CameraHub>) -> Result<Vec<Serial>, StartError> {
        let options = &self.options;
        let library = RealSenseLibrary::load(&options.library).map_err(failed)?;
        let mode = if options.streaming {
            GrabMode::Streaming
        } else {
            GrabMode::PerRequest
        };
        let realsense = RealSense::start(&library, hub.clone(), mode).map_err(|source| {
            StartError::backend(RealSenseStartError::Start {
                version: library.version(),
                source,
            })
        })?;
        let mut software = Vec::new();
        if let Some(scene) = &options.software {
            for camera in SyntheticCamera::all(scene).map_err(StartError::Scene)? {
                software.push(
                    realsense
                        .add_software_d415(camera)
                        .map_err(|e| StartError::backend(RealSenseStartError::Software(e)))?,
                );
            }
        }
        let mut serials = realsense.wait_for_cameras(FIRST_CAMERA).map_err(failed)?;
        // Every virtual camera is announced on librealsense's thread; wait for all.
        let deadline = std::time::Instant::now() + FIRST_CAMERA;
        while software.iter().any(|s| !serials.contains(&s.serial()))
            && std::time::Instant::now() < deadline
        {
            std::thread::sleep(Duration::from_millis(10));
            serials = realsense.wait_for_cameras(FIRST_CAMERA).map_err(failed)?;
        }
        for reason in realsense.rejected() {
            tracing::warn!("librealsense device not served: {reason}");
        }
        self.running = Some(Running {
            _software: software,
            _realsense: realsense,
        });
        Ok(serials)
    }
}

/// librealsense did not serve: how.
#[derive(Debug, thiserror::Error)]
pub enum RealSenseStartError {
    /// It could not be loaded, or its cameras did not come.
    #[error(transparent)]
    RealSense(RealSenseError),
    /// It did not start.
    #[error("starting librealsense {version}")]
    Start {
        /// The library's version.
        version: String,
        /// Why.
        source: RealSenseError,
    },
    /// A scene's camera could not be added to it as a virtual D415.
    #[error("adding a virtual D415 to librealsense")]
    Software(#[source] RealSenseError),
}

/// librealsense could not be loaded, or its cameras did not come.
fn failed(e: RealSenseError) -> StartError {
    StartError::backend(RealSenseStartError::RealSense(e))
}
