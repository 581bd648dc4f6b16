//! Voxel downsampling: one point per occupied voxel, at the centroid of its points.

use nalgebra::Vector3;
use rayon::slice::ParallelSliceMut;

use crate::cloud::is_finite;
use crate::{Point3, PointCloud};

/// Why a downsampling request was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum VoxelError {
    /// The voxel edge is not a positive finite length.
    #[error("voxel size must be a positive finite number of metres, found {voxel_m}")]
    InvalidSize {
        /// The requested edge length.
        voxel_m: f32,
    },
}

/// Downsamples `cloud` on a grid of cubes with edge `voxel_m` metres aligned to the
/// origin: every occupied voxel yields the centroid (summed in `f64`) of its points.
///
/// The output is deterministic: voxels come out in increasing (x, y, z) index order and
/// each centroid sums its points in input order. Points with a non-finite coordinate are
/// dropped.
pub fn voxel_downsample(cloud: &PointCloud, voxel_m: f32) -> Result<PointCloud, VoxelError> {
    if !(voxel_m.is_finite() && voxel_m > 0.0) {
        return Err(VoxelError::InvalidSize { voxel_m });
    }
    let inv = 1.0 / f64::from(voxel_m);
    // (voxel index, point index), sorted: equal voxels become runs, in input order within.
    let mut keyed: Vec<([i64; 3], usize)> = cloud
        .points
        .iter()
        .enumerate()
        .filter(|(_, p)| is_finite(p))
        .map(|(i, p)| {
            // `as` saturates: absurdly distant points share the outermost voxel.
            let key = [
                (f64::from(p.x) * inv).floor() as i64,
                (f64::from(p.y) * inv).floor() as i64,
                (f64::from(p.z) * inv).floor() as i64,
            ];
            (key, i)
        })
        .collect();
    keyed.par_sort_unstable();
    Ok(keyed
        .chunk_by(|a, b| a.0 == b.0)
        .map(|run| {
            let sum: Vector3<f64> = run
                .iter()
                .map(|(_, i)| cloud.points[*i].coords.cast::<f64>())
                .sum();
            Point3::from((sum / run.len() as f64).cast::<f32>())
        })
        .collect())
}
