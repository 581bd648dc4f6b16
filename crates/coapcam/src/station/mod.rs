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

    /// Issue 51, item 4: one record, every output of the station, the same three numbers:
    /// its parcel's, rounded to the division (5 mm), for the parcel measured 322.6 x 241.3
    /// x 99.8 mm. The record's JSON (what the API, CoAP, MQTT, the webhook and the
    /// PostgreSQL table's `body` carry) at its top level and in its first parcel, a
    /// webhook template's pointers, the line output, OPC UA's `LatestResult` and its
    /// event's message, and the text of `measure` and the picture's legend. (`results
    /// --csv` and the page are outside the library: tests/it's
    /// `requests_are_recorded_served_listed_and_verified` and
    /// `the_page_shows_the_numbers_to_bill_on` check them against the record.)
    #[test]
    fn every_output_carries_the_same_numbers_to_bill_on() {
        let record = crate::api::record::tests::billed_record();
        let json = serde_json::to_value(&record).expect("JSON");
        let m = &json["measurement"];
        let keys = ["length_mm", "width_mm", "height_mm"];
        let billed = [325.0, 240.0, 100.0];
        assert_eq!(keys.map(|k| m[k].as_f64()), billed.map(Some), "{m}");
        let parcel = &m["parcels"][0];
        assert_eq!(keys.map(|k| parcel[k].as_f64()), billed.map(Some), "{m}");
        assert_eq!(m["division_mm"].as_f64(), Some(5.0), "{m}");
        let template = webhook::Template::parse(
            r#"{"l": "/measurement/length_mm", "w": "/measurement/width_mm", "h": "/measurement/height_mm"}"#,
        )
        .expect("a template");
        assert_eq!(
            template.fill(&json),
            serde_json::json!({"l": 325.0, "w": 240.0, "h": 100.0})
        );
        let text = "325 x 240 x 100 mm";
        let line = line::format_line(&line::LineFields::of(&record));
        assert_eq!(
            line.split(',')
                .skip(2)
                .take(3)
                .collect::<Vec<_>>()
                .join(" x ")
                + " mm",
            text,
            "{line:?}"
        );
        let reported = record.measurement.reported().expect("measured");
        assert_eq!(reported.dimensions_text(), text);
        assert_eq!(
            crate::report::box_caption(&reported.dimensions(0), reported.division_mm),
            format!("measured box {text}, yaw 0.0 deg")
        );
        #[cfg(feature = "opcua")]
        {
            use ::opcua::types::Variant;
            let values = opcua::result_values(&record);
            assert_eq!(
                values[2..6],
                [325.0, 240.0, 100.0, 5.0].map(Variant::Double),
                "LengthMm, WidthMm, HeightMm, DivisionMm"
            );
        }
    }

    #[test]
    fn an_outputs_name_in_messages_carries_its_id_when_it_has_one() {
        assert_eq!(output_name("webhook", "webhook"), "webhook");
        assert_eq!(output_name("webhook", "webhook/wms"), "webhook `wms`");
        assert_eq!(output_name("MQTT", "mqtt/plant"), "MQTT `plant`");
    }
}
