//! `coapcam calibrate`: writes cameras' `3d-transformation` so their points land in the
//! table's frame (z up, the floor at z = 0).
//!
//! - By default, markers: each camera's color image (at full resolution) is searched for
//!   AprilTag markers; the map's markers it shows place it (`vision::calibration`: PnP,
//!   refined with the floor in its depth). The world frame is the origin marker's, so
//!   every camera lands in one frame. Either every camera is placed and written, or none.
//! - `--floor`: the floor, found in the camera's own depth (the plane with the most points,
//!   RANSAC and a least-squares fit), gives roll, pitch and the camera's height. That is
//!   enough for one camera: the dimensions depend neither on yaw nor on where the camera
//!   stands. Several cameras are each levelled, but not aligned with each other.
//! - `--adjust`: the thesis's manual correction, the post rotation (roll, pitch, yaw in
//!   degrees) and post translation (metres) of one camera's document.

use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use bytes::Bytes;
use clap::Args;
use coap::{Code, ContentFormat};
use geometry::{Point3, PointCloud, Transformation, dominant_plane, floor_transformation};
use image::Rgb;
use markers::{Detection, Family};
use serde_json::json;

use super::{CameraArgs, Exit, TransmissionArgs, outln};
use coapcam::client::CamClient;
use coapcam::client::annotate::projector;
use coapcam::client::measure::full_resolution;
use coapcam::repr::Stream;
use coapcam::repr::cbor::ColorCapture;
use coapcam::repr::clouds::parts_from_depth_cloud;
use coapcam::vision::calibration::{self, Calibration, CameraView, MarkerMap};
use coapcam::vision::picture;

/// Points this close to the floor plane are its inliers, metres (the D415's depth noise
/// at 1-2 m is a few millimetres).
const FLOOR_INLIER_M: f64 = 0.012;
/// RANSAC samples.
const ITERATIONS: usize = 400;

/// Flags of `calibrate`.
#[derive(Debug, Args)]
pub(crate) struct CalibrateArgs {
    #[command(flatten)]
    cameras: CameraArgs,
    /// Markers (the default method): the family.
    #[arg(long, value_name = "F", default_value = "tag36h11")]
    family: String,
    /// Markers: the id of the marker whose centre and axes are the world's origin and
    /// axes (z up).
    #[arg(long, value_name = "N", default_value_t = 0)]
    origin_id: u32,
    /// Markers, without --map: the side of the origin marker's black square, metres.
    #[arg(long, value_name = "M", default_value_t = 0.16, conflicts_with = "map")]
    marker_size: f64,
    /// Markers: where every marker lies, as `[[marker]]` tables (family, id, size,
    /// center, yaw_deg) in a TOML file; a synthetic scene file is one. Every mapped
    /// marker a camera sees then places it, not only the origin marker.
    #[arg(long, value_name = "FILE")]
    map: Option<PathBuf>,
    /// Markers: draw the detected markers and the world axes on each camera's color
    /// image (FILE-<sn>.png), and the merged cloud from above and from the side
    /// (FILE.png, FILE-side.png).
    #[arg(long, value_name = "FILE.png")]
    view: Option<PathBuf>,
    /// Instead of markers, level each camera on the floor it sees: roll, pitch and height
    /// from a plane fit of its depth. Grab with the default application-config (a roi3d
    /// that cuts the floor away leaves nothing to fit).
    #[arg(long, conflicts_with_all = ["map", "view"])]
    floor: bool,
    /// Correct one camera's document by hand: set the post rotation (--roll, --pitch,
    /// --yaw, degrees) and post translation (--dx, --dy, --dz, metres) given, keep the rest.
    #[arg(long, conflicts_with_all = ["floor", "map", "view"], requires = "camera")]
    adjust: bool,
    /// With --adjust: rotation about x, degrees.
    #[arg(long, allow_hyphen_values = true)]
    roll: Option<f64>,
    /// With --adjust: rotation about y, degrees.
    #[arg(long, allow_hyphen_values = true)]
    pitch: Option<f64>,
    /// With --adjust: rotation about z, degrees.
    #[arg(long, allow_hyphen_values = true)]
    yaw: Option<f64>,
    /// With --adjust: translation along x, metres.
    #[arg(long, allow_hyphen_values = true)]
    dx: Option<f64>,
    /// With --adjust: translation along y, metres.
    #[arg(long, allow_hyphen_values = true)]
    dy: Option<f64>,
    /// With --adjust: translation along z, metres.
    #[arg(long, allow_hyphen_values = true)]
    dz: Option<f64>,
    /// Print what would be written, write nothing.
    #[arg(long)]
    dry_run: bool,
    /// Print one JSON object per camera.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    transmission: TransmissionArgs,
}

