//! A camera's pose from points of known position: on a plane seen in an image (PnP), and
//! the rigid motion within the plane that best maps one set of points onto another.

use nalgebra::{
    Isometry3, Matrix3, Rotation2, Rotation3, SMatrix, SVector, Translation3, UnitQuaternion,
    Vector2, Vector3,
};

/// A point of the plane z = 0 (`world`, metres) and the undistorted normalised image ray
/// (`x / z`, `y / z` in the camera's frame) through which the camera sees it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sighting {
    /// (x, y) on the plane z = 0.
    pub world: Vector2<f64>,
    /// The normalised image coordinates.
    pub ray: Vector2<f64>,
}

/// Gauss-Newton steps of the refinement (it converges in a few from the homography's
/// estimate).
const REFINE_STEPS: usize = 20;

/// The pose of a camera (world -> camera) that sees the `sightings`, points of the plane
/// z = 0: a homography's estimate, refined by Gauss-Newton on the reprojection error.
/// `None` with fewer than four sightings or when they are degenerate (collinear, or the
/// plane seen edge-on).
pub fn planar_pnp(sightings: &[Sighting]) -> Option<Isometry3<f64>> {
    let initial = from_homography(sightings)?;
    Some(refine(sightings, initial))
}

/// Root mean square of the reprojection error of `sightings` under `pose` (world ->
/// camera), in normalised image units (multiply by the focal length for pixels).
pub fn reprojection_rms(sightings: &[Sighting], pose: &Isometry3<f64>) -> f64 {
    if sightings.is_empty() {
        return 0.0;
    }
    let sum: f64 = sightings
        .iter()
        .map(|s| {
            let p = pose * nalgebra::Point3::new(s.world.x, s.world.y, 0.0);
            (Vector2::new(p.x / p.z, p.y / p.z) - s.ray).norm_squared()
        })
        .sum();
    (sum / sightings.len() as f64).sqrt()
}

/// Hartley's normalisation of 2D points: the similarity that moves their centroid to
/// the origin and their mean distance to sqrt(2).
fn normalisation(points: impl Iterator<Item = Vector2<f64>> + Clone) -> Option<Matrix3<f64>> {
    let n = points.clone().count() as f64;
    let centroid = points.clone().sum::<Vector2<f64>>() / n;
    let mean = points.map(|p| (p - centroid).norm()).sum::<f64>() / n;
    (mean > 1e-12).then(|| {
        let s = std::f64::consts::SQRT_2 / mean;
        Matrix3::new(
            s,
            0.0,
            -s * centroid.x,
            0.0,
            s,
            -s * centroid.y,
            0.0,
            0.0,
            1.0,
        )
    })
}

