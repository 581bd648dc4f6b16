//! `serve --depth-pngs DIR`: a folder of depth images played as a camera, one camera per
//! folder.
//!
//! The folder holds:
//!
//! - depth frames: every `*.png` directly in it, a 16-bit grayscale PNG of raw depth
//!   units (what `coapcam grab depth -o NAME.png` and `demo`'s `depth.png` write), all of
//!   the size of the intrinsics;
//! - `camera.toml`, what a PNG does not say (no resource of the server gives it, so it
//!   is written by hand, e.g. from librealsense's `rs-enumerate-devices -c`):
//!
//! ```toml
//! serial = "840412060746"   # the camera's name on the server (rgbd::Serial)
//! depth_scale = 0.001       # metres per raw unit
//! fps = 30                  # optional (30): the frame rate the modes say
//! baseline_m = 0.055        # optional: the stereo pair's; left out, the camera has none
//! [intrinsics]              # of the depth images, pixels
//! width = 1280
//! height = 720
//! fx = 640.0
//! fy = 640.0
//! ppx = 640.0
//! ppy = 360.0
//! model = "Brown Conrady"   # optional ("None"): librealsense's name of the distortion
//! coeffs = [0.0, 0.0, 0.0, 0.0, 0.0]  # optional (zeros)
//! ```
//!
//! Every frame is decoded when the server starts (at most [`MAX_BYTES`] of pixels), so
//! a folder it cannot play stops the start, saying which file and why. Each depth grab
//! returns the next frame in the order of the file names and the first again after the
//! last (one PNG: that frame on every grab); grabs are numbered from 1 and stamped with
//! the wall clock, as live frames are. The one depth mode is the images' size at `fps`.
//! The folder has no color: a color grab fails (a station's record then has no photo).

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use image::ImageDecoder as _;
use image::codecs::png::PngDecoder;
use rgbd::{
    Camera, CameraError, CameraHub, ColorFormat, ColorFrame, ColorSettings, DepthFormat,
    DepthFrame, DepthSettings, DistortionModel, Extrinsics, HubError, Intrinsics, ModeTable,
    Pose, ResolutionModes, Scene, Serial, SerialError,
};
use serde::Deserialize;

use super::backend::{Backend, StartError};

/// The most bytes of pixels a folder's frames may decode to (1 GiB).
pub const MAX_BYTES: u64 = 1 << 30;

/// The file beside the PNGs that says what they do not.
pub const CAMERA_FILE: &str = "camera.toml";

/// The flags of the folders of depth PNGs.
#[derive(Debug, Clone, Default, clap::Args)]
#[group(skip)]
pub struct Args {
    /// Play a folder of depth PNGs as a camera instead of synthetic ones; repeatable. In
    /// DIR: every *.png, a 16-bit grayscale PNG of raw depth units (as `coapcam grab
    /// depth -o NAME.png` writes), served in the order of the names and again from the
    /// first; and camera.toml: serial = "SN", depth_scale = metres per unit, optional
    /// fps (30) and baseline_m (the stereo pair's; left out: none), and [intrinsics] of
    /// the images: width, height, fx, fy, ppx, ppy, optional model (librealsense's
    /// distortion name, "None") and coeffs (5 numbers). It has no color: color grabs fail.
    #[arg(long, value_name = "DIR", conflicts_with_all = ["scene", "no_cameras"])]
    depth_pngs: Vec<PathBuf>,
}

impl Args {
    /// Whether folders of depth PNGs are asked for.
    pub fn configured(&self) -> bool {
        !self.depth_pngs.is_empty()
    }

    /// The folders as a backend, when asked for.
    pub fn backend(&self, _scene: &Scene) -> Option<Box<dyn Backend>> {
        self.configured()
            .then(|| Box::new(Folders(self.depth_pngs.clone())) as Box<dyn Backend>)
    }
}

/// The folders of depth PNGs at these paths.
pub struct Folders(pub Vec<PathBuf>);

