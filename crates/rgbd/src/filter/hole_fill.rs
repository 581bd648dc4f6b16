//! Hole-filling filter (librealsense `hole_filling_filter`) on Z16 depth, in place;
//! 0 is a hole.
//!
//! The modes as librealsense's code runs them (its documentation differs):
//! - `fill_from_left`: along each row from column 1, a hole takes the value left of it
//!   (already filled), so a value propagates right through a run of holes; column 0
//!   stays as it is.
//! - `farest_from_around`: rows 1..H-2, columns 1..W-1 in raster order; a hole takes
//!   the largest of its up, up-left, left, down-left and down neighbours (no right-hand
//!   neighbours; up and left already filled). The documentation says "four immediate
//!   neighbours".
//! - `nearest_from_around`: same scan; starting from the up neighbour, each of
//!   up-left, left, down-left and down that is non-zero and smaller replaces it. When
//!   the up neighbour is 0 the hole stays 0.
//!
//! `fill_from_left` runs its rows in parallel. The two "around" modes are a raster
//! recurrence (a filled pixel feeds its right and lower neighbours), so the search for
//! rows with holes runs in parallel and the filling visits only those holes, in order.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::{Checked, FilterError, FrameFilter, check_frame, empty_frame};
use crate::frame::DepthFrame;
use crate::intrinsics::Intrinsics;

/// How holes are filled (librealsense's `HOLES_FILL` option values 0, 1, 2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HoleFillingMode {
    /// 0: copy the pixel to the left.
    FillFromLeft,
    /// 1 (librealsense's default): the farthest valid neighbour.
    FarestFromAround,
    /// 2: the nearest valid neighbour.
    NearestFromAround,
}

impl HoleFillingMode {
    /// Every mode, by option value.
    pub const ALL: [Self; 3] = [
        Self::FillFromLeft,
        Self::FarestFromAround,
        Self::NearestFromAround,
    ];

    /// The name the configuration uses ("fill_from_left", ...).
    pub fn name(self) -> &'static str {
        match self {
            Self::FillFromLeft => "fill_from_left",
            Self::FarestFromAround => "farest_from_around",
            Self::NearestFromAround => "nearest_from_around",
        }
    }
}

/// The hole-filling filter with its scratch and output buffers.
#[derive(Debug, Clone)]
pub struct HoleFilling {
    mode: HoleFillingMode,
    rows_with_holes: Vec<bool>,
    out: DepthFrame,
}

impl HoleFilling {
    /// A filter in `mode`.
    pub fn new(mode: HoleFillingMode) -> Self {
        Self {
            mode,
            rows_with_holes: Vec::new(),
            out: empty_frame(),
        }
    }

    /// The filter's mode.
    pub fn mode(&self) -> HoleFillingMode {
        self.mode
    }

    /// Fills the holes of `frame` in place.
    pub fn apply_in_place(&mut self, frame: &mut DepthFrame) -> Result<(), FilterError> {
        check_frame(frame, None)?;
        let (w, h, stride) = (frame.width as usize, frame.height as usize, frame.stride);
        if w == 0 || h == 0 {
            return Ok(());
        }
        let data = &mut frame.data[..stride * h];
        match self.mode {
            HoleFillingMode::FillFromLeft => {
                data.par_chunks_mut(stride).for_each(|row| {
                    for i in 1..w {
                        if row[i] == 0 {
                            row[i] = row[i - 1];
                        }
                    }
                });
            }
            HoleFillingMode::FarestFromAround | HoleFillingMode::NearestFromAround => {
                if h < 3 || w < 2 {
                    return Ok(());
                }
                self.rows_with_holes.clear();
                self.rows_with_holes.resize(h, false);
                self.rows_with_holes
                    .par_iter_mut()
                    .zip(data.par_chunks(stride))
                    .for_each(|(has, row)| *has = row[1..w].contains(&0));
                let farest = self.mode == HoleFillingMode::FarestFromAround;
                for y in 1..h - 1 {
                    if !self.rows_with_holes[y] {
                        continue;
                    }
                    let (above, rest) = data.split_at_mut(y * stride);
                    let up = &above[(y - 1) * stride..(y - 1) * stride + w];
                    let (row, below) = rest.split_at_mut(stride);
                    let down = &below[..w];
                    for x in 1..w {
                        if row[x] != 0 {
                            continue;
                        }
                        let around = [up[x - 1], row[x - 1], down[x - 1], down[x]];
                        row[x] = if farest {
                            around.into_iter().fold(up[x], u16::max)
                        } else {
                            around.into_iter().filter(|&v| v != 0).fold(up[x], u16::min)
                        };
                    }
                }
            }
        }
        Ok(())
    }
}

impl FrameFilter for HoleFilling {
    /// A filled copy of the frame (compact rows) and its unchanged intrinsics.
    fn filter(&mut self, input: Checked<'_>) -> Result<(&DepthFrame, Intrinsics), FilterError> {
        let mut out = std::mem::replace(&mut self.out, empty_frame());
        super::disparity::copy_compact(input.frame(), &mut out);
        let filled = self.apply_in_place(&mut out);
        self.out = out;
        filled?;
        Ok((&self.out, *input.intrinsics()))
    }
}
