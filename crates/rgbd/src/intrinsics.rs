//! Camera intrinsics and extrinsics as librealsense defines them, and
//! pixel <-> point conversion.
//!
//! Camera frame (librealsense): x right, y down, z forward, metres, origin at the
//! optical centre of the stream (the left imager for depth).

use serde::{Deserialize, Serialize};

/// Lens distortion models, named as librealsense's `rs2_distortion`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum DistortionModel {
    /// Rectilinear image, no distortion.
    None,
    /// Forward Brown-Conrady applied to the already distorted image. librealsense's
    /// release builds deproject it as a plain pinhole (skipping their debug assertion),
    /// and so does this crate.
    ModifiedBrownConrady,
    /// Inverse Brown-Conrady (librealsense's label for D400 color streams).
    InverseBrownConrady,
    /// Brown-Conrady as OpenCV (D400 depth streams, with all coefficients zero).
    BrownConrady,
    /// Kannala-Brandt fisheye with four coefficients.
    KannalaBrandt4,
}

impl DistortionModel {
    /// Every model.
    pub const ALL: [Self; 5] = [
        Self::None,
        Self::ModifiedBrownConrady,
        Self::InverseBrownConrady,
        Self::BrownConrady,
        Self::KannalaBrandt4,
    ];

    /// The model [`DistortionModel::name`] names.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|m| m.name() == name)
    }

    /// The name librealsense prints for the model ("Brown Conrady", ...).
    pub fn name(self) -> &'static str {
        match self {
            Self::None => "None",
            Self::ModifiedBrownConrady => "Modified Brown Conrady",
            Self::InverseBrownConrady => "Inverse Brown Conrady",
            Self::BrownConrady => "Brown Conrady",
            Self::KannalaBrandt4 => "Kannala Brandt4",
        }
    }
}

/// Intrinsics of one stream at one resolution (`rs2_intrinsics`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Principal point, pixels from the left edge.
    pub ppx: f32,
    /// Principal point, pixels from the top edge.
    pub ppy: f32,
    /// Focal length in multiples of the pixel width.
    pub fx: f32,
    /// Focal length in multiples of the pixel height.
    pub fy: f32,
    /// Distortion model of `coeffs`.
    pub model: DistortionModel,
    /// `[k1, k2, p1, p2, k3]` for the Brown models, `[k1, k2, k3, k4, 0]` for Kannala-Brandt.
    pub coeffs: [f32; 5],
}

/// Why a point could not be projected to a pixel.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum ProjectError {
    /// The intrinsics are not pinhole: a Brown model with non-zero coefficients, or
    /// Kannala-Brandt (whatever its coefficients).
    #[error(
        "projection through the {} distortion model is not supported (only pinhole: model None, or a Brown model with all coefficients zero)",
        .0.name()
    )]
    UnsupportedDistortion(DistortionModel),
}

impl Intrinsics {
    /// True when the image is a plain pinhole projection: model `None`, or a Brown
    /// model whose coefficients are all zero (librealsense then skips the distortion
    /// step, as for every D400 depth stream).
    pub fn is_pinhole(&self) -> bool {
        match self.model {
            DistortionModel::None => true,
            DistortionModel::BrownConrady
            | DistortionModel::InverseBrownConrady
            | DistortionModel::ModifiedBrownConrady => {
                self.coeffs.iter().all(|c| c.abs() < f32::EPSILON)
            }
            DistortionModel::KannalaBrandt4 => false,
        }
    }

    /// The 3D point (metres, camera frame) seen at `pixel` (`[u, v]`, pixel units,
    /// integer values at pixel centres as librealsense's point cloud uses them) at
    /// depth `depth_m` along z: `rs2_deproject_pixel_to_point` for every model (see
    /// [`pixel_to_ray`]).
    pub fn deproject(&self, pixel: [f32; 2], depth_m: f32) -> [f32; 3] {
        let [x, y] = pixel_to_ray(self, pixel);
        [depth_m * x, depth_m * y, depth_m]
    }

    /// The pixel at which `point` (metres, camera frame, z > 0) is seen; same
    /// arithmetic as `rs2_project_point_to_pixel` for pinhole intrinsics.
    pub fn project(&self, point: [f32; 3]) -> Result<[f32; 2], ProjectError> {
        if !self.is_pinhole() {
            return Err(ProjectError::UnsupportedDistortion(self.model));
        }
        let x = point[0] / point[2];
        let y = point[1] / point[2];
        Ok([x * self.fx + self.ppx, y * self.fy + self.ppy])
    }
}

