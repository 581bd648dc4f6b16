//! `serve --auto-measure`: the task that watches the table through the cameras and
//! measures each parcel once when it stands still. It is a thin driver of
//! [`Stillness`]: every look grabs one depth frame of each calibrated camera (through
//! the [`Rig`], i.e. the `Camera` the server serves, librealsense's or the synthetic
//! one), places every fourth pixel or so on the table with the camera's
//! 3d-transformation into one [`HeightMap`], and feeds it to the detector. On
//! [`Event::Still`] it makes the measurement ([`measure::measure`], with the
//! codes, the photo and the annotated picture), looks once more, and records the
//! measurement only if the table is still as it was: something that moved during the
//! measurement is not recorded, and is measured again once it stands still.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::{Duration, Instant};

use rgbd::Serial;
use tokio::task::JoinHandle;

use super::Recorder;
use super::auto::{Event, Grid, HeightMap, Stillness, StillnessConfig};
use crate::api::record::Trigger;
use crate::report::{EdgeQuery, Found, Reported};
use crate::server::measure::{self, Rig, RigCamera};

/// How long a look waits for a camera's depth frame.
const GRAB_TIMEOUT: Duration = Duration::from_secs(5);
/// The time between looks while the table is empty: a parcel is seen within this of
/// arriving, long before it can have stood still, and an idle station grabs a few
/// frames a second only.
pub const IDLE_PERIOD: Duration = Duration::from_millis(400);
/// The longest time between looks while something is on the table; with the default
/// `--still-ms` that is five looks over the still time.
pub const ACTIVE_PERIOD: Duration = Duration::from_millis(150);
/// The width of the decimated depth image a look uses, about: a 1280-pixel-wide frame
/// is read every fourth pixel of every fourth row.
const LOOK_WIDTH: u32 = 320;

/// How the station measures by itself (`serve --auto-measure`).
#[derive(Debug, Clone, Copy)]
pub struct AutoConfig {
    /// How the detector decides (`--still-ms` is its `still`).
    pub stillness: StillnessConfig,
    /// What each measurement asks (the codes, the thresholds, the billing).
    pub query: EdgeQuery,
    /// The grid of the height maps.
    pub grid: Grid,
}

impl Default for AutoConfig {
    /// The default detector, the codes read, the default thresholds and billing.
    fn default() -> Self {
        Self {
            stillness: StillnessConfig::default(),
            query: EdgeQuery {
                codes: true,
                ..EdgeQuery::default()
            },
            grid: Grid::default(),
        }
    }
}

impl AutoConfig {
    /// The time between looks while something is on the table: [`ACTIVE_PERIOD`], or a
    /// quarter of the still time when that is shorter (at least 20 ms).
    pub fn active_period(&self) -> Duration {
        ACTIVE_PERIOD
            .min(self.stillness.still / 4)
            .max(Duration::from_millis(20))
    }
}

/// Watches through `rig` and records into `recorder` until the handle is aborted.
pub fn spawn<R: Rig>(rig: Arc<R>, recorder: Recorder, config: AutoConfig) -> JoinHandle<()> {
    tokio::spawn(async move { Watcher::new(config).run(&*rig, &recorder).await })
}

/// What one look saw.
enum Look {
    /// The table, as every calibrated camera saw it.
    Map(HeightMap),
    /// No calibrated camera to look through.
    Blind,
    /// A camera's frame could not be had.
    Failed(String),
}

struct Watcher {
    config: AutoConfig,
    detector: Stillness,
    /// Cameras already named as not calibrated, and whether "no camera" was said.
    warned: BTreeSet<Serial>,
    warned_blind: bool,
    /// The last failure said, so a camera that keeps failing is not named every look.
    last_failure: Option<String>,
}

impl Watcher {
    fn new(config: AutoConfig) -> Self {
        Self {
            config,
            detector: Stillness::new(config.stillness),
            warned: BTreeSet::new(),
            warned_blind: false,
            last_failure: None,
        }
    }

    async fn run<R: Rig>(mut self, rig: &R, recorder: &Recorder) {
        tracing::info!(
            still_ms = self.config.stillness.still.as_millis() as u64,
            "auto-measure: watching the table"
        );
        loop {
            let started = tokio::time::Instant::now();
            if let Some(map) = self.look(rig).await {
                match self.detector.observe(Instant::now(), &map) {
                    Some(Event::Still) => self.measure(rig, recorder).await,
                    Some(event) => tracing::info!("auto-measure: {}", describe(event)),
                    None => {}
                }
            }
            let period = if self.detector.is_empty() {
                IDLE_PERIOD
            } else {
                self.config.active_period()
            };
            tokio::time::sleep_until(started + period).await;
        }
    }

