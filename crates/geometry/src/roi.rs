//! The 3D region of interest: the `roi3d` box of the application-config document (thesis
//! Listing A.3), applied in the output frame after the 3D transformation.
//!
//! ```json
//! { "min_x": -0.25, "max_x": 0.25, "min_y": -0.25, "max_y": 0.25, "min_z": 0.1, "max_z": 0.3 }
//! ```
//!
//! Bounds are inclusive: a point exactly on a face is kept.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::{Point3, PointCloud};

/// Why a `roi3d` box was refused. `Display` is the 4.00 diagnostic.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum RoiError {
    /// A bound is NaN or infinite.
    #[error("roi3d: `{field}` must be a finite number of metres, found {value}")]
    NonFinite {
        /// The JSON key.
        field: &'static str,
        /// The offending value.
        value: f32,
    },
    /// A minimum exceeds its maximum.
    #[error("roi3d: `min_{axis}` ({min}) must not exceed `max_{axis}` ({max})")]
    Inverted {
        /// "x", "y" or "z".
        axis: &'static str,
        /// The minimum.
        min: f32,
        /// The maximum.
        max: f32,
    },
}

/// An axis-aligned box in metres, bounds inclusive. Build it with [`Roi3::new`] or from
/// JSON; both check that bounds are finite and ordered.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "RawRoi3", into = "RawRoi3")]
pub struct Roi3 {
    min: Point3,
    max: Point3,
}

impl Roi3 {
    /// The box between the corners `min` and `max`.
    pub fn new(min: Point3, max: Point3) -> Result<Self, RoiError> {
        RawRoi3 {
            min_x: min.x,
            max_x: max.x,
            min_y: min.y,
            max_y: max.y,
            min_z: min.z,
            max_z: max.z,
        }
        .try_into()
    }

    /// The box that keeps every finite point.
    #[must_use]
    pub fn everything() -> Self {
        Self {
            min: Point3::new(f32::MIN, f32::MIN, f32::MIN),
            max: Point3::new(f32::MAX, f32::MAX, f32::MAX),
        }
    }

    /// The minimum corner.
    #[must_use]
    pub fn min(&self) -> Point3 {
        self.min
    }

    /// The maximum corner.
    #[must_use]
    pub fn max(&self) -> Point3 {
        self.max
    }

    /// True when `p` lies inside or on the box (false for NaN coordinates).
    #[must_use]
    pub fn contains(&self, p: &Point3) -> bool {
        p.x >= self.min.x
            && p.x <= self.max.x
            && p.y >= self.min.y
            && p.y <= self.max.y
            && p.z >= self.min.z
            && p.z <= self.max.z
    }

    /// Keeps only the points of `cloud` inside the box, in their order.
    pub fn retain(&self, cloud: &mut PointCloud) {
        cloud.points.retain(|p| self.contains(p));
    }

    /// The points of `points` inside the box, in their order (parallel).
    #[must_use]
    pub fn crop(&self, points: &[Point3]) -> PointCloud {
        let points = points
            .par_iter()
            .filter(|p| self.contains(p))
            .copied()
            .collect();
        PointCloud { points }
    }
}

/// `roi3d` exactly as JSON spells it.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRoi3 {
    min_x: f32,
    max_x: f32,
    min_y: f32,
    max_y: f32,
    min_z: f32,
    max_z: f32,
}

impl From<Roi3> for RawRoi3 {
    fn from(roi: Roi3) -> Self {
        Self {
            min_x: roi.min.x,
            max_x: roi.max.x,
            min_y: roi.min.y,
            max_y: roi.max.y,
            min_z: roi.min.z,
            max_z: roi.max.z,
        }
    }
}

impl TryFrom<RawRoi3> for Roi3 {
    type Error = RoiError;

    fn try_from(raw: RawRoi3) -> Result<Self, Self::Error> {
        let fields = [
            ("min_x", raw.min_x),
            ("max_x", raw.max_x),
            ("min_y", raw.min_y),
            ("max_y", raw.max_y),
            ("min_z", raw.min_z),
            ("max_z", raw.max_z),
        ];
        if let Some((field, value)) = fields.into_iter().find(|(_, v)| !v.is_finite()) {
            return Err(RoiError::NonFinite { field, value });
        }
        for (axis, min, max) in [
            ("x", raw.min_x, raw.max_x),
            ("y", raw.min_y, raw.max_y),
            ("z", raw.min_z, raw.max_z),
        ] {
            if min > max {
                return Err(RoiError::Inverted { axis, min, max });
            }
        }
        Ok(Self {
            min: Point3::new(raw.min_x, raw.min_y, raw.min_z),
            max: Point3::new(raw.max_x, raw.max_y, raw.max_z),
        })
    }
}
