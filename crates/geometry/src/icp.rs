//! Iterative closest point registration: point-to-point (closed form by SVD) or
//! point-to-plane (linearised least squares against target normals).
//!
//! Each iteration pairs every source point, moved by the current estimate, with its
//! nearest target point (kiddo k-d tree) and drops pairs farther apart than
//! `max_correspondence_m`; it then solves for the rigid increment that best aligns the
//! pairs and composes it onto the estimate. It stops after `max_iterations`, or earlier
//! when an increment both moves less than `translation_epsilon_m` and turns less than
//! `rotation_epsilon_rad` (then `converged` is true). Sums and solves run in `f64`.

use std::num::NonZeroUsize;

use nalgebra::{
    Isometry3, Matrix3, Matrix6, Rotation3, SymmetricEigen, Translation3, UnitQuaternion, Vector3,
    Vector6,
};
use rayon::prelude::*;

use crate::cloud::is_finite;
use crate::index::Index;
use crate::{Point3, PointCloud};

/// How each iteration measures misalignment.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[non_exhaustive]
pub enum IcpMethod {
    /// Sum of squared point distances; solved exactly with the SVD of the 3x3
    /// cross-covariance (Kabsch).
    #[default]
    PointToPoint,
    /// Sum of squared distances along the target normal (estimated by PCA over the
    /// `normal_neighbours` nearest target points); solved as a 6x6 linear system with the
    /// small-angle rotation. Converges in fewer iterations on planar scenes.
    PointToPlane,
}

/// Limits and tolerances of one ICP run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IcpConfig {
    /// Error metric.
    pub method: IcpMethod,
    /// Hard limit on iterations (at least 1).
    pub max_iterations: u32,
    /// Pairs farther apart than this (metres) are ignored. Must exceed the initial
    /// misalignment of corresponding points.
    pub max_correspondence_m: f32,
    /// Convergence: an increment that moves less than this (metres) ...
    pub translation_epsilon_m: f32,
    /// ... and turns less than this (radians) ends the run.
    pub rotation_epsilon_rad: f32,
    /// Fewer pairs than this in an iteration is an error (at least 3; 6 for
    /// point-to-plane).
    pub min_correspondences: usize,
    /// Neighbours used for each target normal (point-to-plane only; at least 3).
    pub normal_neighbours: usize,
}

impl Default for IcpConfig {
    /// Point-to-point, 30 iterations, 5 cm pairs, stop below 10 µm and 10 µrad, 10
    /// neighbours per normal.
    fn default() -> Self {
        Self {
            method: IcpMethod::PointToPoint,
            max_iterations: 30,
            max_correspondence_m: 0.05,
            translation_epsilon_m: 1e-5,
            rotation_epsilon_rad: 1e-5,
            min_correspondences: 10,
            normal_neighbours: 10,
        }
    }
}

/// Why ICP could not run or finish.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum IcpError {
    /// A configuration value is out of range.
    #[error("icp: `{field}` must be {allowed}")]
    InvalidConfig {
        /// The [`IcpConfig`] field.
        field: &'static str,
        /// What is allowed.
        allowed: &'static str,
    },
    /// A cloud has too few finite points.
    #[error("icp: the {cloud} cloud has {found} finite points, at least {needed} are needed")]
    TooFewPoints {
        /// "source" or "target".
        cloud: &'static str,
        /// Finite points found.
        found: usize,
        /// The minimum.
        needed: usize,
    },
    /// The target is too large for the nearest-neighbour index.
    #[error("icp: the target cloud has {points} points, more than the index can number")]
    TooManyPoints {
        /// Points in the target.
        points: usize,
    },
    /// Too few pairs lay within `max_correspondence_m`.
    #[error(
        "icp: iteration {iteration} found {found} point pairs within max_correspondence_m, at least {needed} are needed"
    )]
    TooFewCorrespondences {
        /// The iteration (1-based).
        iteration: u32,
        /// Pairs found.
        found: usize,
        /// The minimum.
        needed: usize,
    },
    /// The pairs do not constrain all six degrees of freedom (for example, one plane).
    #[error("icp: iteration {iteration}: the point pairs do not determine a rigid motion")]
    Degenerate {
        /// The iteration (1-based).
        iteration: u32,
    },
}

/// The result of a run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IcpOutcome {
    /// Maps source points into the target frame (includes the initial guess).
    pub transform: Isometry3<f32>,
    /// Iterations run (1..=`max_iterations`).
    pub iterations: u32,
    /// True when the run stopped on the epsilons rather than the iteration limit.
    pub converged: bool,
    /// Share of finite source points that have a target point within
    /// `max_correspondence_m` after the final transform.
    pub fitness: f32,
    /// Root-mean-square distance of those pairs, metres.
    pub rmse_m: f32,
}

