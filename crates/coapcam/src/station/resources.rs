//! The results log as CoAP resources (docs/design.md §5, docs/station.md):
//! - `/station`: the station's name, version and software checksum, the event counter and
//!   the hash of the legally relevant parameters in force;
//! - `/station/head`: the log's head (newest id and hash), observable: published so a
//!   verifier can later find a log cut off or rewritten before it;
//! - `/station/measurements`: GET the records, newest first; the query selects
//!   (`since=ID`, `before=ID`, `limit=N`, `code=TEXT`); JSON, or CBOR by Accept;
//! - `/station/events`: GET the events (changes of legally relevant parameters), newest
//!   first (`since=ID`, `before=ID`, `limit=N`);
//! - `/station/measurements/latest`: the newest record (`null` before the first),
//!   observable: the server notifies once per new record (see [`LATEST`]);
//! - `/station/measurements/<id>`: one record; `/photo` (image/jpeg) and `/annotated`
//!   (image/png) its pictures while retention keeps them.

use std::hash::{Hash as _, Hasher as _};
use std::sync::Arc;

use coap::{Code, ContentFormat, IncomingRequest, OptionNumber, Response};
use coap_net::{Resource, Router, handler};
use serde::Serialize;

use super::log::ResultsLog;
use super::reads::{self, Kind, Picture, Refusal};
use crate::api::paths::{EVENTS, HEAD, LATEST, MEASUREMENTS, STATION};

/// The list of records.
const PATH: &str = MEASUREMENTS;

/// What gives the hash of the legally relevant parameters in force (the cameras'), for
/// `/station`.
pub(crate) type Parameters = Arc<dyn Fn() -> String + Send + Sync>;

/// Adds the resources of `log` to `router`; `parameters`, when the station has cameras.
pub(crate) fn register(
    router: &Router,
    log: &ResultsLog,
    station: &str,
    parameters: Option<Parameters>,
) {
    let name = station.to_owned();
    let me = log.clone();
    router.add(
        STATION,
        Resource::new()
            .get(handler(move |ctx| {
                let (name, log, parameters) = (name.clone(), me.clone(), parameters.clone());
                async move { identity(&name, &log, parameters.as_ref(), &ctx.request) }
            }))
            .attr("rt", "coapcam.station")
            .attr("ct", "50 60")
            .attr("title", "the station: name, version, software checksum"),
    );
    let me = log.clone();
    router.add(
        PATH,
        Resource::new()
            .get(handler(move |ctx| {
                let log = me.clone();
                async move { list(log, &ctx.request).await }
            }))
            .attr("rt", "coapcam.measurements")
            .attr("ct", "50 60")
            .attr(
                "title",
                "the results log, newest first: ?since=ID ?before=ID ?limit=N ?code=TEXT",
            ),
    );
    let me = log.clone();
    router.add(
        EVENTS,
        Resource::new()
            .get(handler(move |ctx| {
                let log = me.clone();
                async move { events(log, &ctx.request).await }
            }))
            .attr("rt", "coapcam.events")
            .attr("ct", "50 60")
            .attr(
                "title",
                "the changes of legally relevant parameters, newest first: ?since=ID ?before=ID ?limit=N",
            ),
    );
    let me = log.clone();
    router.add(
        HEAD,
        Resource::new()
            .get(handler(move |ctx| {
                let log = me.clone();
                async move { head(log, &ctx.request).await }
            }))
            .attr("rt", "coapcam.head")
            .attr("ct", "50 60")
            .attr(
                "title",
                "the results log's newest id and hash; observe for each new one",
            )
            .observable(),
    );
    let me = log.clone();
    router.add(
        LATEST,
        Resource::new()
            .get(handler(move |ctx| {
                let log = me.clone();
                async move { latest(log, &ctx.request).await }
            }))
            .attr("rt", "coapcam.measurement")
            .attr("ct", "50 60")
            .attr("title", "the newest record; observe for each new one")
            .observable(),
    );
    let me = log.clone();
    router.add(
        &format!("{PATH}/{{id}}"),
        Resource::new().get(handler(move |ctx| {
            let log = me.clone();
            let id = ctx.param("id").unwrap_or_default().to_owned();
            async move { one(log, &id, &ctx.request).await }
        })),
    );
    for which in [Picture::Photo, Picture::Annotated] {
        let me = log.clone();
        router.add(
            &format!("{PATH}/{{id}}/{}", segment(which)),
            Resource::new().get(handler(move |ctx| {
                let log = me.clone();
                let id = ctx.param("id").unwrap_or_default().to_owned();
                async move { picture(log, &id, which, &ctx.request).await }
            })),
        );
    }
}

/// `GET /station/measurements/<id>/photo` or `.../annotated`.
async fn picture(
    log: ResultsLog,
    id: &str,
    picture: Picture,
    request: &IncomingRequest,
) -> Response {
    let cf = match picture {
        Picture::Photo => ContentFormat::IMAGE_JPEG,
        Picture::Annotated => ContentFormat::IMAGE_PNG,
    };
    if let Some(accept) = request.options.accept()
        && accept != cf
    {
        return Response::diagnostic(
            Code::NOT_ACCEPTABLE,
            &format!(
                "{PATH}/{id}/{} is {} only, not {}",
                segment(picture),
                cf.0,
                accept.0
            ),
        );
    }
    match reads::picture(&log, id, picture).await {
        Ok((_, data)) => {
            let etag = etag_of(&data);
            content(data, cf, etag)
        }
        Err(refused) => refusal(&refused),
    }
}

