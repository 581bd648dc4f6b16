//! 2D region-of-interest crop (the application-config `roi2d` of thesis Listing A.3):
//! keeps a `width` x `height` window whose top-left pixel is (`px`, `py`).
//!
//! The crop's intrinsics are the frame's with the principal point moved by the
//! window's origin (`ppx - px`, `ppy - py`) and the window's size, so a pixel of the
//! crop deprojects to the same point as the pixel it came from.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::{Checked, FilterError, FrameFilter, empty_frame, shape_output};
use crate::frame::DepthFrame;
use crate::intrinsics::Intrinsics;

/// Rows per parallel task.
const ROWS_PER_TASK: usize = 32;

/// A window of an image, in pixels (keys as thesis Listing A.3 `roi2d`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Roi2 {
    /// Left column.
    pub px: u32,
    /// Top row.
    pub py: u32,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
}

impl Roi2 {
    /// True when the window lies inside a `width` x `height` image.
    pub fn fits(&self, width: u32, height: u32) -> bool {
        u64::from(self.px) + u64::from(self.width) <= u64::from(width)
            && u64::from(self.py) + u64::from(self.height) <= u64::from(height)
    }
}

/// Crops depth frames to a [`Roi2`], reusing its output buffer.
#[derive(Debug, Clone)]
pub struct RoiCrop {
    roi: Roi2,
    out: DepthFrame,
}

impl RoiCrop {
    /// A crop to `roi`.
    pub fn new(roi: Roi2) -> Self {
        Self {
            roi,
            out: empty_frame(),
        }
    }
}

impl FrameFilter for RoiCrop {
    /// The window of the frame (compact rows) and its intrinsics; fails when the window
    /// does not lie inside the frame.
    fn filter(&mut self, input: Checked<'_>) -> Result<(&DepthFrame, Intrinsics), FilterError> {
        let (frame, intrinsics) = (input.frame(), input.intrinsics());
        let r = self.roi;
        if !r.fits(frame.width, frame.height) {
            return Err(FilterError::RoiOutside {
                px: r.px,
                py: r.py,
                width: r.width,
                height: r.height,
                frame_width: frame.width,
                frame_height: frame.height,
            });
        }
        shape_output(&mut self.out, frame, r.width, r.height);
        let (w, px, stride) = (r.width as usize, r.px as usize, frame.stride);
        // A window of width 0 copies nothing; one of width > 0 lies in a frame of that
        // width, whose rows `process` has found in `data`.
        if w > 0 {
            let src = &frame.data[r.py as usize * stride..];
            self.out
                .data
                .par_chunks_mut(w * ROWS_PER_TASK)
                .enumerate()
                .for_each(|(block, dst)| {
                    for (i, d_row) in dst.chunks_mut(w).enumerate() {
                        let start = (block * ROWS_PER_TASK + i) * stride + px;
                        d_row.copy_from_slice(&src[start..start + w]);
                    }
                });
        }
        let k = Intrinsics {
            width: r.width,
            height: r.height,
            ppx: intrinsics.ppx - r.px as f32,
            ppy: intrinsics.ppy - r.py as f32,
            ..*intrinsics
        };
        Ok((&self.out, k))
    }
}
