//! Seeded synthetic scenes: a floor at z = 0 and a box standing on it, sampled uniformly
//! on the visible surfaces (lid and four sides; the floor under the box is left out).

use geometry::{Point3, PointCloud};
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore, SeedableRng};

/// A seeded source of uniform and normal samples.
pub(crate) struct Sampler(ChaCha8Rng);

impl Sampler {
    pub(crate) fn new(seed: u64) -> Self {
        Self(ChaCha8Rng::seed_from_u64(seed))
    }

    /// Uniform in [0, 1).
    pub(crate) fn unit(&mut self) -> f32 {
        (self.0.next_u32() >> 8) as f32 / (1u32 << 24) as f32
    }

    /// Uniform in [lo, hi).
    pub(crate) fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.unit()
    }

    /// Normal with mean 0 and deviation `sigma` (Box-Muller).
    pub(crate) fn normal(&mut self, sigma: f32) -> f32 {
        let u1 = self.unit().max(f32::MIN_POSITIVE);
        let u2 = self.unit();
        sigma * (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
    }
}

/// A box standing on the floor.
#[derive(Clone, Copy)]
pub(crate) struct BoxSpec {
    pub(crate) center_xy: [f32; 2],
    pub(crate) length_m: f32,
    pub(crate) width_m: f32,
    pub(crate) height_m: f32,
    pub(crate) yaw_deg: f32,
}

impl BoxSpec {
    /// A box at `center_xy`, `size` its length (along x before yaw), width and height.
    pub(crate) fn new(center_xy: [f32; 2], size: [f32; 3], yaw_deg: f32) -> Self {
        Self {
            center_xy,
            length_m: size[0],
            width_m: size[1],
            height_m: size[2],
            yaw_deg,
        }
    }

    pub(crate) fn world_point(&self, local_x: f32, local_y: f32, z: f32) -> Point3 {
        let (s, c) = self.yaw_deg.to_radians().sin_cos();
        Point3::new(
            self.center_xy[0] + c * local_x - s * local_y,
            self.center_xy[1] + s * local_x + c * local_y,
            z,
        )
    }

    pub(crate) fn covers(&self, x: f32, y: f32) -> bool {
        let (s, c) = self.yaw_deg.to_radians().sin_cos();
        let (dx, dy) = (x - self.center_xy[0], y - self.center_xy[1]);
        let (lx, ly) = (c * dx + s * dy, -s * dx + c * dy);
        lx.abs() <= self.length_m / 2.0 && ly.abs() <= self.width_m / 2.0
    }
}

/// Samples `n` points over a square floor of half-size `floor_half_m` and the box
/// surfaces, about one point per equal area.
pub(crate) fn scene(sampler: &mut Sampler, n: usize, floor_half_m: f32, b: &BoxSpec) -> PointCloud {
    let floor_area = (2.0 * floor_half_m).powi(2) - b.length_m * b.width_m;
    let lid_area = b.length_m * b.width_m;
    let side_area = 2.0 * (b.length_m + b.width_m) * b.height_m;
    let total = floor_area + lid_area + side_area;
    let mut points = Vec::with_capacity(n);
    while points.len() < n {
        let pick = sampler.range(0.0, total);
        let (hl, hw) = (b.length_m / 2.0, b.width_m / 2.0);
        if pick < floor_area {
            let x = sampler.range(-floor_half_m, floor_half_m);
            let y = sampler.range(-floor_half_m, floor_half_m);
            if !b.covers(x, y) {
                points.push(Point3::new(x, y, 0.0));
            }
        } else if pick < floor_area + lid_area {
            let (x, y) = (sampler.range(-hl, hl), sampler.range(-hw, hw));
            points.push(b.world_point(x, y, b.height_m));
        } else {
            let z = sampler.range(0.0, b.height_m);
            let along = sampler.range(0.0, 2.0 * (b.length_m + b.width_m));
            let (x, y) = if along < b.length_m {
                (along - hl, -hw)
            } else if along < b.length_m + b.width_m {
                (hl, along - b.length_m - hw)
            } else if along < 2.0 * b.length_m + b.width_m {
                (along - b.length_m - b.width_m - hl, hw)
            } else {
                (-hl, along - 2.0 * b.length_m - b.width_m - hw)
            };
            points.push(b.world_point(x, y, z));
        }
    }
    PointCloud::from(points)
}

/// The box of the ICP and dimension tests: 400 x 300 x 200 mm at yaw 30 deg, off centre.
pub(crate) fn parcel() -> BoxSpec {
    BoxSpec {
        center_xy: [0.05, -0.03],
        length_m: 0.4,
        width_m: 0.3,
        height_m: 0.2,
        yaw_deg: 30.0,
    }
}
