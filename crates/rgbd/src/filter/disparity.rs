//! Depth <-> disparity (librealsense `disparity_transform`, DISPARITY32).
//!
//! Disparity is in 1/32 pixel: `d = factor / z_raw` with
//! `factor = baseline_m * fx * 32 / depth_scale` in `f32`, where `baseline_m` is the
//! stereo baseline in millimetres times 0.001 (librealsense's sensors report it in
//! millimetres) and `fx` that of the frame being converted. To disparity: `factor / raw`
//! for raw != 0, else 0 (no rounding). Back to depth: `(u16)(factor / d + 0.5)` when
//! `d` is a normal float, else 0.

use rayon::prelude::*;

use super::{FilterError, check_frame, empty_frame, rows, shape_output};
use crate::frame::DepthFrame;
use crate::intrinsics::Intrinsics;

/// Rows per parallel task.
const ROWS_PER_TASK: usize = 16;

/// One disparity image (DISPARITY32) and the factor that links it to depth.
#[derive(Debug, Clone, PartialEq)]
pub struct DisparityFrame {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Metres per raw depth unit of the depth frame this came from.
    pub depth_scale: f32,
    /// `baseline_m * fx * 32 / depth_scale`: disparity (1/32 px) times raw depth.
    pub factor: f32,
    /// Capture time of the depth frame, microseconds.
    pub timestamp_us: u64,
    /// Frame number of the depth frame.
    pub frame_number: u64,
    /// Disparity in 1/32 pixel, row-major, compact; 0 = no data.
    pub data: Vec<f32>,
}

/// librealsense's conversion factor between raw depth and disparity in 1/32 pixel.
pub fn disparity_factor(baseline_mm: f32, fx: f32, depth_scale: f32) -> f32 {
    let baseline_m = baseline_mm * 0.001;
    (baseline_m * fx * 32.0) / depth_scale
}

/// Depth -> disparity, with its output buffer.
#[derive(Debug, Clone)]
pub struct DepthToDisparity {
    baseline_mm: f32,
    out: DisparityFrame,
}

impl DepthToDisparity {
    /// A transform for a stereo camera with this baseline (millimetres, > 0; the
    /// D415's is 55).
    pub fn new(baseline_mm: f32) -> Result<Self, FilterError> {
        if !(baseline_mm.is_finite() && baseline_mm > 0.0) {
            return Err(FilterError::Parameter {
                field: "baseline_mm",
                value: baseline_mm.to_string(),
                allowed: "a positive number of millimetres",
            });
        }
        Ok(Self {
            baseline_mm,
            out: DisparityFrame {
                width: 0,
                height: 0,
                depth_scale: DepthFrame::DEFAULT_DEPTH_SCALE,
                factor: 0.0,
                timestamp_us: 0,
                frame_number: 0,
                data: Vec::new(),
            },
        })
    }

    /// The disparity image of `frame`; mutable so that the spatial filter can work on
    /// it in place.
    pub fn process(
        &mut self,
        frame: &DepthFrame,
        intrinsics: &Intrinsics,
    ) -> Result<&mut DisparityFrame, FilterError> {
        check_frame(frame, Some(intrinsics))?;
        let factor = disparity_factor(self.baseline_mm, intrinsics.fx, frame.depth_scale);
        let out = &mut self.out;
        out.width = frame.width;
        out.height = frame.height;
        out.depth_scale = frame.depth_scale;
        out.factor = factor;
        out.timestamp_us = frame.timestamp_us;
        out.frame_number = frame.frame_number;
        out.data
            .resize(frame.width as usize * frame.height as usize, 0.0);
        let width = (frame.width as usize).max(1);
        let input: Vec<&[u16]> = rows(frame).collect();
        out.data
            .par_chunks_mut(width * ROWS_PER_TASK)
            .zip(input.par_chunks(ROWS_PER_TASK))
            .for_each(|(dst, src)| {
                for (d_row, s_row) in dst.chunks_mut(width).zip(src) {
                    for (d, &raw) in d_row.iter_mut().zip(s_row.iter()) {
                        *d = if raw == 0 {
                            0.0
                        } else {
                            factor / f32::from(raw)
                        };
                    }
                }
            });
        Ok(&mut self.out)
    }
}

/// Disparity -> depth, with its output buffer.
#[derive(Debug, Clone)]
pub struct DisparityToDepth {
    out: DepthFrame,
}

impl Default for DisparityToDepth {
    fn default() -> Self {
        Self::new()
    }
}

impl DisparityToDepth {
    /// A transform with an empty output buffer.
    pub fn new() -> Self {
        Self { out: empty_frame() }
    }

    /// The depth frame of `disparity`; mutable so that hole filling can work on it in
    /// place.
    pub fn process(&mut self, disparity: &DisparityFrame) -> &mut DepthFrame {
        let out = &mut self.out;
        out.width = disparity.width;
        out.height = disparity.height;
        out.stride = disparity.width as usize;
        out.depth_scale = disparity.depth_scale;
        out.timestamp_us = disparity.timestamp_us;
        out.frame_number = disparity.frame_number;
        out.data.resize(disparity.data.len(), 0);
        let factor = disparity.factor;
        out.data
            .par_chunks_mut(1 << 14)
            .zip(disparity.data.par_chunks(1 << 14))
            .for_each(|(dst, src)| {
                for (d, &v) in dst.iter_mut().zip(src) {
                    // librealsense: (uint16_t)(factor / d + 0.5) for normal d. The
                    // `as` conversion truncates like C's; values past 65535 (not
                    // reachable from Z16 input) saturate instead of wrapping.
                    *d = if v.is_normal() {
                        (factor / v + 0.5) as u16
                    } else {
                        0
                    };
                }
            });
        out
    }
}

/// Copies `frame` into `out` (compact rows), for the chain's in-place stages.
pub(crate) fn copy_compact(frame: &DepthFrame, out: &mut DepthFrame) {
    shape_output(out, frame, frame.width, frame.height);
    let width = (frame.width as usize).max(1);
    for (d_row, s_row) in out.data.chunks_mut(width).zip(rows(frame)) {
        d_row.copy_from_slice(s_row);
    }
}
