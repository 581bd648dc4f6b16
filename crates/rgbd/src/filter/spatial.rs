//! Spatial edge-preserving filter (librealsense `spatial_filter`) in the disparity
//! domain, the domain librealsense recommends and the one its float code path serves.
//!
//! Each iteration runs a first-order recursive filter (an exponential moving average)
//! along every row, left to right then right to left, then along every column, top to
//! bottom then bottom to top. Along a line, with `state` the last output and `prev`
//! the previous *raw* input:
//! - a value is valid when its bit pattern, read as a signed 32-bit integer, is
//!   positive (so +0.0 and negatives are holes);
//! - a valid value whose predecessor is valid and within `delta` of it
//!   (`-delta < prev - cur < delta`, strict) becomes `cur * alpha + state * (1 - alpha)`
//!   (in `f32`, no rounding) and the new state; any other valid value passes unchanged
//!   and re-seeds the state; holes stay holes;
//! - the first value of each direction only seeds the state.
//!
//! `delta` is in disparity units (1/32 pixel), as librealsense uses the option value
//! unscaled in this domain. With holes filling on (radius 2, 4, 8, 16 or 255 for modes
//! 1 to 5), after all iterations every row is scanned left to right and then right to
//! left and a hole (bit pattern 0) copies its neighbour while the run of holes is
//! shorter than the radius (`++run < radius`). librealsense's right-to-left scan of a
//! row starts with the row's last pixel and takes its neighbour from the first pixel of
//! the next row; we do the same, and treat the pixel after the last row (beyond the
//! buffer in librealsense) as a hole.
//!
//! Rows and column strips are independent, so both passes run in parallel and give
//! exactly the sequential result.

use rayon::prelude::*;

use super::FilterError;
use super::disparity::DisparityFrame;

/// Columns per parallel task of the vertical pass.
const STRIP: usize = 64;

/// Parameters of the spatial filter, named and bounded as librealsense's options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpatialParams {
    /// Weight of the current pixel, 0.25..=1 (`FILTER_SMOOTH_ALPHA`, default 0.5).
    pub alpha: f32,
    /// Edge threshold in disparity units, 1..=50 (`FILTER_SMOOTH_DELTA`, default 20).
    pub delta: u8,
    /// Passes, 1..=5 (`FILTER_MAGNITUDE`, default 2).
    pub iterations: u8,
    /// Holes filling mode 0..=5: off, radius 2, 4, 8, 16, unlimited (`HOLES_FILL`,
    /// default 0).
    pub holes_fill: u8,
}

impl Default for SpatialParams {
    fn default() -> Self {
        Self {
            alpha: 0.5,
            delta: 20,
            iterations: 2,
            holes_fill: 0,
        }
    }
}

impl SpatialParams {
    /// Checks every parameter against librealsense's option ranges.
    pub fn validate(&self) -> Result<(), FilterError> {
        let bad = |field, value: String, allowed| {
            Err(FilterError::Parameter {
                field,
                value,
                allowed,
            })
        };
        if !(0.25..=1.0).contains(&self.alpha) {
            return bad("alpha", self.alpha.to_string(), "a number from 0.25 to 1");
        }
        if !(1..=50).contains(&self.delta) {
            return bad("delta", self.delta.to_string(), "an integer from 1 to 50");
        }
        if !(1..=5).contains(&self.iterations) {
            return bad(
                "iterations",
                self.iterations.to_string(),
                "an integer from 1 to 5",
            );
        }
        if self.holes_fill > 5 {
            return bad(
                "holes_fill",
                self.holes_fill.to_string(),
                "an integer from 0 (off) to 5 (unlimited)",
            );
        }
        Ok(())
    }

    /// Run length the holes filling covers: 0 (off), 2, 4, 8, 16 or 255.
    pub fn holes_fill_radius(&self) -> u32 {
        match self.holes_fill {
            0 => 0,
            1..=4 => 1 << self.holes_fill,
            _ => 255,
        }
    }
}

/// The spatial filter with its scratch buffer.
#[derive(Debug, Clone)]
pub struct SpatialFilter {
    params: SpatialParams,
    first_column: Vec<f32>,
}

/// librealsense's validity test: the bit pattern as a signed integer is positive.
fn valid(v: f32) -> bool {
    (v.to_bits() as i32) > 0
}

/// One step of the recursive filter along a line (see the module documentation),
/// written without branches so that independent lines can advance side by side.
#[inline(always)]
fn step(cur: &mut f32, state: &mut f32, prev: &mut f32, alpha: f32, delta: f32) {
    let raw = *cur;
    let d = *prev - raw;
    let cur_valid = valid(raw);
    let smooth = cur_valid & valid(*prev) & (d < delta) & (d > -delta);
    let blended = raw * alpha + *state * (1.0 - alpha);
    *state = if smooth {
        blended
    } else if cur_valid {
        raw
    } else {
        *state
    };
    *cur = if smooth { blended } else { raw };
    *prev = raw;
}

/// Rows filtered side by side in the horizontal pass: independent recurrences hide
/// each other's latency.
const ROWS_PER_TASK: usize = 8;

