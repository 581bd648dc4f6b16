//! `/cams/dimensions`, measurement at the edge (an extension; docs/design.md §6): `POST`
//! grabs every camera of this server, merges the clouds in the common frame, measures the
//! parcel and, when asked, reads the codes; the answer is the document of
//! `measure --json` (JSON, or CBOR by Accept), about a kilobyte instead of the clouds.
//! `GET` (and Observe) gives the latest measurement. `Cams` serves it with these parts;
//! `Cams::measure_now` makes one in process, and the `POST` handler wraps it.

use std::hash::{Hash as _, Hasher as _};
use std::sync::Arc;
use std::time::{Duration, Instant};

use coap::{Code, ContentFormat, IncomingRequest, Response};
use geometry::DimensionError;
use rgbd::{Camera, Serial};
use tokio::task::JoinHandle;

use super::budget::Busy;
use super::grab::{self, Frame};
use crate::documents::AppConfig;
use crate::report::{Measurement, MeasurementError, Seen};
use crate::repr::raster;
use crate::vision::codes;

/// The path of the resource.
pub(super) const PATH: &str = crate::api::paths::DIMENSIONS;

/// The latest measurement and its ETag.
pub(super) type Latest = Option<Arc<(Measurement, [u8; 8])>>;

/// Why the server could not measure.
#[derive(Debug, thiserror::Error)]
pub enum EdgeError {
    /// No camera is connected.
    #[error("no camera is connected")]
    NoCamera,
    /// Every camera's grab failed.
    #[error("no camera gave a cloud: {}", .0.join("; "))]
    NoCloud(Vec<String>),
    /// The grabs in progress hold the memory budget.
    #[error(transparent)]
    Busy(#[from] Busy),
    /// The measurement failed (its thresholds are checked by the query's ranges).
    #[error("measuring: {0}")]
    Measuring(#[from] DimensionError),
    /// The measuring task panicked or was cancelled.
    #[error("measuring task: {0}")]
    Task(#[from] tokio::task::JoinError),
    /// The measurement could not be encoded.
    #[error(transparent)]
    Encoding(#[from] MeasurementError),
}

impl EdgeError {
    /// The answer to a `POST` that failed so: 5.03 (with Max-Age when busy) when there is
    /// nothing to measure with yet, 5.00 otherwise.
    pub(super) fn response(&self) -> Response {
        match self {
            Self::Busy(busy) => busy.response(),
            Self::NoCamera | Self::NoCloud(_) => {
                Response::diagnostic(Code::SERVICE_UNAVAILABLE, &self.to_string())
            }
            Self::Measuring(_) | Self::Task(_) | Self::Encoding(_) => {
                Response::diagnostic(Code::INTERNAL_SERVER_ERROR, &self.to_string())
            }
        }
    }
}

/// Grabs a color image of each camera and reads the codes in it, all at once and off the
/// executor: each code once with the cameras that read it, what failed, and how long it
/// took since `started`.
pub(super) fn read_codes(
    cameras: Vec<(Serial, Arc<dyn Camera>, AppConfig)>,
    started: Instant,
) -> JoinHandle<(Vec<Seen>, Vec<String>, Duration)> {
    let tasks: Vec<_> = cameras
        .into_iter()
        .map(|(sn, camera, app)| {
            tokio::task::spawn_blocking(move || match grab::color(camera.as_ref(), &app) {
                Ok(Frame::Color(frame, ..)) => {
                    Ok((sn.to_string(), codes::read(&raster::color_gray(&frame))))
                }
                Ok(_) => Err(format!("camera {sn}: the color grab gave no color frame")),
                Err(e) => Err(format!("camera {sn}: color for the codes: {e}")),
            })
        })
        .collect();
    tokio::spawn(async move {
        let mut read = Vec::new();
        let mut failed = Vec::new();
        for task in tasks {
            match task.await {
                Ok(Ok(one)) => read.push(one),
                Ok(Err(e)) => failed.push(e),
                Err(e) => failed.push(format!("code reading task: {e}")),
            }
        }
        (Seen::gather(read), failed, started.elapsed())
    })
}

/// JSON unless the request accepts CBOR; 4.06 for anything else.
#[expect(
    clippy::result_large_err,
    reason = "a refusal is the Response sent; it keeps its options inline"
)]
pub(super) fn negotiate(request: &IncomingRequest) -> Result<ContentFormat, Response> {
    match request.options.accept() {
        None | Some(ContentFormat::JSON) => Ok(ContentFormat::JSON),
        Some(ContentFormat::CBOR) => Ok(ContentFormat::CBOR),
        Some(other) => Err(Response::diagnostic(
            Code::NOT_ACCEPTABLE,
            &format!(
                "{PATH} is application/json (50) or application/cbor (60), not {}",
                other.0
            ),
        )),
    }
}

/// The measurement with its ETag (a hash of its JSON document).
pub(super) fn stored(m: Measurement) -> Result<(Measurement, [u8; 8]), MeasurementError> {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    m.to_json()?.hash(&mut h);
    Ok((m, h.finish().to_be_bytes()))
}

/// The document in `cf` (JSON or CBOR), with its ETag: the measurement's, distinct per
/// format.
pub(super) fn body(
    stored: &(Measurement, [u8; 8]),
    cf: ContentFormat,
) -> Result<(Vec<u8>, [u8; 8]), MeasurementError> {
    let (m, etag) = stored;
    let body = if cf == ContentFormat::CBOR {
        m.to_cbor()?
    } else {
        m.to_json()?.into_bytes()
    };
    let mut h = std::collections::hash_map::DefaultHasher::new();
    (etag, cf.0).hash(&mut h);
    Ok((body, h.finish().to_be_bytes()))
}
