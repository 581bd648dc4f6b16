//! The point cloud: a list of points in metres, in no particular order.

use crate::Point3;

/// Points in metres. Order carries no meaning; operations keep it where they can.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PointCloud {
    /// The points.
    pub points: Vec<Point3>,
}

impl PointCloud {
    /// An empty cloud with room for `capacity` points.
    #[must_use]
    pub fn with_capacity(capacity: usize) -> Self {
        Self {
            points: Vec::with_capacity(capacity),
        }
    }

    /// Number of points.
    #[must_use]
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// True when the cloud holds no point.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Appends the points of `other` (already in the same frame) to this cloud.
    pub fn extend_from(&mut self, other: &Self) {
        self.points.extend_from_slice(&other.points);
    }

    /// Merges clouds that are already in one frame (each camera's after its
    /// [`Transform`](crate::Transform)): the points of each, in the order given.
    #[must_use]
    pub fn merge<'a>(clouds: impl IntoIterator<Item = &'a Self>) -> Self {
        let clouds: Vec<&Self> = clouds.into_iter().collect();
        let mut merged = Self::with_capacity(clouds.iter().map(|c| c.len()).sum());
        for cloud in clouds {
            merged.extend_from(cloud);
        }
        merged
    }
}

impl From<Vec<Point3>> for PointCloud {
    fn from(points: Vec<Point3>) -> Self {
        Self { points }
    }
}

impl FromIterator<Point3> for PointCloud {
    fn from_iter<I: IntoIterator<Item = Point3>>(iter: I) -> Self {
        Self {
            points: iter.into_iter().collect(),
        }
    }
}

/// True when all three coordinates are finite.
pub(crate) fn is_finite(p: &Point3) -> bool {
    p.x.is_finite() && p.y.is_finite() && p.z.is_finite()
}