/// The resource of camera `sn`'s 3d-transformation.
fn path(sn: &str) -> String {
    format!("/cams/{sn}/3d-transformation")
}

/// Runs `calibrate`.
pub(crate) async fn run(args: CalibrateArgs) -> anyhow::Result<Exit> {
    if !(args.marker_size.is_finite() && args.marker_size > 0.0) {
        bail!("--marker-size must be a positive number of metres");
    }
    let client = args.cameras.connect(&args.transmission).await?;
    let serials = match &args.cameras.camera {
        Some(sn) => vec![sn.clone()],
        None => client.cameras().await?,
    };
    if serials.is_empty() {
        bail!("the server has no camera");
    }
    if !(args.floor || args.adjust) {
        return by_markers(&client, &serials, &args).await;
    }
    if args.floor && serials.len() > 1 {
        eprintln!(
            "coapcam: warning: --floor levels each of the {} cameras, but cannot align them with each other (yaw and position on the floor stay each camera's own); markers can",
            serials.len()
        );
    }
    for sn in &serials {
        let (transformation, report) = if args.adjust {
            (adjusted(&client, sn, &args).await?, json!({}))
        } else {
            level(&client, sn).await?
        };
        write(&client, sn, &transformation, report, &args).await?;
    }
    Ok(Exit::Success)
}

/// Writes camera `sn`'s document (unless `--dry-run`) and prints what was done.
async fn write(
    client: &CamClient,
    sn: &str,
    transformation: &Transformation,
    mut report: serde_json::Value,
    args: &CalibrateArgs,
) -> anyhow::Result<()> {
    let document = transformation.to_json();
    if !args.dry_run {
        put(client, sn, &document).await?;
    }
    report["camera"] = sn.into();
    report["written"] = (!args.dry_run).into();
    report["3d-transformation"] = serde_json::from_str(&document).unwrap_or_default();
    if args.json {
        outln!("{report}");
    } else {
        outln!("{}", text(&report));
    }
    Ok(())
}

/// PUTs camera `sn`'s 3d-transformation `document`.
pub(crate) async fn put(client: &CamClient, sn: &str, document: &str) -> anyhow::Result<()> {
    let body = Bytes::from(document.as_bytes().to_vec());
    client
        .call(Code::PUT, &path(sn), body, Some(ContentFormat::JSON), None)
        .await?;
    Ok(())
}

/// The marker map of `args`: the `--map` file's markers, or the origin marker alone.
fn marker_map(args: &CalibrateArgs) -> anyhow::Result<MarkerMap> {
    let family: Family = args.family.parse()?;
    match &args.map {
        Some(file) => {
            let scene = rgbd::Scene::load(file)?;
            MarkerMap::from_scene(&scene, family, args.origin_id)
                .with_context(|| format!("--map {}", file.display()))
        }
        None => Ok(MarkerMap::single(family, args.origin_id, args.marker_size)),
    }
}

/// What one camera showed and where the markers place it.
pub(crate) struct Placed {
    serial: String,
    capture: ColorCapture,
    detections: Vec<Detection>,
    points: Vec<Point3>,
    /// Where the markers place the camera.
    pub(crate) calibration: Calibration,
}

