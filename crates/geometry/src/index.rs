//! Nearest-neighbour index over a slice of points (kiddo's immutable k-d tree).

use std::num::NonZeroUsize;

use kiddo::{ImmutableKdTree, SquaredEuclidean};

use crate::Point3;

/// A k-d tree over finite points; items are indices into the slice it was built from.
pub(crate) struct Index {
    tree: ImmutableKdTree<f32, 3>,
}

/// The index could not be built: kiddo numbers items with `u32`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct TooManyPoints(pub(crate) usize);

impl Index {
    /// Builds the index; every point must be finite (callers filter first).
    pub(crate) fn new(points: &[Point3]) -> Result<Self, TooManyPoints> {
        let coords: Vec<[f32; 3]> = points.iter().map(|p| [p.x, p.y, p.z]).collect();
        ImmutableKdTree::new_from_slice(&coords)
            .map(|tree| Self { tree })
            .map_err(|_| TooManyPoints(points.len()))
    }

    /// Index and squared distance of the nearest point. The index must not be empty.
    pub(crate) fn nearest(&self, p: &Point3) -> (usize, f32) {
        let found = self
            .tree
            .query(&[p.x, p.y, p.z])
            .nearest_one::<SquaredEuclidean<f32>>()
            .execute();
        (found.item as usize, found.distance)
    }

    /// Indices of the `n` nearest points, nearest first.
    pub(crate) fn nearest_n(&self, p: &Point3, n: NonZeroUsize) -> Vec<usize> {
        self.tree
            .query(&[p.x, p.y, p.z])
            .nearest_n::<SquaredEuclidean<f32>>(n)
            .execute()
            .into_iter()
            .map(|found| found.item as usize)
            .collect()
    }
}
