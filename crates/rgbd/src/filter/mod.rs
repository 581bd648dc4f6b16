//! Depth post-processing as librealsense's processing blocks do it, bit for bit where
//! librealsense is deterministic (threshold, decimation, hole filling, depth <->
//! disparity) and to the last float rounding for the spatial filter. One stage is
//! coapcam's own, with no librealsense counterpart: [`flying`], which drops the pixels
//! that float between a depth step's two surfaces.
//!
//! Every filter owns its output or scratch buffers and reuses them from one frame to
//! the next; the work is spread over rayon's pool. Filters take a [`DepthFrame`] with
//! its [`Intrinsics`] and give back the filtered frame with the intrinsics that describe
//! it (decimation scales them, the 2D crop shifts the principal point).
//!
//! The filters that make a new frame of a depth frame (threshold, decimation, hole
//! filling, the 2D crop) are [`FrameFilter`]s: each filters a [`Checked`] frame, and
//! [`FrameFilter::process`] checks the frame and its intrinsics first, once for all.
//!
//! Where librealsense's code departs from its documentation we follow the code; each
//! module says where.

pub mod chain;
pub mod decimation;
pub mod disparity;
pub mod flying;
pub mod hole_fill;
pub mod roi;
pub mod spatial;
pub mod threshold;

pub use chain::{
    DecimationConfig, FlyingPixelsConfig, HoleFillingConfig, PostProcessing, PostProcessingConfig,
    PostProcessingError, SpatialConfig,
};
pub use decimation::Decimation;
pub use disparity::{DepthToDisparity, DisparityFrame, DisparityToDepth};
pub use flying::FlyingPixels;
pub use hole_fill::{HoleFilling, HoleFillingMode};
pub use roi::{Roi2, RoiCrop};
pub use spatial::{SpatialFilter, SpatialParams};
pub use threshold::Threshold;

use crate::frame::DepthFrame;
use crate::intrinsics::Intrinsics;

/// Why a filter refused a frame or a parameter.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum FilterError {
    /// The frame's buffer is shorter than `stride * height`, or its stride is narrower
    /// than a row.
    #[error(
        "depth frame {width}x{height} with stride {stride} needs {needed} values, it holds {len}"
    )]
    FrameSize {
        /// Frame width, pixels.
        width: u32,
        /// Frame height, pixels.
        height: u32,
        /// Frame stride, values.
        stride: usize,
        /// Values a frame of this size needs.
        needed: usize,
        /// Values the frame holds.
        len: usize,
    },
    /// A disparity frame's buffer is shorter than `width * height`.
    #[error("disparity frame {width}x{height} needs {needed} values, it holds {len}")]
    DisparitySize {
        /// Frame width, pixels.
        width: u32,
        /// Frame height, pixels.
        height: u32,
        /// Values a frame of this size needs.
        needed: usize,
        /// Values the frame holds.
        len: usize,
    },
    /// The intrinsics describe an image of another size than the frame.
    #[error("intrinsics are for {k_width}x{k_height} but the frame is {width}x{height}")]
    IntrinsicsSize {
        /// Frame width, pixels.
        width: u32,
        /// Frame height, pixels.
        height: u32,
        /// Width of the intrinsics.
        k_width: u32,
        /// Height of the intrinsics.
        k_height: u32,
    },
    /// A filter parameter outside what librealsense allows.
    #[error("{field} = {value} is not allowed: {allowed}")]
    Parameter {
        /// The parameter's name.
        field: &'static str,
        /// The rejected value.
        value: String,
        /// What the parameter accepts.
        allowed: &'static str,
    },
    /// A 2D region of interest that does not lie inside the frame.
    #[error(
        "region of interest {width}x{height} at ({px}, {py}) does not fit the {frame_width}x{frame_height} frame"
    )]
    RoiOutside {
        /// Left column of the region.
        px: u32,
        /// Top row of the region.
        py: u32,
        /// Region width.
        width: u32,
        /// Region height.
        height: u32,
        /// Frame width.
        frame_width: u32,
        /// Frame height.
        frame_height: u32,
    },
    /// The spatial filter was asked of a camera without a stereo pair: it works on
    /// disparity, which only a stereo baseline gives.
    #[error(
        "postprocessing.spatial works on disparity and needs a stereo pair, which this camera has not got"
    )]
    NoStereoPair,
}

