//! `bench accuracy`: a built-in, seeded set of synthetic parcel scenes ([`scenes`])
//! measured end to end over CoAP on loopback, each scene's errors, and their summary.

pub mod cert;
pub mod lane;
pub mod scenes;

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use geometry::DimensionConfig;
use markers::Family;
use rgbd::Scene;

use crate::client::CamClient;
use crate::client::calibrate;
use crate::client::measure::{self, Source, prepare_cameras, truth, yaw_difference};
use crate::server::SceneServer;
use crate::stats::{self, AbsSummary, Spread};
use crate::vision::calibration::{MarkerMap, pose_transformation};
use scenes::{calibration_scenes, scene};

/// What to run.
#[derive(Debug, Clone)]
pub struct Config {
    /// Number of scenes (at least 1).
    pub scenes: usize,
    /// Seed of the scene generator.
    pub seed: u64,
    /// Start every scene with its cameras uncalibrated, calibrate them on the empty
    /// table's markers, then measure.
    pub calibrate: bool,
    /// The measurement's thresholds.
    pub dimension: DimensionConfig,
}

/// One scene's result.
pub struct Row {
    /// The scene's index in the set.
    pub index: usize,
    /// How many cameras see it.
    pub cameras: usize,
    /// The first camera's height, metres.
    pub camera_z: f64,
    /// Length, width, height (mm) and yaw (degrees) of the box.
    pub truth: [f64; 4],
    /// What was measured, in the same units; `None` when nothing was.
    pub measured: Option<[f64; 4]>,
    /// The whole measurement, milliseconds.
    pub cycle_ms: f64,
    /// Its grabs, milliseconds.
    pub grab_ms: f64,
    /// Why nothing was measured.
    pub error: Option<String>,
    /// With `--calibrate`: each camera's pose error (mm, degrees) and the time the
    /// calibration of all cameras took.
    pub calibration: Option<(Vec<[f64; 2]>, f64)>,
    /// With `--calibrate`: the same parcel measured with the cameras' true poses, which
    /// tells the calibration's share of the errors from the measurement's.
    pub with_true_poses: Option<[f64; 4]>,
    /// What did not go as asked but did not stop the scene.
    pub warnings: Vec<String>,
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
            warnings: Vec::new(),
        })
    }

    /// Errors of length, width, height (mm) and yaw (deg).
    pub fn errors(&self) -> Option<[f64; 4]> {
        let m = self.measured?;
        Some([
            m[0] - self.truth[0],
            m[1] - self.truth[1],
            m[2] - self.truth[2],
            yaw_difference(m[3], self.truth[3]),
        ])
    }
}

/// Measures `scene` (cameras already in place) through `client`.
async fn measure_scene(
    client: &CamClient,
    index: usize,
    scene: &Scene,
    config: &DimensionConfig,
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
        Err(e) => Some(crate::error_text(e)),
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
    config: &DimensionConfig,
) -> anyhow::Result<Row> {
    let (parcel, table) = calibration_scenes(seed, index)?;
    let dir = state.join(index.to_string());
    let server = SceneServer::start(&table, &dir, SocketAddr::from(([127, 0, 0, 1], 0))).await?;
    let client = CamClient::at(server.addr()?, Duration::from_secs(30))?;
    let map = MarkerMap::from_scene(&table, Family::Tag36h11, 0)?;
    let started = Instant::now();
    let mut errors = Vec::with_capacity(table.cameras.len());
    let mut warnings = Vec::new();
    let mut failure = None;
    for camera in &table.cameras {
        let sn = camera.serial.to_string();
        match calibrate::place(&client, &sn, &map).await {
            Ok(placed) => {
                warnings.extend(placed.warnings.iter().cloned());
                let c = &placed.calibration;
                calibrate::put(&client, &sn, &c.transformation()).await?;
                let truth = camera.pose().context("the scene camera has no pose")?;
                errors.push(c.error_from(&truth));
            }
            Err(e) => {
                failure = Some(format!(
                    "calibrating camera {sn}: {}",
                    crate::error_text(&e)
                ));
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
            let truth = pose_transformation(&pose);
            calibrate::put(&client, &camera.serial.to_string(), &truth).await?;
        }
        row.with_true_poses = measure_scene(&client, index, &parcel, config)
            .await?
            .measured;
        row
    };
    row.calibration = Some((errors, calibrate_ms));
    row.warnings = warnings;
    drop(server);
    std::fs::remove_dir_all(&dir).ok();
    Ok(row)
}

/// Runs the scenes of `config` one after the other, handing each row to `on_row` as it
/// is measured; every row. A scene that fails to measure is a row with its error; an
/// error means the benchmark could not run.
pub async fn run(
    config: &Config,
    mut on_row: impl FnMut(&Row) -> anyhow::Result<()>,
) -> anyhow::Result<Vec<Row>> {
    if config.scenes == 0 {
        bail!("--scenes must be at least 1");
    }
    let state = std::env::temp_dir().join(format!("coapcam-bench-{}", std::process::id()));
    let dimension = &config.dimension;
    let mut rows = Vec::new();
    if config.calibrate {
        for index in 0..config.scenes {
            let row = calibrate_and_measure(&state, config.seed, index, dimension).await?;
            on_row(&row)?;
            rows.push(row);
        }
    } else {
        let first = scene(config.seed, 0)?;
        let server =
            SceneServer::start(&first, &state, SocketAddr::from(([127, 0, 0, 1], 0))).await?;
        let client = CamClient::at(server.addr()?, Duration::from_secs(30))?;
        let mut next;
        for index in 0..config.scenes {
            // The server started with scene 0.
            let scene = if index == 0 {
                &first
            } else {
                next = scene(config.seed, index)?;
                server.load(&next)?;
                &next
            };
            let row = measure_scene(&client, index, scene, dimension).await?;
            on_row(&row)?;
            rows.push(row);
        }
    }
    std::fs::remove_dir_all(&state).ok();
    Ok(rows)
}

/// Serves the scenes `make(index)` of `indices` one after the other from one scene server
/// on loopback (`name` names its state folder), each loaded in place of the last, and hands
/// each to `measure` with a client socket of its own: a message ID may not be used again
/// with the server within EXCHANGE_LIFETIME (247 s), so one endpoint sustains 265
/// messages a second. Unprepared clouds (the floor too) take about 700 blocks a scene, and
/// one socket for a whole 720-scene lane run ran out of IDs every ~90 scenes and waited
/// longer than a request may (3 scenes "timed out" each time).
async fn each_scene<S>(
    name: &str,
    indices: std::ops::Range<usize>,
    make: impl Fn(usize) -> S,
    scene: impl Fn(&S) -> &Scene,
    mut measure: impl AsyncFnMut(&CamClient, &S) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    let state = std::env::temp_dir().join(format!("coapcam-bench-{name}-{}", std::process::id()));
    let mut server: Option<SceneServer> = None;
    for index in indices {
        let current = make(index);
        let addr = match &server {
            Some(s) => {
                s.load(scene(&current))?;
                s.addr()?
            }
            None => {
                let loopback = SocketAddr::from(([127, 0, 0, 1], 0));
                let s = SceneServer::start(scene(&current), &state, loopback).await?;
                server.insert(s).addr()?
            }
        };
        let client = CamClient::at(addr, Duration::from_secs(60))?;
        measure(&client, &current).await?;
    }
    drop(server);
    std::fs::remove_dir_all(&state).ok();
    Ok(())
}

/// Median, 95th percentile (nearest rank) and maximum.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Quantiles {
    /// Of an even count, the mean of the middle two.
    pub median: f64,
    /// Nearest rank.
    pub p95: f64,
    /// The largest.
    pub max: f64,
}

