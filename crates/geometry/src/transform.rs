//! The 3D transformation of thesis Listing A.4 (docs/design.md §5) and its JSON document.
//!
//! A camera point `p` (librealsense frame: x right, y down, z forward, metres) goes to
//!
//! ```text
//! p1 = R * (scale .* p) + t
//! p2 = post_scale .* (Rpost * p1 + t_post),   Rpost = Rz(yaw) * Ry(pitch) * Rx(roll)
//! ```
//!
//! where `post_rotation_matrix` = [roll, pitch, yaw] in degrees: roll about x is applied
//! first, then pitch about y, then yaw about z, all about the fixed axes of the frame of
//! `p1`. The document keeps the thesis key names and shapes: `rotation_matrix` is 3x3 by
//! rows, every other entry a column `[[x],[y],[z]]`.
//!
//! ```json
//! {
//!   "scale_matrix": [[1.0],[1.0],[1.0]],
//!   "rotation_matrix": [[0.999524,0.030429,-0.005019],
//!                       [0.030511,-0.999388,0.017115],
//!                       [-0.004495,-0.017260,-0.999841]],
//!   "translation_matrix": [[-0.113241],[0.111672],[-0.769009]],
//!   "post_scale_matrix": [[1.0],[1.0],[1.0]],
//!   "post_rotation_matrix": [[0.0],[0.0],[0.0]],
//!   "post_translation_matrix": [[0.0],[0.0],[0.0]]
//! }
//! ```
//!
//! `rotation_matrix` and `translation_matrix` are required; the four others default to the
//! identity (scales 1, angles and translation 0) when absent. `R` is used as given: the
//! thesis tool writes the rotation it estimated, and manual corrections may leave it
//! slightly off orthonormal, so it is not re-orthonormalised or checked for it.

use nalgebra::{Isometry3, Matrix3, Rotation3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::{Point3, PointCloud, Roi3};

/// Why a 3d-transformation document was refused. `Display` is the 4.00 diagnostic: it
/// names the field and says what is allowed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum TransformError {
    /// Not JSON of the expected shape (syntax, a missing or unknown key, a value that is
    /// not a list of lists of numbers); serde_json's message names the key.
    #[error("3d-transformation: {message}")]
    Json {
        /// serde_json's description, with line and column.
        message: String,
    },
    /// A matrix has the wrong number of rows or columns.
    #[error("3d-transformation: `{field}` must be {expected}, found {found}")]
    Shape {
        /// The JSON key.
        field: &'static str,
        /// The allowed shape, spelled as JSON.
        expected: &'static str,
        /// What the document had.
        found: String,
    },
    /// An entry is NaN, infinite, or outside the `f32` range the points are computed in.
    #[error(
        "3d-transformation: `{field}[{row}][{col}]` must be a finite number within ±3.4e38, found {value}"
    )]
    NonFinite {
        /// The JSON key.
        field: &'static str,
        /// Row of the entry (0-based).
        row: usize,
        /// Column of the entry (0-based).
        col: usize,
        /// The offending value.
        value: f64,
    },
    /// A scale is 0 (or nearly), or the rotation matrix is singular: the transform
    /// would flatten the cloud onto a plane, a line or a point, so nothing could be
    /// measured in it.
    #[error(
        "3d-transformation: `{field}` {what}; the transform would flatten every point cloud, so it is refused"
    )]
    Singular {
        /// The JSON key.
        field: &'static str,
        /// What is wrong with it.
        what: String,
    },
    /// Every entry is finite, but the composed transform overflows `f32`.
    #[error(
        "3d-transformation: the scales, rotation and translations compose to a transform outside the f32 range; keep their products within ±3.4e38"
    )]
    Overflow,
}

const ROTATION_SHAPE: &str = "a 3x3 matrix by rows [[r00,r01,r02],[r10,r11,r12],[r20,r21,r22]]";
const COLUMN_SHAPE: &str = "a 3x1 column [[x],[y],[z]]";

