//! The station: a camera server and what it does by itself for a parcel lane
//! (docs/station.md). The station is above the server: it uses the server, the server
//! never the station.
//! - `start`: [`Station`], the composition: the camera server ([`crate::server`]), the
//!   results log, its resources and outputs, the watcher;
//! - [`crate::api::record`] (the record of a measurement, shared with the client);
//! - [`log`]: the results log, append-only and hash-chained in SQLite, with retention;
//! - [`clock`]: the clocks the log reads (wall, monotonic, synchronised or not);
//! - `recorder`: [`Recorder`], which appends a measurement under the station's name (and
//!   is how the camera server keeps what it measures for clients);
//! - [`follow`]: the one follower of the log, and the `Sink` trait of its outputs;
//! - [`outputs`]: the list of the outputs, each with its flags ([`Outputs`]), and a
//!   configuration file's `[[output]]` tables;
//! - [`keys`]: a configuration file's key as the flag it names (its value as words);
//! - `reads`: the log's read API (list, one record, pictures, refusals), once for both
//!   front ends;
//! - `resources`: the log as CoAP resources (`/station/measurements...`);
//! - [`mqtt`]: every record published to an MQTT broker, none lost while it is away;
//! - [`line`](mod@line): a plain text line per measurement to the readers of a TCP port;
//! - [`http`]: the page and the JSON API over HTTP (`serve --http`);
//! - [`writer`]: the lock that makes a station its results log's one writer;
//! - [`signing`]: the station key that signs the records, and its public half;
//! - [`webhook`]: every record POSTed to an HTTP URL, none lost while it is away;
//! - [`postgres`]: every record copied into a PostgreSQL table, once, none lost while the
//!   server is away;
//! - [`opcua`]: an OPC UA server with the station's identity, its latest result, a
//!   method to measure now and an event per record;
//! - [`auto`]: automatic measurement's core: height maps of the table and the stillness
//!   detector that says when a parcel stands still; [`watch`]: the task that drives it.

pub mod auto;
pub mod clock;
pub mod follow;
pub mod http;
pub mod keys;
pub mod line;
pub mod log;
pub mod mqtt;
#[cfg(feature = "opcua")]
pub mod opcua;
pub mod outputs;
pub mod postgres;
pub(crate) mod reads;
mod recorder;
pub(crate) mod resources;
pub mod signing;
mod start;
mod tls;
pub mod watch;
pub mod webhook;
pub mod writer;

use std::path::{Path, PathBuf};

use self::log::Retention;
pub use outputs::{OutputError, Outputs};
pub use recorder::Recorder;
pub use start::{StartError, Station};

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

/// An output's name in the station's messages, from what it is (`webhook`, `MQTT`) and
/// its durable cursor's name (`webhook`, or `webhook/ID` for an `[[output]]` with an `id`
/// of its own: [`follow::OutputId::cursor`]): `` webhook `ID` ``, so that the messages
/// of two outputs of a kind (their backlog, their failures) say which one they are of.
fn output_name(what: &str, cursor: &str) -> String {
    match cursor.split_once('/') {
        Some((_, id)) => format!("{what} `{id}`"),
        None => what.to_owned(),
    }
}

/// What the station adds to its camera server (`serve`'s station flags).
#[derive(Debug, Clone)]
pub struct Config {
    /// The station's name, in every record (`--station-name`).
    pub name: String,
    /// The results log's file (`--results`), `None` for [`RESULTS_FILE`] in the state
    /// directory.
    pub results: Option<PathBuf>,
    /// How much of the log is kept (`--results-keep-pictures`, `--results-max-bytes`).
    pub retention: Retention,
    /// The station key's file: every record is signed with it (`--signing-key`).
    pub signing_key: Option<PathBuf>,
    /// The outputs that follow the log (`--mqtt`, `--line-output`, `--webhook`,
    /// `--postgres`).
    pub outputs: Outputs,
    /// Serve the page and the HTTP API on this address (`--http`).
    pub http: Option<std::net::SocketAddr>,
    /// The hosts the HTTP-CoAP proxy reaches besides the station's own CoAP servers
    /// (`--proxy-allow`).
    pub proxy_allow: Vec<http::proxy::Allowed>,
    /// Measure each parcel placed on the table by itself (`--auto-measure`,
    /// `--still-ms`); `None`: only when a client asks.
    pub auto_measure: Option<watch::AutoConfig>,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            name: host_name(),
            results: None,
            retention: Retention::default(),
            signing_key: None,
            outputs: Outputs::default(),
            http: None,
            proxy_allow: Vec::new(),
            auto_measure: None,
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_outputs_name_in_messages_carries_its_id_when_it_has_one() {
        assert_eq!(output_name("webhook", "webhook"), "webhook");
        assert_eq!(output_name("webhook", "webhook/wms"), "webhook `wms`");
        assert_eq!(output_name("MQTT", "mqtt/plant"), "MQTT `plant`");
    }
}
