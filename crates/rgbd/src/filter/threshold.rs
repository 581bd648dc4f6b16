//! Threshold filter (librealsense `threshold_filter`): keeps depth between a minimum
//! and a maximum distance, zeroes the rest.
//!
//! librealsense keeps a raw value iff `min <= depth_scale * raw <= max`, computed in
//! `f32` with both bounds inclusive; raw 0 stays 0. Options range over 0..16 m,
//! defaults 0.1 m and 4 m.

use rayon::prelude::*;

use super::{Checked, FilterError, FrameFilter, check_frame, empty_frame, rows, shape_output};
use crate::frame::DepthFrame;
use crate::intrinsics::Intrinsics;

/// Rows per parallel task.
const ROWS_PER_TASK: usize = 16;

/// Keeps depth within `[min_m, max_m]`.
#[derive(Debug, Clone)]
pub struct Threshold {
    min_m: f32,
    max_m: f32,
    out: DepthFrame,
}

impl Threshold {
    /// librealsense's default minimum distance, metres.
    pub const DEFAULT_MIN_M: f32 = 0.1;
    /// librealsense's default maximum distance, metres.
    pub const DEFAULT_MAX_M: f32 = 4.0;
    /// Largest distance librealsense accepts for either bound, metres.
    pub const LIMIT_M: f32 = 16.0;

    /// A threshold keeping `min_m..=max_m` (each within 0..=16 m as librealsense
    /// allows; `min_m > max_m` keeps nothing, as in librealsense).
    pub fn new(min_m: f32, max_m: f32) -> Result<Self, FilterError> {
        for (field, value) in [("min_distance", min_m), ("max_distance", max_m)] {
            if !(0.0..=Self::LIMIT_M).contains(&value) {
                return Err(FilterError::Parameter {
                    field,
                    value: value.to_string(),
                    allowed: "0 to 16 metres",
                });
            }
        }
        Ok(Self {
            min_m,
            max_m,
            out: empty_frame(),
        })
    }

    fn keep(&self, raw: u16, scale: f32) -> u16 {
        let dist = scale * f32::from(raw);
        if dist >= self.min_m && dist <= self.max_m {
            raw
        } else {
            0
        }
    }

    /// Zeroes, in place, every pixel of `frame` outside the range.
    pub fn apply_in_place(&self, frame: &mut DepthFrame) -> Result<(), FilterError> {
        check_frame(frame, None)?;
        if frame.width == 0 || frame.height == 0 {
            return Ok(());
        }
        let (width, stride, scale) = (frame.width as usize, frame.stride, frame.depth_scale);
        let len = stride * frame.height as usize;
        frame.data[..len]
            .par_chunks_mut(stride * ROWS_PER_TASK)
            .for_each(|block| {
                for row in block.chunks_mut(stride) {
                    for v in &mut row[..width] {
                        *v = self.keep(*v, scale);
                    }
                }
            });
        Ok(())
    }
}

impl FrameFilter for Threshold {
    /// The thresholded copy of the frame (compact rows) and its unchanged intrinsics.
    fn filter(&mut self, input: Checked<'_>) -> Result<(&DepthFrame, Intrinsics), FilterError> {
        let (frame, intrinsics) = (input.frame(), input.intrinsics());
        let mut out = std::mem::replace(&mut self.out, empty_frame());
        shape_output(&mut out, frame, frame.width, frame.height);
        let width = (frame.width as usize).max(1);
        let input: Vec<&[u16]> = rows(frame).collect();
        let scale = frame.depth_scale;
        out.data
            .par_chunks_mut(width * ROWS_PER_TASK)
            .zip(input.par_chunks(ROWS_PER_TASK))
            .for_each(|(dst, src)| {
                for (d_row, s_row) in dst.chunks_mut(width).zip(src) {
                    for (d, &s) in d_row.iter_mut().zip(s_row.iter()) {
                        *d = self.keep(s, scale);
                    }
                }
            });
        self.out = out;
        Ok((&self.out, *intrinsics))
    }
}