/// A picture's last path segment.
fn segment(picture: Picture) -> &'static str {
    match picture {
        Picture::Photo => "photo",
        Picture::Annotated => "annotated",
    }
}

/// `GET /station`.
fn identity(
    station: &str,
    log: &ResultsLog,
    parameters: Option<&Parameters>,
    request: &IncomingRequest,
) -> Response {
    let cf = match negotiate(request) {
        Ok(cf) => cf,
        Err(refused) => return refused,
    };
    let identity = Identity {
        station,
        version: crate::identity::VERSION,
        software_sha256: crate::identity::SOFTWARE_SHA256,
        events: log.events(),
        parameters_sha256: parameters.map(|p| p()),
        public_key: log.public_key().map(|k| k.to_string()),
    };
    document(&identity, cf)
}

/// The station and its software, as `GET /station` names them.
#[derive(Debug, Serialize)]
struct Identity<'a> {
    station: &'a str,
    version: &'static str,
    software_sha256: &'static str,
    /// The event counter: the changes of legally relevant parameters the log holds.
    events: u64,
    /// The hash of the legally relevant parameters in force (none without cameras).
    #[serde(skip_serializing_if = "Option::is_none")]
    parameters_sha256: Option<String>,
    /// The public half of the station key that signs the records (none when unsigned).
    #[serde(skip_serializing_if = "Option::is_none")]
    public_key: Option<String>,
}

/// `GET /station/measurements`.
async fn list(log: ResultsLog, request: &IncomingRequest) -> Response {
    let cf = match negotiate(request) {
        Ok(cf) => cf,
        Err(refused) => return refused,
    };
    match reads::list(&log, request.options.uri_query(), PATH).await {
        Ok(records) => document(&records, cf),
        Err(refused) => refusal(&refused),
    }
}

/// `GET /station/events`.
async fn events(log: ResultsLog, request: &IncomingRequest) -> Response {
    let cf = match negotiate(request) {
        Ok(cf) => cf,
        Err(refused) => return refused,
    };
    match reads::events(&log, request.options.uri_query(), EVENTS).await {
        Ok(events) => document(&events, cf),
        Err(refused) => refusal(&refused),
    }
}

/// `GET /station/measurements/latest`.
async fn latest(log: ResultsLog, request: &IncomingRequest) -> Response {
    let cf = match negotiate(request) {
        Ok(cf) => cf,
        Err(refused) => return refused,
    };
    if let Some(item) = request.options.uri_query().next() {
        return Response::diagnostic(
            Code::BAD_REQUEST,
            &format!("{LATEST} takes no query ({item}); {PATH} does"),
        );
    }
    match reads::latest(&log).await {
        Ok(record) => document(&record, cf),
        Err(refused) => refusal(&refused),
    }
}

/// `GET /station/head`.
async fn head(log: ResultsLog, request: &IncomingRequest) -> Response {
    let cf = match negotiate(request) {
        Ok(cf) => cf,
        Err(refused) => return refused,
    };
    match reads::head(&log).await {
        Ok(head) => document(&head, cf),
        Err(refused) => refusal(&refused),
    }
}

/// `GET /station/measurements/<id>`.
async fn one(log: ResultsLog, id: &str, request: &IncomingRequest) -> Response {
    let cf = match negotiate(request) {
        Ok(cf) => cf,
        Err(refused) => return refused,
    };
    match reads::one(&log, id).await {
        Ok(record) => document(&record, cf),
        Err(refused) => refusal(&refused),
    }
}

/// A refusal of the results log as its CoAP response.
fn refusal(refused: &Refusal) -> Response {
    let code = match refused.kind {
        Kind::BadRequest => Code::BAD_REQUEST,
        Kind::NotFound => Code::NOT_FOUND,
        Kind::Failed => Code::INTERNAL_SERVER_ERROR,
    };
    Response::diagnostic(code, &refused.why)
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
                "the results log is application/json (50) or application/cbor (60), not {}",
                other.0
            ),
        )),
    }
}

/// `value` as a 2.05 in `cf`.
fn document<T: Serialize>(value: &T, cf: ContentFormat) -> Response {
    let body = if cf == ContentFormat::CBOR {
        let mut out = Vec::new();
        match ciborium::into_writer(value, &mut out) {
            Ok(()) => out,
            Err(e) => {
                return Response::diagnostic(Code::INTERNAL_SERVER_ERROR, &format!("CBOR: {e}"));
            }
        }
    } else {
        match serde_json::to_vec(value) {
            Ok(out) => out,
            Err(e) => {
                return Response::diagnostic(Code::INTERNAL_SERVER_ERROR, &format!("JSON: {e}"));
            }
        }
    };
    let etag = etag_of(&body);
    content(body, cf, etag)
}

fn etag_of(body: &[u8]) -> [u8; 8] {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    body.hash(&mut h);
    h.finish().to_be_bytes()
}

fn content(body: Vec<u8>, cf: ContentFormat, etag: [u8; 8]) -> Response {
    let mut r = Response::new(Code::CONTENT).with_payload(body);
    r.options
        .set_uint(OptionNumber::CONTENT_FORMAT, u32::from(cf.0));
    r.options.set(OptionNumber::ETAG, etag);
    r
}