/// Filters up to [`ROWS_PER_TASK`] rows of width `w` (left to right, then right to
/// left), advancing them together.
fn filter_rows(block: &mut [f32], w: usize, alpha: f32, delta: f32) {
    let mut rows: Vec<&mut [f32]> = block.chunks_mut(w).collect();
    let mut state = [0f32; ROWS_PER_TASK];
    let mut prev = [0f32; ROWS_PER_TASK];
    for (r, row) in rows.iter().enumerate() {
        state[r] = row[0];
        prev[r] = row[0];
    }
    for x in 1..w {
        for ((row, s), p) in rows.iter_mut().zip(&mut state).zip(&mut prev) {
            step(&mut row[x], s, p, alpha, delta);
        }
    }
    for (r, row) in rows.iter().enumerate() {
        state[r] = row[w - 1];
        prev[r] = row[w - 1];
    }
    for x in (0..w - 1).rev() {
        for ((row, s), p) in rows.iter_mut().zip(&mut state).zip(&mut prev) {
            step(&mut row[x], s, p, alpha, delta);
        }
    }
}

/// Filters the columns of a strip (one slice per row, all of the same width).
fn filter_strip(rows: &mut [&mut [f32]], alpha: f32, delta: f32) {
    let Some(w) = rows.first().map(|r| r.len()) else {
        return;
    };
    let mut state = [0f32; STRIP];
    let mut prev = [0f32; STRIP];
    let (state, prev) = (&mut state[..w], &mut prev[..w]);
    let Some((first, rest)) = rows.split_first_mut() else {
        return;
    };
    state.copy_from_slice(first);
    prev.copy_from_slice(first);
    for row in rest.iter_mut() {
        for ((v, s), p) in row.iter_mut().zip(state.iter_mut()).zip(prev.iter_mut()) {
            step(v, s, p, alpha, delta);
        }
    }
    let Some((last, rest)) = rows.split_last_mut() else {
        return;
    };
    state.copy_from_slice(last);
    prev.copy_from_slice(last);
    for row in rest.iter_mut().rev() {
        for ((v, s), p) in row.iter_mut().zip(state.iter_mut()).zip(prev.iter_mut()) {
            step(v, s, p, alpha, delta);
        }
    }
}

/// Holes filling of one row; `next_first` is the first pixel of the next row.
fn fill_row(row: &mut [f32], next_first: f32, radius: u32) {
    let empty = |v: f32| v.to_bits() == 0;
    let mut run = 0u32;
    for i in 1..row.len() {
        if empty(row[i]) {
            run += 1;
            if run < radius {
                row[i] = row[i - 1];
            }
        } else {
            run = 0;
        }
    }
    run = 0;
    for i in (1..row.len()).rev() {
        if empty(row[i]) {
            run += 1;
            if run < radius {
                row[i] = row.get(i + 1).copied().unwrap_or(next_first);
            }
        } else {
            run = 0;
        }
    }
}

impl SpatialFilter {
    /// A filter with these parameters (checked against librealsense's ranges).
    pub fn new(params: SpatialParams) -> Result<Self, FilterError> {
        params.validate()?;
        Ok(Self {
            params,
            first_column: Vec::new(),
        })
    }

    /// Filters `disparity` in place; fails when its data is shorter than
    /// `width * height`.
    pub fn apply(&mut self, disparity: &mut DisparityFrame) -> Result<(), FilterError> {
        let (w, h) = (disparity.width as usize, disparity.height as usize);
        let needed = w.saturating_mul(h);
        let len = disparity.data.len();
        let Some(data) = disparity.data.get_mut(..needed) else {
            return Err(FilterError::DisparitySize {
                width: disparity.width,
                height: disparity.height,
                needed,
                len,
            });
        };
        if w == 0 || h == 0 {
            return Ok(());
        }
        let alpha = self.params.alpha;
        let delta = f32::from(self.params.delta);
        for _ in 0..self.params.iterations {
            data.par_chunks_mut(w * ROWS_PER_TASK)
                .for_each(|block| filter_rows(block, w, alpha, delta));
            let mut strips: Vec<Vec<&mut [f32]>> = (0..w.div_ceil(STRIP))
                .map(|_| Vec::with_capacity(h))
                .collect();
            for row in data.chunks_mut(w) {
                for (strip, part) in strips.iter_mut().zip(row.chunks_mut(STRIP)) {
                    strip.push(part);
                }
            }
            strips
                .par_iter_mut()
                .for_each(|strip| filter_strip(strip, alpha, delta));
        }
        let radius = self.params.holes_fill_radius();
        if radius > 0 {
            self.first_column.clear();
            self.first_column
                .extend(data.chunks(w).skip(1).map(|row| row[0]));
            self.first_column.push(0.0);
            let next_firsts = &self.first_column;
            data.par_chunks_mut(w)
                .zip(next_firsts.par_iter())
                .for_each(|(row, &next)| fill_row(row, next, radius));
        }
        Ok(())
    }
}
