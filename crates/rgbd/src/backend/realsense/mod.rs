//! Intel RealSense D400 cameras through librealsense2's C API, loaded at run time.
//!
//! Nothing is linked at build time: [`RealSenseLibrary::load`] finds the library when
//! the program runs, in this order, and the first rule that names a library decides:
//!
//! 1. an explicit path (`coapcam serve --librealsense PATH`);
//! 2. the environment variable `LIBREALSENSE2_PATH`;
//! 3. the system: every `librealsense2.so.2.*` in `LD_LIBRARY_PATH` and the usual
//!    library directories (newest version first), then `librealsense2.so` through the
//!    dynamic loader's own search.
//!
//! A path named by rule 1 or 2 is never silently replaced by another library. When
//! nothing loads, [`RealSenseError::NotLoaded`] lists every path tried and why it
//! failed. Libraries that must be in the process first (the libpython a pyrealsense2
//! wheel's module needs) are preloaded with [`LibrarySearch::preload`].
//!
//! [`RealSense::start`] opens a librealsense context, serves every D400 device it
//! lists, and follows hot-plug through `rs2_set_devices_changed_callback`: a camera
//! plugged in is added to the [`CameraHub`], one pulled out is removed (its grabs then
//! fail with [`CameraError::Disconnected`]). A device is served only when its product
//! line is D400 and its serial number (`RS2_CAMERA_INFO_SERIAL_NUMBER`) is exactly 12
//! ASCII digits, as [`Serial`] requires (every D400 serial is); any other device is
//! left out and listed by [`RealSense::rejected`] with the reason.
//!
//! Settings are validated against the D415 mode table, then applied by choosing the
//! sensor's stream profile with that stream, format, resolution and frame rate. Grabs
//! follow [`GrabMode`]: per request (open the sensor with the profile, start it into a
//! frame queue, wait for one frame, stop, close; the thesis's way) or streaming (keep
//! the sensor open and return the newest frame). Intrinsics come from the profile,
//! depth->color extrinsics from `rs2_get_extrinsics`, the depth scale from the depth
//! sensor's `RS2_OPTION_DEPTH_UNITS`, and the advanced config (the camera's
//! [`AdvancedMode`](crate::AdvancedMode)) from `rs2_serialize_json` / `rs2_load_json` (a
//! device with the advanced mode disabled answers
//! [`CameraError::AdvancedModeUnavailable`]).
//!
//! [`SoftwareD415`] puts a virtual D415 into the same context: a librealsense software
//! device whose frames a [`SyntheticCamera`](crate::SyntheticCamera) renders. It goes
//! through exactly the code path of a real camera (librealsense does not list software
//! devices in `rs2_query_devices`, but announces them to the hot-plug callback).

mod camera;
#[allow(unsafe_code)]
mod ffi;
mod software;

use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

pub use camera::RealSenseCamera;
pub use ffi::RsError;
pub use software::SoftwareD415;

use crate::camera::{Camera as _, CameraError, CameraHub, Serial};
use ffi::{Context, Device, DeviceList, Lib};

/// Environment variable naming the librealsense2 library to load.
pub const LIBRARY_ENV: &str = "LIBREALSENSE2_PATH";

/// File-name prefix of versioned librealsense2 libraries.
const VERSIONED_PREFIX: &str = "librealsense2.so.2.";

/// Library directories searched for `librealsense2.so.2.*` after `LD_LIBRARY_PATH`.
const SYSTEM_DIRS: [&str; 6] = [
    "/usr/local/lib",
    "/usr/local/lib64",
    "/usr/lib",
    "/usr/lib64",
    "/lib",
    "/lib64",
];

/// Product line a served device reports (`RS2_CAMERA_INFO_PRODUCT_LINE`).
const D400: &str = "D400";

/// Errors of loading librealsense and of the backend.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum RealSenseError {
    /// No candidate library loaded.
    #[error("librealsense2 could not be loaded; tried: {}", list_attempts(.tried))]
    NotLoaded {
        /// Every path tried and why it failed.
        tried: Vec<Attempt>,
    },
    /// A library to preload did not load.
    #[error("preloading {path} for librealsense2 failed: {reason}")]
    Preload {
        /// The library.
        path: PathBuf,
        /// The loader's message.
        reason: String,
    },
    /// A librealsense call failed.
    #[error("librealsense: {0}")]
    Call(#[from] RsError),
    /// The library works but no D400 camera appeared.
    #[error(
        "librealsense {version} ({}) found no Intel RealSense D400 camera within {waited_ms} ms{}",
        .library.display(),
        rejected_suffix(.rejected)
    )]
    NoCamera {
        /// The loaded library.
        library: PathBuf,
        /// Its version ("2.59.1").
        version: String,
        /// How long the backend waited.
        waited_ms: u64,
        /// Devices seen but not served, with the reason.
        rejected: Vec<String>,
    },
}