impl Backend for Folders {
    fn start(&mut self, hub: &Arc<CameraHub>) -> Result<Vec<Serial>, StartError> {
        let mut serials = Vec::new();
        for dir in &self.0 {
            let camera = DepthPngCamera::open(dir).map_err(StartError::backend)?;
            serials.push(camera.serial);
            hub.add(Arc::new(camera)).map_err(|source| {
                StartError::backend(DepthPngsError::Add {
                    dir: dir.clone(),
                    source,
                })
            })?;
        }
        Ok(serials)
    }
}

/// A folder of depth PNGs could not be played.
#[derive(Debug, thiserror::Error)]
pub enum DepthPngsError {
    /// The folder, or a file in it, could not be read.
    #[error("reading {}", path.display())]
    Read {
        /// The folder or file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// `camera.toml` is not what the module documentation shows.
    #[error("{}: {why}", path.display())]
    CameraFile {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        why: String,
    },
    /// The serial of `camera.toml` is not one.
    #[error("{}: serial", path.display())]
    Serial {
        /// The file.
        path: PathBuf,
        /// Why.
        source: SerialError,
    },
    /// The folder holds no `*.png`.
    #[error("no .png file in {}: a depth frame is a 16-bit grayscale PNG", dir.display())]
    NoPngs {
        /// The folder.
        dir: PathBuf,
    },
    /// The frames would decode to more than [`MAX_BYTES`].
    #[error("{} holds {frames} frames of {width}x{height}: {bytes} bytes of pixels, over the {} allowed", dir.display(), MAX_BYTES)]
    TooLarge {
        /// The folder.
        dir: PathBuf,
        /// How many PNGs.
        frames: usize,
        /// The intrinsics' width.
        width: u32,
        /// The intrinsics' height.
        height: u32,
        /// What they would take.
        bytes: u64,
    },
    /// A PNG could not be decoded.
    #[error("decoding {}", path.display())]
    Decode {
        /// The PNG.
        path: PathBuf,
        /// Why.
        source: image::ImageError,
    },
    /// A PNG is not 16-bit grayscale.
    #[error("{} is {found:?}, not a 16-bit grayscale PNG of raw depth units", path.display())]
    BitDepth {
        /// The PNG.
        path: PathBuf,
        /// Its pixels' type (`L8`, `Rgb8`, ...).
        found: image::ColorType,
    },
    /// A PNG is not of the intrinsics' size.
    #[error("{} is {width}x{height}, but camera.toml's intrinsics are {want_width}x{want_height}", path.display())]
    Size {
        /// The PNG.
        path: PathBuf,
        /// Its width.
        width: u32,
        /// Its height.
        height: u32,
        /// The intrinsics' width.
        want_width: u32,
        /// The intrinsics' height.
        want_height: u32,
    },
    /// The camera could not go into the hub.
    #[error("adding the camera of {}", dir.display())]
    Add {
        /// The folder.
        dir: PathBuf,
        /// Why.
        source: HubError,
    },
}

/// `camera.toml` as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CameraFile {
    serial: String,
    depth_scale: f32,
    #[serde(default = "default_fps")]
    fps: u32,
    baseline_m: Option<f32>,
    intrinsics: IntrinsicsFile,
}

/// The `[intrinsics]` table.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct IntrinsicsFile {
    width: u32,
    height: u32,
    fx: f32,
    fy: f32,
    ppx: f32,
    ppy: f32,
    #[serde(default = "default_model")]
    model: String,
    #[serde(default)]
    coeffs: [f32; 5],
}

fn default_fps() -> u32 {
    30
}

fn default_model() -> String {
    DistortionModel::None.name().to_owned()
}

/// Where the next grab is.
#[derive(Debug, Default)]
struct Cursor {
    /// The next frame's index.
    index: usize,
    /// Grabs so far.
    grabs: u64,
    /// The last grab's timestamp, µs since the epoch.
    last_us: u64,
}

