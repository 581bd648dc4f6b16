//! `coapcam calibrate`: writes cameras' `3d-transformation` so their points land in the
//! table's frame (z up, the floor at z = 0).
//!
//! - `--floor`: the floor, found in the camera's own depth (the plane with the most points,
//!   RANSAC and a least-squares fit), gives roll, pitch and the camera's height. That is
//!   enough for one camera: the dimensions depend neither on yaw nor on where the camera
//!   stands. Several cameras are each levelled, but not aligned with each other.
//! - `--adjust`: the thesis's manual correction, the post rotation (roll, pitch, yaw in
//!   degrees) and post translation (metres) of one camera's document.

use anyhow::{Context as _, bail};
use bytes::Bytes;
use clap::Args;
use coap::{Code, ContentFormat};
use geometry::{Transformation, dominant_plane, floor_transformation};
use serde_json::json;

use super::{Exit, TransmissionArgs, outln};
use coapcam::client::CamClient;
use coapcam::repr::Stream;
use coapcam::repr::clouds::parts_from_depth_cloud;

/// Points this close to the floor plane are its inliers, metres (the D415's depth noise
/// at 1-2 m is a few millimetres).
const FLOOR_INLIER_M: f64 = 0.012;
/// RANSAC samples.
const ITERATIONS: usize = 400;
/// Fewer floor points than this and the fit is refused.
const MIN_FLOOR_POINTS: usize = 2_000;

/// Flags of `calibrate`.
#[derive(Debug, Args)]
pub(crate) struct CalibrateArgs {
    /// The server, e.g. coap://127.0.0.1.
    #[arg(long, value_name = "URI")]
    server: String,
    /// Only this camera (default: every camera of the server).
    #[arg(long, value_name = "SN")]
    camera: Option<String>,
    /// Level each camera on the floor it sees: roll, pitch and height from a plane fit
    /// of its depth. Grab with the default application-config (a roi3d that cuts the
    /// floor away leaves nothing to fit).
    #[arg(long, required_unless_present = "adjust")]
    floor: bool,
    /// Correct one camera's document by hand: set the post rotation (--roll, --pitch,
    /// --yaw, degrees) and post translation (--dx, --dy, --dz, metres) given, keep the rest.
    #[arg(long, conflicts_with = "floor", requires = "camera")]
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
    let client = CamClient::connect(
        &args.server,
        args.transmission.endpoint_config(),
        args.transmission.psk().as_ref(),
        args.transmission.timeout()?,
    )
    .await?;
    let serials = match &args.camera {
        Some(sn) => vec![sn.clone()],
        None => client.cameras().await?,
    };
    if serials.is_empty() {
        bail!("the server has no camera");
    }
    if args.floor && serials.len() > 1 {
        eprintln!(
            "coapcam: warning: --floor levels each of the {} cameras, but cannot align them with each other (yaw and position on the floor stay each camera's own)",
            serials.len()
        );
    }
    for sn in &serials {
        let (transformation, mut report) = if args.adjust {
            (adjusted(&client, sn, &args).await?, json!({}))
        } else {
            level(&client, sn).await?
        };
        let document = transformation.to_json();
        if !args.dry_run {
            let body = Bytes::from(document.clone().into_bytes());
            client
                .call(Code::PUT, &path(sn), body, Some(ContentFormat::JSON), None)
                .await?;
        }
        report["camera"] = sn.as_str().into();
        report["written"] = (!args.dry_run).into();
        report["3d-transformation"] = serde_json::from_str(&document).unwrap_or_default();
        if args.json {
            outln!("{report}");
        } else {
            outln!("{}", text(&report));
        }
    }
    Ok(Exit::Success)
}

/// The floor of camera `sn`, from one compact point-cloud grab (its depth window and
/// intrinsics, in the camera's frame): the transformation, and what the fit found.
async fn level(
    client: &CamClient,
    sn: &str,
) -> anyhow::Result<(Transformation, serde_json::Value)> {
    let r = client.grab_compact(sn, Stream::Pointcloud).await?;
    if r.options.content_format() != Some(ContentFormat::DEPTH_CLOUD) {
        bail!("camera {sn}: the server sends no compact cloud (65103), which --floor needs");
    }
    let parts = parts_from_depth_cloud(&r.payload)?;
    let part = parts
        .into_iter()
        .next()
        .with_context(|| format!("camera {sn}: the cloud has no depth"))?;
    let points = rgbd::deproject_frame(&part.depth, &part.intrinsics)?;
    let floor = dominant_plane(&points, FLOOR_INLIER_M, ITERATIONS, 1)
        .with_context(|| format!("camera {sn}: finding the floor in {} points", points.len()))?;
    if floor.inliers < MIN_FLOOR_POINTS {
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
    out += if report["written"] == true {
        "; 3d-transformation written"
    } else {
        "; nothing written (--dry-run)"
    };
    out
}
