//! The station: what a camera server does by itself for a parcel lane (docs/station.md).
//! - [`crate::api::record`] (the record of a measurement, shared with the client);
//! - [`log`]: the results log, append-only and hash-chained in SQLite, with retention;
//! - `reads`: the log's read API (list, one record, pictures, refusals), once for both
//!   front ends;
//! - `resources`: the log as CoAP resources (`/station/measurements...`);
//! - [`mqtt`]: every record published to an MQTT broker, none lost while it is away;
//! - [`line`](mod@line): a plain text line per measurement to the readers of a TCP port;
//! - [`http`]: the page and the JSON API over HTTP (`serve --http`);
//! - [`webhook`]: every record POSTed to an HTTP URL, none lost while it is away;
//! - [`auto`]: automatic measurement's core: height maps of the table and the stillness
//!   detector that says when a parcel stands still.

pub mod auto;
pub mod follow;
pub mod http;
pub mod line;
pub mod log;
pub mod measure;
pub mod mqtt;
pub(crate) mod reads;
pub(crate) mod resources;
pub mod watch;
pub mod webhook;

use std::path::{Path, PathBuf};

use self::log::{LogError, ResultsLog, Retention};
use crate::api::record::{CameraPose, NewRecord, Record, Trigger, UtcTime};

/// The name of the results log's file in the state directory.
pub const RESULTS_FILE: &str = "results.sqlite";

/// The file in the state directory `state_dir` that keeps the last id the results log
/// at `log` issued, so that a log lost with its file is not followed by ids issued again:
/// the log's file name and `.last-id` (`results.sqlite.last-id`), one for each log, so
/// that two stations sharing a state directory with logs of their own (`--results`)
/// keep apart.
pub fn last_id_path(state_dir: &Path, log: &Path) -> PathBuf {
    let name = log
        .file_name()
        .map_or_else(|| RESULTS_FILE.into(), |n| n.to_string_lossy().into_owned());
    state_dir.join(format!("{name}.last-id"))
}

/// The station's part of a server's configuration (`serve`'s station flags).
#[derive(Debug, Clone)]
pub struct Config {
    /// The station's name, in every record (`--station-name`).
    pub name: String,
    /// The results log's file (`--results`), `None` for [`RESULTS_FILE`] in the state
    /// directory.
    pub results: Option<PathBuf>,
    /// How much of the log is kept (`--results-keep-pictures`, `--results-max-bytes`).
    pub retention: Retention,
    /// Publish every record to this MQTT broker (`--mqtt`).
    pub mqtt: Option<mqtt::Target>,
    /// Serve a text line per measurement on this TCP address (`--line-output`).
    pub line_output: Option<std::net::SocketAddr>,
    /// Serve the page and the HTTP API on this address (`--http`).
    pub http: Option<std::net::SocketAddr>,
    /// The hosts the HTTP-CoAP proxy reaches besides the station's own CoAP servers
    /// (`--proxy-allow`).
    pub proxy_allow: Vec<http::proxy::Allowed>,
    /// POST every record to this URL (`--webhook`).
    pub webhook: Option<webhook::Target>,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            name: host_name(),
            results: None,
            retention: Retention::default(),
            mqtt: None,
            line_output: None,
            http: None,
            proxy_allow: Vec::new(),
            webhook: None,
        }
    }
}

impl Config {
    /// The results log's file with `state_dir` as the state directory.
    pub fn results_path(&self, state_dir: &Path) -> PathBuf {
        self.results
            .clone()
            .unwrap_or_else(|| state_dir.join(RESULTS_FILE))
    }
}

/// This machine's host name (the kernel's, else `$HOSTNAME`, else `coapcam`).
pub fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .or_else(|_| std::fs::read_to_string("/etc/hostname"))
        .ok()
        .map(|s| s.trim().to_owned())
        .filter(|s| !s.is_empty())
        .or_else(|| std::env::var("HOSTNAME").ok().filter(|s| !s.is_empty()))
        .unwrap_or_else(|| "coapcam".to_owned())
}

/// Records measurements in the log under the station's name: what every measurement
/// path (a client's `POST /cams/dimensions`, the automatic one) calls once it has
/// measured, before it tells anyone.
#[derive(Debug, Clone)]
pub struct Recorder {
    log: ResultsLog,
    station: String,
}

/// What a measurement path hands [`Recorder::record`].
#[derive(Debug, Clone)]
pub struct Measured {
    /// What made it.
    pub trigger: Trigger,
    /// The measurement.
    pub measurement: crate::report::Measurement,
    /// Each camera's serial and 3d-transformation.
    pub cameras: Vec<CameraPose>,
    /// The photo, JPEG.
    pub photo_jpeg: Option<Vec<u8>>,
    /// The annotated picture, PNG.
    pub annotated_png: Option<Vec<u8>>,
}

impl Recorder {
    /// Records into `log` as station `station`.
    pub fn new(log: ResultsLog, station: String) -> Self {
        Self { log, station }
    }

    /// The log.
    pub fn log(&self) -> &ResultsLog {
        &self.log
    }

    /// The station's name.
    pub fn station(&self) -> &str {
        &self.station
    }

    /// Appends `measured`, timed now, on the blocking pool; the record is on disk when
    /// this returns.
    pub async fn record(&self, measured: Measured) -> Result<Record, LogError> {
        let new = NewRecord {
            time: UtcTime::now(),
            station: self.station.clone(),
            trigger: measured.trigger,
            measurement: measured.measurement,
            cameras: measured.cameras,
            version: NewRecord::VERSION.to_owned(),
            photo_jpeg: measured.photo_jpeg,
            annotated_png: measured.annotated_png,
        };
        let log = self.log.clone();
        match tokio::task::spawn_blocking(move || log.append(new)).await {
            Ok(appended) => appended,
            Err(e) => Err(LogError::Failed {
                path: self.log.path().to_owned(),
                why: format!("the appending task failed: {e}"),
            }),
        }
    }
}
