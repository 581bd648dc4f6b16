//! Grabs (blocking; run them off the executor): a color or depth image cropped to
//! `roi2d`, or a point cloud through depth -> roi2d -> post-processing -> deprojection
//! -> 3D transformation -> roi3d.

use geometry::{Point3, TransformError, Transformation};

use crate::repr::clouds::DepthPart;
use crate::repr::no_depth::NoDepth;
use rgbd::FrameFilter as _;
use rgbd::filter::{Roi2, RoiCrop};
use rgbd::{
    Camera, CameraError, ColorFrame, DepthFrame, Extrinsics, FilterError, Intrinsics,
    PostProcessing,
};

use crate::documents::AppConfig;
use crate::server::clock::ServerClock;

/// A grabbed frame as the resources keep it; images with the intrinsics of their pixels
/// (after the `roi2d` crop).
#[derive(Debug, Clone)]
pub(crate) enum Frame {
    /// The frame, its intrinsics, and the depth->color extrinsics of its camera.
    Color(ColorFrame, Intrinsics, Extrinsics),
    Depth(DepthFrame, Intrinsics),
    /// The points and what they were computed from (the compact cloud sends that), and
    /// the height of the lowest points of the camera's whole view before `roi3d`
    /// ([`crate::report::floor_level`]): the calibration check, which a region that cuts
    /// the floor away would otherwise fool. And the parts of the table from which the
    /// camera's pixels returned no depth ([`DepthPart::no_depth`]), found before the
    /// region zeroes the floor's pixels.
    Cloud {
        points: Vec<Point3>,
        part: DepthPart,
        floor_m: Option<f32>,
        no_depth: Vec<NoDepth>,
    },
}

impl Frame {
    pub(crate) fn frame_number(&self) -> u64 {
        match self {
            Self::Color(f, ..) => f.frame_number,
            Self::Depth(f, _) => f.frame_number,
            Self::Cloud { part, .. } => part.depth.frame_number,
        }
    }

    /// The frame with its capture time on the server's clock (the backends stamp the
    /// system's).
    pub(crate) fn on_clock(mut self, clock: &ServerClock) -> Self {
        let t = match &mut self {
            Self::Color(f, ..) => &mut f.timestamp_us,
            Self::Depth(f, _) => &mut f.timestamp_us,
            Self::Cloud { part, .. } => &mut part.depth.timestamp_us,
        };
        *t = clock.shift(*t);
        self
    }

    pub(crate) fn timestamp_us(&self) -> u64 {
        match self {
            Self::Color(f, ..) => f.timestamp_us,
            Self::Depth(f, _) => f.timestamp_us,
            Self::Cloud { part, .. } => part.depth.timestamp_us,
        }
    }
}