/// Rigid transform from one stream's frame to another's (`rs2_extrinsics`):
/// `to = R * from + t`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Extrinsics {
    /// 3x3 rotation, column-major as librealsense stores it.
    pub rotation: [f32; 9],
    /// Translation in metres.
    pub translation: [f32; 3],
}

impl Extrinsics {
    /// The identity transform.
    pub const IDENTITY: Self = Self {
        rotation: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        translation: [0.0; 3],
    };

    /// Transforms `point` (`rs2_transform_point_to_point`).
    pub fn transform(&self, point: [f32; 3]) -> [f32; 3] {
        let r = &self.rotation;
        let [x, y, z] = point;
        [
            r[0] * x + r[3] * y + r[6] * z + self.translation[0],
            r[1] * x + r[4] * y + r[7] * z + self.translation[1],
            r[2] * x + r[5] * y + r[8] * z + self.translation[2],
        ]
    }
}

/// Pose of a camera's depth frame in the world (z up, metres): `world = R * camera + t`.
/// This is the rotation and translation of the 3d-transformation resource
/// (thesis Listing A.4) with unit scales and no post transform.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// 3x3 rotation, row-major (`rotation[row][col]`), as Listing A.4 writes it.
    pub rotation: [[f64; 3]; 3],
    /// Position of the camera's optical centre in the world, metres.
    pub translation: [f64; 3],
}

impl Pose {
    /// Transforms a camera-frame point into the world.
    pub fn transform_point(&self, p: [f64; 3]) -> [f64; 3] {
        let r = &self.rotation;
        let t = &self.translation;
        [
            r[0][0] * p[0] + r[0][1] * p[1] + r[0][2] * p[2] + t[0],
            r[1][0] * p[0] + r[1][1] * p[1] + r[1][2] * p[2] + t[1],
            r[2][0] * p[0] + r[2][1] * p[1] + r[2][2] * p[2] + t[2],
        ]
    }
}

/// Iterations librealsense runs for the Brown-Conrady models.
const BROWN_ITERATIONS: usize = 10;

/// Newton steps librealsense allows for Kannala-Brandt.
const KB4_STEPS: usize = 4;

/// The undistorted normalised ray (z = 1) through `pixel`, as librealsense computes it.
pub fn pixel_to_ray(k: &Intrinsics, pixel: [f32; 2]) -> [f32; 2] {
    let x = (pixel[0] - k.ppx) / k.fx;
    let y = (pixel[1] - k.ppy) / k.fy;
    undistort(k, x, y)
}