/// The pose whose homography (direct linear transform) maps the plane's points onto the
/// rays.
fn from_homography(sightings: &[Sighting]) -> Option<Isometry3<f64>> {
    if sightings.len() < 4 {
        return None;
    }
    let tw = normalisation(sightings.iter().map(|s| s.world))?;
    let tr = normalisation(sightings.iter().map(|s| s.ray))?;
    // Points on one line leave the homography undetermined: the normalised points'
    // spread must have two clear axes.
    let spread = sightings
        .iter()
        .map(|s| {
            let w = (tw * Vector3::new(s.world.x, s.world.y, 1.0)).xy();
            w * w.transpose()
        })
        .sum::<nalgebra::Matrix2<f64>>()
        / sightings.len() as f64;
    if spread.symmetric_eigenvalues().min() < 1e-6 {
        return None;
    }
    // Two rows per sighting of A h = 0; A^T A accumulated (9 x 9).
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for s in sightings {
        let w = tw * Vector3::new(s.world.x, s.world.y, 1.0);
        let r = tr * Vector3::new(s.ray.x, s.ray.y, 1.0);
        let (x, y) = (r.x / r.z, r.y / r.z);
        let rows = [
            SVector::<f64, 9>::from_column_slice(&[
                w.x,
                w.y,
                w.z,
                0.0,
                0.0,
                0.0,
                -x * w.x,
                -x * w.y,
                -x * w.z,
            ]),
            SVector::<f64, 9>::from_column_slice(&[
                0.0,
                0.0,
                0.0,
                w.x,
                w.y,
                w.z,
                -y * w.x,
                -y * w.y,
                -y * w.z,
            ]),
        ];
        for row in rows {
            ata += row * row.transpose();
        }
    }
    let eigen = ata.symmetric_eigen();
    let h = eigen
        .eigenvectors
        .column(eigen.eigenvalues.imin())
        .into_owned();
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    let hm = tr.try_inverse()? * hn * tw;
    // hm ~ [r1 r2 t]: scale so that r1 and r2 have unit length on average, and the plane
    // lies in front of the camera.
    let (c1, c2, c3) = (hm.column(0), hm.column(1), hm.column(2));
    let mut scale = 2.0 / (c1.norm() + c2.norm());
    if !scale.is_finite() {
        return None;
    }
    if c3.z * scale < 0.0 {
        scale = -scale;
    }
    let (r1, r2, t) = (c1 * scale, c2 * scale, c3 * scale);
    let approx = Matrix3::from_columns(&[r1, r2, r1.cross(&r2)]);
    // The nearest rotation.
    let svd = approx.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut r = u * v_t;
    if r.determinant() < 0.0 {
        let mut u = u;
        u.column_mut(2).neg_mut();
        r = u * v_t;
    }
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    Some(Isometry3::from_parts(Translation3::from(t), rotation))
}

/// Gauss-Newton on the reprojection error, over a rotation increment (left-multiplied)
/// and the translation.
fn refine(sightings: &[Sighting], mut pose: Isometry3<f64>) -> Isometry3<f64> {
    for _ in 0..REFINE_STEPS {
        let mut jtj = SMatrix::<f64, 6, 6>::zeros();
        let mut jtr = SVector::<f64, 6>::zeros();
        for s in sightings {
            let rotated = pose.rotation * Vector3::new(s.world.x, s.world.y, 0.0);
            let p = rotated + pose.translation.vector;
            if p.z <= 1e-9 {
                continue;
            }
            let residual = Vector2::new(p.x / p.z, p.y / p.z) - s.ray;
            // d(x/z, y/z)/dp, then dp/d(omega) = -[rotated]x and dp/dt = I.
            let dproj = SMatrix::<f64, 2, 3>::new(
                1.0 / p.z,
                0.0,
                -p.x / (p.z * p.z),
                0.0,
                1.0 / p.z,
                -p.y / (p.z * p.z),
            );
            let dp_domega = -rotated.cross_matrix();
            let mut j = SMatrix::<f64, 2, 6>::zeros();
            j.fixed_view_mut::<2, 3>(0, 0)
                .copy_from(&(dproj * dp_domega));
            j.fixed_view_mut::<2, 3>(0, 3).copy_from(&dproj);
            jtj += j.transpose() * j;
            jtr += j.transpose() * residual;
        }
        let Some(step) = jtj.cholesky().map(|c| c.solve(&(-jtr))) else {
            break;
        };
        let omega = step.fixed_rows::<3>(0).into_owned();
        let dt = step.fixed_rows::<3>(3).into_owned();
        pose.rotation = UnitQuaternion::from_scaled_axis(omega) * pose.rotation;
        pose.translation.vector += dt;
        if step.norm() < 1e-12 {
            break;
        }
    }
    pose
}

