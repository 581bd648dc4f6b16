//! Flying-pixel filter (coapcam's own stage; librealsense has none): zeroes every pixel
//! that lies clearly behind one of its eight neighbours.
//!
//! Where a pixel's footprint straddles a depth step (a lid's edge over the floor, a
//! parcel's side over a lower neighbour), a stereo camera reports a depth between the two
//! surfaces: a point that floats along the camera's ray, beyond the nearer surface's edge
//! and above the farther one. From a tilted camera such points land centimetres beyond a
//! parcel's side, and where two parcels stand close they bridge the gap between them.
//! Such a pixel always has a neighbour on the nearer surface, clearly nearer than itself.
//! So does the first pixel of the farther surface beside the step (it is dropped too: it
//! lies where the nearer surface hides the farther one's edge anyway), while every pixel
//! of the nearer surface, up to its edge, stays.
//!
//! "Clearly" is a share of the pixel's own depth (`step`, 2 % by default: 30 mm at
//! 1.5 m, several times a D415's noise there and more than two neighbours differ on a
//! surface seen at 80 degrees). Pixels without depth are no neighbours.

use rayon::prelude::*;

use super::{Checked, FilterError, FrameFilter, shape_output};
use crate::frame::DepthFrame;
use crate::intrinsics::Intrinsics;

/// Rows per parallel task.
const ROWS_PER_TASK: usize = 16;

/// Drops the pixels that lie clearly behind a neighbour.
#[derive(Debug, Clone)]
pub struct FlyingPixels {
    step: f32,
    out: DepthFrame,
}

impl FlyingPixels {
    /// The default step, as a share of the pixel's depth.
    pub const DEFAULT_STEP: f32 = 0.02;
    /// The steps a filter takes.
    pub const STEPS: std::ops::RangeInclusive<f32> = 0.005..=0.5;

    /// A filter dropping pixels more than `step` (a share of their depth, 0.005 to 0.5)
    /// behind a neighbour.
    pub fn new(step: f32) -> Result<Self, FilterError> {
        if !Self::STEPS.contains(&step) {
            return Err(FilterError::Parameter {
                field: "step",
                value: step.to_string(),
                allowed: "a share of the depth from 0.005 to 0.5",
            });
        }
        Ok(Self {
            step,
            out: super::empty_frame(),
        })
    }
}

impl FrameFilter for FlyingPixels {
    fn filter(&mut self, input: Checked<'_>) -> Result<(&DepthFrame, Intrinsics), FilterError> {
        let frame = input.frame();
        let (width, height) = (frame.width as usize, frame.height as usize);
        shape_output(&mut self.out, frame, frame.width, frame.height);
        self.out.data.resize(width * height, 0);
        if width == 0 || height == 0 {
            return Ok((&self.out, *input.intrinsics()));
        }
        let (stride, step) = (frame.stride, 1.0 - self.step);
        let src = &frame.data;
        self.out
            .data
            .par_chunks_mut(width * ROWS_PER_TASK)
            .enumerate()
            .for_each(|(task, block)| {
                for (i, out_row) in block.chunks_mut(width).enumerate() {
                    let v = task * ROWS_PER_TASK + i;
                    let rows = v.saturating_sub(1)..(v + 2).min(height);
                    for (u, out) in out_row.iter_mut().enumerate() {
                        let z = src[v * stride + u];
                        // A neighbour nearer than (1 - step) z: in f32, as the share is.
                        let limit = f32::from(z) * step;
                        let columns = u.saturating_sub(1)..(u + 2).min(width);
                        let behind = z != 0
                            && rows.clone().any(|r| {
                                src[r * stride + columns.start..r * stride + columns.end]
                                    .iter()
                                    .any(|&n| n != 0 && f32::from(n) < limit)
                            });
                        *out = if behind { 0 } else { z };
                    }
                }
            });
        Ok((&self.out, *input.intrinsics()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(width: u32, data: Vec<u16>) -> (DepthFrame, Intrinsics) {
        let height = data.len() as u32 / width;
        let frame = DepthFrame {
            width,
            height,
            stride: width as usize,
            depth_scale: 0.001,
            timestamp_us: 0,
            frame_number: 1,
            data,
        };
        let k = Intrinsics {
            width,
            height,
            ppx: 0.0,
            ppy: 0.0,
            fx: 1.0,
            fy: 1.0,
            model: crate::DistortionModel::None,
            coeffs: [0.0; 5],
        };
        (frame, k)
    }

    #[test]
    fn a_pixel_between_a_lid_and_the_floor_goes_and_the_lids_edge_stays() {
        // A lid at 1.2 m, one flying pixel at 1.35 m, the floor at 1.5 m, across a row;
        // a second row the same.
        let row = [1200, 1200, 1350, 1500, 1500, 1500];
        let (f, k) = frame(6, [row, row].concat());
        let mut filter = FlyingPixels::new(FlyingPixels::DEFAULT_STEP).unwrap();
        let (out, _) = filter.process(&f, &k).unwrap();
        // The floor's first pixel beside the flying one lies behind it: it goes too.
        let kept = [1200, 1200, 0, 0, 1500, 1500];
        assert_eq!(out.data, [kept, kept].concat());
    }

    #[test]
    fn noise_and_a_slope_stay_and_holes_are_no_neighbours() {
        let (f, k) = frame(
            5,
            vec![1500, 1505, 0, 1498, 1510, 1512, 1515, 1518, 0, 1520],
        );
        let mut filter = FlyingPixels::new(FlyingPixels::DEFAULT_STEP).unwrap();
        let (out, _) = filter.process(&f, &k).unwrap();
        assert_eq!(out.data, f.data);
    }

    #[test]
    fn a_step_outside_its_range_is_refused() {
        assert!(FlyingPixels::new(0.0).is_err());
        assert!(FlyingPixels::new(0.6).is_err());
    }
}
