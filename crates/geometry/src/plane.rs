//! The floor seen by one camera: the plane with the most points (RANSAC), refined by a
//! least-squares fit of its inliers, and the pose that puts it at z = 0.

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use crate::{Point3, Transformation};

/// A plane `normal · p + offset = 0`, `normal` of unit length.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    /// The unit normal.
    pub normal: Vector3<f64>,
    /// The offset: minus the distance of the plane from the origin along `normal`.
    pub offset: f64,
    /// Points within the inlier distance of the plane.
    pub inliers: usize,
    /// The root mean square distance of the inliers from the plane, metres.
    pub rms: f64,
}

impl Plane {
    /// The signed distance of `p` from the plane.
    pub fn distance(&self, p: &Point3) -> f64 {
        self.normal.dot(&p.coords.cast::<f64>()) + self.offset
    }
}

/// Why no plane was found.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PlaneError {
    /// Fewer than three points.
    #[error("too few points to fit a plane ({0})")]
    TooFew(usize),
    /// No plane holds enough of the points.
    #[error("no plane holds a tenth of the points")]
    NoPlane,
}

/// The plane holding the most of `points` within `inlier_m` (RANSAC over `iterations`
/// samples, drawn with `seed`), refined by least squares over its inliers.
pub fn dominant_plane(
    points: &[Point3],
    inlier_m: f64,
    iterations: usize,
    seed: u64,
) -> Result<Plane, PlaneError> {
    if points.len() < 3 {
        return Err(PlaneError::TooFew(points.len()));
    }
    // Candidates are scored on a subsample, so that a sample costs the same whatever the
    // cloud's size; the winner is refined on every point.
    let step = (points.len() / 20_000).max(1);
    let sample: Vec<Point3> = points.iter().step_by(step).copied().collect();
    let mut state = seed;
    let mut next = |n: usize| {
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) % n as u64) as usize
    };
    let mut best: Option<(usize, Vector3<f64>, f64)> = None;
    for _ in 0..iterations {
        let [a, b, c] = [next(sample.len()), next(sample.len()), next(sample.len())]
            .map(|i| sample[i].coords.cast::<f64>());
        let Some(normal) = (b - a).cross(&(c - a)).try_normalize(1e-12) else {
            continue;
        };
        let offset = -normal.dot(&a);
        let count = sample
            .iter()
            .filter(|p| (normal.dot(&p.coords.cast::<f64>()) + offset).abs() <= inlier_m)
            .count();
        if best.is_none_or(|(n, ..)| count > n) {
            best = Some((count, normal, offset));
        }
    }
    let Some((count, normal, offset)) = best else {
        return Err(PlaneError::NoPlane);
    };
    if count * 10 < sample.len() {
        return Err(PlaneError::NoPlane);
    }
    plane_near(points, normal, offset, inlier_m)
}

/// The least-squares plane of the points within `inlier_m` of the plane `normal · p +
/// offset = 0`: through their centroid, normal to their covariance's smallest axis
/// (turned to agree with the given normal).
pub fn plane_near(
    points: &[Point3],
    normal: Vector3<f64>,
    offset: f64,
    inlier_m: f64,
) -> Result<Plane, PlaneError> {
    let inliers: Vec<Vector3<f64>> = points
        .iter()
        .map(|p| p.coords.cast::<f64>())
        .filter(|p| (normal.dot(p) + offset).abs() <= inlier_m)
        .collect();
    if inliers.len() < 3 {
        return Err(PlaneError::TooFew(inliers.len()));
    }
    let n = inliers.len() as f64;
    let centroid = inliers.iter().sum::<Vector3<f64>>() / n;
    let covariance = inliers
        .iter()
        .map(|p| (p - centroid) * (p - centroid).transpose())
        .sum::<Matrix3<f64>>()
        / n;
    let eigen = SymmetricEigen::new(covariance);
    let smallest = eigen.eigenvalues.imin();
    let mut refined = eigen.eigenvectors.column(smallest).into_owned();
    if refined.dot(&normal) < 0.0 {
        refined = -refined;
    }
    let offset = -refined.dot(&centroid);
    let rms = (inliers
        .iter()
        .map(|p| (refined.dot(p) + offset).powi(2))
        .sum::<f64>()
        / n)
        .sqrt();
    Ok(Plane {
        normal: refined,
        offset,
        inliers: inliers.len(),
        rms,
    })
}

/// The 3d-transformation that puts `floor`, seen in the camera's frame, at z = 0 with
/// z up (towards the camera), the camera above the origin, and x along the camera's x
/// axis laid on the floor. Roll, pitch and the camera's height come from the floor;
/// yaw and the position on the floor cannot, and stay as the camera's.
pub fn floor_transformation(floor: &Plane) -> Transformation {
    // The normal that points to the camera (at the origin of its frame).
    let (up, height) = if floor.offset >= 0.0 {
        (floor.normal, floor.offset)
    } else {
        (-floor.normal, -floor.offset)
    };
    let x = Vector3::x();
    let along = (x - up * up.dot(&x))
        .try_normalize(1e-9)
        .unwrap_or_else(|| (Vector3::y() - up * up.dot(&Vector3::y())).normalize());
    let y = up.cross(&along);
    let rotation = Matrix3::from_rows(&[along.transpose(), y.transpose(), up.transpose()]);
    Transformation::rigid(rotation, Vector3::new(0.0, 0.0, height))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A floor 1.2 m from a camera tilted 30 degrees, with 10 % of the points a box top.
    fn tilted_floor() -> Vec<Point3> {
        let tilt = 30f64.to_radians();
        let up = Vector3::new(0.0, -tilt.cos(), -tilt.sin());
        let (a, b) = (Vector3::x(), up.cross(&Vector3::x()));
        let mut points = Vec::new();
        for i in 0..100 {
            for j in 0..100 {
                let (u, v) = (f64::from(i) / 50.0 - 1.0, f64::from(j) / 50.0 - 1.0);
                let lift = if i < 30 && j < 30 { 0.2 } else { 0.0 };
                let p = -up * 1.2 + a * u + b * v + up * lift;
                points.push(Point3::new(p.x as f32, p.y as f32, p.z as f32));
            }
        }
        points
    }

    #[test]
    fn the_floor_of_a_tilted_camera_goes_to_z_0() {
        let points = tilted_floor();
        let floor = dominant_plane(&points, 0.01, 200, 1).expect("a plane");
        assert!(floor.inliers >= 9000, "{floor:?}");
        let t = floor_transformation(&floor).to_transform().expect("valid");
        for p in &points {
            let q = t.apply(p);
            let on_floor = q.z.abs() < 1e-4;
            let on_box = (q.z - 0.2).abs() < 1e-4;
            assert!(on_floor || on_box, "{p:?} -> {q:?}");
        }
        // The camera (the origin of its frame) is 1.2 m above the floor.
        let camera = t.apply(&Point3::origin());
        assert!((camera.z - 1.2).abs() < 1e-4, "{camera:?}");
    }

    #[test]
    fn too_few_points_or_no_plane_is_an_error() {
        assert_eq!(
            dominant_plane(&[Point3::origin()], 0.01, 10, 1),
            Err(PlaneError::TooFew(1))
        );
    }
}