/// The rotation angle (radians) and translation of the rigid motion of the plane that
/// maps `from[i]` closest to `to[i]` (least squares). `None` with fewer than two pairs,
/// or when the points of `from` coincide.
pub fn rigid_2d(from: &[Vector2<f64>], to: &[Vector2<f64>]) -> Option<(f64, Vector2<f64>)> {
    if from.len() != to.len() || from.len() < 2 {
        return None;
    }
    let n = from.len() as f64;
    let (ca, cb) = (
        from.iter().sum::<Vector2<f64>>() / n,
        to.iter().sum::<Vector2<f64>>() / n,
    );
    let (mut cos, mut sin) = (0.0, 0.0);
    for (a, b) in from.iter().zip(to) {
        let (a, b) = (a - ca, b - cb);
        cos += a.dot(&b);
        sin += a.x * b.y - a.y * b.x;
    }
    if cos.hypot(sin) < 1e-15 {
        return None;
    }
    let angle = sin.atan2(cos);
    let translation = cb - Rotation2::new(angle) * ca;
    Some((angle, translation))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A camera 1.3 m from the plane, tilted 30 degrees and turned, seeing the corners of
    /// two 16 cm squares.
    fn setup() -> (Isometry3<f64>, Vec<Sighting>) {
        let camera_to_world = Isometry3::from_parts(
            Translation3::new(0.2, -0.7, 1.1),
            UnitQuaternion::from_euler_angles(-150f64.to_radians(), 0.0, 20f64.to_radians()),
        );
        let pose = camera_to_world.inverse();
        let mut sightings = Vec::new();
        for (cx, cy) in [(0.0, 0.0), (0.4, 0.1)] {
            for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
                let world = Vector2::new(cx + sx * 0.08, cy + sy * 0.08);
                let p = pose * nalgebra::Point3::new(world.x, world.y, 0.0);
                assert!(p.z > 0.5, "in front: {p:?}");
                sightings.push(Sighting {
                    world,
                    ray: Vector2::new(p.x / p.z, p.y / p.z),
                });
            }
        }
        (pose, sightings)
    }

    #[test]
    fn exact_sightings_give_the_exact_pose() {
        let (truth, sightings) = setup();
        let pose = planar_pnp(&sightings).expect("a pose");
        assert!((pose.translation.vector - truth.translation.vector).norm() < 1e-9);
        assert!(pose.rotation.angle_to(&truth.rotation) < 1e-9);
        assert!(reprojection_rms(&sightings, &pose) < 1e-12);
    }

    #[test]
    fn noisy_sightings_are_refined_beyond_the_homography() {
        let (truth, mut sightings) = setup();
        // +-0.3 px at a focal length of 1400 px, alternating.
        for (i, s) in sightings.iter_mut().enumerate() {
            let e = if i % 2 == 0 { 0.3 } else { -0.3 } / 1400.0;
            s.ray += Vector2::new(e, -e);
        }
        let pose = planar_pnp(&sightings).expect("a pose");
        assert!((pose.translation.vector - truth.translation.vector).norm() < 0.005);
        assert!(pose.rotation.angle_to(&truth.rotation).to_degrees() < 0.5);
        let refined = reprojection_rms(&sightings, &pose);
        let initial = reprojection_rms(&sightings, &from_homography(&sightings).unwrap());
        assert!(refined <= initial, "{refined} > {initial}");
    }

    #[test]
    fn too_few_or_collinear_sightings_give_no_pose() {
        let (_, sightings) = setup();
        assert!(planar_pnp(&sightings[..3]).is_none());
        let line: Vec<Sighting> = (0..5)
            .map(|i| Sighting {
                world: Vector2::new(f64::from(i), 0.0),
                ray: Vector2::new(f64::from(i) * 0.1, 0.0),
            })
            .collect();
        assert!(planar_pnp(&line).is_none());
    }

    #[test]
    fn rigid_2d_recovers_a_turn_and_a_shift() {
        let from = [
            Vector2::new(0.0, 0.0),
            Vector2::new(1.0, 0.0),
            Vector2::new(0.3, 2.0),
        ];
        let (angle, shift) = (0.7, Vector2::new(-0.4, 1.5));
        let to: Vec<_> = from
            .iter()
            .map(|p| Rotation2::new(angle) * p + shift)
            .collect();
        let (a, t) = rigid_2d(&from, &to).expect("a motion");
        assert!((a - angle).abs() < 1e-12 && (t - shift).norm() < 1e-12);
        assert!(rigid_2d(&from[..1], &to[..1]).is_none());
    }
}
