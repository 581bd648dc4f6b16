//! `/cams/dimensions`, measurement at the edge (an extension; docs/design.md §6): `POST`
//! grabs every camera of this server, merges the clouds in the common frame, measures the
//! parcel and, when asked, reads the codes; the answer is the document of
//! `measure --json` (JSON, or CBOR by Accept), a few hundred bytes instead of the clouds.
//! `GET` (and Observe) gives the latest measurement. `Cams` serves it with these parts.

use std::hash::{Hash as _, Hasher as _};
use std::sync::Arc;
use std::time::{Duration, Instant};

use coap::{Code, ContentFormat, IncomingRequest, Response};
use rgbd::{Camera, Serial};
use serde_json::Value;
use tokio::task::JoinHandle;

use super::config::AppConfig;
use super::grab::{self, Frame};
use crate::report::Seen;
use crate::repr::raster;
use crate::vision::codes;

/// The path of the resource.
pub(super) const PATH: &str = "/cams/dimensions";

/// The latest measurement: its document and ETag.
pub(super) type Latest = Option<Arc<(Value, [u8; 8])>>;

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

/// The document in `cf` (JSON or CBOR), with its ETag: the measurement's, distinct per
/// format.
pub(super) fn body(
    stored: &(Value, [u8; 8]),
    cf: ContentFormat,
) -> Result<(Vec<u8>, [u8; 8]), String> {
    let (doc, etag) = stored;
    let body = if cf == ContentFormat::CBOR {
        let mut out = Vec::new();
        ciborium::into_writer(doc, &mut out).map_err(|e| format!("CBOR: {e}"))?;
        out
    } else {
        doc.to_string().into_bytes()
    };
    let mut h = std::collections::hash_map::DefaultHasher::new();
    (etag, cf.0).hash(&mut h);
    Ok((body, h.finish().to_be_bytes()))
}