/// A depth frame whose buffer holds its pixels, with intrinsics of its size: only
/// [`FrameFilter::process`] makes one, so a filter indexes its rows without checking.
#[derive(Debug, Clone, Copy)]
pub struct Checked<'a> {
    frame: &'a DepthFrame,
    intrinsics: &'a Intrinsics,
}

impl<'a> Checked<'a> {
    /// The frame.
    pub fn frame(&self) -> &'a DepthFrame {
        self.frame
    }

    /// Its intrinsics.
    pub fn intrinsics(&self) -> &'a Intrinsics {
        self.intrinsics
    }
}

/// A filter that makes a new frame, which it owns, of a depth frame, with the intrinsics
/// that describe the result.
pub trait FrameFilter {
    /// The filtered frame of a checked `input` and its intrinsics.
    fn filter(&mut self, input: Checked<'_>) -> Result<(&DepthFrame, Intrinsics), FilterError>;

    /// Checks that `frame` holds its pixels and that `intrinsics` describe an image of
    /// its size, then filters it.
    fn process(
        &mut self,
        frame: &DepthFrame,
        intrinsics: &Intrinsics,
    ) -> Result<(&DepthFrame, Intrinsics), FilterError> {
        check_frame(frame, Some(intrinsics))?;
        self.filter(Checked { frame, intrinsics })
    }
}

/// Checks that `frame` holds its pixels and, when given, that `intrinsics` describe
/// an image of its size.
pub(crate) fn check_frame(
    frame: &DepthFrame,
    intrinsics: Option<&Intrinsics>,
) -> Result<(), FilterError> {
    let width = frame.width as usize;
    let needed = frame.stride.saturating_mul(frame.height as usize);
    if frame.stride < width || frame.data.len() < needed {
        return Err(FilterError::FrameSize {
            width: frame.width,
            height: frame.height,
            stride: frame.stride,
            needed: needed.max(width * frame.height as usize),
            len: frame.data.len(),
        });
    }
    if let Some(k) = intrinsics
        && (k.width != frame.width || k.height != frame.height)
    {
        return Err(FilterError::IntrinsicsSize {
            width: frame.width,
            height: frame.height,
            k_width: k.width,
            k_height: k.height,
        });
    }
    Ok(())
}

/// The rows of `frame` without their stride padding.
pub(crate) fn rows(frame: &DepthFrame) -> impl Iterator<Item = &[u16]> {
    let width = frame.width as usize;
    frame
        .data
        .chunks(frame.stride.max(1))
        .take(frame.height as usize)
        .map(move |row| &row[..width])
}

/// Resizes `out` into a compact `width` x `height` frame carrying `like`'s scale and
/// time stamps, reusing its allocation; pixel values are left for the caller to write.
pub(crate) fn shape_output(out: &mut DepthFrame, like: &DepthFrame, width: u32, height: u32) {
    out.width = width;
    out.height = height;
    out.stride = width as usize;
    out.depth_scale = like.depth_scale;
    out.timestamp_us = like.timestamp_us;
    out.frame_number = like.frame_number;
    out.data.resize(width as usize * height as usize, 0);
}

/// An empty frame to be shaped by [`shape_output`].
pub(crate) fn empty_frame() -> DepthFrame {
    DepthFrame {
        width: 0,
        height: 0,
        stride: 0,
        depth_scale: DepthFrame::DEFAULT_DEPTH_SCALE,
        timestamp_us: 0,
        frame_number: 0,
        data: Vec::new(),
    }
}
