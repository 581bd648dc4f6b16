//! `/cams/dimensions`, measurement at the edge (an extension; docs/design.md §6): `POST`
//! grabs every camera of this server, merges the clouds in the common frame, measures the
//! parcel and, when asked, reads the codes; the answer is the document of
//! `measure --json` (JSON, or CBOR by Accept), a few hundred bytes instead of the clouds.
//! `GET` (and Observe) gives the latest measurement.

use std::hash::{Hash as _, Hasher as _};
use std::sync::Arc;
use std::time::Instant;

use coap::{Code, ContentFormat, IncomingRequest, Response};
use serde_json::Value;

use super::{CamState, Cams, content, grab, lock};
use crate::report::{self, EdgeQuery, Parcel, Seen};
use crate::repr::raster;
use crate::vision::codes;

/// The path of the resource.
pub(super) const PATH: &str = "/cams/dimensions";

/// The latest measurement: its document and ETag.
pub(super) type Latest = Option<Arc<(Value, [u8; 8])>>;

impl Cams {
    /// `POST /cams/dimensions`: a new measurement with every camera of this server.
    pub(super) async fn measure(&self, request: &IncomingRequest) -> Response {
        let cf = match negotiate(request) {
            Ok(cf) => cf,
            Err(refused) => return refused,
        };
        let query = match EdgeQuery::parse(request.options.uri_query()) {
            Ok(q) => q,
            Err(why) => return Response::diagnostic(Code::BAD_REQUEST, &why),
        };
        let cams: Vec<(rgbd::Serial, Arc<CamState>)> = lock(&self.cams)
            .iter()
            .map(|(sn, c)| (*sn, c.clone()))
            .collect();
        if cams.is_empty() {
            return Response::diagnostic(Code::SERVICE_UNAVAILABLE, "no camera is connected");
        }
        let started = Instant::now();
        // The color images for the codes are grabbed and read while the clouds are.
        let codes = query.codes.then(|| {
            let tasks: Vec<_> = cams.iter().map(|(sn, cam)| read_codes(*sn, cam)).collect();
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
        });
        let merged = self.grab_merged().await;
        let grab_ms = report::ms(started.elapsed());
        let config = query.config;
        let (parcel, merged) = match tokio::task::spawn_blocking(move || {
            (Parcel::measure(&merged.cloud, &config), merged)
        })
        .await
        {
            Ok((Ok(parcel), merged)) => (parcel, merged),
            Ok((Err(e), _)) => {
                return Response::diagnostic(
                    Code::INTERNAL_SERVER_ERROR,
                    &format!("measuring: {e}"),
                );
            }
            Err(e) => {
                return Response::diagnostic(
                    Code::INTERNAL_SERVER_ERROR,
                    &format!("measuring task: {e}"),
                );
            }
        };
        let mut doc = parcel.fields(&query.billing);
        let mut warnings = merged.failed;
        doc.insert("cloud_points".into(), merged.cloud.len().into());
        doc.insert(
            "cameras".into(),
            merged
                .serials
                .iter()
                .map(ToString::to_string)
                .collect::<Vec<_>>()
                .into(),
        );
        doc.insert("frames_unix_us".into(), merged.frames_us.into());
        doc.insert("grab_ms".into(), grab_ms.into());
        if let Some(task) = codes {
            match task.await {
                Ok((seen, failed, took)) => {
                    doc.insert(
                        "codes".into(),
                        seen.iter().map(Seen::to_json).collect::<Vec<_>>().into(),
                    );
                    doc.insert("codes_ms".into(), report::ms(took).into());
                    warnings.extend(failed);
                }
                Err(e) => warnings.push(format!("code reading: {e}")),
            }
        }
        doc.insert("measure_ms".into(), report::ms(started.elapsed()).into());
        doc.insert("warnings".into(), warnings.into());
        let doc = Value::Object(doc);
        let mut h = std::collections::hash_map::DefaultHasher::new();
        doc.to_string().hash(&mut h);
        let stored = Arc::new((doc, h.finish().to_be_bytes()));
        *lock(&self.measured) = Some(stored.clone());
        let _ = self.changed.send(PATH.to_string());
        represent(&stored, cf)
    }

    /// `GET /cams/dimensions`: the latest measurement.
    pub(super) fn latest_measurement(&self, request: &IncomingRequest) -> Response {
        let cf = match negotiate(request) {
            Ok(cf) => cf,
            Err(refused) => return refused,
        };
        match lock(&self.measured).clone() {
            Some(stored) => represent(&stored, cf),
            None => Response::diagnostic(Code::NOT_FOUND, "no measurement yet: POST measures"),
        }
    }
}

/// Grabs a color image of one camera and reads the codes in it, off the executor.
fn read_codes(
    sn: rgbd::Serial,
    cam: &Arc<CamState>,
) -> tokio::task::JoinHandle<Result<(String, Vec<codes::Code>), String>> {
    let app = lock(&cam.app).clone();
    let camera = cam.camera.clone();
    tokio::task::spawn_blocking(move || match grab::color(camera.as_ref(), &app) {
        Ok(grab::Frame::Color(frame, ..)) => {
            Ok((sn.to_string(), codes::read(&raster::color_gray(&frame))))
        }
        Ok(_) => Err(format!("camera {sn}: the color grab gave no color frame")),
        Err(e) => Err(format!("camera {sn}: color for the codes: {e}")),
    })
}

/// JSON unless the request accepts CBOR; 4.06 for anything else.
#[expect(
    clippy::result_large_err,
    reason = "a refusal is the Response sent; it keeps its options inline"
)]
fn negotiate(request: &IncomingRequest) -> Result<ContentFormat, Response> {
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

fn represent(stored: &(Value, [u8; 8]), cf: ContentFormat) -> Response {
    let (doc, etag) = stored;
    let body = if cf == ContentFormat::CBOR {
        let mut out = Vec::new();
        if let Err(e) = ciborium::into_writer(doc, &mut out) {
            return Response::diagnostic(Code::INTERNAL_SERVER_ERROR, &format!("CBOR: {e}"));
        }
        out
    } else {
        doc.to_string().into_bytes()
    };
    let mut h = std::collections::hash_map::DefaultHasher::new();
    (etag, cf.0).hash(&mut h);
    content(body, cf, h.finish().to_be_bytes())
}