/// Places every camera by the markers it sees; writes them all, or none when one fails.
async fn by_markers(
    client: &CamClient,
    serials: &[String],
    args: &CalibrateArgs,
) -> anyhow::Result<Exit> {
    let map = marker_map(args)?;
    let mut placed = Vec::with_capacity(serials.len());
    let mut failed = Vec::new();
    for sn in serials {
        match place(client, sn, &map).await {
            Ok(p) => placed.push(p),
            Err(e) => failed.push(format!("camera {sn}: {e:#}")),
        }
    }
    if !failed.is_empty() {
        for f in &failed {
            eprintln!("coapcam: {f}");
        }
        bail!(
            "{} of {} cameras could not be calibrated; nothing was written",
            failed.len(),
            serials.len()
        );
    }
    for p in &placed {
        let c = &p.calibration;
        let camera = c.depth_to_world.translation.vector * 1000.0;
        let view_down = (c.depth_to_world.rotation * nalgebra::Vector3::z()).z;
        let report = json!({
            "method": "markers",
            "family": map.family.to_string(),
            "markers": c.used,
            "ignored_markers": c.unknown,
            "reprojection_px": c.reprojection_px,
            "floor_points": c.floor_points,
            "floor_rms_mm": c.floor_rms_m * 1000.0,
            "camera_mm": [camera.x, camera.y, camera.z],
            "tilt_deg": (-view_down).clamp(-1.0, 1.0).acos().to_degrees(),
        });
        write(client, &p.serial, &c.transformation(), report, args).await?;
    }
    if let Some(view) = &args.view {
        draw_views(&placed, view)?;
    }
    Ok(Exit::Success)
}

/// Grabs camera `sn`'s color (at full resolution) and depth, and places it.
pub(crate) async fn place(client: &CamClient, sn: &str, map: &MarkerMap) -> anyhow::Result<Placed> {
    let capture = full_resolution_color(client, sn).await?;
    let gray = image::imageops::grayscale(&capture.image);
    let (w, h) = gray.dimensions();
    let detections = markers::detect(map.family, gray.as_raw(), w as usize, h as usize)?;
    let points = depth_points(client, sn).await?;
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
    })
}

/// A color frame of `sn` at full resolution ([`full_resolution`]), its color-settings put
/// back afterwards; at the current settings, with a warning, if the camera refuses that
/// mode.
async fn full_resolution_color(client: &CamClient, sn: &str) -> anyhow::Result<ColorCapture> {
    let current = client.get_json(sn, "color-settings").await?;
    let full = full_resolution(&current);
    let changed = full != current
        && match client.put_json(sn, "color-settings", &full).await {
            Ok(()) => true,
            Err(e) => {
                eprintln!(
                    "coapcam: warning: camera {sn}: searching markers at {}x{}: {}x{} refused ({e:#})",
                    current["width"], current["height"], full["width"], full["height"]
                );
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
            .with_context(|| format!("camera {sn}: putting its color-settings back"))?;
    }
    ColorCapture::from_cbor(&grabbed?.payload)
}

/// Camera `sn`'s depth points in its own frame, from one compact point-cloud grab (its
/// depth window and intrinsics).
async fn depth_points(client: &CamClient, sn: &str) -> anyhow::Result<Vec<Point3>> {
    let r = client.grab_compact(sn, Stream::Pointcloud).await?;
    if r.options.content_format() != Some(ContentFormat::DEPTH_CLOUD) {
        bail!("the server sends no compact cloud (65103), which calibration needs");
    }
    let part = parts_from_depth_cloud(&r.payload)?
        .into_iter()
        .next()
        .context("the cloud has no depth")?;
    Ok(rgbd::deproject_frame(&part.depth, &part.intrinsics)?)
}

const YELLOW: Rgb<u8> = Rgb([255, 220, 0]);
const RED: Rgb<u8> = Rgb([230, 40, 40]);
const GREEN: Rgb<u8> = Rgb([40, 200, 60]);
const BLUE: Rgb<u8> = Rgb([60, 110, 255]);

/// How far from the origin the views show the merged cloud, metres (a tilted camera sees
/// the floor for metres; the table is near the markers).
const VIEW_REACH_M: f32 = 1.5;

/// `--view`: each camera's color image with its markers and the world axes drawn, and
/// the merged cloud (within [`VIEW_REACH_M`] of the origin in x and y) from above and
/// from the side.
fn draw_views(placed: &[Placed], path: &Path) -> anyhow::Result<()> {
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
            Err(e) => eprintln!(
                "coapcam: warning: camera {}: --view draws no axes: {e:#}",
                p.serial
            ),
        }
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
    )
}

