//! Pixels to points as librealsense computes them (`rs2_deproject_pixel_to_point`
//! and the point-cloud block), for every distortion model of [`DistortionModel`].
//!
//! A pixel (u, v) becomes the normalised ray `x = (u - ppx) / fx`, `y = (v - ppy) / fy`
//! (f32), then the model's undistortion, then `point = (z x, z y, z)` with
//! `z = depth_scale * raw` metres. Camera frame: x right, y down, z forward.
//!
//! Undistortion per model, as librealsense's code runs it ([`crate::intrinsics::pixel_to_ray`]):
//! - `None`: nothing.
//! - `BrownConrady`: ten fixed-point iterations of OpenCV's `undistortPoints`:
//!   `icd = 1 / (1 + ((k3 r2 + k2) r2 + k1) r2)`, tangential terms from the current
//!   estimate, `x = (x0 - dx) icd`.
//! - `InverseBrownConrady`: the same ten iterations, with the tangential terms taken
//!   at `x / icd`, `y / icd`.
//! - `KannalaBrandt4`: `rd = |(x, y)|` (at least `f32::EPSILON`), up to four Newton
//!   steps on `theta (1 + k1 t2 + k2 t2^2 + k3 t2^3 + k4 t2^4) = rd` (stopping when the
//!   residual is below `f32::EPSILON`), then `(x, y) *= tan(theta) / rd`; applied even
//!   when every coefficient is zero.
//! - `ModifiedBrownConrady`: librealsense asserts that such an image cannot be
//!   deprojected; its release builds (the SDK and pyrealsense2) skip the assertion and
//!   return the plain pinhole ray. We return what librealsense returns.
//!
//! [`Deprojector`] turns a whole frame into points for its valid (non-zero) pixels,
//! in row-major order, in parallel, reusing its tables and buffers between frames.

use nalgebra::Point3;
use rayon::prelude::*;

use crate::filter::{FilterError, check_frame, rows};
use crate::frame::DepthFrame;
use crate::intrinsics::{DistortionModel, Intrinsics, pixel_to_ray};

/// Rows per parallel task.
const ROWS_PER_TASK: usize = 16;

/// True when undistortion leaves every ray unchanged, so rays separate into a
/// column term and a row term.
fn separable(k: &Intrinsics) -> bool {
    match k.model {
        DistortionModel::None | DistortionModel::ModifiedBrownConrady => true,
        DistortionModel::BrownConrady | DistortionModel::InverseBrownConrady => {
            k.coeffs.iter().all(|&c| c == 0.0)
        }
        DistortionModel::KannalaBrandt4 => false,
    }
}

/// Per-pixel rays of one set of intrinsics.
#[derive(Debug, Clone, PartialEq)]
enum Rays {
    /// Pinhole: `x` per column, `y` per row.
    Separable { xs: Vec<f32>, ys: Vec<f32> },
    /// Distorted: one ray per pixel, row-major.
    Table(Vec<[f32; 2]>),
}

fn build_rays(k: &Intrinsics) -> Rays {
    let (w, h) = (k.width as usize, k.height as usize);
    if separable(k) {
        return Rays::Separable {
            xs: (0..w).map(|u| (u as f32 - k.ppx) / k.fx).collect(),
            ys: (0..h).map(|v| (v as f32 - k.ppy) / k.fy).collect(),
        };
    }
    let mut table = vec![[0.0; 2]; w * h];
    table
        .par_chunks_mut(w.max(1))
        .enumerate()
        .for_each(|(v, row)| {
            for (u, ray) in row.iter_mut().enumerate() {
                *ray = pixel_to_ray(k, [u as f32, v as f32]);
            }
        });
    Rays::Table(table)
}

/// Whole-frame deprojection with cached rays and reused buffers.
#[derive(Debug, Clone, Default)]
pub struct Deprojector {
    cached: Option<(Intrinsics, Rays)>,
    counts: Vec<usize>,
}

impl Deprojector {
    /// A deprojector with empty caches.
    pub fn new() -> Self {
        Self::default()
    }

    fn rays(&mut self, k: &Intrinsics) -> &Rays {
        if self.cached.as_ref().is_some_and(|(key, _)| key != k) {
            self.cached = None;
        }
        let (_, rays) = self.cached.get_or_insert_with(|| (*k, build_rays(k)));
        rays
    }

    /// Replaces `out` with the points (metres) of the valid pixels of `frame`,
    /// row-major; pixels with raw depth 0 give no point.
    pub fn deproject_frame(
        &mut self,
        frame: &DepthFrame,
        intrinsics: &Intrinsics,
        out: &mut Vec<Point3<f32>>,
    ) -> Result<(), FilterError> {
        check_frame(frame, Some(intrinsics))?;
        let input: Vec<&[u16]> = rows(frame).collect();
        let mut counts = std::mem::take(&mut self.counts);
        counts.clear();
        input
            .par_chunks(ROWS_PER_TASK)
            .map(|block| {
                block
                    .iter()
                    .map(|row| row.iter().filter(|&&raw| raw != 0).count())
                    .sum::<usize>()
            })
            .collect_into_vec(&mut counts);
        out.clear();
        out.resize(counts.iter().sum(), Point3::origin());
        let mut slices = Vec::with_capacity(counts.len());
        let mut rest = out.as_mut_slice();
        for &n in &counts {
            let (head, tail) = rest.split_at_mut(n);
            slices.push(head);
            rest = tail;
        }
        self.counts = counts;
        let scale = frame.depth_scale;
        let width = frame.width as usize;
        let rays = self.rays(intrinsics);
        slices
            .into_par_iter()
            .zip(input.par_chunks(ROWS_PER_TASK))
            .enumerate()
            .for_each(|(task, (dst, block))| {
                let mut next = dst.iter_mut();
                for (i, row) in block.iter().enumerate() {
                    let v = task * ROWS_PER_TASK + i;
                    for (u, &raw) in row.iter().enumerate() {
                        if raw == 0 {
                            continue;
                        }
                        let z = scale * f32::from(raw);
                        let [x, y] = match rays {
                            Rays::Separable { xs, ys } => [xs[u], ys[v]],
                            Rays::Table(table) => table[v * width + u],
                        };
                        if let Some(p) = next.next() {
                            *p = Point3::new(z * x, z * y, z);
                        }
                    }
                }
            });
        Ok(())
    }
}

/// The points (metres) of the valid pixels of `frame`, row-major (see
/// [`Deprojector::deproject_frame`]; keep a [`Deprojector`] to reuse its buffers).
pub fn deproject_frame(
    frame: &DepthFrame,
    intrinsics: &Intrinsics,
) -> Result<Vec<Point3<f32>>, FilterError> {
    let mut out = Vec::new();
    Deprojector::new().deproject_frame(frame, intrinsics, &mut out)?;
    Ok(out)
}