/// One library the search tried.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Attempt {
    /// The path or name given to the loader.
    pub path: String,
    /// Why it did not load.
    pub reason: String,
}

fn list_attempts(tried: &[Attempt]) -> String {
    tried
        .iter()
        .map(|a| format!("{} ({})", a.path, a.reason))
        .collect::<Vec<_>>()
        .join("; ")
}

fn rejected_suffix(rejected: &[String]) -> String {
    if rejected.is_empty() {
        String::new()
    } else {
        format!("; devices left out: {}", rejected.join("; "))
    }
}

/// Where to look for librealsense2 (see the module docs for the order).
#[derive(Debug, Clone, Default)]
pub struct LibrarySearch {
    /// An explicit library path (rule 1).
    pub explicit: Option<PathBuf>,
    /// Libraries loaded first, globally (e.g. the libpython of a pyrealsense2 wheel).
    pub preload: Vec<PathBuf>,
}

/// A loaded librealsense2.
#[derive(Clone)]
pub struct RealSenseLibrary {
    lib: Arc<Lib>,
    path: PathBuf,
    /// Preloaded libraries, kept loaded as long as librealsense is.
    _preloaded: Arc<Vec<Preloaded>>,
}

impl fmt::Debug for RealSenseLibrary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("RealSenseLibrary")
            .field("path", &self.path)
            .field("version", &self.version())
            .finish()
    }
}

#[cfg(unix)]
type Preloaded = libloading::os::unix::Library;

#[cfg(unix)]
fn preload(path: &Path) -> Result<Preloaded, String> {
    ffi::open_global(path)
}

#[cfg(not(unix))]
type Preloaded = ();

#[cfg(not(unix))]
fn preload(_path: &Path) -> Result<Preloaded, String> {
    Err("preloading is supported on Unix only".to_owned())
}

