//! Decimation filter (librealsense `decimation_filter`, Z16 path): shrinks a depth
//! frame by an integer magnitude `s` in 1..=8.
//!
//! As librealsense computes it:
//! - the output has `W / s` x `H / s` pixels of data (integer division: leftover input
//!   rows and columns are dropped), padded with zeros to the next multiple of 4 in each
//!   direction; the frame and its intrinsics have the padded size;
//! - for `s` = 2 and 3 each pixel is the lower median (`sorted[(k - 1) / 2]`) of the
//!   `k` non-zero pixels of its `s` x `s` block, for other magnitudes their integer mean
//!   (sum / k, truncated); 0 when the block has no depth;
//! - intrinsics: `fx / s`, `fy / s`, `ppx / s`, `ppy / s` in `f32` (no half-pixel
//!   correction), model and coefficients unchanged.
//!
//! librealsense's documentation names the range 2..8; its code accepts 1.

use rayon::prelude::*;

use super::{Checked, FilterError, FrameFilter, empty_frame, shape_output};
use crate::frame::DepthFrame;
use crate::intrinsics::Intrinsics;

/// Output rows per parallel task.
const ROWS_PER_TASK: usize = 8;

/// The decimation filter with its output buffer.
#[derive(Debug, Clone)]
pub struct Decimation {
    magnitude: u32,
    out: DepthFrame,
}

impl Decimation {
    /// librealsense's default magnitude.
    pub const DEFAULT_MAGNITUDE: u8 = 2;
    /// Largest magnitude librealsense accepts.
    pub const MAX_MAGNITUDE: u8 = 8;

    /// A filter of `magnitude` 1..=8.
    pub fn new(magnitude: u8) -> Result<Self, FilterError> {
        if !(1..=Self::MAX_MAGNITUDE).contains(&magnitude) {
            return Err(FilterError::Parameter {
                field: "magnitude",
                value: magnitude.to_string(),
                allowed: "an integer from 1 to 8",
            });
        }
        Ok(Self {
            magnitude: u32::from(magnitude),
            out: empty_frame(),
        })
    }

    /// Size of the output for a `width` x `height` input: (data size, padded size).
    pub fn output_size(&self, width: u32, height: u32) -> ((u32, u32), (u32, u32)) {
        let (w, h) = (width / self.magnitude, height / self.magnitude);
        ((w, h), (w.div_ceil(4) * 4, h.div_ceil(4) * 4))
    }
}

impl FrameFilter for Decimation {
    /// The decimated frame and its intrinsics.
    fn filter(&mut self, input: Checked<'_>) -> Result<(&DepthFrame, Intrinsics), FilterError> {
        let (frame, intrinsics) = (input.frame(), input.intrinsics());
        let s = self.magnitude as usize;
        let ((real_w, real_h), (pad_w, pad_h)) = self.output_size(frame.width, frame.height);
        shape_output(&mut self.out, frame, pad_w, pad_h);
        let (real_w, pad_w, stride) = (real_w as usize, pad_w as usize, frame.stride);
        let data_rows = real_h as usize * pad_w;
        let input = &frame.data;
        let (data, padding) = self.out.data.split_at_mut(data_rows);
        padding.fill(0);
        data.par_chunks_mut((pad_w * ROWS_PER_TASK).max(1))
            .enumerate()
            .for_each(|(task, block)| {
                for (i, row) in block.chunks_mut(pad_w).enumerate() {
                    let top = (task * ROWS_PER_TASK + i) * s * stride;
                    let src = &input[top..];
                    let (cells, pad) = row.split_at_mut(real_w);
                    pad.fill(0);
                    match s {
                        2 => decimate_median2(src, stride, cells),
                        3 => decimate_median3(src, stride, cells),
                        _ => decimate_mean(src, stride, s, cells),
                    }
                }
            });
        let sf = s as f32;
        let k = Intrinsics {
            width: self.out.width,
            height: pad_h,
            ppx: intrinsics.ppx / sf,
            ppy: intrinsics.ppy / sf,
            fx: intrinsics.fx / sf,
            fy: intrinsics.fy / sf,
            ..*intrinsics
        };
        Ok((&self.out, k))
    }
}

/// Sorts two values in place (a compare-exchange of a sorting network).
fn order(a: &mut u16, b: &mut u16) {
    let (lo, hi) = ((*a).min(*b), (*a).max(*b));
    *a = lo;
    *b = hi;
}

/// 2x2 blocks: lower median of the non-zero pixels. Zeros sort first, so with `k`
/// non-zero values in the sorted four, the lower median sits at `4 - k + (k - 1) / 2`.
fn decimate_median2(src: &[u16], stride: usize, cells: &mut [u16]) {
    let (r0, r1) = (src, &src[stride..]);
    for (i, cell) in cells.iter_mut().enumerate() {
        let x = 2 * i;
        let mut v = [r0[x], r0[x + 1], r1[x], r1[x + 1]];
        let k = v.iter().filter(|&&p| p != 0).count();
        let [a, b, c, d] = &mut v;
        order(a, b);
        order(c, d);
        order(a, c);
        order(b, d);
        order(b, c);
        *cell = if k == 0 { 0 } else { v[4 - k + (k - 1) / 2] };
    }
}

/// 3x3 blocks: lower median of the non-zero pixels.
fn decimate_median3(src: &[u16], stride: usize, cells: &mut [u16]) {
    for (i, cell) in cells.iter_mut().enumerate() {
        let x = 3 * i;
        let mut v = [0u16; 9];
        let mut k = 0;
        for r in 0..3 {
            for &p in &src[r * stride + x..r * stride + x + 3] {
                if p != 0 {
                    v[k] = p;
                    k += 1;
                }
            }
        }
        *cell = if k == 0 {
            0
        } else {
            let nz = &mut v[..k];
            nz.sort_unstable();
            nz[(k - 1) / 2]
        };
    }
}

/// `s` x `s` blocks: integer mean of the non-zero pixels (truncated).
fn decimate_mean(src: &[u16], stride: usize, s: usize, cells: &mut [u16]) {
    for (i, cell) in cells.iter_mut().enumerate() {
        let x = s * i;
        let (mut sum, mut k) = (0u32, 0u32);
        for r in 0..s {
            for &p in &src[r * stride + x..r * stride + x + s] {
                sum += u32::from(p);
                k += u32::from(p != 0);
            }
        }
        // The mean of u16 values fits u16; no values gives 0.
        *cell = sum.checked_div(k).unwrap_or(0) as u16;
    }
}