/// The validated 3d-transformation document (thesis Listing A.4).
///
/// Serde reads and writes the thesis JSON (through [`Self::from_json`]-style validation);
/// fields are public so that tools can build one, and [`Self::validate`] /
/// [`Self::to_transform`] check them again.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "RawTransformation", into = "RawTransformation")]
pub struct Transformation {
    /// `scale_matrix`: per-axis scale applied to camera points first.
    pub scale: Vector3<f64>,
    /// `rotation_matrix`: `R`.
    pub rotation: Matrix3<f64>,
    /// `translation_matrix`: `t`, metres.
    pub translation: Vector3<f64>,
    /// `post_scale_matrix`: per-axis scale applied last.
    pub post_scale: Vector3<f64>,
    /// `post_rotation_matrix`: [roll, pitch, yaw] in degrees, about x, y, z.
    pub post_rotation_deg: Vector3<f64>,
    /// `post_translation_matrix`: `t_post`, metres.
    pub post_translation: Vector3<f64>,
}

impl Default for Transformation {
    /// The identity: unit scales, `R = I`, no translation, no post rotation.
    fn default() -> Self {
        Self::identity()
    }
}

impl Transformation {
    /// The identity document.
    #[must_use]
    pub fn identity() -> Self {
        Self {
            scale: Vector3::repeat(1.0),
            rotation: Matrix3::identity(),
            translation: Vector3::zeros(),
            post_scale: Vector3::repeat(1.0),
            post_rotation_deg: Vector3::zeros(),
            post_translation: Vector3::zeros(),
        }
    }

    /// The document of a rigid motion: `rotation` and `translation`, no scales, no post
    /// transform.
    #[must_use]
    pub fn rigid(rotation: Matrix3<f64>, translation: Vector3<f64>) -> Self {
        Self {
            rotation,
            translation,
            ..Self::identity()
        }
    }

    /// Parses and validates a document.
    pub fn from_json(json: &[u8]) -> Result<Self, TransformError> {
        let raw: RawTransformation =
            serde_json::from_slice(json).map_err(|e| TransformError::Json {
                message: e.to_string(),
            })?;
        Self::try_from(raw)
    }

    /// The document as pretty JSON in the thesis shape, all six keys present.
    #[must_use]
    pub fn to_json(&self) -> String {
        let raw = RawTransformation::from(*self);
        // A struct of lists of f64 always serialises; non-finite f64 become `null`, which
        // from_json then refuses with a message naming the key.
        serde_json::to_string_pretty(&raw).unwrap_or_default()
    }

    /// Checks that every entry is finite within the `f32` range.
    pub fn validate(&self) -> Result<(), TransformError> {
        check_finite("scale_matrix", self.scale.as_slice(), 1)?;
        // nalgebra stores column-major; report (row, col) as written in the document.
        for row in 0..3 {
            for col in 0..3 {
                let value = self.rotation[(row, col)];
                if !finite_f32(value) {
                    return Err(TransformError::NonFinite {
                        field: "rotation_matrix",
                        row,
                        col,
                        value,
                    });
                }
            }
        }
        check_finite("translation_matrix", self.translation.as_slice(), 1)?;
        check_finite("post_scale_matrix", self.post_scale.as_slice(), 1)?;
        check_finite("post_rotation_matrix", self.post_rotation_deg.as_slice(), 1)?;
        check_finite(
            "post_translation_matrix",
            self.post_translation.as_slice(),
            1,
        )?;
        for (field, scale) in [
            ("scale_matrix", &self.scale),
            ("post_scale_matrix", &self.post_scale),
        ] {
            if let Some(i) = scale.iter().position(|v| v.abs() < MIN_SCALE) {
                return Err(TransformError::Singular {
                    field,
                    what: format!("[{i}][0] is {}, must not be 0", scale[i]),
                });
            }
        }
        let det = self.rotation.determinant();
        if !det.is_finite() || det.abs() < MIN_SCALE.powi(3) {
            return Err(TransformError::Singular {
                field: "rotation_matrix",
                what: format!("has determinant {det}, must be invertible"),
            });
        }
        Ok(())
    }

    /// `Rpost = Rz(yaw) * Ry(pitch) * Rx(roll)` from the degrees of `post_rotation_matrix`.
    #[must_use]
    pub fn post_rotation(&self) -> Matrix3<f64> {
        let [roll, pitch, yaw] = [
            self.post_rotation_deg.x.to_radians(),
            self.post_rotation_deg.y.to_radians(),
            self.post_rotation_deg.z.to_radians(),
        ];
        let rx = Rotation3::from_axis_angle(&Vector3::x_axis(), roll);
        let ry = Rotation3::from_axis_angle(&Vector3::y_axis(), pitch);
        let rz = Rotation3::from_axis_angle(&Vector3::z_axis(), yaw);
        (rz * ry * rx).into_inner()
    }

