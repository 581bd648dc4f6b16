//! Calibration's client side: each camera's color (at full resolution) and depth grabbed
//! from a server and placed by the markers it sees (`vision::calibration`), or levelled on
//! the floor in its depth, or its document adjusted by hand; the 3d-transformation
//! written back; `--view`'s pictures of what the markers placed.

use std::path::Path;

use bytes::Bytes;
use coap::{Code, ContentFormat};
use geometry::{
    PlaneError, Point3, PointCloud, TransformError, Transformation, dominant_plane,
    floor_transformation,
};
use image::Rgb;
use markers::Detection;
use rgbd::ColorSettings;

use super::annotate::projector;
use super::measure::full_resolution;
use super::{CallError, CamClient, DocumentError};
use crate::documents::AppConfig;
use crate::repr::Stream;
use crate::repr::cbor::{ColorCapture, DepthCapture};
use crate::repr::clouds::parts_from_depth_cloud;
use crate::repr::codec::{CborError, DepthCloudError};
use crate::vision::calibration::{self, Calibration, CalibrationError, CameraView, MarkerMap};
use crate::vision::picture::{self, SaveError};

/// Points this close to the floor plane are its inliers, metres (the D415's depth noise
/// at 1-2 m is a few millimetres).
const FLOOR_INLIER_M: f64 = 0.012;
/// RANSAC samples.
const ITERATIONS: usize = 400;