/// A folder of depth PNGs played as a camera (see the module documentation).
#[derive(Debug)]
pub struct DepthPngCamera {
    dir: PathBuf,
    serial: Serial,
    modes: ModeTable,
    depth: DepthSettings,
    color: ColorSettings,
    intrinsics: Intrinsics,
    depth_scale: f32,
    baseline_m: Option<f32>,
    frames: Vec<Vec<u16>>,
    cursor: Mutex<Cursor>,
}

impl DepthPngCamera {
    /// Reads `dir`'s `camera.toml` and decodes its PNGs.
    ///
    /// # Errors
    ///
    /// When the folder or `camera.toml` cannot be read or is not as documented, there is
    /// no PNG, or a PNG is not 16-bit grayscale of the intrinsics' size.
    pub fn open(dir: &Path) -> Result<Self, DepthPngsError> {
        let read = |path: &Path| {
            let path = path.to_owned();
            move |source| DepthPngsError::Read { path, source }
        };
        let mut pngs = Vec::new();
        for entry in std::fs::read_dir(dir).map_err(read(dir))? {
            let path = entry.map_err(read(dir))?.path();
            let png = path
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("png"));
            if png && path.is_file() {
                pngs.push(path);
            }
        }
        pngs.sort();
        let file_path = dir.join(CAMERA_FILE);
        let text = std::fs::read_to_string(&file_path).map_err(read(&file_path))?;
        let bad = |why: String| DepthPngsError::CameraFile {
            path: file_path.clone(),
            why,
        };
        let file: CameraFile = toml::from_str(&text).map_err(|e| bad(e.message().to_owned()))?;
        let serial = Serial::parse(&file.serial).map_err(|source| DepthPngsError::Serial {
            path: file_path.clone(),
            source,
        })?;
        let k = file.intrinsics;
        let model = DistortionModel::from_name(&k.model).ok_or_else(|| {
            let names: Vec<_> = DistortionModel::ALL.iter().map(|m| m.name()).collect();
            bad(format!(
                "intrinsics.model {:?} is none of {}",
                k.model,
                names.join(", ")
            ))
        })?;
        let positive = [
            ("depth_scale", file.depth_scale),
            ("intrinsics.fx", k.fx),
            ("intrinsics.fy", k.fy),
        ];
        if let Some((name, _)) = positive.iter().find(|(_, v)| !(v.is_finite() && *v > 0.0)) {
            return Err(bad(format!("{name} must be a number above 0")));
        }
        if k.width == 0 || k.height == 0 || file.fps == 0 {
            return Err(bad(
                "intrinsics.width, intrinsics.height and fps must be above 0".into(),
            ));
        }
        if pngs.is_empty() {
            return Err(DepthPngsError::NoPngs {
                dir: dir.to_owned(),
            });
        }
        let bytes = pngs.len() as u64 * u64::from(k.width) * u64::from(k.height) * 2;
        if bytes > MAX_BYTES {
            return Err(DepthPngsError::TooLarge {
                dir: dir.to_owned(),
                frames: pngs.len(),
                width: k.width,
                height: k.height,
                bytes,
            });
        }
        let frames = pngs
            .iter()
            .map(|path| decode(path, k.width, k.height))
            .collect::<Result<_, _>>()?;
        let mode = ResolutionModes {
            width: k.width,
            height: k.height,
            fps: vec![file.fps],
        };
        Ok(Self {
            dir: dir.to_owned(),
            serial,
            modes: ModeTable {
                color_formats: vec![ColorFormat::Rgb8],
                color: vec![mode.clone()],
                depth_formats: vec![DepthFormat::Z16],
                depth: vec![mode],
            },
            depth: DepthSettings {
                format: DepthFormat::Z16,
                fps: file.fps,
                width: k.width,
                height: k.height,
            },
            color: ColorSettings {
                format: ColorFormat::Rgb8,
                fps: file.fps,
                width: k.width,
                height: k.height,
            },
            intrinsics: Intrinsics {
                width: k.width,
                height: k.height,
                ppx: k.ppx,
                ppy: k.ppy,
                fx: k.fx,
                fy: k.fy,
                model,
                coeffs: k.coeffs,
            },
            depth_scale: file.depth_scale,
            baseline_m: file.baseline_m,
            frames,
            cursor: Mutex::new(Cursor::default()),
        })
    }
}