    /// Composes the document into one affine map `p2 = A p + b` (in `f64`, then rounded to
    /// `f32`): `A = diag(post_scale) Rpost R diag(scale)`,
    /// `b = diag(post_scale) (Rpost t + t_post)`.
    pub fn to_transform(&self) -> Result<Transform, TransformError> {
        self.validate()?;
        let post_scale = Matrix3::from_diagonal(&self.post_scale);
        let rpost = self.post_rotation();
        let linear = post_scale * rpost * self.rotation * Matrix3::from_diagonal(&self.scale);
        let translation = post_scale * (rpost * self.translation + self.post_translation);
        let linear: Matrix3<f32> = linear.cast();
        let translation: Vector3<f32> = translation.cast();
        if linear
            .iter()
            .chain(translation.iter())
            .all(|v| v.is_finite())
        {
            Ok(Transform {
                linear,
                translation,
            })
        } else {
            Err(TransformError::Overflow)
        }
    }
}

/// The smallest scale (in absolute value) a document may have: a micrometre per metre.
const MIN_SCALE: f64 = 1e-6;

fn finite_f32(value: f64) -> bool {
    value.is_finite() && (value as f32).is_finite()
}

fn check_finite(field: &'static str, values: &[f64], cols: usize) -> Result<(), TransformError> {
    match values.iter().position(|v| !finite_f32(*v)) {
        None => Ok(()),
        Some(i) => Err(TransformError::NonFinite {
            field,
            row: i / cols,
            col: i % cols,
            value: values[i],
        }),
    }
}

/// The document exactly as JSON spells it.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawTransformation {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    scale_matrix: Option<Vec<Vec<f64>>>,
    rotation_matrix: Vec<Vec<f64>>,
    translation_matrix: Vec<Vec<f64>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    post_scale_matrix: Option<Vec<Vec<f64>>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    post_rotation_matrix: Option<Vec<Vec<f64>>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    post_translation_matrix: Option<Vec<Vec<f64>>>,
}

fn column(v: &Vector3<f64>) -> Vec<Vec<f64>> {
    v.iter().map(|x| vec![*x]).collect()
}

impl From<Transformation> for RawTransformation {
    fn from(t: Transformation) -> Self {
        Self {
            scale_matrix: Some(column(&t.scale)),
            rotation_matrix: (0..3)
                .map(|r| (0..3).map(|c| t.rotation[(r, c)]).collect())
                .collect(),
            translation_matrix: column(&t.translation),
            post_scale_matrix: Some(column(&t.post_scale)),
            post_rotation_matrix: Some(column(&t.post_rotation_deg)),
            post_translation_matrix: Some(column(&t.post_translation)),
        }
    }
}

/// Rows shown by [`shape_of`]; the message stays short whatever the document holds.
const SHAPE_ROWS_SHOWN: usize = 3;

/// "3 rows of [3, 2, 3] entries"; beyond [`SHAPE_ROWS_SHOWN`] rows the rest is elided.
fn shape_of(rows: &[Vec<f64>]) -> String {
    let lens: Vec<String> = rows
        .iter()
        .take(SHAPE_ROWS_SHOWN)
        .map(|r| r.len().to_string())
        .collect();
    let more = if rows.len() > SHAPE_ROWS_SHOWN {
        ", …"
    } else {
        ""
    };
    format!("{} rows of [{}{more}] entries", rows.len(), lens.join(", "))
}

fn parse_column(field: &'static str, rows: &[Vec<f64>]) -> Result<Vector3<f64>, TransformError> {
    match rows {
        [x, y, z] if x.len() == 1 && y.len() == 1 && z.len() == 1 => {
            let v = Vector3::new(x[0], y[0], z[0]);
            check_finite(field, v.as_slice(), 1)?;
            Ok(v)
        }
        _ => Err(TransformError::Shape {
            field,
            expected: COLUMN_SHAPE,
            found: shape_of(rows),
        }),
    }
}

fn parse_optional_column(
    field: &'static str,
    rows: Option<&Vec<Vec<f64>>>,
    default: Vector3<f64>,
) -> Result<Vector3<f64>, TransformError> {
    rows.map_or(Ok(default), |rows| parse_column(field, rows))
}