/// Why a grab failed.
#[derive(Debug, thiserror::Error)]
pub(crate) enum GrabError {
    #[error(transparent)]
    Camera(#[from] CameraError),
    #[error("depth processing: {0}")]
    Filter(#[from] FilterError),
    #[error("3d-transformation: {0}")]
    Transform(#[from] TransformError),
    #[error("application-config roi2d lies outside the {width}x{height} frame")]
    RoiOutside { width: u32, height: u32 },
}

fn roi(app: &AppConfig, width: u32, height: u32) -> Result<Roi2, GrabError> {
    app.roi_in(width, height)
        .ok_or(GrabError::RoiOutside { width, height })
}

/// A color frame cropped to `roi2d`.
pub(crate) fn color(camera: &dyn Camera, app: &AppConfig) -> Result<Frame, GrabError> {
    let intrinsics = camera.color_intrinsics()?;
    let extrinsics = camera.depth_to_color()?;
    let frame = camera.grab_color(app.color_timeout())?;
    let r = roi(app, frame.width, frame.height)?;
    if (r.width, r.height) == (frame.width, frame.height) {
        return Ok(Frame::Color(frame, intrinsics, extrinsics));
    }
    let cropped = Intrinsics {
        width: r.width,
        height: r.height,
        ppx: intrinsics.ppx - r.px as f32,
        ppy: intrinsics.ppy - r.py as f32,
        ..intrinsics
    };
    let bpp = frame.format.bytes_per_pixel();
    let row = r.width as usize * bpp;
    let mut data = Vec::with_capacity(row * r.height as usize);
    for y in r.py..r.py + r.height {
        let start = y as usize * frame.stride + r.px as usize * bpp;
        if let Some(pixels) = frame.data.get(start..start + row) {
            data.extend_from_slice(pixels);
        }
    }
    Ok(Frame::Color(
        ColorFrame {
            width: r.width,
            height: r.height,
            stride: row,
            data,
            ..frame
        },
        cropped,
        extrinsics,
    ))
}

/// A depth frame cropped to `roi2d`.
pub(crate) fn depth(camera: &dyn Camera, app: &AppConfig) -> Result<Frame, GrabError> {
    let intrinsics = camera.depth_intrinsics()?;
    let frame = camera.grab_depth(app.depth_timeout())?;
    let r = roi(app, frame.width, frame.height)?;
    if (r.width, r.height) == (frame.width, frame.height) {
        return Ok(Frame::Depth(frame, intrinsics));
    }
    let mut crop = RoiCrop::new(r);
    let (cropped, k) = crop.process(&frame, &intrinsics)?;
    Ok(Frame::Depth(cropped.clone(), k))
}

/// A point cloud in the output frame of `transformation`, inside `roi3d`.
pub(crate) fn cloud(
    camera: &dyn Camera,
    app: &AppConfig,
    transformation: &Transformation,
) -> Result<Frame, GrabError> {
    let transform = transformation.to_transform()?;
    let intrinsics = camera.depth_intrinsics()?;
    let frame = camera.grab_depth(app.depth_timeout())?;
    let r = roi(app, frame.width, frame.height)?;
    let mut crop = RoiCrop::new(r);
    let (cropped, k) = crop.process(&frame, &intrinsics)?;
    let baseline_m = camera.stereo_baseline_m();
    // The parts of the table without depth, from the pixels as the camera returned them:
    // the flying-pixel stage drops pixels at depth steps, which returned depth, and hole
    // filling fills the holes a dark parcel leaves.
    let no_depth = crate::repr::no_depth::no_depth(cropped, &k, &transform, &app.roi3d, baseline_m);
    let mut chain = PostProcessing::new(&app.postprocessing, baseline_m.map(|b| b * 1000.0))?;
    let (processed, k) = chain.process(cropped, &k)?;
    let mut part = DepthPart {
        serial: camera.serial().to_string(),
        depth: DepthFrame {
            timestamp_us: frame.timestamp_us,
            frame_number: frame.frame_number,
            ..processed.clone()
        },
        intrinsics: k,
        transform,
        roi: app.roi3d,
        correction: None,
    };
    let floor_m = floor_level(&part);
    let points = part.points()?;
    Ok(Frame::Cloud {
        points,
        part,
        floor_m,
        no_depth,
    })
}

/// Every [`FLOOR_SAMPLE`]-th pixel of each [`FLOOR_SAMPLE`]-th row of the part's depth,
/// deprojected and moved into the common frame, without the region: the height of the
/// lowest points the camera sees ([`crate::report::floor_level`]).
fn floor_level(part: &DepthPart) -> Option<f32> {
    let d = &part.depth;
    let k = &part.intrinsics;
    let z = (0..d.height).step_by(FLOOR_SAMPLE).flat_map(|y| {
        (0..d.width).step_by(FLOOR_SAMPLE).filter_map(move |x| {
            let raw = d.raw_at(x, y).filter(|&raw| raw != 0)?;
            let [px, py, pz] = k.deproject([x as f32, y as f32], f32::from(raw) * d.depth_scale);
            Some(part.transform.apply(&Point3::new(px, py, pz)).z)
        })
    });
    crate::report::floor_level(z)
}

/// The floor check looks at one pixel in this many, each way (1/16 of a 640x480 view,
/// 19,200 points, is plenty for a percentile).
const FLOOR_SAMPLE: usize = 4;