/// The raw units of the 16-bit grayscale PNG at `path`, which must be `width`x`height`.
fn decode(path: &Path, width: u32, height: u32) -> Result<Vec<u16>, DepthPngsError> {
    let failed = |source| DepthPngsError::Decode {
        path: path.to_owned(),
        source,
    };
    let file = std::fs::File::open(path).map_err(|source| DepthPngsError::Read {
        path: path.to_owned(),
        source,
    })?;
    let decoder = PngDecoder::new(std::io::BufReader::new(file)).map_err(failed)?;
    let found = decoder.color_type();
    if found != image::ColorType::L16 {
        return Err(DepthPngsError::BitDepth {
            path: path.to_owned(),
            found,
        });
    }
    let (w, h) = decoder.dimensions();
    if (w, h) != (width, height) {
        return Err(DepthPngsError::Size {
            path: path.to_owned(),
            width: w,
            height: h,
            want_width: width,
            want_height: height,
        });
    }
    let image = image::DynamicImage::from_decoder(decoder).map_err(failed)?;
    Ok(image.into_luma16().into_raw())
}

impl Camera for DepthPngCamera {
    fn serial(&self) -> Serial {
        self.serial
    }

    fn model(&self) -> &str {
        "folder of depth PNGs"
    }

    fn stream_modes(&self) -> &ModeTable {
        &self.modes
    }

    fn color_settings(&self) -> ColorSettings {
        self.color
    }

    fn set_color_settings(&self, settings: ColorSettings) -> Result<(), CameraError> {
        settings.validate(&self.modes)?;
        Ok(())
    }

    fn depth_settings(&self) -> DepthSettings {
        self.depth
    }

    fn set_depth_settings(&self, settings: DepthSettings) -> Result<(), CameraError> {
        settings.validate(&self.modes)?;
        Ok(())
    }

    fn grab_color(&self, _timeout: Duration) -> Result<ColorFrame, CameraError> {
        Err(CameraError::Device(format!(
            "{} is a folder of depth PNGs: it has no color",
            self.dir.display()
        )))
    }

    fn grab_depth(&self, _timeout: Duration) -> Result<DepthFrame, CameraError> {
        let (index, frame_number, timestamp_us) = {
            // Every update is a few assignments; a panicking holder leaves it consistent.
            let mut c = self.cursor.lock().unwrap_or_else(PoisonError::into_inner);
            let index = c.index;
            c.index = (index + 1) % self.frames.len().max(1);
            c.grabs += 1;
            let now_us = SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map_or(0, |d| u64::try_from(d.as_micros()).unwrap_or(u64::MAX));
            c.last_us = now_us.max(c.last_us + 1);
            (index, c.grabs, c.last_us)
        };
        Ok(DepthFrame {
            width: self.depth.width,
            height: self.depth.height,
            stride: self.depth.width as usize,
            depth_scale: self.depth_scale,
            timestamp_us,
            frame_number,
            data: self.frames.get(index).cloned().unwrap_or_default(),
        })
    }

    fn depth_intrinsics(&self) -> Result<Intrinsics, CameraError> {
        Ok(self.intrinsics)
    }

    fn color_intrinsics(&self) -> Result<Intrinsics, CameraError> {
        Ok(self.intrinsics)
    }

    fn depth_to_color(&self) -> Result<Extrinsics, CameraError> {
        Ok(Extrinsics::IDENTITY)
    }

    fn depth_scale(&self) -> f32 {
        self.depth_scale
    }

    fn stereo_baseline_m(&self) -> Option<f32> {
        self.baseline_m
    }

    fn true_pose(&self) -> Option<Pose> {
        None
    }
}
