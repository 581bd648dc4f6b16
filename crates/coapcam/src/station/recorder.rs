//! [`Recorder`]: what every measurement path calls once it has measured, and how the
//! camera server keeps what it measures for clients ([`Records`]).

use std::future::Future;
use std::pin::Pin;

use super::log::{LogError, ResultsLog};
use crate::api::record::{Event, NewEvent, NewRecord, Record, Trigger};
use crate::report::{EdgeQuery, Found};
use crate::server::measure::{self, Measured, Records, Rig};

/// Records measurements in the log under the station's name: what every measurement
/// path (a client's `POST /cams/dimensions`, the automatic one) calls once it has
/// measured, before it tells anyone.
#[derive(Debug, Clone)]
pub struct Recorder {
    log: ResultsLog,
    station: String,
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
            time: self.log.now(),
            station: self.station.clone(),
            trigger: measured.trigger,
            measurement: measured.measurement,
            cameras: measured.cameras,
            version: NewRecord::VERSION.to_owned(),
            software_sha256: crate::identity::SOFTWARE_SHA256.to_owned(),
            photo_jpeg: measured.photo_jpeg,
            annotated_png: measured.annotated_png,
            parameters_sha256: Some(measured.parameters_sha256),
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

impl Recorder {
    /// Measures with every camera of `rig` as `query` asks, with the photo and the
    /// annotated picture, and records it, as a client's request (trigger `request`): the
    /// new record, or `None` when it found no parcel (not recorded, as over CoAP and
    /// HTTP); an error says why nothing was measured or recorded.
    pub(crate) async fn measure_now<R: Rig>(
        &self,
        rig: &R,
        query: &EdgeQuery,
    ) -> Result<Option<Record>, String> {
        let measured = measure::measure(rig, query, Trigger::Request, true)
            .await
            .map_err(|e| format!("measuring failed: {e}"))?;
        if measured.measurement.parcel == Found::Nothing {
            return Ok(None);
        }
        self.record(measured).await.map(Some).map_err(|e| {
            tracing::error!("a measurement could not be recorded: {e}");
            format!(
                "measured, but the measurement could not be recorded: {}",
                e.public_text()
            )
        })
    }
}

/// The camera server keeps what it measures for a client in the log.
impl Records for Recorder {
    fn keep(
        &self,
        measured: Measured,
    ) -> Pin<Box<dyn Future<Output = Result<(), String>> + Send + '_>> {
        Box::pin(async move {
            self.record(measured).await.map(drop).map_err(|e| {
                tracing::error!("a measurement could not be recorded: {e}");
                e.public_text()
            })
        })
    }

    fn change(&self, event: Event) -> Result<(), String> {
        let new = NewEvent {
            time: self.log.now(),
            station: self.station.clone(),
            event,
        };
        match self.log.append_event(new) {
            Ok(recorded) => {
                tracing::info!(
                    id = recorded.id,
                    counter = recorded.counter,
                    "event: {} {} by {}",
                    recorded.event.change.method(),
                    recorded.event.document,
                    recorded.event.by
                );
                Ok(())
            }
            Err(e) => {
                tracing::error!("a parameter change could not be recorded: {e}");
                Err(e.public_text())
            }
        }
    }
}
