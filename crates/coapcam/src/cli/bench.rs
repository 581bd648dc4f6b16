//! `coapcam bench accuracy`: a built-in, seeded set of synthetic parcel scenes measured
//! end to end over CoAP on loopback, with per-scene errors and a summary; `bench transfer`,
//! `bench repr` and `bench load` are in their own files.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use clap::{Args, Subcommand};
use markers::Family;
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore as _, SeedableRng as _};
use rgbd::scene::{Noise, SceneBox, SceneCamera, SceneMarker, Timeline};
use rgbd::{Scene, Serial};

use super::{DimensionArgs, Exit, calibrate, outln};
use coapcam::client::CamClient;
use coapcam::client::measure::{self, Source, prepare_cameras, truth, yaw_difference};
use coapcam::server::SceneServer;
use coapcam::stats::{self, AbsSummary};
use coapcam::vision::calibration::{MarkerMap, pose_transformation};

/// `bench transfer` (declared here, not in `cli/mod.rs`, with its file beside this one).
#[path = "bench_transfer.rs"]
mod transfer;

/// `bench repr`, the same way.
#[path = "bench_repr.rs"]
mod repr;

/// `bench load`, the same way.
#[path = "bench_load.rs"]
mod load;

/// Flags of `bench`.
#[derive(Debug, Args)]
pub(crate) struct BenchArgs {
    #[command(subcommand)]
    what: BenchKind,
}

#[derive(Debug, Subcommand)]
enum BenchKind {
    /// Measure a built-in set of synthetic parcels (10-80 cm, yaw 0-90 deg, 2-60 cm high,
    /// one or two D415s 0.8-1.5 m above the floor) end to end over CoAP and print the
    /// errors.
    Accuracy(AccuracyArgs),
    /// Time whole-body GETs through emulated links (loopback, 20 ms, 2 % and 5 % loss, a
    /// 50 Mbit/s bottleneck) with our stop-and-wait, window and Q-Block2 clients, libcoap
    /// 4.3.1 and 4.3.5 and QUIC, each body checked bit-exact; print a markdown table,
    /// optionally JSON and a PNG plot.
    Transfer(transfer::TransferArgs),
    /// Print the bytes of every representation of one depth frame, one color frame and
    /// the merged point cloud of a scene, and the milliseconds to encode and decode each.
    Repr(repr::ReprArgs),
    /// Run many concurrent clients (discovery, uploads, grabs, observers) against a
    /// running server for a while; print discovery latency and what each role counted,
    /// every transfer checked; exit 1 when anything failed, mismatched or was lost.
    Load(load::LoadArgs),
}

#[derive(Debug, Args)]
struct AccuracyArgs {
    /// Number of scenes (at least 1).
    #[arg(long, default_value_t = 40)]
    scenes: usize,
    /// Seed of the scene generator.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Print one JSON object (every scene and the summary) instead of tables.
    #[arg(long)]
    json: bool,
    /// Start every scene with its cameras uncalibrated (identity 3d-transformation), as
    /// real cameras start: calibrate them on the empty table, where 25 tag36h11 markers
    /// lie, then put the parcel on it and measure. Prints the cameras' pose errors too.
    /// The scenes differ: one to three D415s 0.8-1.6 m from the parcel's lid, tilted
    /// 0-35 degrees, parcels 10-60 cm wide and 2-40 cm high.
    #[arg(long)]
    calibrate: bool,
    #[command(flatten)]
    dimension: DimensionArgs,
}

/// Half fields of view of the D415 depth stream, degrees (wide and narrow axis).
const DEPTH_HALF_FOV_DEG: [f64; 2] = [32.5, 21.0];