fn undistort(k: &Intrinsics, x0: f32, y0: f32) -> [f32; 2] {
    let c = &k.coeffs;
    match k.model {
        DistortionModel::None | DistortionModel::ModifiedBrownConrady => [x0, y0],
        // With every coefficient +0 each iteration gives back (x0, y0) exactly (the
        // factor is 1 / (1 + 0), the shift +0): D400 depth streams say Brown-Conrady
        // with zero coefficients, and the ten iterations were most of the time the
        // server's floor check took over its pixels.
        DistortionModel::BrownConrady | DistortionModel::InverseBrownConrady
            if c.iter().all(|v| v.to_bits() == 0) =>
        {
            [x0, y0]
        }
        DistortionModel::BrownConrady | DistortionModel::InverseBrownConrady => {
            let inverse = k.model == DistortionModel::InverseBrownConrady;
            let (mut x, mut y) = (x0, y0);
            for _ in 0..BROWN_ITERATIONS {
                let r2 = x * x + y * y;
                let icd = 1.0 / (1.0 + ((c[4] * r2 + c[1]) * r2 + c[0]) * r2);
                let (tx, ty) = if inverse { (x / icd, y / icd) } else { (x, y) };
                let dx = 2.0 * c[2] * tx * ty + c[3] * (r2 + 2.0 * tx * tx);
                let dy = 2.0 * c[3] * tx * ty + c[2] * (r2 + 2.0 * ty * ty);
                x = (x0 - dx) * icd;
                y = (y0 - dy) * icd;
            }
            [x, y]
        }
        DistortionModel::KannalaBrandt4 => {
            let rd = (x0 * x0 + y0 * y0).sqrt().max(f32::EPSILON);
            let (mut theta, mut theta2) = (rd, rd * rd);
            for _ in 0..KB4_STEPS {
                let f = theta
                    * (1.0 + theta2 * (c[0] + theta2 * (c[1] + theta2 * (c[2] + theta2 * c[3]))))
                    - rd;
                if f.abs() < f32::EPSILON {
                    break;
                }
                let df = 1.0
                    + theta2
                        * (3.0 * c[0]
                            + theta2 * (5.0 * c[1] + theta2 * (7.0 * c[2] + 9.0 * theta2 * c[3])));
                theta -= f / df;
                theta2 = theta * theta;
            }
            let r = theta.tan();
            [x0 * (r / rd), y0 * (r / rd)]
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pinhole() -> Intrinsics {
        Intrinsics {
            width: 1280,
            height: 720,
            ppx: 637.0,
            ppy: 364.0,
            fx: 896.0,
            fy: 896.0,
            model: DistortionModel::BrownConrady,
            coeffs: [0.0; 5],
        }
    }

    #[test]
    fn zero_coefficients_deproject_as_a_pinhole_bit_for_bit() {
        for model in [
            DistortionModel::BrownConrady,
            DistortionModel::InverseBrownConrady,
        ] {
            let k = Intrinsics { model, ..pinhole() };
            for (u, v) in [(0.0, 0.0), (637.0, 364.0), (1279.5, 719.5), (100.25, 600.0)] {
                let ray = pixel_to_ray(&k, [u, v]);
                assert_eq!(ray, [(u - k.ppx) / k.fx, (v - k.ppy) / k.fy], "{model:?}");
            }
        }
        // Any coefficient that is not +0 takes the iterations.
        let mut k = pinhole();
        k.coeffs[0] = 0.1;
        let ray = pixel_to_ray(&k, [1200.0, 700.0]);
        assert_ne!(ray, [(1200.0 - k.ppx) / k.fx, (700.0 - k.ppy) / k.fy]);
    }

    #[test]
    fn deproject_then_project_returns_the_pixel() {
        let k = pinhole();
        let p = k.deproject([100.0, 600.0], 1.25);
        let px = k.project(p).unwrap();
        assert!((px[0] - 100.0).abs() < 1e-3 && (px[1] - 600.0).abs() < 1e-3);
    }

    #[test]
    fn principal_point_deprojects_onto_the_optical_axis() {
        assert_eq!(pinhole().deproject([637.0, 364.0], 2.0), [0.0, 0.0, 2.0]);
    }

    #[test]
    fn projection_through_distortion_is_refused_not_guessed() {
        let mut k = pinhole();
        k.model = DistortionModel::InverseBrownConrady;
        k.coeffs[0] = 0.1;
        assert_eq!(
            k.project([0.0, 0.0, 1.0]),
            Err(ProjectError::UnsupportedDistortion(
                DistortionModel::InverseBrownConrady
            ))
        );
    }

    #[test]
    fn kannala_brandt_is_refused_even_with_zero_coefficients_and_modified_brown_deprojects_as_pinhole()
     {
        let mut k = pinhole();
        k.model = DistortionModel::KannalaBrandt4;
        let e = k.project([0.0, 0.0, 1.0]).unwrap_err();
        assert_eq!(
            e,
            ProjectError::UnsupportedDistortion(DistortionModel::KannalaBrandt4)
        );
        assert!(e.to_string().starts_with("projection through the"), "{e}");
        assert!(!e.to_string().contains("non-zero coefficients is"), "{e}");
        let mut m = pinhole();
        m.model = DistortionModel::ModifiedBrownConrady;
        m.coeffs[0] = 0.1;
        assert_eq!(
            m.deproject([100.0, 50.0], 2.0),
            pinhole().deproject([100.0, 50.0], 2.0)
        );
    }

    #[test]
    fn extrinsics_rotation_is_column_major() {
        // 90 degrees about z: x -> y.
        let e = Extrinsics {
            rotation: [0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            translation: [0.5, 0.0, 0.0],
        };
        assert_eq!(e.transform([1.0, 0.0, 0.0]), [0.5, 1.0, 0.0]);
    }
}