fn parse_rotation(rows: &[Vec<f64>]) -> Result<Matrix3<f64>, TransformError> {
    const FIELD: &str = "rotation_matrix";
    if rows.len() != 3 || rows.iter().any(|r| r.len() != 3) {
        return Err(TransformError::Shape {
            field: FIELD,
            expected: ROTATION_SHAPE,
            found: shape_of(rows),
        });
    }
    let mut m = Matrix3::zeros();
    for (row, values) in rows.iter().enumerate() {
        check_finite(FIELD, values, 3).map_err(|e| match e {
            TransformError::NonFinite { col, value, .. } => TransformError::NonFinite {
                field: FIELD,
                row,
                col,
                value,
            },
            other => other,
        })?;
        for (col, value) in values.iter().enumerate() {
            m[(row, col)] = *value;
        }
    }
    Ok(m)
}

impl TryFrom<RawTransformation> for Transformation {
    type Error = TransformError;

    fn try_from(raw: RawTransformation) -> Result<Self, Self::Error> {
        let ones = Vector3::repeat(1.0);
        let transformation = Self {
            scale: parse_optional_column("scale_matrix", raw.scale_matrix.as_ref(), ones)?,
            rotation: parse_rotation(&raw.rotation_matrix)?,
            translation: parse_column("translation_matrix", &raw.translation_matrix)?,
            post_scale: parse_optional_column(
                "post_scale_matrix",
                raw.post_scale_matrix.as_ref(),
                ones,
            )?,
            post_rotation_deg: parse_optional_column(
                "post_rotation_matrix",
                raw.post_rotation_matrix.as_ref(),
                Vector3::zeros(),
            )?,
            post_translation: parse_optional_column(
                "post_translation_matrix",
                raw.post_translation_matrix.as_ref(),
                Vector3::zeros(),
            )?,
        };
        transformation.to_transform()?;
        Ok(transformation)
    }
}

/// Points per parallel task of [`Transform::apply_and_crop`].
const CROP_CHUNK: usize = 16 * 1024;

/// A compiled affine map `p -> linear * p + translation` on `f32` points, from a
/// [`Transformation`] document, an ICP result or a composition of both.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Transform {
    /// The 3x3 part.
    pub linear: Matrix3<f32>,
    /// The translation, metres.
    pub translation: Vector3<f32>,
}

impl Default for Transform {
    fn default() -> Self {
        Self::identity()
    }
}

impl From<Isometry3<f32>> for Transform {
    fn from(iso: Isometry3<f32>) -> Self {
        Self {
            linear: iso.rotation.to_rotation_matrix().into_inner(),
            translation: iso.translation.vector,
        }
    }
}

impl Transform {
    /// The identity map.
    #[must_use]
    pub fn identity() -> Self {
        Self {
            linear: Matrix3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// Maps one point.
    #[must_use]
    pub fn apply(&self, p: &Point3) -> Point3 {
        Point3::from(self.linear * p.coords + self.translation)
    }

    /// `self` followed by `next`: `next.apply(&self.apply(p))` for every `p`.
    #[must_use]
    pub fn then(&self, next: &Self) -> Self {
        Self {
            linear: next.linear * self.linear,
            translation: next.linear * self.translation + next.translation,
        }
    }

    /// Maps every point of `cloud` in place (parallel).
    pub fn apply_in_place(&self, cloud: &mut PointCloud) {
        cloud.points.par_iter_mut().for_each(|p| *p = self.apply(p));
    }

    /// Maps `points` and keeps those inside `roi` (in the output frame), in input order;
    /// one parallel pass. Points with a non-finite coordinate never pass.
    #[must_use]
    pub fn apply_and_crop(&self, points: &[Point3], roi: &Roi3) -> PointCloud {
        // Per-chunk vectors then one copy: cheaper than rayon's unindexed collect.
        let kept: Vec<Vec<Point3>> = points
            .par_chunks(CROP_CHUNK)
            .map(|chunk| {
                chunk
                    .iter()
                    .map(|p| self.apply(p))
                    .filter(|p| roi.contains(p))
                    .collect()
            })
            .collect();
        PointCloud {
            points: kept.concat(),
        }
    }
}
