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

use std::path::PathBuf;

use anyhow::{Context as _, bail};
use clap::Args;
use geometry::Transformation;
use markers::Family;
use serde_json::json;

use super::{CameraArgs, Exit, TransmissionArgs, outln, usage, values};
use coapcam::client::CamClient;
use coapcam::client::calibrate;
use coapcam::vision::calibration::MarkerMap;

/// Flags of `calibrate`.
#[derive(Debug, Args)]
pub(crate) struct CalibrateArgs {
    #[command(flatten)]
    cameras: CameraArgs,
    /// Markers (the default method): the family.
    #[arg(long, value_name = "F", default_value = "tag36h11", value_parser = clap::value_parser!(Family))]
    family: Family,
    /// Markers: the id of the marker whose centre and axes are the world's origin and
    /// axes (z up).
    #[arg(long, value_name = "N", default_value_t = 0)]
    origin_id: u32,
    /// Markers, without --map: the side of the origin marker's black square, metres
    /// (0.005 to 2; `coapcam markers` prints markers at a given size).
    #[arg(long, value_name = "M", default_value = "0.16", conflicts_with = "map",
          value_parser = values::marker_metres)]
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

/// Runs `calibrate`.
pub(crate) async fn run(args: CalibrateArgs) -> anyhow::Result<Exit> {
    if let Some(view) = &args.view
        && !view
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("png"))
    {
        usage!("--view writes PNG: give a file name ending in .png");
    }
    if let Some(view) = &args.view {
        super::folder_exists(view)?;
    }
    if args.origin_id >= args.family.ids() {
        usage!(
            "--origin-id {}: {} has markers 0 to {}",
            args.origin_id,
            args.family,
            args.family.ids() - 1
        );
    }
    // The map is read before anything is sent: a file that is not one fails first.
    let map = if args.floor || args.adjust {
        None
    } else {
        Some(marker_map(&args)?)
    };
    let client = args.cameras.connect(&args.transmission).await?;
    let serials = match &args.cameras.camera {
        Some(sn) => vec![sn.clone()],
        None => client.cameras().await?,
    };
    if serials.is_empty() {
        bail!("the server has no camera");
    }
    if let Some(map) = &map {
        return by_markers(&client, &serials, map, &args).await;
    }
    if args.floor && serials.len() > 1 {
        eprintln!(
            "coapcam: warning: --floor levels each of the {} cameras, but cannot align them with each other (yaw and position on the floor stay each camera's own); markers can",
            serials.len()
        );
    }
    for sn in &serials {
        let (transformation, report) = if args.adjust {
            let rotation = [args.roll, args.pitch, args.yaw];
            let translation = [args.dx, args.dy, args.dz];
            let t = calibrate::adjusted(&client, sn, rotation, translation).await?;
            (t, json!({}))
        } else {
            let l = calibrate::level(&client, sn).await?;
            for note in &l.notes {
                eprintln!("coapcam: {note}");
            }
            let report = json!({
                "method": "floor",
                "floor_points": l.floor_points,
                "floor_rms_mm": l.floor_rms_m * 1000.0,
                "height_mm": l.height_m * 1000.0,
                "tilt_deg": l.tilt_deg,
            });
            (l.transformation, report)
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
        calibrate::put(client, sn, transformation).await?;
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

/// The marker map of `args`: the `--map` file's markers, or the origin marker alone.
fn marker_map(args: &CalibrateArgs) -> anyhow::Result<MarkerMap> {
    let family = args.family;
    match &args.map {
        Some(file) => {
            // A marker map is read as a scene file, but a file that cannot be read is
            // the marker map to the user, not a scene.
            let scene = rgbd::Scene::load(file).map_err(|e| match e {
                rgbd::SceneError::Io { source, .. } => anyhow::anyhow!(
                    "--map {}: cannot read the marker map: {source}",
                    file.display()
                ),
                e => anyhow::Error::new(e)
                    .context(format!("--map {}: the marker map", file.display())),
            })?;
            MarkerMap::from_scene(&scene, family, args.origin_id)
                .with_context(|| format!("--map {}", file.display()))
        }
        None => Ok(MarkerMap::single(family, args.origin_id, args.marker_size)),
    }
}

/// Places every camera by the markers it sees; writes them all, or none when one fails.
async fn by_markers(
    client: &CamClient,
    serials: &[String],
    map: &MarkerMap,
    args: &CalibrateArgs,
) -> anyhow::Result<Exit> {
    let mut placed = Vec::with_capacity(serials.len());
    let mut failed = Vec::new();
    for sn in serials {
        match calibrate::place(client, sn, map).await {
            Ok(p) => {
                for w in &p.warnings {
                    eprintln!("coapcam: warning: {w}");
                }
                placed.push(p);
            }
            Err(e) => failed.push(anyhow::Error::from(e).context(format!("camera {sn}"))),
        }
    }
    if let Some(last) = failed.pop() {
        let count = failed.len() + 1;
        for f in &failed {
            eprintln!("coapcam: {}", super::error_text(f.as_ref()));
        }
        // The run ends as its last failure does (a server's 4.04 for an unknown serial
        // is status 3, as with --floor), with the count.
        return Err(last.context(format!(
            "{count} of {} cameras could not be calibrated; nothing was written",
            serials.len()
        )));
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
        for w in calibrate::draw_views(&placed, view)? {
            eprintln!("coapcam: warning: {w}");
        }
    }
    Ok(Exit::Success)
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