impl IcpConfig {
    fn validate(&self) -> Result<(), IcpError> {
        let positive = |v: f32| v.is_finite() && v > 0.0;
        let non_negative = |v: f32| v.is_finite() && v >= 0.0;
        let needed_pairs = match self.method {
            IcpMethod::PointToPoint => 3,
            IcpMethod::PointToPlane => 6,
        };
        let checks = [
            (self.max_iterations >= 1, "max_iterations", "at least 1"),
            (
                positive(self.max_correspondence_m),
                "max_correspondence_m",
                "a positive finite number of metres",
            ),
            (
                non_negative(self.translation_epsilon_m),
                "translation_epsilon_m",
                "a finite number of metres >= 0",
            ),
            (
                non_negative(self.rotation_epsilon_rad),
                "rotation_epsilon_rad",
                "a finite number of radians >= 0",
            ),
            (
                self.min_correspondences >= needed_pairs,
                "min_correspondences",
                "at least 3 (point-to-point) or 6 (point-to-plane)",
            ),
            (
                self.normal_neighbours >= 3,
                "normal_neighbours",
                "at least 3",
            ),
        ];
        match checks.into_iter().find(|(ok, _, _)| !ok) {
            None => Ok(()),
            Some((_, field, allowed)) => Err(IcpError::InvalidConfig { field, allowed }),
        }
    }
}

/// One source point paired with a target point.
struct Pair {
    source: Vector3<f64>,
    target: usize,
    distance_sq: f64,
}

/// Registers `source` onto `target`, starting from `init` (source -> target frame).
pub fn icp(
    source: &PointCloud,
    target: &PointCloud,
    init: &Isometry3<f32>,
    config: &IcpConfig,
) -> Result<IcpOutcome, IcpError> {
    config.validate()?;
    let source: Vec<Point3> = source.points.iter().copied().filter(is_finite).collect();
    let target: Vec<Point3> = target.points.iter().copied().filter(is_finite).collect();
    let needed = config.min_correspondences;
    for (cloud, found) in [("source", source.len()), ("target", target.len())] {
        if found < needed {
            return Err(IcpError::TooFewPoints {
                cloud,
                found,
                needed,
            });
        }
    }
    let index = Index::new(&target).map_err(|e| IcpError::TooManyPoints { points: e.0 })?;
    let normals = match config.method {
        IcpMethod::PointToPoint => Vec::new(),
        IcpMethod::PointToPlane => estimate_normals(&target, &index, config.normal_neighbours),
    };
    let target64: Vec<Vector3<f64>> = target.iter().map(|p| p.coords.cast()).collect();
    let max_sq = f64::from(config.max_correspondence_m).powi(2);

    let mut estimate: Isometry3<f64> = init.cast();
    let mut iterations = 0;
    let mut converged = false;
    while iterations < config.max_iterations {
        iterations += 1;
        let pairs = pair_up(&source, &index, &target64, &estimate, max_sq, &normals);
        if pairs.len() < needed {
            return Err(IcpError::TooFewCorrespondences {
                iteration: iterations,
                found: pairs.len(),
                needed,
            });
        }
        let step = match config.method {
            IcpMethod::PointToPoint => point_to_point_step(&pairs, &target64),
            IcpMethod::PointToPlane => point_to_plane_step(&pairs, &target64, &normals),
        }
        .ok_or(IcpError::Degenerate {
            iteration: iterations,
        })?;
        estimate = step * estimate;
        if step.translation.vector.norm() < f64::from(config.translation_epsilon_m)
            && step.rotation.angle() < f64::from(config.rotation_epsilon_rad)
        {
            converged = true;
            break;
        }
    }

    // Fitness and RMSE count every pair within reach, with or without a target normal.
    let pairs = pair_up(&source, &index, &target64, &estimate, max_sq, &[]);
    let (fitness, rmse_m) = if pairs.is_empty() {
        (0.0, 0.0)
    } else {
        let sum_sq: f64 = pairs.iter().map(|p| p.distance_sq).sum();
        (
            pairs.len() as f32 / source.len() as f32,
            (sum_sq / pairs.len() as f64).sqrt() as f32,
        )
    };
    Ok(IcpOutcome {
        transform: estimate.cast(),
        iterations,
        converged,
        fitness,
        rmse_m,
    })
}

/// Pairs each moved source point with its nearest target point within `max_sq`
/// (squared metres); with normals, targets without a normal are skipped.
fn pair_up(
    source: &[Point3],
    index: &Index,
    target: &[Vector3<f64>],
    estimate: &Isometry3<f64>,
    max_sq: f64,
    normals: &[Option<Vector3<f64>>],
) -> Vec<Pair> {
    source
        .par_iter()
        .filter_map(|p| {
            let moved = (estimate * p.cast::<f64>()).coords;
            let (nearest, _) = index.nearest(&Point3::from(moved.cast::<f32>()));
            if !normals.is_empty() && normals[nearest].is_none() {
                return None;
            }
            let distance_sq = (target[nearest] - moved).norm_squared();
            (distance_sq <= max_sq).then_some(Pair {
                source: moved,
                target: nearest,
                distance_sq,
            })
        })
        .collect()
}