/// The floor of camera `sn`, from its depth points: the transformation, and what the fit
/// found.
async fn level(
    client: &CamClient,
    sn: &str,
) -> anyhow::Result<(Transformation, serde_json::Value)> {
    let points = depth_points(client, sn)
        .await
        .with_context(|| format!("camera {sn}"))?;
    let floor = dominant_plane(&points, FLOOR_INLIER_M, ITERATIONS, 1)
        .with_context(|| format!("camera {sn}: finding the floor in {} points", points.len()))?;
    if floor.inliers < calibration::MIN_FLOOR_POINTS {
        bail!(
            "camera {sn}: only {} points lie on the floor; is its roi3d cutting it away?",
            floor.inliers
        );
    }
    let t = floor_transformation(&floor);
    // The angle between the camera's view (its z axis) and straight down.
    let view_down = t.rotation.column(2).dot(&-nalgebra::Vector3::z());
    let report = json!({
        "method": "floor",
        "floor_points": floor.inliers,
        "floor_rms_mm": floor.rms * 1000.0,
        "height_mm": t.translation.z * 1000.0,
        "tilt_deg": view_down.clamp(-1.0, 1.0).acos().to_degrees(),
    });
    Ok((t, report))
}

/// Camera `sn`'s document with the post rotation and translation of `args` set.
async fn adjusted(
    client: &CamClient,
    sn: &str,
    args: &CalibrateArgs,
) -> anyhow::Result<Transformation> {
    let current = client
        .call(Code::GET, &path(sn), Bytes::new(), None, None)
        .await?;
    let mut t = Transformation::from_json(&current.payload)
        .with_context(|| format!("camera {sn}: reading its 3d-transformation"))?;
    for (i, value) in [args.roll, args.pitch, args.yaw].into_iter().enumerate() {
        if let Some(v) = value {
            t.post_rotation_deg[i] = v;
        }
    }
    for (i, value) in [args.dx, args.dy, args.dz].into_iter().enumerate() {
        if let Some(v) = value {
            t.post_translation[i] = v;
        }
    }
    t.validate()?;
    Ok(t)
}

fn text(report: &serde_json::Value) -> String {
    let f = |k: &str| report[k].as_f64().unwrap_or(f64::NAN);
    let mut out = format!("camera {}", report["camera"].as_str().unwrap_or("?"));
    if report["method"] == "floor" {
        out += &format!(
            ": floor {} points, rms {:.1} mm; camera {:.0} mm above it, tilted {:.1} deg",
            report["floor_points"],
            f("floor_rms_mm"),
            f("height_mm"),
            f("tilt_deg")
        );
    }
    if report["method"] == "markers" {
        let ids = |k: &str| {
            let list: Vec<String> = report[k]
                .as_array()
                .map(|a| a.iter().map(ToString::to_string).collect())
                .unwrap_or_default();
            list.join(", ")
        };
        let at = |i: usize| report["camera_mm"][i].as_f64().unwrap_or(f64::NAN);
        out += &format!(
            ": {} markers {}; reprojection {:.2} px; floor {} points, rms {:.1} mm; camera at ({:.0}, {:.0}, {:.0}) mm, tilted {:.1} deg",
            report["family"].as_str().unwrap_or("?"),
            ids("markers"),
            f("reprojection_px"),
            report["floor_points"],
            f("floor_rms_mm"),
            at(0),
            at(1),
            at(2),
            f("tilt_deg")
        );
        if report["ignored_markers"]
            .as_array()
            .is_some_and(|a| !a.is_empty())
        {
            out += &format!(" (not in the map, ignored: {})", ids("ignored_markers"));
        }
    }
    out += if report["written"] == true {
        "; 3d-transformation written"
    } else {
        "; nothing written (--dry-run)"
    };
    // The document's rotation rows and translation, compactly.
    let doc = &report["3d-transformation"];
    let numbers = |v: &serde_json::Value| -> Vec<String> {
        v.as_array()
            .map(|a| {
                a.iter()
                    .flat_map(|x| x.as_array().cloned().unwrap_or_else(|| vec![x.clone()]))
                    .map(|x| format!("{:.4}", x.as_f64().unwrap_or(f64::NAN)))
                    .collect()
            })
            .unwrap_or_default()
    };
    let rotation = numbers(&doc["rotation_matrix"]);
    if rotation.len() == 9 {
        out += &format!(
            "\n  rotation [{}; {}; {}], translation [{}] m",
            rotation[0..3].join(", "),
            rotation[3..6].join(", "),
            rotation[6..9].join(", "),
            numbers(&doc["translation_matrix"]).join(", ")
        );
    }
    out
}
