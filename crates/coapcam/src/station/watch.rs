//! `serve --auto-measure`: the task that watches the table through the cameras and
//! measures each parcel once when it stands still. It is a thin driver of
//! [`Stillness`]: every look grabs one depth frame of each calibrated camera (through
//! the [`Rig`], i.e. the `Camera` the server serves, librealsense's or the synthetic
//! one), places every fourth pixel or so on the table with the camera's
//! 3d-transformation into one [`HeightMap`], and feeds it to the detector with the time
//! its frames were captured (not the time the look ended: rendering and placing a frame
//! takes a varying while on a busy machine, and a hand that rested half a second must not
//! look as if it had rested for `--still-ms`). On
//! [`Event::Still`] it makes the measurement ([`measure::measure`], with the
//! codes, the photo and the annotated picture), looks once more, and records the
//! measurement only if the table is still as it was: something that moved during the
//! measurement is not recorded, and is measured again once it stands still.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

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
    /// The table, as every calibrated camera saw it, and when ([`taken_at`]).
    Map(HeightMap, Instant),
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
            if let Some((map, taken)) = self.look(rig).await {
                match self.detector.observe(taken, &map) {
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

    /// One look at the table and when it was taken; `None` (having said why, once) when
    /// there is no map.
    async fn look<R: Rig>(&mut self, rig: &R) -> Option<(HeightMap, Instant)> {
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
            Look::Map(map, taken) => {
                self.warned_blind = false;
                self.last_failure = None;
                Some((map, taken))
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
        if let Some((map, taken)) = self.look(rig).await
            && let Some(event @ (Event::Moved | Event::Left)) = self.detector.observe(taken, &map)
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

/// A depth frame of every camera of `cameras` at once, placed on one map, taken when
/// its oldest frame was captured; off the executor.
async fn look(cameras: Vec<RigCamera>, grid: Grid) -> Look {
    if cameras.is_empty() {
        return Look::Blind;
    }
    let asked = Instant::now();
    let tasks: Vec<_> = cameras
        .into_iter()
        .map(|c| {
            tokio::task::spawn_blocking(move || -> Result<(HeightMap, u64), String> {
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
                Ok((map, depth.timestamp_us))
            })
        })
        .collect();
    let mut merged = HeightMap::new(grid);
    let mut oldest_us = u64::MAX;
    for task in tasks {
        match task.await {
            Ok(Ok((map, captured_us))) => {
                merged.merge(&map);
                oldest_us = oldest_us.min(captured_us);
            }
            Ok(Err(why)) => return Look::Failed(why),
            Err(e) => return Look::Failed(format!("a look's task failed: {e}")),
        }
    }
    let now_us = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_micros()).unwrap_or(u64::MAX));
    Look::Map(merged, taken_at(oldest_us, now_us, asked, Instant::now()))
}

/// When a look was taken on the monotonic clock, its oldest frame having been captured at
/// `captured_us` (µs since the UNIX epoch, as frames are stamped), the wall clock reading
/// `now_us` at `now`: `now` less the frame's age, but within the look (from `asked`, when
/// its grabs began, to `now`), so a step of the wall clock (or a frame a camera held
/// before it was asked) moves it within the look only, and times never go backwards
/// from one look to the next.
fn taken_at(captured_us: u64, now_us: u64, asked: Instant, now: Instant) -> Instant {
    let age = Duration::from_micros(now_us.saturating_sub(captured_us));
    now.checked_sub(age).map_or(asked, |t| t.max(asked))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::station::auto::StillnessConfig;

    /// A µs since the UNIX epoch and a moment of the monotonic clock that stand for scene
    /// time `ms`.
    fn clocks() -> (impl Fn(u64) -> u64, impl Fn(u64) -> Instant) {
        let base = Instant::now();
        (
            |ms| 1_796_000_000_000_000 + ms * 1000,
            move |ms| base + Duration::from_millis(ms),
        )
    }

    #[test]
    fn a_look_is_taken_when_its_frames_were_captured_within_the_look() {
        let (us, at) = clocks();
        // Asked at 1000 ms, the frame captured at 1020, placed by 1400.
        assert_eq!(taken_at(us(1020), us(1400), at(1000), at(1400)), at(1020));
        // A frame from before the look (held by the camera, or the wall clock stepped
        // forward): its start.
        assert_eq!(taken_at(us(900), us(1400), at(1000), at(1400)), at(1000));
        // A frame after the wall clock's now (the wall clock stepped back): its end.
        assert_eq!(taken_at(us(1500), us(1400), at(1000), at(1400)), at(1400));
    }

    /// The lane test's hand rests beside the parcel from 18.5 s to 19.0 s, shorter than
    /// the still time (600 ms). On a busy machine the first look that saw it resting was
    /// placed 100 ms after its frame, the last one 300 ms after: timed by the ends of the
    /// looks it stood still 650 ms and was measured (and then, gone during the
    /// measurement, the parcel was measured anew); timed by its frames, 450 ms.
    #[test]
    fn a_hand_resting_shorter_than_the_still_time_is_not_still_however_slow_the_looks() {
        let (us, at) = clocks();
        // 4 x 4 cells of 2 cm, 30 cm high (the test's hand, a cylinder 10 cm across).
        let hand = HeightMap::from_rows(0.02, &vec![vec![Some(0.3); 4]; 4]);
        let looks = [(18_450, 18_500, 18_600), (18_900, 18_950, 19_250)];
        let mut by_frames = Stillness::new(StillnessConfig::default());
        let mut by_ends = Stillness::new(StillnessConfig::default());
        let mut events = (Vec::new(), Vec::new());
        for (asked, captured, placed) in looks {
            let taken = taken_at(us(captured), us(placed), at(asked), at(placed));
            events.0.push(by_frames.observe(taken, &hand));
            events.1.push(by_ends.observe(at(placed), &hand));
        }
        assert_eq!(events.0, [Some(Event::Arrived), None]);
        assert_eq!(events.1, [Some(Event::Arrived), Some(Event::Still)]);
    }
}
