//! The results log as CoAP resources (docs/design.md §5, docs/station.md):
//! - `/station/measurements`: GET the records, newest first; the query selects
//!   (`since=ID`, `before=ID`, `limit=N`, `code=TEXT`); JSON, or CBOR by Accept;
//! - `/station/measurements/latest`: the newest record (`null` before the first),
//!   observable: the server notifies once per new record (see [`LATEST`]);
//! - `/station/measurements/<id>`: one record; `/photo` (image/jpeg) and `/annotated`
//!   (image/png) its pictures while retention keeps them.

use std::hash::{Hash as _, Hasher as _};

use coap::{Code, ContentFormat, IncomingRequest, OptionNumber, Response};
use coap_net::{Resource, Router, handler};
use serde::Serialize;

use super::log::{LogError, ResultsLog};
use crate::api::paths::{LATEST, MEASUREMENTS};
use crate::api::results::ListQuery;

/// The list of records.
const PATH: &str = MEASUREMENTS;

/// Adds the resources of `log` to `router`.
pub(crate) fn register(router: &Router, log: &ResultsLog) {
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
    for picture in [Picture::Photo, Picture::Annotated] {
        let me = log.clone();
        router.add(
            &format!("{PATH}/{{id}}/{}", picture.name()),
            Resource::new().get(handler(move |ctx| {
                let log = me.clone();
                let id = ctx.param("id").unwrap_or_default().to_owned();
                async move { picture.get(log, &id, &ctx.request).await }
            })),
        );
    }
}

/// A record's picture.
#[derive(Debug, Clone, Copy)]
enum Picture {
    Photo,
    Annotated,
}

impl Picture {
    fn name(self) -> &'static str {
        match self {
            Self::Photo => "photo",
            Self::Annotated => "annotated",
        }
    }

    fn format(self) -> ContentFormat {
        match self {
            Self::Photo => ContentFormat::IMAGE_JPEG,
            Self::Annotated => ContentFormat::IMAGE_PNG,
        }
    }

    async fn get(self, log: ResultsLog, id: &str, request: &IncomingRequest) -> Response {
        let id = match parse_id(id) {
            Ok(id) => id,
            Err(refused) => return refused,
        };
        let cf = self.format();
        if let Some(accept) = request.options.accept()
            && accept != cf
        {
            return Response::diagnostic(
                Code::NOT_ACCEPTABLE,
                &format!(
                    "{PATH}/{id}/{} is {} only, not {}",
                    self.name(),
                    cf.0,
                    accept.0
                ),
            );
        }
        let found = blocking(log, move |log| {
            let record = log.get(id)?;
            let data = match self {
                Self::Photo => log.photo(id)?,
                Self::Annotated => log.annotated(id)?,
            };
            Ok((record, data))
        })
        .await;
        match found {
            Ok((_, Some(data))) => {
                let etag = etag_of(&data);
                content(data, cf, etag)
            }
            Ok((None, _)) => no_record(id),
            Ok((Some(record), None)) => {
                let recorded = match self {
                    Self::Photo => record.photo_sha256.is_some(),
                    Self::Annotated => record.annotated_sha256.is_some(),
                };
                let why = if recorded {
                    format!(
                        "record {id}'s {} was pruned by the retention (its SHA-256 stays in the record)",
                        self.name()
                    )
                } else {
                    format!("record {id} has no {}", self.name())
                };
                Response::diagnostic(Code::NOT_FOUND, &why)
            }
            Err(e) => failed(&e),
        }
    }
}

/// `GET /station/measurements`.
async fn list(log: ResultsLog, request: &IncomingRequest) -> Response {
    let cf = match negotiate(request) {
        Ok(cf) => cf,
        Err(refused) => return refused,
    };
    let query = match ListQuery::parse(request.options.uri_query(), PATH) {
        Ok(q) => q,
        Err(why) => return Response::diagnostic(Code::BAD_REQUEST, &why),
    };
    match blocking(log, move |log| log.list(&query)).await {
        Ok(records) => document(&records, cf),
        Err(e) => failed(&e),
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
    match blocking(log, |log| log.latest()).await {
        Ok(record) => document(&record, cf),
        Err(e) => failed(&e),
    }
}

/// `GET /station/measurements/<id>`.
async fn one(log: ResultsLog, id: &str, request: &IncomingRequest) -> Response {
    let cf = match negotiate(request) {
        Ok(cf) => cf,
        Err(refused) => return refused,
    };
    let id = match parse_id(id) {
        Ok(id) => id,
        Err(refused) => return refused,
    };
    match blocking(log, move |log| log.get(id)).await {
        Ok(Some(record)) => document(&record, cf),
        Ok(None) => no_record(id),
        Err(e) => failed(&e),
    }
}

#[expect(
    clippy::result_large_err,
    reason = "a refusal is the Response sent; it keeps its options inline"
)]
fn parse_id(text: &str) -> Result<u64, Response> {
    match text.parse::<u64>() {
        Ok(id) if id > 0 => Ok(id),
        _ => Err(Response::diagnostic(
            Code::BAD_REQUEST,
            &format!("{text} is not a record id (a whole number from 1)"),
        )),
    }
}

fn no_record(id: u64) -> Response {
    Response::diagnostic(
        Code::NOT_FOUND,
        &format!("no record {id} in the results log"),
    )
}

fn failed(e: &LogError) -> Response {
    tracing::warn!("results log: {e}");
    Response::diagnostic(Code::INTERNAL_SERVER_ERROR, &e.public_text())
}

/// Runs `f` on the log off the executor.
async fn blocking<T: Send + 'static>(
    log: ResultsLog,
    f: impl FnOnce(&ResultsLog) -> Result<T, LogError> + Send + 'static,
) -> Result<T, LogError> {
    let path = log.path().to_owned();
    match tokio::task::spawn_blocking(move || f(&log)).await {
        Ok(result) => result,
        Err(e) => Err(LogError::Failed {
            path,
            why: format!("the reading task failed: {e}"),
        }),
    }
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