impl Quantiles {
    /// Of `values`.
    pub fn of(values: &[f64]) -> Self {
        Self {
            median: stats::median(values).unwrap_or(f64::NAN),
            p95: stats::percentile(values, 0.95).unwrap_or(f64::NAN),
            max: Spread::of(values).map_or(f64::NAN, |s| s.max),
        }
    }
}

/// What the rows say together.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    /// Of the errors of length, width, height (mm) and yaw (degrees) of the measured
    /// scenes.
    pub errors: [AbsSummary; 4],
    /// Scenes where nothing was measured.
    pub failed: usize,
    /// Of the measurements' times, milliseconds.
    pub cycle_ms: Quantiles,
    /// With `--calibrate`: of every camera's pose error.
    pub calibration: Option<CalibrationSummary>,
}

/// The cameras' pose errors and calibration times of `--calibrate`.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationSummary {
    /// Cameras calibrated.
    pub cameras: usize,
    /// Of their position errors, millimetres.
    pub position_mm: Quantiles,
    /// Of their angle errors, degrees.
    pub angle_deg: Quantiles,
    /// Median of the calibration time per camera of each scene, milliseconds.
    pub median_per_camera_ms: f64,
    /// Their maximum.
    pub max_per_camera_ms: f64,
}

impl Summary {
    /// Of `rows`.
    pub fn of(rows: &[Row]) -> Self {
        let errors: Vec<[f64; 4]> = rows.iter().filter_map(Row::errors).collect();
        let column = |i: usize| AbsSummary::of(&errors.iter().map(|e| e[i]).collect::<Vec<_>>());
        let cycles: Vec<f64> = rows.iter().map(|r| r.cycle_ms).collect();
        let poses: Vec<[f64; 2]> = rows
            .iter()
            .filter_map(|r| r.calibration.as_ref())
            .flat_map(|(e, _)| e.iter().copied())
            .collect();
        let pose_column = |i: usize| Quantiles::of(&poses.iter().map(|p| p[i]).collect::<Vec<_>>());
        let times: Vec<f64> = rows
            .iter()
            .filter_map(|r| {
                r.calibration
                    .as_ref()
                    .map(|(e, ms)| ms / e.len().max(1) as f64)
            })
            .collect();
        let times = Spread::of(&times);
        let calibrated = rows.iter().any(|r| r.calibration.is_some());
        Self {
            errors: [column(0), column(1), column(2), column(3)],
            failed: rows.len() - errors.len(),
            cycle_ms: Quantiles::of(&cycles),
            calibration: calibrated.then(|| CalibrationSummary {
                cameras: poses.len(),
                position_mm: pose_column(0),
                angle_deg: pose_column(1),
                median_per_camera_ms: times.map_or(f64::NAN, |s| s.median),
                max_per_camera_ms: times.map_or(f64::NAN, |s| s.max),
            }),
        }
    }
}