/// Relative size below which a singular value of the cross-covariance counts as zero;
/// the points are `f32`, so collinearity is only resolvable to about `f32` precision.
const RANK_TOLERANCE: f64 = 1e-6;

/// Kabsch: the rotation and translation minimising the summed squared pair distances;
/// `None` when the pairs lie on one line (or one point).
fn point_to_point_step(pairs: &[Pair], target: &[Vector3<f64>]) -> Option<Isometry3<f64>> {
    let n = pairs.len() as f64;
    let (sum_s, sum_t) = pairs
        .iter()
        .fold((Vector3::zeros(), Vector3::zeros()), |(s, t), pair| {
            (s + pair.source, t + target[pair.target])
        });
    let (mean_s, mean_t) = (sum_s / n, sum_t / n);
    let h: Matrix3<f64> = pairs
        .iter()
        .map(|pair| (pair.source - mean_s) * (target[pair.target] - mean_t).transpose())
        .sum();
    let svd = h.svd(true, true);
    // Pairs on one line (rank 1) leave the rotation about that line arbitrary.
    let mut sigma = [
        svd.singular_values[0],
        svd.singular_values[1],
        svd.singular_values[2],
    ];
    sigma.sort_by(|a, b| b.total_cmp(a));
    if !sigma[1].is_finite() || sigma[1] <= RANK_TOLERANCE * sigma[0] {
        return None;
    }
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut v = v_t.transpose();
    if (v * u.transpose()).determinant() < 0.0 {
        let mut last = v.column_mut(2);
        last.neg_mut();
    }
    let rotation = Rotation3::from_matrix_unchecked(v * u.transpose());
    let translation = mean_t - rotation * mean_s;
    Some(Isometry3::from_parts(
        Translation3::from(translation),
        UnitQuaternion::from_rotation_matrix(&rotation),
    ))
}

/// Linearised point-to-plane: solves for (w, t) minimising
/// Σ ((p + w × p + t − q) · n)², then applies the exact rotation exp(w).
fn point_to_plane_step(
    pairs: &[Pair],
    target: &[Vector3<f64>],
    normals: &[Option<Vector3<f64>>],
) -> Option<Isometry3<f64>> {
    let mut ata = Matrix6::<f64>::zeros();
    let mut atb = Vector6::<f64>::zeros();
    for pair in pairs {
        let n = normals[pair.target]?;
        let p = pair.source;
        let c = p.cross(&n);
        let a = Vector6::new(c.x, c.y, c.z, n.x, n.y, n.z);
        let b = (target[pair.target] - p).dot(&n);
        ata += a * a.transpose();
        atb += a * b;
    }
    let x = ata.cholesky()?.solve(&atb);
    let w = Vector3::new(x[0], x[1], x[2]);
    let t = Vector3::new(x[3], x[4], x[5]);
    Some(Isometry3::from_parts(
        Translation3::from(t),
        UnitQuaternion::from_scaled_axis(w),
    ))
}

/// Unit normal of each target point: the eigenvector of the smallest eigenvalue of the
/// covariance of its `k` nearest neighbours; `None` when the neighbourhood has no
/// well-defined plane (fewer than 3 points or collinear).
fn estimate_normals(points: &[Point3], index: &Index, k: usize) -> Vec<Option<Vector3<f64>>> {
    let Some(k) = NonZeroUsize::new(k) else {
        return vec![None; points.len()];
    };
    points
        .par_iter()
        .map(|p| {
            let neighbours = index.nearest_n(p, k);
            if neighbours.len() < 3 {
                return None;
            }
            let pts: Vec<Vector3<f64>> = neighbours
                .iter()
                .map(|i| points[*i].coords.cast())
                .collect();
            let mean = pts.iter().sum::<Vector3<f64>>() / pts.len() as f64;
            let cov: Matrix3<f64> = pts
                .iter()
                .map(|q| (q - mean) * (q - mean).transpose())
                .sum();
            let eigen = SymmetricEigen::new(cov);
            let mut order = [0, 1, 2];
            order.sort_by(|a, b| eigen.eigenvalues[*a].total_cmp(&eigen.eigenvalues[*b]));
            // Collinear or coincident neighbours: the two smallest eigenvalues vanish.
            if eigen.eigenvalues[order[1]] <= f64::EPSILON * eigen.eigenvalues[order[2]].abs() {
                return None;
            }
            let normal: Vector3<f64> = eigen.eigenvectors.column(order[0]).into();
            Some(normal.normalize())
        })
        .collect()
}