impl RealSenseLibrary {
    /// Finds and loads librealsense2 (after the preloads).
    pub fn load(search: &LibrarySearch) -> Result<Self, RealSenseError> {
        let preloaded = search
            .preload
            .iter()
            .map(|path| {
                preload(path).map_err(|reason| RealSenseError::Preload {
                    path: path.clone(),
                    reason,
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        let env = std::env::var_os(LIBRARY_ENV).filter(|v| !v.is_empty());
        let candidates: Vec<PathBuf> = match (&search.explicit, env) {
            (Some(path), _) => vec![path.clone()],
            (None, Some(path)) => vec![PathBuf::from(path)],
            (None, None) => system_candidates(),
        };
        let mut tried = Vec::new();
        for path in candidates {
            match Lib::open(&path) {
                Ok(lib) => {
                    return Ok(Self {
                        lib,
                        path,
                        _preloaded: Arc::new(preloaded),
                    });
                }
                Err(reason) => tried.push(Attempt {
                    path: path.display().to_string(),
                    reason,
                }),
            }
        }
        Err(RealSenseError::NotLoaded { tried })
    }

    /// The path (or name) the library was loaded from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The library's API version, "major.minor.patch".
    pub fn version(&self) -> String {
        let v = self.lib.version();
        format!("{}.{}.{}", v / 10000, v / 100 % 100, v % 100)
    }
}

/// Versioned libraries in the library directories (newest first), then the bare name.
fn system_candidates() -> Vec<PathBuf> {
    let mut dirs: Vec<PathBuf> = std::env::var_os("LD_LIBRARY_PATH")
        .map(|v| std::env::split_paths(&v).collect())
        .unwrap_or_default();
    let multiarch = format!("/usr/lib/{}-linux-gnu", std::env::consts::ARCH);
    dirs.push(PathBuf::from(multiarch));
    dirs.extend(SYSTEM_DIRS.iter().map(PathBuf::from));
    let mut found = Vec::new();
    for dir in dirs {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        let mut here: Vec<(Vec<u32>, PathBuf)> = entries
            .filter_map(Result::ok)
            .filter_map(|e| {
                let name = e.file_name().into_string().ok()?;
                let version = name.strip_prefix(VERSIONED_PREFIX)?;
                let key = version.split('.').map(|p| p.parse().unwrap_or(0)).collect();
                Some((key, e.path()))
            })
            .collect();
        here.sort_by(|a, b| b.0.cmp(&a.0));
        found.extend(here.into_iter().map(|(_, p)| p));
    }
    found.push(PathBuf::from("librealsense2.so"));
    found
}

/// How a camera grabs frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum GrabMode {
    /// Open the sensor, start it, wait for one frame, stop and close it, per grab (the
    /// thesis's way: the camera idles between requests; each grab pays the start-up).
    #[default]
    PerRequest,
    /// Keep the sensor streaming with the current profile and return the newest frame
    /// (lower latency; the sensor runs all the time). A settings change restarts it.
    Streaming,
}

struct Shared {
    lib: Arc<Lib>,
    hub: Arc<CameraHub>,
    mode: GrabMode,
    served: Mutex<Vec<Arc<RealSenseCamera>>>,
    rejected: Mutex<Vec<String>>,
}

impl Shared {
    fn served(&self) -> MutexGuard<'_, Vec<Arc<RealSenseCamera>>> {
        // A list of handles: consistent after any panic.
        self.served.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn reject(&self, reason: String) {
        self.rejected
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(reason);
    }

    /// Serves `device` unless it is already served or not a usable D400.
    fn add(&self, device: Device) {
        let camera = match RealSenseCamera::new(Arc::clone(&self.lib), device, self.mode) {
            Ok(camera) => Arc::new(camera),
            Err(reason) => return self.reject(reason),
        };
        let mut served = self.served();
        if served.iter().any(|c| c.serial() == camera.serial()) {
            return;
        }
        match self.hub.add(camera.clone()) {
            Ok(()) => served.push(camera),
            Err(e) => self.reject(e.to_string()),
        }
    }

    fn changed(&self, removed: &DeviceList, added: &DeviceList) {
        let mut served = self.served();
        served.retain(|camera| {
            let gone = camera.is_in(removed).unwrap_or(false);
            if gone {
                camera.set_disconnected();
                self.hub.remove(&camera.serial());
            }
            !gone
        });
        drop(served);
        let count = match added.len() {
            Ok(n) => n,
            Err(e) => return self.reject(e.to_string()),
        };
        for i in 0..count {
            match added.device(i) {
                Ok(device) => self.add(device),
                Err(e) => self.reject(e.to_string()),
            }
        }
    }
}

/// The librealsense backend: a context whose D400 cameras are kept in a hub.
pub struct RealSense {
    // Dropped first: stops the hot-plug callback.
    context: Context,
    library: RealSenseLibrary,
    shared: Arc<Shared>,
}

impl fmt::Debug for RealSense {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("RealSense")
            .field("library", &self.library)
            .field("hub", &self.shared.hub)
            .finish()
    }
}

impl RealSense {
    /// Opens a context, adds every D400 camera librealsense lists to `hub`, and
    /// follows hot-plug from then on. Finding no camera is not an error here (see
    /// [`RealSense::wait_for_cameras`]).
    pub fn start(
        library: &RealSenseLibrary,
        hub: Arc<CameraHub>,
        mode: GrabMode,
    ) -> Result<Self, RealSenseError> {
        let shared = Arc::new(Shared {
            lib: Arc::clone(&library.lib),
            hub,
            mode,
            served: Mutex::new(Vec::new()),
            rejected: Mutex::new(Vec::new()),
        });
        let mut context = Context::new(&library.lib)?;
        let weak = Arc::downgrade(&shared);
        context.on_devices_changed(Box::new(move |removed, added| {
            if let Some(shared) = weak.upgrade() {
                shared.changed(&removed, &added);
            }
        }))?;
        let devices = context.query_devices()?;
        for i in 0..devices.len()? {
            shared.add(devices.device(i)?);
        }
        Ok(Self {
            library: library.clone(),
            shared,
            context,
        })
    }

    /// Waits up to `timeout` until at least one camera is served; returns their
    /// serials, or [`RealSenseError::NoCamera`].
    pub fn wait_for_cameras(&self, timeout: Duration) -> Result<Vec<Serial>, RealSenseError> {
        let start = Instant::now();
        loop {
            let serials: Vec<Serial> = self.shared.served().iter().map(|c| c.serial()).collect();
            if !serials.is_empty() {
                return Ok(serials);
            }
            if start.elapsed() >= timeout {
                return Err(RealSenseError::NoCamera {
                    library: self.library.path.clone(),
                    version: self.library.version(),
                    waited_ms: timeout.as_millis().try_into().unwrap_or(u64::MAX),
                    rejected: self.rejected(),
                });
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// The cameras served now.
    pub fn cameras(&self) -> Vec<Arc<RealSenseCamera>> {
        self.shared.served().clone()
    }

    /// Devices seen but not served, each with the reason.
    pub fn rejected(&self) -> Vec<String> {
        self.shared
            .rejected
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Puts a virtual D415 fed by `synthetic` into this context (see [`SoftwareD415`]);
    /// the hot-plug callback then serves it like a connected camera.
    pub fn add_software_d415(
        &self,
        synthetic: Arc<crate::SyntheticCamera>,
    ) -> Result<SoftwareD415, RealSenseError> {
        SoftwareD415::new(&self.library.lib, &self.context, synthetic)
    }
}

impl From<RsError> for CameraError {
    fn from(e: RsError) -> Self {
        Self::Device(e.to_string())
    }
}