fn uniform(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> f64 {
    let unit = (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
    lo + (hi - lo) * unit
}

/// Scene `index` of the set: a box with random size, yaw and position near the origin,
/// seen by one camera above it (even indices) or two cameras on either end of its long
/// side (odd ones), turned so the long side runs along the image's wide axis and high
/// enough that the whole lid is in view.
pub(crate) fn scene(seed: u64, index: usize) -> anyhow::Result<Scene> {
    let mut rng =
        ChaCha8Rng::seed_from_u64(seed.wrapping_mul(1_000_003).wrapping_add(index as u64));
    let (length, width) = {
        let a = uniform(&mut rng, 0.10, 0.80);
        let b = uniform(&mut rng, 0.10, 0.80);
        (a.max(b), a.min(b))
    };
    let two = index % 2 == 1;
    let offset = if two { 0.12 } else { 0.0 };
    // A camera `d` above the lid sees d * tan(half angle) either side of its axis; keep
    // 15 % of margin.
    let [wide, narrow] = DEPTH_HALF_FOV_DEG.map(|a| a.to_radians().tan() * 0.85);
    let needed = ((length / 2.0 + offset) / wide).max(width / 2.0 / narrow);
    let height_max = (1.5 - needed).min(0.60);
    let height = uniform(&mut rng, 0.02, height_max.max(0.02));
    let camera_z = uniform(&mut rng, (height + needed).max(0.8), 1.5).min(1.5);
    let yaw_deg = uniform(&mut rng, 0.0, 90.0);
    let center = [
        uniform(&mut rng, -0.05, 0.05),
        uniform(&mut rng, -0.05, 0.05),
    ];
    let (sin, cos) = yaw_deg.to_radians().sin_cos();
    // Up in the image is the box's width axis, so the image's x runs along its length.
    let up = [-sin, cos, 0.0];
    let camera = |n: u64, along: f64, z: f64| -> anyhow::Result<SceneCamera> {
        Ok(SceneCamera {
            serial: Serial::parse(&format!("{:012}", 840_412_060_700 + n))
                .map_err(|e| anyhow::anyhow!("{e}"))?,
            position: [center[0] + along * cos, center[1] + along * sin, z],
            look_at: [center[0], center[1], height],
            up: Some(up),
            noise: Noise::D415,
            calibrated: true,
        })
    };
    let cameras = if two {
        vec![
            camera(1, offset, camera_z)?,
            camera(2, -offset, camera_z - 0.05)?,
        ]
    } else {
        vec![camera(0, 0.0, camera_z)?]
    };
    Ok(parcel_scene(
        rng.next_u64(),
        cameras,
        [length, width, height],
        center,
        yaw_deg,
    ))
}

/// A scene of one plain box (no label) seen by `cameras`.
fn parcel_scene(
    seed: u64,
    cameras: Vec<SceneCamera>,
    size: [f64; 3],
    center: [f64; 2],
    yaw_deg: f64,
) -> Scene {
    Scene {
        seed,
        cameras,
        boxes: vec![SceneBox {
            size,
            center,
            yaw_deg,
            color: [180, 140, 90],
            label: None,
            timeline: Timeline::default(),
        }],
        ..Scene::default_single()
    }
}

/// The markers of the calibration table: a 5 x 5 grid 0.22 m apart, 12 cm wide, id 0
/// (the origin) in the middle at the world's origin, the others turned by 15 degree steps.
fn marker_grid() -> Vec<SceneMarker> {
    let mut grid = Vec::with_capacity(25);
    let mut id = 1;
    for row in -2i32..=2 {
        for col in -2i32..=2 {
            let origin = row == 0 && col == 0;
            grid.push(SceneMarker {
                family: "tag36h11".to_owned(),
                id: if origin { 0 } else { id },
                size: 0.12,
                center: [f64::from(col) * 0.22, f64::from(row) * 0.22],
                yaw_deg: if origin {
                    0.0
                } else {
                    f64::from(id % 6) * 15.0
                },
                timeline: Timeline::default(),
            });
            id += u32::from(!origin);
        }
    }
    grid
}

/// Scene `index` of the `--calibrate` set, as (the parcel's scene, the empty table's): a
/// box 10-60 cm wide and 2-40 cm high near the origin, seen by one to three uncalibrated
/// cameras spread around it, each 0.8-1.6 m from the centre of its lid (far enough that
/// the whole lid is in view) and tilted 0-35 degrees from straight down; the table has
/// the same cameras and [`marker_grid`] instead of the box.
pub(crate) fn calibration_scenes(seed: u64, index: usize) -> anyhow::Result<(Scene, Scene)> {
    let mut rng = ChaCha8Rng::seed_from_u64(
        seed.wrapping_mul(1_000_033)
            .wrapping_add(index as u64)
            .wrapping_add(0xca1b),
    );
    let (length, width) = {
        let a = uniform(&mut rng, 0.10, 0.60);
        let b = uniform(&mut rng, 0.10, 0.60);
        (a.max(b), a.min(b))
    };
    let height = uniform(&mut rng, 0.02, 0.40);
    let yaw_deg = uniform(&mut rng, 0.0, 90.0);
    let center = [
        uniform(&mut rng, -0.05, 0.05),
        uniform(&mut rng, -0.05, 0.05),
    ];
    // The lid's half diagonal within 85 % of the narrow half angle.
    let narrow = DEPTH_HALF_FOV_DEG[1].to_radians().tan() * 0.85;
    let needed = (length.hypot(width) / 2.0 / narrow).max(0.8);
    let count = index % 3 + 1;
    let azimuth = uniform(&mut rng, 0.0, 360.0);
    let mut cameras = Vec::with_capacity(count);
    for k in 0..count {
        let distance = uniform(&mut rng, needed, 1.6_f64.max(needed));
        let tilt = uniform(&mut rng, if count == 1 { 0.0 } else { 10.0 }, 35.0).to_radians();
        let turn = (azimuth + 360.0 * k as f64 / count as f64 + uniform(&mut rng, -20.0, 20.0))
            .to_radians();
        let lid = [center[0], center[1], height];
        cameras.push(SceneCamera {
            serial: Serial::parse(&format!("{:012}", 840_412_060_800 + k))
                .map_err(|e| anyhow::anyhow!("{e}"))?,
            position: [
                lid[0] + distance * tilt.sin() * turn.cos(),
                lid[1] + distance * tilt.sin() * turn.sin(),
                lid[2] + distance * tilt.cos(),
            ],
            look_at: lid,
            up: None,
            noise: Noise::D415,
            calibrated: false,
        });
    }
    let parcel = parcel_scene(
        rng.next_u64(),
        cameras,
        [length, width, height],
        center,
        yaw_deg,
    );
    let table = Scene {
        boxes: Vec::new(),
        markers: marker_grid(),
        ..parcel.clone()
    };
    parcel.validate()?;
    table.validate()?;
    Ok((parcel, table))
}

/// One scene's result.
struct Row {
    index: usize,
    cameras: usize,
    camera_z: f64,
    truth: [f64; 4],
    measured: Option<[f64; 4]>,
    cycle_ms: f64,
    grab_ms: f64,
    error: Option<String>,
    /// With `--calibrate`: each camera's pose error (mm, degrees) and the time the
    /// calibration of all cameras took.
    calibration: Option<(Vec<[f64; 2]>, f64)>,
    /// With `--calibrate`: the same parcel measured with the cameras' true poses, which
    /// tells the calibration's share of the errors from the measurement's.
    with_true_poses: Option<[f64; 4]>,
}

impl Row {
    /// The row of scene `index`, nothing measured yet.
    fn new(index: usize, scene: &Scene) -> anyhow::Result<Self> {
        Ok(Self {
            index,
            cameras: scene.cameras.len(),
            camera_z: scene.cameras[0].position[2],
            truth: truth(scene).context("the scene has no box")?,
            measured: None,
            cycle_ms: f64::NAN,
            grab_ms: f64::NAN,
            error: None,
            calibration: None,
            with_true_poses: None,
        })
    }

    /// Errors of length, width, height (mm) and yaw (deg).
    fn errors(&self) -> Option<[f64; 4]> {
        let m = self.measured?;
        Some([
            m[0] - self.truth[0],
            m[1] - self.truth[1],
            m[2] - self.truth[2],
            yaw_difference(m[3], self.truth[3]),
        ])
    }
}

/// Runs `bench`.
pub(crate) async fn run(args: BenchArgs) -> anyhow::Result<Exit> {
    match args.what {
        BenchKind::Accuracy(a) => accuracy(a).await,
        BenchKind::Transfer(a) => transfer::run(a).await,
        BenchKind::Repr(a) => repr::run(a).await,
        BenchKind::Load(a) => load::run(a).await,
    }
}

/// Measures `scene` (cameras already in place) through `client`.
async fn measure_scene(
    client: &CamClient,
    index: usize,
    scene: &Scene,
    config: &geometry::DimensionConfig,
) -> anyhow::Result<Row> {
    let serials: Vec<String> = scene.cameras.iter().map(|c| c.serial.to_string()).collect();
    prepare_cameras(client, &serials, 1.0, false).await?;
    let result = measure::measure_once(client, &Source::All, config).await;
    let mut row = Row::new(index, scene)?;
    if let Ok(m) = &result {
        row.cycle_ms = m.cycle.as_secs_f64() * 1e3;
        row.grab_ms = m.grab.as_secs_f64() * 1e3;
        row.measured = m
            .dimensions()
            .map(|d| [d.length_mm, d.width_mm, d.height_mm, d.yaw_deg]);
    }
    row.error = match &result {
        Ok(m) if m.dimensions().is_none() => Some("nothing on the table".into()),
        Ok(_) => None,
        Err(e) => Some(super::error_text(e)),
    };
    Ok(row)
}

/// `--calibrate`'s scene `index`: a server (state of its own) on the empty table, every
/// camera calibrated by its markers and written, then the parcel put on the table and
/// measured.
async fn calibrate_and_measure(
    state: &std::path::Path,
    seed: u64,
    index: usize,
    config: &geometry::DimensionConfig,
) -> anyhow::Result<Row> {
    let (parcel, table) = calibration_scenes(seed, index)?;
    let dir = state.join(index.to_string());
    let server = SceneServer::start(&table, &dir, SocketAddr::from(([127, 0, 0, 1], 0))).await?;
    let client = CamClient::at(server.addr()?, Duration::from_secs(30))?;
    let map = MarkerMap::from_scene(&table, Family::Tag36h11, 0)?;
    let started = Instant::now();
    let mut errors = Vec::with_capacity(table.cameras.len());
    let mut failure = None;
    for camera in &table.cameras {
        let sn = camera.serial.to_string();
        match calibrate::place(&client, &sn, &map).await {
            Ok(placed) => {
                let c = &placed.calibration;
                calibrate::put(&client, &sn, &c.transformation().to_json()).await?;
                let truth = camera.pose().context("the scene camera has no pose")?;
                errors.push(c.error_from(&truth));
            }
            Err(e) => {
                failure = Some(format!("calibrating camera {sn}: {e:#}"));
                break;
            }
        }
    }
    let calibrate_ms = started.elapsed().as_secs_f64() * 1e3;
    let mut row = if let Some(error) = failure {
        Row {
            error: Some(error),
            ..Row::new(index, &parcel)?
        }
    } else {
        // The same cameras, their 3d-transformation restored from the state directory.
        server.load(&parcel)?;
        let mut row = measure_scene(&client, index, &parcel, config).await?;
        for camera in &parcel.cameras {
            let pose = camera.pose().context("the scene camera has no pose")?;
            let truth = pose_transformation(&pose).to_json();
            calibrate::put(&client, &camera.serial.to_string(), &truth).await?;
        }
        row.with_true_poses = measure_scene(&client, index, &parcel, config)
            .await?
            .measured;
        row
    };
    row.calibration = Some((errors, calibrate_ms));
    drop(server);
    std::fs::remove_dir_all(&dir).ok();
    Ok(row)
}

async fn accuracy(args: AccuracyArgs) -> anyhow::Result<Exit> {
    if args.scenes == 0 {
        bail!("--scenes must be at least 1");
    }
    let state = std::env::temp_dir().join(format!("coapcam-bench-{}", std::process::id()));
    let config = args.dimension.config();
    let mut rows = Vec::new();
    if args.calibrate {
        for index in 0..args.scenes {
            let row = calibrate_and_measure(&state, args.seed, index, &config).await?;
            if !args.json {
                print_row(&row)?;
            }
            rows.push(row);
        }
    } else {
        let first = scene(args.seed, 0)?;
        let server =
            SceneServer::start(&first, &state, SocketAddr::from(([127, 0, 0, 1], 0))).await?;
        let client = CamClient::at(server.addr()?, Duration::from_secs(30))?;
        let mut next;
        for index in 0..args.scenes {
            // The server started with scene 0.
            let scene = if index == 0 {
                &first
            } else {
                next = scene(args.seed, index)?;
                server.load(&next)?;
                &next
            };
            let row = measure_scene(&client, index, scene, &config).await?;
            if !args.json {
                print_row(&row)?;
            }
            rows.push(row);
        }
    }
    std::fs::remove_dir_all(&state).ok();
    let errors: Vec<[f64; 4]> = rows.iter().filter_map(Row::errors).collect();
    let column = |i: usize| {
        let s = AbsSummary::of(&errors.iter().map(|e| e[i]).collect::<Vec<_>>());
        [s.mean, s.p95, s.max]
    };
    let cycles: Vec<f64> = rows.iter().map(|r| r.cycle_ms).collect();
    let median_cycle = stats::median(&cycles).unwrap_or(f64::NAN);
    let AbsSummary {
        p95: p95_cycle,
        max: max_cycle,
        ..
    } = AbsSummary::of(&cycles);
    let failed = rows.len() - errors.len();
    let names = ["length_mm", "width_mm", "height_mm", "yaw_deg"];
    // With --calibrate: every camera's pose errors, and the calibration times.
    let poses: Vec<[f64; 2]> = rows
        .iter()
        .filter_map(|r| r.calibration.as_ref())
        .flat_map(|(e, _)| e.iter().copied())
        .collect();
    let pose_column = |i: usize| {
        let v: Vec<f64> = poses.iter().map(|p| p[i]).collect();
        let s = AbsSummary::of(&v);
        [stats::median(&v).unwrap_or(f64::NAN), s.p95, s.max]
    };
    let times: Vec<f64> = rows
        .iter()
        .filter_map(|r| {
            r.calibration
                .as_ref()
                .map(|(e, ms)| ms / e.len().max(1) as f64)
        })
        .collect();
    let (median_time, max_time) =
        stats::Spread::of(&times).map_or((f64::NAN, f64::NAN), |s| (s.median, s.max));
    if args.json {
        let scenes: Vec<serde_json::Value> = rows
            .iter()
            .map(|r| {
                serde_json::json!({
                    "scene": r.index, "cameras": r.cameras, "camera_z_m": r.camera_z,
                    "truth": r.truth, "measured": r.measured, "cycle_ms": r.cycle_ms, "grab_ms": r.grab_ms,
                    "error": r.error,
                    "pose_errors_mm_deg": r.calibration.as_ref().map(|c| &c.0),
                    "calibrate_ms": r.calibration.as_ref().map(|c| c.1),
                    "measured_with_true_poses": r.with_true_poses,
                })
            })
            .collect();
        let summary: serde_json::Map<String, serde_json::Value> = names
            .iter()
            .enumerate()
            .map(|(i, n)| {
                let [mae, p95, max] = column(i);
                (
                    (*n).to_owned(),
                    serde_json::json!({"mae": mae, "p95": p95, "max": max}),
                )
            })
            .collect();
        outln!(
            "{}",
            serde_json::json!({
                "scenes": scenes, "summary": summary, "failed": failed,
                "cycle_ms": {"median": median_cycle, "p95": p95_cycle, "max": max_cycle},
                "calibration": args.calibrate.then(|| {
                    let ([pm, pp, px], [am, ap, ax]) = (pose_column(0), pose_column(1));
                    serde_json::json!({
                        "cameras": poses.len(),
                        "position_mm": {"median": pm, "p95": pp, "max": px},
                        "angle_deg": {"median": am, "p95": ap, "max": ax},
                        "per_camera_ms": {"median": median_time, "max": max_time},
                    })
                }),
            })
        );
    } else {
        outln!("");
        outln!("{:<10} {:>8} {:>8} {:>8}", "", "MAE", "p95", "max");
        for (i, name) in ["length mm", "width mm", "height mm", "yaw deg"]
            .iter()
            .enumerate()
        {
            let [mae, p95, max] = column(i);
            outln!("{name:<10} {mae:>8.2} {p95:>8.2} {max:>8.2}");
        }
        outln!(
            "{} scenes, {failed} failed; cycle median {median_cycle:.0} ms, p95 {p95_cycle:.0} ms, max {max_cycle:.0} ms",
            rows.len()
        );
        if args.calibrate {
            outln!("");
            outln!(
                "{:<13} {:>8} {:>8} {:>8}",
                "pose error",
                "median",
                "p95",
                "max"
            );
            for (i, name) in ["position mm", "angle deg"].iter().enumerate() {
                let [median, p95, max] = pose_column(i);
                outln!("{name:<13} {median:>8.2} {p95:>8.2} {max:>8.3}");
            }
            outln!(
                "{} cameras calibrated; per camera median {median_time:.0} ms, max {max_time:.0} ms (grabs over CoAP, detection, fit)",
                poses.len()
            );
        }
    }
    Ok(if failed == 0 {
        Exit::Success
    } else {
        Exit::Failure
    })
}

fn print_row(r: &Row) -> anyhow::Result<()> {
    if let Some((errors, ms)) = &r.calibration {
        let each: Vec<String> = errors
            .iter()
            .map(|[mm, deg]| format!("{mm:.2} mm {deg:.3} deg"))
            .collect();
        let truth = r.with_true_poses.map_or(String::new(), |m| {
            format!(
                "; with the true poses {:.1} x {:.1} x {:.1} mm",
                m[0], m[1], m[2]
            )
        });
        outln!(
            "scene {:>2}: calibrated in {ms:.0} ms, pose errors: {}{truth}",
            r.index,
            each.join(", ")
        );
    }
    let t = r.truth;
    match (r.errors(), &r.error) {
        (Some(e), _) => outln!(
            "scene {:>2}: {} cam at {:.2} m  {:>5.0} x {:>5.0} x {:>5.0} mm  yaw {:>4.1}  error {:>+6.1} {:>+6.1} {:>+6.1} mm {:>+5.1} deg  {:>4.0} ms ({:.0} grab)",
            r.index,
            r.cameras,
            r.camera_z,
            t[0],
            t[1],
            t[2],
            t[3],
            e[0],
            e[1],
            e[2],
            e[3],
            r.cycle_ms,
            r.grab_ms
        ),
        (None, Some(err)) => outln!(
            "scene {:>2}: {} cam at {:.2} m  {:>5.0} x {:>5.0} x {:>5.0} mm  FAILED: {err}",
            r.index,
            r.cameras,
            r.camera_z,
            t[0],
            t[1],
            t[2]
        ),
        (None, None) => {}
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scene_set_covers_the_ranges_and_is_reproducible() {
        let scenes: Vec<Scene> = (0..40).map(|i| scene(1, i).unwrap()).collect();
        assert_eq!(scenes[7], scene(1, 7).unwrap());
        let boxes: Vec<&SceneBox> = scenes.iter().map(|s| &s.boxes[0]).collect();
        for b in &boxes {
            assert!(
                b.size[0] >= 0.1 && b.size[0] <= 0.8 && b.size[1] >= 0.1,
                "{b:?}"
            );
            assert!(b.size[2] >= 0.02 && b.size[2] <= 0.6, "{b:?}");
            assert!((0.0..=90.0).contains(&b.yaw_deg));
        }
        for s in &scenes {
            for c in &s.cameras {
                assert!(c.position[2] >= 0.75 && c.position[2] <= 1.5, "{c:?}");
            }
        }
        assert!(scenes.iter().any(|s| s.cameras.len() == 2));
        assert!(scenes.iter().any(|s| s.cameras.len() == 1));
    }

    #[test]
    fn the_calibration_set_has_one_to_three_uncalibrated_tilted_cameras_and_a_marker_table() {
        let sets: Vec<(Scene, Scene)> =
            (0..30).map(|i| calibration_scenes(1, i).unwrap()).collect();
        assert_eq!(sets[4], calibration_scenes(1, 4).unwrap());
        let mut tilts = Vec::new();
        for (i, (parcel, table)) in sets.iter().enumerate() {
            assert_eq!(parcel.cameras.len(), i % 3 + 1);
            assert_eq!(parcel.cameras, table.cameras);
            assert!(table.boxes.is_empty() && table.markers.len() == 25);
            assert!(parcel.markers.is_empty());
            let b = &parcel.boxes[0];
            assert!(
                b.size[0] <= 0.6 && b.size[1] >= 0.1 && b.size[2] <= 0.4,
                "{b:?}"
            );
            for c in &parcel.cameras {
                assert!(!c.calibrated);
                let d: Vec<f64> = (0..3).map(|k| c.position[k] - c.look_at[k]).collect();
                let distance = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                assert!((0.8..=1.6).contains(&distance), "{c:?}");
                let tilt = (d[2] / distance).acos().to_degrees();
                assert!(tilt <= 35.0, "{c:?}");
                tilts.push(tilt);
            }
        }
        assert!(tilts.iter().any(|t| *t > 30.0) && tilts.iter().any(|t| *t < 10.0));
        let origin = &sets[0].1.markers.iter().find(|m| m.id == 0).unwrap();
        assert_eq!((origin.center, origin.yaw_deg), ([0.0, 0.0], 0.0));
    }
}