    /// One look at the table; `None` (having said why, once) when there is no map.
    async fn look<R: Rig>(&mut self, rig: &R) -> Option<HeightMap> {
        let cameras = rig.cameras();
        for c in cameras.iter().filter(|c| !calibrated(c)) {
            if self.warned.insert(c.serial) {
                tracing::warn!(
                    serial = %c.serial,
                    "auto-measure: camera {} is not calibrated (identity 3d-transformation) and is not watched; calibrate it (coapcam calibrate)",
                    c.serial
                );
            }
        }
        let watched: Vec<RigCamera> = cameras.into_iter().filter(calibrated).collect();
        match look(watched, self.config.grid).await {
            Look::Map(map) => {
                self.warned_blind = false;
                self.last_failure = None;
                Some(map)
            }
            Look::Blind => {
                if !std::mem::replace(&mut self.warned_blind, true) {
                    tracing::warn!("auto-measure: no calibrated camera to watch the table with");
                }
                None
            }
            Look::Failed(why) => {
                if self.last_failure.as_ref() != Some(&why) {
                    tracing::warn!("auto-measure: {why}");
                    self.last_failure = Some(why);
                }
                None
            }
        }
    }

    /// Measures what stands still, looks again, and records it if nothing moved.
    async fn measure<R: Rig>(&mut self, rig: &R, recorder: &Recorder) {
        tracing::info!("auto-measure: a parcel stands still; measuring");
        let measured = measure::measure(rig, &self.config.query, Trigger::Auto, true).await;
        let measured = match measured {
            Ok(measured) => measured,
            Err(e) => {
                tracing::warn!(
                    "auto-measure: measuring failed ({e}); measuring again once it stands still"
                );
                self.detector.forget(Instant::now());
                return;
            }
        };
        if let Some(map) = self.look(rig).await
            && let Some(event @ (Event::Moved | Event::Left)) =
                self.detector.observe(Instant::now(), &map)
        {
            tracing::info!(
                "auto-measure: {} during the measurement; it is not recorded",
                describe(event)
            );
            self.detector.forget(Instant::now());
            return;
        }
        if let Found::Unsynced { reason } = &measured.measurement.parcel {
            tracing::warn!("auto-measure: not measured, recorded as such: {reason}");
        }
        if measured.measurement.parcel == Found::Nothing {
            tracing::info!("auto-measure: the measurement found no parcel; not recorded");
            return;
        }
        if let Found::Uncalibrated { uncalibrated } = &measured.measurement.parcel {
            tracing::warn!(
                "auto-measure: camera(s) {} are not calibrated, so no dimensions; not recorded",
                uncalibrated.join(", ")
            );
            return;
        }
        match recorder.record(measured).await {
            Ok(record) => {
                let dims = record
                    .measurement
                    .reported()
                    .map_or_else(String::new, Reported::dimensions_text);
                tracing::info!(
                    id = record.id,
                    "auto-measure: recorded measurement {}: {dims}",
                    record.id
                );
            }
            Err(e) => tracing::error!("auto-measure: the measurement could not be recorded: {e}"),
        }
    }
}

fn calibrated(c: &RigCamera) -> bool {
    c.transformation != geometry::Transformation::identity()
}

fn describe(event: Event) -> &'static str {
    match event {
        Event::Arrived => "something arrived on the table",
        Event::Still => "a parcel stands still",
        Event::Moved => "what stood on the table moved",
        Event::Left => "the table is empty",
    }
}

/// A depth frame of every camera of `cameras` at once, placed on one map; off the
/// executor.
async fn look(cameras: Vec<RigCamera>, grid: Grid) -> Look {
    if cameras.is_empty() {
        return Look::Blind;
    }
    let tasks: Vec<_> = cameras
        .into_iter()
        .map(|c| {
            tokio::task::spawn_blocking(move || -> Result<HeightMap, String> {
                let fail = |what: &str, e: &dyn std::fmt::Display| {
                    format!("camera {}: {what}: {e}", c.serial)
                };
                let to_table = c
                    .transformation
                    .to_transform()
                    .map_err(|e| fail("3d-transformation", &e))?;
                let depth = c
                    .camera
                    .grab_depth(GRAB_TIMEOUT)
                    .map_err(|e| fail("depth", &e))?;
                let k = c
                    .camera
                    .depth_intrinsics()
                    .map_err(|e| fail("depth intrinsics", &e))?;
                let step = (depth.width / LOOK_WIDTH).max(1) as usize;
                let mut map = HeightMap::new(grid);
                map.add_depth(&depth, &k, &to_table, step);
                Ok(map)
            })
        })
        .collect();
    let mut merged = HeightMap::new(grid);
    for task in tasks {
        match task.await {
            Ok(Ok(map)) => merged.merge(&map),
            Ok(Err(why)) => return Look::Failed(why),
            Err(e) => return Look::Failed(format!("a look's task failed: {e}")),
        }
    }
    Look::Map(merged)
}