/// A camera could not be placed, levelled, adjusted or written, or `--view`'s pictures
/// not drawn.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CalibrateError {
    /// A request failed (transparent: the causes the command's exit status looks for
    /// are the [`CallError`]'s sources, not itself).
    #[error(transparent)]
    Call(#[from] CallError),
    /// A camera's document could not be read or written (transparent, as `Call`).
    #[error(transparent)]
    Document(#[from] DocumentError),
    /// A color or depth frame did not decode.
    #[error(transparent)]
    Frame(#[from] CborError),
    /// A compact cloud did not decode.
    #[error(transparent)]
    DepthCloud(#[from] DepthCloudError),
    /// A depth image could not be deprojected.
    #[error(transparent)]
    Deproject(#[from] rgbd::FilterError),
    /// The markers could not be searched.
    #[error(transparent)]
    Detect(#[from] markers::DetectError),
    /// The markers seen do not place the camera.
    #[error(transparent)]
    Place(#[from] CalibrationError),
    /// A 3d-transformation is not one.
    #[error(transparent)]
    Transformation(#[from] TransformError),
    /// A picture could not be written.
    #[error(transparent)]
    Save(#[from] SaveError),
    /// The camera's color-settings, changed for the markers, could not be put back.
    #[error("camera {serial}: putting its color-settings back")]
    PutBack {
        /// The camera.
        serial: String,
        /// Why.
        source: DocumentError,
    },
    /// The server does not offer the compact cloud.
    #[error("the server sends no compact cloud (65103), which calibration needs")]
    NoCompactCloud,
    /// The compact cloud has no part.
    #[error("the cloud has no depth")]
    NoDepth,
    /// Camera `serial`'s depth points could not be had.
    #[error("camera {serial}")]
    Camera {
        /// The camera.
        serial: String,
        /// Why.
        source: Box<Self>,
    },
    /// No floor plane was found in the camera's depth points.
    #[error("camera {serial}: finding the floor in {points} points")]
    Floor {
        /// The camera.
        serial: String,
        /// How many points it was searched in.
        points: usize,
        /// Why.
        source: PlaneError,
    },
    /// Too few points lie on the floor found.
    #[error(
        "camera {serial}: only {inliers} points lie on the floor; is its roi3d cutting it away?"
    )]
    FewFloorPoints {
        /// The camera.
        serial: String,
        /// The points on the floor.
        inliers: usize,
    },
    /// The camera's 3d-transformation, as the server sent it, is not one.
    #[error("camera {serial}: reading its 3d-transformation")]
    ReadTransformation {
        /// The camera.
        serial: String,
        /// Why.
        source: TransformError,
    },
}

/// The resource of camera `sn`'s 3d-transformation.
fn path(sn: &str) -> String {
    crate::api::paths::camera(sn, "3d-transformation")
}

/// PUTs camera `sn`'s 3d-transformation.
pub async fn put(
    client: &CamClient,
    sn: &str,
    transformation: &Transformation,
) -> Result<(), CalibrateError> {
    let body = Bytes::from(transformation.to_json().into_bytes());
    client
        .call(Code::PUT, &path(sn), body, Some(ContentFormat::JSON), None)
        .await?;
    Ok(())
}

/// What one camera showed and where the markers place it.
pub struct Placed {
    /// The camera's serial number.
    pub serial: String,
    /// Its color frame.
    pub capture: ColorCapture,
    /// The markers found in it.
    pub detections: Vec<Detection>,
    /// Its depth points, in its own frame.
    pub points: Vec<Point3>,
    /// Where the markers place the camera.
    pub calibration: Calibration,
    /// What did not go as asked but did not stop the placing (a camera that refused the
    /// full resolution was searched at its current one).
    pub warnings: Vec<String>,
}

/// Grabs camera `sn`'s color (at full resolution) and depth, and places it.
pub async fn place(
    client: &CamClient,
    sn: &str,
    map: &MarkerMap,
) -> Result<Placed, CalibrateError> {
    let mut warnings = Vec::new();
    let capture = full_resolution_color(client, sn, &mut warnings).await?;
    let gray = image::imageops::grayscale(&capture.image);
    let (w, h) = gray.dimensions();
    let detections = markers::detect(map.family, gray.as_raw(), w as usize, h as usize)?;
    let points = depth_points(client, sn, &mut warnings).await?;
    let view = CameraView {
        detections: &detections,
        color: &capture.intrinsics,
        depth_to_color: &capture.depth_to_color,
        depth_points: &points,
    };
    let calibration = calibration::calibrate(&view, map)?;
    Ok(Placed {
        serial: sn.to_owned(),
        capture,
        detections,
        points,
        calibration,
        warnings,
    })
}

/// A color frame of `sn` at full resolution ([`full_resolution`]), its color-settings put
/// back afterwards; at the current settings, with a warning, if the camera refuses that
/// mode.
async fn full_resolution_color(
    client: &CamClient,
    sn: &str,
    warnings: &mut Vec<String>,
) -> Result<ColorCapture, CalibrateError> {
    let current: ColorSettings = client.get_json(sn, "color-settings").await?;
    let full = full_resolution(&current);
    let changed = full != current
        && match client.put_json(sn, "color-settings", &full).await {
            Ok(()) => true,
            Err(e) => {
                warnings.push(format!(
                    "camera {sn}: searching markers at {}x{}: {}x{} refused ({e:#})",
                    current.width, current.height, full.width, full.height
                ));
                false
            }
        };
    let grabbed = client
        .grab(sn, Stream::Color, Some(ContentFormat::CBOR))
        .await;
    if changed {
        client
            .put_json(sn, "color-settings", &current)
            .await
            .map_err(|source| CalibrateError::PutBack {
                serial: sn.to_owned(),
                source,
            })?;
    }
    Ok(ColorCapture::from_cbor(&grabbed?.payload)?)
}

/// Camera `sn`'s depth points in its own frame, from one compact point-cloud grab (its
/// depth window and intrinsics, filtered as the camera's application-config says).
/// Calibration needs the floor, so when that config's `roi3d` keeps less than every
/// point (`measure --prepare` cuts the floor and everything beside the table away; the
/// parcel's lid would be taken for the floor) the points come from the whole depth image
/// instead (`roi2d` still applies), unfiltered, and a note in `notes` says so.
pub async fn depth_points(
    client: &CamClient,
    sn: &str,
    notes: &mut Vec<String>,
) -> Result<Vec<Point3>, CalibrateError> {
    let app: AppConfig = client.get_json(sn, "application-config").await?;
    if app.roi3d != AppConfig::default().roi3d {
        let r = client
            .grab(sn, Stream::Depth, Some(ContentFormat::CBOR))
            .await?;
        let depth = DepthCapture::from_cbor(&r.payload)?;
        let (min, max) = (app.roi3d.min(), app.roi3d.max());
        notes.push(format!(
            "camera {sn}: its application-config's roi3d (x {:.3} to {:.3}, y {:.3} to {:.3}, z {:.3} to {:.3} m) would cut the floor away, so the whole depth image was used",
            min.x, max.x, min.y, max.y, min.z, max.z
        ));
        return Ok(rgbd::deproject_frame(&depth.frame, &depth.intrinsics)?);
    }
    let r = client.grab_compact(sn, Stream::Pointcloud).await?;
    if r.options.content_format() != Some(crate::repr::DEPTH_CLOUD) {
        return Err(CalibrateError::NoCompactCloud);
    }
    let part = parts_from_depth_cloud(&r.payload)?
        .into_iter()
        .next()
        .ok_or(CalibrateError::NoDepth)?;
    Ok(rgbd::deproject_frame(&part.depth, &part.intrinsics)?)
}

const YELLOW: Rgb<u8> = Rgb([255, 220, 0]);
const RED: Rgb<u8> = Rgb([230, 40, 40]);
const GREEN: Rgb<u8> = Rgb([40, 200, 60]);
const BLUE: Rgb<u8> = Rgb([60, 110, 255]);

/// How far from the origin the views show the merged cloud, metres (a tilted camera sees
/// the floor for metres; the table is near the markers).
const VIEW_REACH_M: f32 = 1.5;

/// `--view`: each camera's color image with its markers and the world axes drawn
/// (`FILE-<sn>.png`), and the merged cloud (within `VIEW_REACH_M` of the origin in x
/// and y) from above (`path`) and from the side (`FILE-side.png`). What could not be
/// drawn (a camera's axes) is returned as warnings.
pub fn draw_views(placed: &[Placed], path: &Path) -> Result<Vec<String>, CalibrateError> {
    let mut warnings = Vec::new();
    let mut merged = PointCloud::default();
    for p in placed {
        let transform = p.calibration.transformation().to_transform()?;
        let mut image = p.capture.image.clone();
        let thickness = (image.width() / 600).max(2);
        let scale = (image.width() / 640).max(1);
        for d in &p.detections {
            let known = p.calibration.used.contains(&d.id);
            let colour = if known { YELLOW } else { RED };
            let corner = |i: usize| d.corners[i % 4].map(|v| v as f32);
            for i in 0..4 {
                picture::draw_line(&mut image, corner(i), corner(i + 1), colour, thickness);
            }
            let at = corner(3).map(|v| v.max(0.0) as u32);
            picture::draw_text(
                &mut image,
                (at[0], at[1].saturating_sub(10 * scale)),
                &d.id.to_string(),
                scale,
                colour,
            );
        }
        match projector(&p.capture, &transform) {
            Ok(project) => {
                if let Some(origin) = project([0.0; 3]) {
                    for (tip, colour) in [
                        ([0.1, 0.0, 0.0], RED),
                        ([0.0, 0.1, 0.0], GREEN),
                        ([0.0, 0.0, 0.1], BLUE),
                    ] {
                        if let Some(tip) = project(tip) {
                            picture::draw_line(&mut image, origin, tip, colour, thickness);
                        }
                    }
                }
            }
            Err(e) => warnings.push(format!("camera {}: --view draws no axes: {e:#}", p.serial)),
        }
        let text = picture::text_scale(&image).max(scale);
        picture::legend(&mut image, (0, 0), &view_legend(p), text);
        picture::save(&image, &picture::sibling(path, &format!("-{}", p.serial)))?;
        merged.points.extend(
            p.points
                .iter()
                .map(|q| transform.apply(q))
                .filter(|q| q.x.abs() <= VIEW_REACH_M && q.y.abs() <= VIEW_REACH_M),
        );
    }
    picture::save(&picture::top_view(&merged, None), path)?;
    picture::save(
        &picture::side_view(&merged),
        &picture::sibling(path, "-side"),
    )?;
    Ok(warnings)
}

/// The key of a camera's `--view` picture: which markers placed it and what the axes are.
fn view_legend(p: &Placed) -> Vec<(String, Rgb<u8>)> {
    let ids = |used: bool| {
        let ids: Vec<String> = p
            .detections
            .iter()
            .filter(|d| p.calibration.used.contains(&d.id) == used)
            .map(|d| d.id.to_string())
            .collect();
        if ids.is_empty() {
            "none".to_owned()
        } else {
            ids.join(", ")
        }
    };
    vec![
        (format!("camera {}", p.serial), Rgb([255, 255, 255])),
        (
            format!("yellow: markers that placed it: {}", ids(true)),
            YELLOW,
        ),
        (format!("red: markers seen, not used: {}", ids(false)), RED),
        (
            "axes from the origin, 10 cm: x red, y green, z blue".to_owned(),
            Rgb([255, 255, 255]),
        ),
    ]
}

/// A camera levelled on the floor it sees.
#[derive(Debug, Clone)]
pub struct Levelled {
    /// The 3d-transformation that puts the floor at z = 0, z up.
    pub transformation: Transformation,
    /// Depth points on the floor plane.
    pub floor_points: usize,
    /// Their RMS distance from it, metres.
    pub floor_rms_m: f64,
    /// The camera's height above the floor, metres.
    pub height_m: f64,
    /// The angle between the camera's view and straight down, degrees.
    pub tilt_deg: f64,
    /// How the points were taken, when not as usual ([`depth_points`]).
    pub notes: Vec<String>,
}

/// The floor of camera `sn`, from its depth points ([`depth_points`]): roll, pitch and
/// height.
pub async fn level(client: &CamClient, sn: &str) -> Result<Levelled, CalibrateError> {
    let mut notes = Vec::new();
    let points = depth_points(client, sn, &mut notes)
        .await
        .map_err(|source| CalibrateError::Camera {
            serial: sn.to_owned(),
            source: Box::new(source),
        })?;
    let floor = dominant_plane(&points, FLOOR_INLIER_M, ITERATIONS, 1).map_err(|source| {
        CalibrateError::Floor {
            serial: sn.to_owned(),
            points: points.len(),
            source,
        }
    })?;
    if floor.inliers < calibration::MIN_FLOOR_POINTS {
        return Err(CalibrateError::FewFloorPoints {
            serial: sn.to_owned(),
            inliers: floor.inliers,
        });
    }
    let t = floor_transformation(&floor);
    // The angle between the camera's view (its z axis) and straight down.
    let view_down = t.rotation.column(2).dot(&-nalgebra::Vector3::z());
    Ok(Levelled {
        notes,
        floor_points: floor.inliers,
        floor_rms_m: floor.rms,
        height_m: t.translation.z,
        tilt_deg: view_down.clamp(-1.0, 1.0).acos().to_degrees(),
        transformation: t,
    })
}

/// Camera `sn`'s document with the post rotation (roll, pitch, yaw, degrees) and post
/// translation (x, y, z, metres) given set, the rest kept.
pub async fn adjusted(
    client: &CamClient,
    sn: &str,
    rotation_deg: [Option<f64>; 3],
    translation: [Option<f64>; 3],
) -> Result<Transformation, CalibrateError> {
    let current = client
        .call(Code::GET, &path(sn), Bytes::new(), None, None)
        .await?;
    let mut t = Transformation::from_json(&current.payload).map_err(|source| {
        CalibrateError::ReadTransformation {
            serial: sn.to_owned(),
            source,
        }
    })?;
    for (i, value) in rotation_deg.into_iter().enumerate() {
        if let Some(v) = value {
            t.post_rotation_deg[i] = v;
        }
    }
    for (i, value) in translation.into_iter().enumerate() {
        if let Some(v) = value {
            t.post_translation[i] = v;
        }
    }
    t.validate()?;
    Ok(t)
}
