//! The station over HTTP/1.1 (`serve --http`, docs/station.md "HTTP"): the page at `/`
//! and a JSON API over the results log and the cameras, on hyper.
//! - `GET /api/measurements` (`?since=ID&before=ID&limit=N&code=TEXT`), `GET
//!   /api/measurements/<id>`, `.../<id>/photo.jpg`, `.../<id>/annotated.png`: the log, the
//!   same records as `/station/measurements`;
//! - `POST /api/measure`: measures now, as `POST /cams/dimensions` does, records it and
//!   answers the record (201), or 200 with the measurement and no record when it found
//!   no parcel; from this machine only unless configuration is open;
//! - `GET /api/cameras`, `GET /api/cameras/<serial>/color.jpg`: the cameras and a new
//!   color image of one;
//! - `GET /api/station`: the station's name and what this client may do;
//! - `GET /api/log/head`: the results log's head (newest id and hash);
//! - `GET /api/events`: every new record as a Server-Sent Event (`event: measurement`,
//!   `id:` the record's id; `Last-Event-ID` or `?since=ID` resumes).
//!
//! - `/hc/<coap URI>`: the HTTP-CoAP proxy of RFC 8075 ([`proxy`]).
//!
//! Errors are JSON, `{"error": "..."}`, with a 4xx or 5xx status.
//!
//! Bounds ([`limits`]): connections per client and in all ([`CONNECTIONS_PER_CLIENT`],
//! [`MAX_CONNECTIONS`]; over them 429 or 503 and closed), event streams likewise
//! ([`EVENT_STREAMS_PER_CLIENT`], [`MAX_EVENT_STREAMS`]), a write timeout on every
//! connection ([`WRITE_TIMEOUT`]), and lists longer than a page written as they are read.

pub mod limits;
pub mod proxy;

use std::collections::HashMap;
use std::convert::Infallible;
use std::net::{IpAddr, SocketAddr};
use std::pin::Pin;
use std::sync::{Arc, Mutex, PoisonError};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use bytes::Bytes;
use http_body_util::combinators::BoxBody;
use http_body_util::{BodyExt as _, Full, Limited};
use hyper::body::{Body, Frame, Incoming};
use hyper::header::{self, HeaderValue};
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::rt::{TokioIo, TokioTimer};
use serde::Serialize;
use tokio::net::TcpListener;
use tokio::sync::{Semaphore, mpsc};
use tokio::task::{JoinHandle, JoinSet};

use super::Recorder;
use super::follow::{self, Next, Sink, Start};
use super::log::ResultsLog;
use super::reads::{self, Kind, Picture, Refusal};
use crate::api::record::{Record, Trigger};
use crate::api::results::{ListQuery, MAX_LIST};
use crate::report::EdgeQuery;
use crate::repr::raster;
use crate::server::measure::Rig;

/// The page, served at `/`.
const PAGE: &str = include_str!("page.html");

/// The most bytes a request's body may have (413 beyond).
pub const MAX_BODY: usize = 64 * 1024;

/// The most connections served at once; more are answered 503 and closed.
pub const MAX_CONNECTIONS: usize = 1024;

/// The most connections one client (an IPv4 address or an IPv6 /64) has served at once;
/// more are answered 429 and closed.
pub const CONNECTIONS_PER_CLIENT: usize = 64;

/// The most event streams (`/api/events`) open at once: a quarter of the connections, so
/// that streams never take every place (503 beyond).
pub const MAX_EVENT_STREAMS: usize = 256;

/// The most event streams one client has open at once (429 beyond). A browser keeps at
/// most 6 connections to a server, one a page for its stream.
pub const EVENT_STREAMS_PER_CLIENT: usize = 16;

/// How long a client may take no bytes of an answer or an event stream before its
/// connection is dropped, and what was held for it freed.
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(10);

/// What hyper buffers of an answer for one connection, at most (and the longest request
/// head it reads).
const CONNECTION_BUFFER: usize = 64 * 1024;

/// Records read from the log and written at a time by a streamed list (about 2 KB each).
const LIST_PAGE: usize = 16;

/// Pages of lists read from the log at once. The log has one database connection, so
/// more would only wait for it, each holding a thread of the blocking pool (300 clients
/// asking at once held 300 threads).
const LIST_READERS: usize = 2;

/// Refused connections whose answer (429, 503) is under way at once (each waits at most
/// [`REFUSE_WAIT`] for the request's head, a few KiB); beyond, a refused connection is
/// closed without one.
const REFUSING: usize = 1024;

/// The first wait after accepting a connection failed; it doubles up to
/// [`ACCEPT_WAIT_MAX`] while accepting fails (a connection that ends cuts it short).
const ACCEPT_WAIT_MIN: Duration = Duration::from_millis(100);

/// The longest wait between two tries to accept a connection while accepting fails.
const ACCEPT_WAIT_MAX: Duration = Duration::from_secs(2);

/// How long a refused connection may take to get its answer.
const REFUSE_WAIT: Duration = Duration::from_secs(2);

/// How long a client may take to send a request's head.
const HEAD_TIMEOUT: Duration = Duration::from_secs(10);

/// How often an event stream without news says it is alive (a comment line).
const KEEP_ALIVE: Duration = Duration::from_secs(15);

/// How long a color image grabbed for `/api/cameras/<serial>/color.jpg` is served again
/// to other requests (many pages open at once make one grab).
const COLOR_FRESH: Duration = Duration::from_millis(300);

/// JPEG quality of the cameras' live images.
const COLOR_QUALITY: u8 = 80;

/// The address of `--http`: `ADDR:PORT`, or a bare port for the loopback address.
pub fn parse_listen(text: &str) -> Result<SocketAddr, String> {
    if let Ok(port) = text.parse::<u16>() {
        return Ok(SocketAddr::from(([127, 0, 0, 1], port)));
    }
    text.parse::<SocketAddr>().map_err(|_| {
        format!("{text}: an HTTP address is ADDR:PORT (e.g. 127.0.0.1:8080, [::]:8080) or a port")
    })
}

/// The HTTP server of a station: serving until dropped.
#[derive(Debug)]
pub struct HttpServer {
    addr: SocketAddr,
    task: JoinHandle<()>,
}

impl Drop for HttpServer {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// What the server serves.
struct App<R> {
    rig: Arc<R>,
    recorder: Recorder,
    /// Measuring and configuring from anywhere (`--allow-unauthenticated-config`), not
    /// only from this machine.
    open: bool,
    /// The newest color image of each camera, for [`COLOR_FRESH`].
    colors: Mutex<HashMap<String, ColorSlot>>,
    /// Whom the proxy reaches.
    reach: proxy::Reach,
    /// The proxy's requests under way, per client and in all.
    fetches: Arc<Mutex<limits::Counter>>,
    /// The event streams open, per client and in all.
    streams: Arc<Mutex<limits::Counter>>,
    /// The reads of lists' pages under way ([`LIST_READERS`]).
    list_readers: Arc<Semaphore>,
}

/// A camera's newest live color image (JPEG) and when it was grabbed; held while a grab
/// is under way, so that requests meanwhile wait for that grab.
type ColorSlot = Arc<tokio::sync::Mutex<Option<(Instant, Bytes)>>>;

/// An answer's body: its bytes, or an error that aborts the connection (a streamed list
/// that could not be read on).
type AnswerBody = BoxBody<Bytes, std::io::Error>;

type Answer = Response<AnswerBody>;

impl HttpServer {
    /// Listens on `addr` and serves the log of `recorder` and the cameras of `rig`;
    /// `open` lets any client measure (otherwise only clients on this machine); the proxy
    /// reaches the servers of `reach`.
    pub async fn start<R: Rig>(
        addr: SocketAddr,
        rig: Arc<R>,
        recorder: Recorder,
        open: bool,
        reach: proxy::Reach,
    ) -> std::io::Result<Self> {
        let listener = TcpListener::bind(addr).await?;
        let addr = listener.local_addr()?;
        let app = Arc::new(App {
            rig,
            recorder,
            open,
            colors: Mutex::default(),
            reach,
            fetches: limits::Counter::new("proxied requests", proxy::PER_CLIENT, proxy::IN_ALL),
            streams: limits::Counter::new(
                "event streams",
                EVENT_STREAMS_PER_CLIENT,
                MAX_EVENT_STREAMS,
            ),
            list_readers: Arc::new(Semaphore::new(LIST_READERS)),
        });
        let task = tokio::spawn(accept(listener, app));
        Ok(Self { addr, task })
    }

    /// The address it listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }
}

/// Accepts connections and serves each on a task of its own, within
/// [`CONNECTIONS_PER_CLIENT`] and [`MAX_CONNECTIONS`], or less when the process may open
/// fewer files ([`limits::Bounds`]); the connections end with this task (their set is
/// dropped with it). When accepting fails (out of files all the same: other outputs, other
/// processes), it says so once, and tries again as a connection ends or after a wait that
/// doubles up to [`ACCEPT_WAIT_MAX`].
async fn accept<R: Rig>(listener: TcpListener, app: Arc<App<R>>) {
    let files = limits::open_files();
    let bounds = limits::Bounds::within(files, MAX_CONNECTIONS, CONNECTIONS_PER_CLIENT, REFUSING);
    if bounds.connections < MAX_CONNECTIONS {
        tracing::info!(
            "http: serving at most {} connections, {} to one client: this process may open {} files (LimitNOFILE= of the unit, ulimit -n), and its connections take at most half of them ({MAX_CONNECTIONS} connections need a limit of {} or more)",
            bounds.connections,
            bounds.per_client,
            files.unwrap_or_default(),
            MAX_CONNECTIONS * 5 / 2,
        );
    }
    let counter = limits::Counter::new("connections", bounds.per_client, bounds.connections);
    let refusing = Arc::new(Semaphore::new(bounds.refusing));
    let mut connections = JoinSet::new();
    // While accepting fails: the next wait.
    let mut failing: Option<Duration> = None;
    loop {
        while connections.try_join_next().is_some() {}
        let (stream, peer) = match listener.accept().await {
            Ok(accepted) => {
                if failing.take().is_some() {
                    tracing::info!("http: accepting connections again");
                }
                accepted
            }
            Err(e) => {
                let wait = match failing {
                    Some(wait) => (wait * 2).min(ACCEPT_WAIT_MAX),
                    None => {
                        say_accept_failed(&e, files);
                        ACCEPT_WAIT_MIN
                    }
                };
                failing = Some(wait);
                // A connection that ends frees its file: try again then, or after the wait.
                tokio::select! {
                    _ = connections.join_next(), if !connections.is_empty() => {}
                    () = tokio::time::sleep(wait) => {}
                }
                continue;
            }
        };
        let slot = match limits::Counter::start(&counter, peer.ip()) {
            Ok(slot) => slot,
            Err(full) => {
                if let Ok(permit) = refusing.clone().try_acquire_owned() {
                    connections.spawn(async move {
                        refuse(stream, full, bounds).await;
                        drop(permit);
                    });
                }
                continue;
            }
        };
        let app = app.clone();
        connections.spawn(async move {
            let service = hyper::service::service_fn(move |request| {
                let app = app.clone();
                async move { Ok::<_, Infallible>(app.answer(request, peer).await) }
            });
            let io = limits::WriteTimeout::new(stream, WRITE_TIMEOUT);
            let served = hyper::server::conn::http1::Builder::new()
                .timer(TokioTimer::new())
                .header_read_timeout(HEAD_TIMEOUT)
                .max_buf_size(CONNECTION_BUFFER)
                .serve_connection(TokioIo::new(io), service)
                .await;
            if let Err(e) = served {
                tracing::debug!("http: connection from {peer}: {e}");
            }
            drop(slot);
        });
    }
}

/// Says once that accepting a connection failed (`e`), and what to do when the process is
/// out of files (it may open `files`).
fn say_accept_failed(e: &std::io::Error, files: Option<u64>) {
    let out_of_files = [nix::errno::Errno::EMFILE, nix::errno::Errno::ENFILE]
        .into_iter()
        .any(|n| e.raw_os_error() == Some(n as i32));
    if out_of_files {
        let limit = files.map_or_else(String::new, |n| format!(", of the {n} it may open"));
        tracing::warn!(
            "http: accepting a connection: {e} (this process has every file open{limit}): new connections wait until one ends; raise the limit (LimitNOFILE= of the unit, ulimit -n). Said once, until one is accepted"
        );
    } else {
        tracing::warn!(
            "http: accepting a connection: {e}; trying again. Said once, until one is accepted"
        );
    }
}

/// Answers a connection over its bound 429 (its client's) or 503 (the station's) and
/// closes it, within [`REFUSE_WAIT`]. The request's head is read first (up to 8 KiB), so
/// that closing does not reset the connection before the client has read the answer.
async fn refuse(mut stream: tokio::net::TcpStream, full: limits::Full, bounds: limits::Bounds) {
    use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
    let (status, why) = match full {
        limits::Full::Client => (
            "429 Too Many Requests",
            format!(
                "this client (its IPv4 address or IPv6 /64) has {} connections open, the most the station serves one client: close one, or try again later",
                bounds.per_client
            ),
        ),
        limits::Full::All => (
            "503 Service Unavailable",
            format!(
                "the station serves {} connections already, the most it serves: try again later",
                bounds.connections
            ),
        ),
    };
    let body = serde_json::json!({ "error": why }).to_string();
    let answer = format!(
        "HTTP/1.1 {status}\r\nServer: coapcam\r\nContent-Type: application/json\r\nContent-Length: {}\r\nRetry-After: 10\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    let _ = tokio::time::timeout(REFUSE_WAIT, async {
        let mut head = Vec::new();
        let mut buf = [0u8; 1024];
        while head.len() < 8 * 1024 && !head.windows(4).any(|w| w == b"\r\n\r\n") {
            match stream.read(&mut buf).await? {
                0 => break,
                n => head.extend_from_slice(&buf[..n]),
            }
        }
        stream.write_all(answer.as_bytes()).await?;
        stream.shutdown().await
    })
    .await;
}

/// Whether `peer` is on this machine.
fn is_local(peer: SocketAddr) -> bool {
    match peer.ip() {
        IpAddr::V4(v4) => v4.is_loopback(),
        IpAddr::V6(v6) => v6
            .to_ipv4_mapped()
            .map_or_else(|| v6.is_loopback(), |v4| v4.is_loopback()),
    }
}

impl<R: Rig> App<R> {
    async fn answer(&self, request: Request<Incoming>, peer: SocketAddr) -> Answer {
        let path = request.uri().path().to_owned();
        if path.starts_with(proxy::PREFIX) {
            return self.proxy(request, peer).await;
        }
        let query = request.uri().query().unwrap_or("").to_owned();
        let segments: Vec<&str> = path.trim_end_matches('/').split('/').skip(1).collect();
        let get = request.method() == Method::GET || request.method() == Method::HEAD;
        let post = request.method() == Method::POST;
        let mut answer = match (segments.as_slice(), get, post) {
            ([] | [""], true, _) => page(),
            (["api", "measurements"], true, _) => self.list(&query).await,
            (["api", "measurements", id], true, _) => self.one(id).await,
            (["api", "measurements", id, picture], true, _) => {
                let if_none_match = request.headers().get(header::IF_NONE_MATCH).cloned();
                self.picture(id, picture, if_none_match).await
            }
            (["api", "measure"], _, true) => self.measure(request, &query, peer).await,
            (["api", "cameras"], true, _) => self.cameras(),
            (["api", "cameras", serial, "color.jpg"], true, _) => {
                self.live(serial, Live::Color).await
            }
            (["api", "cameras", serial, "depth.jpg"], true, _) => {
                self.live(serial, Live::Depth).await
            }
            (["api", "station"], true, _) => self.station(peer),
            (["api", "log", "head"], true, _) => match reads::head(self.recorder.log()).await {
                Ok(head) => json(StatusCode::OK, &head),
                Err(refused) => refusal(&refused),
            },
            (["api", "log", "events"], true, _) => match query_items(&query) {
                Ok(items) => {
                    match reads::events(self.recorder.log(), &items, "/api/log/events").await {
                        Ok(events) => json(StatusCode::OK, &events),
                        Err(refused) => refusal(&refused),
                    }
                }
                Err(why) => error(StatusCode::BAD_REQUEST, &why),
            },
            (["api", "events"], true, _) => {
                let last = request
                    .headers()
                    .get("last-event-id")
                    .and_then(|v| v.to_str().ok())
                    .map(str::to_owned);
                self.events(&query, last.as_deref(), peer)
            }
            ([] | [""] | ["api", ..], _, _) if known(&segments) => error(
                StatusCode::METHOD_NOT_ALLOWED,
                &format!("{} does not take {}", path, request.method()),
            ),
            _ => error(
                StatusCode::NOT_FOUND,
                &format!("no such page or resource: {path} (the API is under /api/)"),
            ),
        };
        answer
            .headers_mut()
            .insert(header::SERVER, HeaderValue::from_static("coapcam"));
        answer
    }

    /// `GET /api/measurements`.
    async fn list(&self, query: &str) -> Answer {
        let items = match query_items(query) {
            Ok(items) => items,
            Err(why) => return error(StatusCode::BAD_REQUEST, &why),
        };
        let mut query = match ListQuery::parse(&items, "/api/measurements") {
            Ok(query) => query,
            Err(why) => return error(StatusCode::BAD_REQUEST, &why),
        };
        // The first page before the answer, so that a log that cannot be read is a 500.
        let wanted = query.limit.clamp(1, MAX_LIST);
        query.limit = wanted.min(LIST_PAGE);
        let first = match read_page(self.recorder.log(), &query, &self.list_readers).await {
            Ok(records) => records,
            Err(refused) => return refusal(&refused),
        };
        if first.len() < query.limit || first.len() >= wanted {
            // The whole list in one page: written whole, with its length.
            return json(StatusCode::OK, &first);
        }
        let (tx, rx) = mpsc::channel(1);
        tokio::spawn(stream_list(
            self.recorder.log().clone(),
            self.list_readers.clone(),
            query,
            wanted,
            first,
            tx,
        ));
        let mut answer = Response::new(BoxBody::new(Streamed(rx)));
        let h = answer.headers_mut();
        h.insert(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/json"),
        );
        h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
        answer
    }

    /// `GET /api/measurements/<id>`.
    async fn one(&self, id: &str) -> Answer {
        match reads::one(self.recorder.log(), id).await {
            Ok(record) => json(StatusCode::OK, &record),
            Err(refused) => refusal(&refused),
        }
    }

    /// `GET /api/measurements/<id>/photo.jpg` and `.../annotated.png`.
    async fn picture(&self, id: &str, name: &str, if_none_match: Option<HeaderValue>) -> Answer {
        let (picture, ct) = match name {
            "photo.jpg" => (Picture::Photo, "image/jpeg"),
            "annotated.png" => (Picture::Annotated, "image/png"),
            _ => {
                return error(
                    StatusCode::NOT_FOUND,
                    &format!("a record has photo.jpg and annotated.png, not {name}"),
                );
            }
        };
        let (record, data) = match reads::picture(self.recorder.log(), id, picture).await {
            Ok(found) => found,
            Err(refused) => return refusal(&refused),
        };
        let sha = match picture {
            Picture::Photo => &record.photo_sha256,
            Picture::Annotated => &record.annotated_sha256,
        };
        // A record's picture never changes: its SHA-256 is its ETag.
        let etag = sha.as_ref().map(|s| format!("\"{s}\""));
        let mut answer = match (&etag, if_none_match) {
            (Some(etag), Some(given)) if given.as_bytes() == etag.as_bytes() => {
                let mut a = Response::new(empty());
                *a.status_mut() = StatusCode::NOT_MODIFIED;
                a
            }
            _ => bytes(ct, data),
        };
        if let Some(etag) = etag.and_then(|e| HeaderValue::from_str(&e).ok()) {
            answer.headers_mut().insert(header::ETAG, etag);
        }
        answer.headers_mut().insert(
            header::CACHE_CONTROL,
            HeaderValue::from_static("public, max-age=31536000, immutable"),
        );
        answer
    }

    /// `POST /api/measure`: measured, recorded, answered with the record (a measurement
    /// that found no parcel: answered, not recorded).
    async fn measure(&self, request: Request<Incoming>, query: &str, peer: SocketAddr) -> Answer {
        if !self.open && !is_local(peer) {
            return error(
                StatusCode::FORBIDDEN,
                "measuring is accepted only from the station's own machine (its operator can allow it with serve --allow-unauthenticated-config)",
            );
        }
        if let Some(refused) = too_large(&request) {
            return refused;
        }
        // The body says nothing (the query does) but is read, within bounds, so that the
        // connection can go on.
        if let Err(e) = Limited::new(request.into_body(), MAX_BODY).collect().await {
            if e.downcast_ref::<http_body_util::LengthLimitError>()
                .is_some()
            {
                return body_too_large();
            }
            return error(StatusCode::BAD_REQUEST, &format!("reading the body: {e}"));
        }
        let items = match query_items(query) {
            Ok(items) => items,
            Err(why) => return error(StatusCode::BAD_REQUEST, &why),
        };
        let query = match EdgeQuery::parse(&items) {
            Ok(q) => q,
            Err(why) => return error(StatusCode::BAD_REQUEST, &why),
        };
        let measured = match crate::server::measure::measure(
            self.rig.as_ref(),
            &query,
            Trigger::Request,
            true,
        )
        .await
        {
            Ok(measured) => measured,
            Err(e) => return error(StatusCode::SERVICE_UNAVAILABLE, &e.to_string()),
        };
        // An empty table (setting up) is no result, as over CoAP and for --auto-measure:
        // answered 200 with the measurement ("parcel": "nothing"), not recorded, and so
        // not published.
        if measured.measurement.parcel == crate::report::Found::Nothing {
            tracing::info!("POST /api/measure found no parcel: not recorded");
            return json(StatusCode::OK, &measured.measurement);
        }
        match self.recorder.record(measured).await {
            Ok(record) => {
                let mut answer = json(StatusCode::CREATED, &record);
                if let Ok(location) =
                    HeaderValue::from_str(&format!("/api/measurements/{}", record.id))
                {
                    answer.headers_mut().insert(header::LOCATION, location);
                }
                answer
            }
            Err(e) => {
                tracing::error!("a measurement could not be recorded: {e}");
                error(
                    StatusCode::SERVICE_UNAVAILABLE,
                    &format!(
                        "measured, but the measurement could not be recorded: {}",
                        e.public_text()
                    ),
                )
            }
        }
    }

    /// `GET /api/cameras`.
    fn cameras(&self) -> Answer {
        let cameras: Vec<CameraInfo> = self
            .rig
            .cameras()
            .into_iter()
            .map(|cam| {
                let calibrated = cam.transformation != geometry::Transformation::identity();
                let mut warnings = Vec::new();
                if !calibrated {
                    warnings.push(
                        "not calibrated: its 3d-transformation is the identity (run coapcam calibrate); automatic measurement leaves it out"
                            .to_owned(),
                    );
                }
                let settings = |json: String| {
                    serde_json::from_str(&json).unwrap_or(serde_json::Value::Null)
                };
                CameraInfo {
                    serial: cam.serial.to_string(),
                    model: cam.camera.model().to_owned(),
                    color: settings(cam.camera.color_settings().to_json()),
                    depth: settings(cam.camera.depth_settings().to_json()),
                    calibrated,
                    transformation: cam.transformation,
                    warnings,
                }
            })
            .collect();
        json(StatusCode::OK, &cameras)
    }

    /// `GET /api/cameras/<serial>/color.jpg` and `depth.jpg`: a new image (or one at most
    /// [`COLOR_FRESH`] old); depth colour-mapped, near blue and far red, with its scale.
    async fn live(&self, serial: &str, kind: Live) -> Answer {
        let Some(cam) = self
            .rig
            .cameras()
            .into_iter()
            .find(|c| c.serial.to_string() == serial)
        else {
            return error(
                StatusCode::NOT_FOUND,
                &format!("no camera {serial} is connected"),
            );
        };
        let slot = self
            .colors
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .entry(format!("{serial}/{kind:?}"))
            .or_default()
            .clone();
        let mut newest = slot.lock().await;
        if let Some((at, jpeg)) = newest.as_ref()
            && at.elapsed() < COLOR_FRESH
        {
            return bytes_no_store("image/jpeg", jpeg.clone());
        }
        let encoded = match kind {
            Live::Color => {
                let shot = match self.rig.shot(cam.serial).await {
                    Ok(shot) => shot,
                    Err(why) => return error(StatusCode::SERVICE_UNAVAILABLE, &why),
                };
                tokio::task::spawn_blocking(move || {
                    raster::color_jpeg(&shot.frame, COLOR_QUALITY).map_err(|e| e.to_string())
                })
                .await
            }
            Live::Depth => tokio::task::spawn_blocking(move || depth_jpeg(&cam)).await,
        };
        match encoded {
            Ok(Ok(jpeg)) => {
                let jpeg = Bytes::from(jpeg);
                *newest = Some((Instant::now(), jpeg.clone()));
                bytes_no_store("image/jpeg", jpeg)
            }
            Ok(Err(why)) => error(
                StatusCode::SERVICE_UNAVAILABLE,
                &format!("camera {serial}: {why}"),
            ),
            Err(e) => error(
                StatusCode::INTERNAL_SERVER_ERROR,
                &format!("image task: {e}"),
            ),
        }
    }

    /// `GET /api/station`: who the station is and what this client may do.
    fn station(&self, peer: SocketAddr) -> Answer {
        let local = is_local(peer);
        json(
            StatusCode::OK,
            &serde_json::json!({
                "station": self.recorder.station(),
                "version": crate::identity::VERSION,
                "software_sha256": crate::identity::SOFTWARE_SHA256,
                "newest": self.recorder.log().newest(),
                "events": self.recorder.log().events(),
                "parameters_sha256": self.rig.parameters_sha256(),
                "public_key": self.recorder.log().public_key().map(|k| k.to_string()),
                "read": "open to every client",
                "configure": if self.open { "open to every client (--allow-unauthenticated-config)" } else { "this machine only" },
                "you_may_measure": self.open || local,
            }),
        )
    }

    /// `GET /api/events`: new records as Server-Sent Events, after `Last-Event-ID` or
    /// `?since=ID`, else after the newest record now.
    fn events(&self, query: &str, last_event_id: Option<&str>, peer: SocketAddr) -> Answer {
        let items = match query_items(query) {
            Ok(items) => items,
            Err(why) => return error(StatusCode::BAD_REQUEST, &why),
        };
        let mut since = None;
        for item in &items {
            match item.split_once('=') {
                Some(("since", v)) => match v.parse::<u64>() {
                    Ok(id) => since = Some(id),
                    Err(_) => {
                        return error(
                            StatusCode::BAD_REQUEST,
                            &format!("since={v}: a record id, a whole number"),
                        );
                    }
                },
                _ => {
                    return error(
                        StatusCode::BAD_REQUEST,
                        &format!("unknown query item {item}: /api/events takes since=ID"),
                    );
                }
            }
        }
        let log = self.recorder.log().clone();
        let start = last_event_id
            .and_then(|v| v.trim().parse::<u64>().ok())
            .or(since)
            .unwrap_or_else(|| log.newest());
        let stream = match limits::Counter::start(&self.streams, peer.ip()) {
            Ok(counted) => counted,
            Err(limits::Full::Client) => {
                return error(
                    StatusCode::TOO_MANY_REQUESTS,
                    &format!(
                        "this client (its IPv4 address or IPv6 /64) has {EVENT_STREAMS_PER_CLIENT} event streams open, the most the station serves one client: close one first"
                    ),
                );
            }
            Err(limits::Full::All) => {
                return error(
                    StatusCode::SERVICE_UNAVAILABLE,
                    &format!(
                        "the station serves {MAX_EVENT_STREAMS} event streams already, the most it serves: try again later"
                    ),
                );
            }
        };
        let (tx, rx) = mpsc::channel(16);
        tokio::spawn(async move {
            stream_events(log, start, tx).await;
            drop(stream);
        });
        let mut answer = Response::new(BoxBody::new(Streamed(rx)));
        let h = answer.headers_mut();
        h.insert(
            header::CONTENT_TYPE,
            HeaderValue::from_static("text/event-stream"),
        );
        h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
        answer
    }

    /// `/hc/<coap URI>`: the request forwarded to that CoAP server, its answer mapped
    /// back (RFC 8075). Methods other than GET and HEAD only from this machine unless
    /// configuration is open, as the CoAP server on this machine takes the proxy's
    /// requests as local ones.
    async fn proxy(&self, request: Request<Incoming>, peer: SocketAddr) -> Answer {
        let raw = request
            .uri()
            .path_and_query()
            .map_or("", |p| p.as_str())
            .to_owned();
        let Some(target) = proxy::target(&raw) else {
            return error(StatusCode::BAD_REQUEST, "the proxy's target is not a URI");
        };
        // Another scheme is told what the proxy reaches (coap:// alone), not what a CoAP
        // URI may be.
        let scheme = target
            .split_once("://")
            .map(|(s, _)| s.to_ascii_lowercase());
        if !matches!(scheme.as_deref(), Some("coap" | "coaps")) {
            return error(
                StatusCode::BAD_REQUEST,
                &format!("{target}: the proxy reaches coap:// servers only"),
            );
        }
        let uri = match coap_net::Uri::parse(&target) {
            Ok(uri) if !uri.secure => uri,
            Ok(_) => {
                return error(
                    StatusCode::BAD_GATEWAY,
                    "the proxy reaches coap:// servers only (it has no DTLS keys)",
                );
            }
            Err(e) => return error(StatusCode::BAD_REQUEST, &format!("{target}: {e}")),
        };
        let Some(method) = proxy::method(request.method()) else {
            return error(
                StatusCode::NOT_IMPLEMENTED,
                &format!(
                    "the proxy maps GET, HEAD, POST, PUT and DELETE, not {}",
                    request.method()
                ),
            );
        };
        if method != coap::Code::GET && !self.open && !is_local(peer) {
            return error(
                StatusCode::FORBIDDEN,
                "the proxy forwards changes (POST, PUT, DELETE) only for clients on the station's own machine (its operator can allow them with serve --allow-unauthenticated-config)",
            );
        }
        let head = request.method() == Method::HEAD;
        let headers = request.headers().clone();
        let mut options = uri.options();
        // Whom a change came from, for the results log's events.
        options.set(crate::api::paths::FORWARDED_FOR, format!("http://{peer}"));
        if head {
            // The first block of 16 bytes and the size, no more blocks (the client does
            // not go on when the request names its Block2).
            options.set_block(
                coap::OptionNumber::BLOCK2,
                coap::BlockOpt {
                    num: 0,
                    more: false,
                    szx: 0,
                },
            );
            options.set_uint(coap::OptionNumber::SIZE2, 0);
        }
        let server = match uri.resolve().await {
            Ok(addr) => proxy::canonical(addr),
            Err(e) => return error(StatusCode::BAD_GATEWAY, &format!("{}: {e}", uri.host)),
        };
        if let Err(why) = self.reach.check(server).await {
            return error(StatusCode::FORBIDDEN, &why);
        }
        if let Some(ct) = headers.get(header::CONTENT_TYPE) {
            let ct = ct.to_str().unwrap_or("");
            match proxy::content_format(ct) {
                Some(cf) => options.set_uint(coap::OptionNumber::CONTENT_FORMAT, u32::from(cf.0)),
                None => {
                    return error(
                        StatusCode::UNSUPPORTED_MEDIA_TYPE,
                        &format!("{ct} has no CoAP Content-Format"),
                    );
                }
            }
        }
        if let Some(cf) = headers
            .get(header::ACCEPT)
            .and_then(|v| v.to_str().ok())
            .and_then(proxy::accept)
        {
            options.set_uint(coap::OptionNumber::ACCEPT, u32::from(cf.0));
        }
        let conditional = headers.contains_key(header::IF_NONE_MATCH);
        if let Some(v) = headers
            .get(header::IF_NONE_MATCH)
            .and_then(|v| v.to_str().ok())
        {
            // A GET that validates: the ETags it has (2.03 Valid then means 304).
            for tag in proxy::etags(v) {
                options.push(coap::OptionNumber::ETAG, tag);
            }
        }
        if let Some(v) = headers.get(header::IF_MATCH).and_then(|v| v.to_str().ok()) {
            for tag in proxy::etags(v) {
                options.push(coap::OptionNumber::IF_MATCH, tag);
            }
        }
        if let Some(length) = headers
            .get(header::CONTENT_LENGTH)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.parse::<u64>().ok())
            && length > proxy::MAX_REQUEST as u64
        {
            return proxy_too_large();
        }
        let body = match Limited::new(request.into_body(), proxy::MAX_REQUEST)
            .collect()
            .await
        {
            Ok(body) => body.to_bytes(),
            Err(e)
                if e.downcast_ref::<http_body_util::LengthLimitError>()
                    .is_some() =>
            {
                return proxy_too_large();
            }
            Err(e) => return error(StatusCode::BAD_REQUEST, &format!("reading the body: {e}")),
        };
        let Ok(_fetch) = limits::Counter::start(&self.fetches, peer.ip()) else {
            return error(
                StatusCode::TOO_MANY_REQUESTS,
                &format!(
                    "the proxy already forwards {} requests for this client ({} in all), each answer up to {} MiB: try again when one has ended",
                    proxy::PER_CLIENT,
                    proxy::IN_ALL,
                    proxy::MAX_RESPONSE >> 20
                ),
            );
        };
        let client = match proxy_client(server) {
            Ok(client) => client,
            Err(e) => {
                return error(
                    StatusCode::INTERNAL_SERVER_ERROR,
                    &format!("the proxy's CoAP socket: {e}"),
                );
            }
        };
        let mut coap_request = coap::Request::new(method, "/").with_payload(body);
        coap_request.options = options;
        coap_request.timeout = Some(proxy::TIMEOUT);
        let answer = match client.send(server, coap_request).await {
            Ok(answer) => answer,
            Err(coap_net::Error::Request(coap::RequestError::Timeout)) => {
                return error(
                    StatusCode::GATEWAY_TIMEOUT,
                    &format!("{target}: no answer within {} s", proxy::TIMEOUT.as_secs()),
                );
            }
            Err(coap_net::Error::Request(coap::RequestError::TooLarge { .. })) => {
                return error(
                    StatusCode::BAD_GATEWAY,
                    &format!(
                        "{target}: the answer is larger than the {} MiB the proxy passes on",
                        proxy::MAX_RESPONSE >> 20
                    ),
                );
            }
            Err(e) => return error(StatusCode::BAD_GATEWAY, &format!("{target}: {e}")),
        };
        let status = if answer.code == coap::Code::VALID && !conditional {
            StatusCode::OK
        } else {
            proxy::status(answer.code, answer.payload.is_empty())
        };
        let content_type = answer
            .options
            .uint(coap::OptionNumber::CONTENT_FORMAT)
            .and_then(|cf| u16::try_from(cf).ok())
            .map(|cf| proxy::media_type(coap::ContentFormat(cf)))
            .or_else(|| {
                // A diagnostic payload (RFC 7252 §5.5.2) is UTF-8 text.
                (answer.code.0 >> 5 >= 4 && !answer.payload.is_empty())
                    .then(|| "text/plain; charset=utf-8".to_owned())
            });
        let body = if head || status == StatusCode::NOT_MODIFIED || status == StatusCode::NO_CONTENT
        {
            Bytes::new()
        } else {
            answer.payload.clone()
        };
        let mut reply = Response::new(full(body));
        *reply.status_mut() = status;
        let h = reply.headers_mut();
        if head
            && let Some(size) = answer.options.uint(coap::OptionNumber::SIZE2).or_else(|| {
                let whole = answer.options.block2().is_none_or(|b| !b.more);
                whole.then(|| u32::try_from(answer.payload.len()).unwrap_or(u32::MAX))
            })
        {
            // What a GET would bring (RFC 9110 §9.3.2).
            h.insert(header::CONTENT_LENGTH, HeaderValue::from(size));
        }
        if let Some(ct) = content_type.and_then(|ct| HeaderValue::from_str(&ct).ok()) {
            h.insert(header::CONTENT_TYPE, ct);
        }
        if let Some(tag) = answer.options.first(coap::OptionNumber::ETAG)
            && let Ok(tag) = HeaderValue::from_str(&proxy::etag(tag))
        {
            h.insert(header::ETAG, tag);
        }
        if answer.code.0 >> 5 == 2
            && let Ok(cc) = HeaderValue::from_str(&proxy::cache_control(&answer.options))
        {
            h.insert(header::CACHE_CONTROL, cc);
        }
        let authority = match server {
            SocketAddr::V6(a) => format!("[{}]:{}", a.ip(), a.port()),
            SocketAddr::V4(a) => a.to_string(),
        };
        if let Some(loc) = proxy::location(&answer.options, "coap", &authority)
            .and_then(|l| HeaderValue::from_str(&l).ok())
        {
            h.insert(header::LOCATION, loc);
        }
        reply
    }
}

/// A CoAP client of the proxy's own for one request to `server`, which ends with it. Not
/// one client for every request: a client's message IDs come round every 65,536 and may
/// not be used again within EXCHANGE_LIFETIME (247 s), so a shared one that forwarded
/// 6 answers of 16 MB (about 96,000 block requests) had to wait minutes for a free ID,
/// and every block-wise transfer through it ended in 504 until then (issue 46). An
/// answer of [`proxy::MAX_RESPONSE`] takes 16,384.
fn proxy_client(server: SocketAddr) -> std::io::Result<coap_net::Client> {
    let mut config = coap::EndpointConfig {
        rng_seed: coap_net::fresh_seed(),
        ..coap::EndpointConfig::default()
    };
    config.limits.client_body_bytes = proxy::MAX_RESPONSE;
    coap_net::Client::for_peer(server, config)
}

/// A live image of a camera.
#[derive(Debug, Clone, Copy)]
enum Live {
    Color,
    Depth,
}

/// A new depth frame of `cam`, colour-mapped, as JPEG (blocking).
fn depth_jpeg(cam: &crate::server::measure::RigCamera) -> Result<Vec<u8>, String> {
    let frame = cam
        .camera
        .grab_depth(Duration::from_secs(2))
        .map_err(|e| format!("depth: {e}"))?;
    let width = frame.width as usize;
    let values = (0..frame.height as usize)
        .flat_map(|y| {
            let start = y * frame.stride;
            frame
                .data
                .get(start..start + width)
                .unwrap_or(&[])
                .iter()
                .copied()
        })
        .collect::<Vec<u16>>();
    if values.len() != width * frame.height as usize {
        return Err("depth: a frame shorter than its size".to_owned());
    }
    let image = crate::repr::packet::DepthImage {
        width: frame.width,
        height: frame.height,
        timestamp_s: u32::try_from(frame.timestamp_us / 1_000_000).unwrap_or(u32::MAX),
        depth_scale: frame.depth_scale,
        values,
    };
    let (_, colored) = crate::vision::picture::depth_views(&image);
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, COLOR_QUALITY)
        .encode_image(&colored)
        .map_err(|e| format!("JPEG: {e}"))?;
    Ok(out)
}

/// What `/api/cameras` says of a camera.
#[derive(Serialize)]
struct CameraInfo {
    serial: String,
    model: String,
    color: serde_json::Value,
    depth: serde_json::Value,
    calibrated: bool,
    transformation: geometry::Transformation,
    warnings: Vec<String>,
}

/// The JSON array of the records `query` selects, up to `wanted` of them, newest first,
/// to `tx` a page of [`LIST_PAGE`] at a time (the same bytes as the array written whole),
/// `first` the first page; until the client has gone. A page that cannot be read ends
/// the body with an error, which aborts the connection: the client sees a cut-off answer,
/// not a shorter list.
async fn stream_list(
    log: ResultsLog,
    readers: Arc<Semaphore>,
    mut query: ListQuery,
    wanted: usize,
    first: Vec<Record>,
    tx: mpsc::Sender<Result<Bytes, std::io::Error>>,
) {
    let mut page = first;
    let mut sent = 0;
    let mut out = b"[".to_vec();
    loop {
        let last = page.len() < query.limit;
        for record in &page {
            if sent > 0 {
                out.push(b',');
            }
            if let Err(e) = serde_json::to_writer(&mut out, record) {
                let _ = tx.send(Err(std::io::Error::other(e))).await;
                return;
            }
            sent += 1;
        }
        if last || sent >= wanted {
            out.push(b']');
            let _ = tx.send(Ok(Bytes::from(out))).await;
            return;
        }
        if tx
            .send(Ok(Bytes::from(std::mem::take(&mut out))))
            .await
            .is_err()
        {
            return;
        }
        query.before = page.last().map(|r| r.id);
        query.limit = (wanted - sent).min(LIST_PAGE);
        page = match read_page(&log, &query, &readers).await {
            Ok(records) => records,
            Err(refused) => {
                let _ = tx.send(Err(std::io::Error::other(refused.why))).await;
                return;
            }
        };
    }
}

/// A page of a list, read when one of `readers` is free.
async fn read_page(
    log: &ResultsLog,
    query: &ListQuery,
    readers: &Semaphore,
) -> Result<Vec<Record>, Refusal> {
    let _reading = readers.acquire().await;
    reads::list(log, query.items(), "/api/measurements").await
}

/// Sends the records after `after` to `tx` as events, then each new one, until the
/// client has gone.
async fn stream_events(
    log: ResultsLog,
    after: u64,
    tx: mpsc::Sender<Result<Bytes, std::io::Error>>,
) {
    if tx
        .send(Ok(Bytes::from_static(
            b"retry: 2000\n: coapcam measurements\n\n",
        )))
        .await
        .is_err()
    {
        return;
    }
    follow::run(log, Events { after, tx }).await;
}

/// One client's event stream as a [`Sink`]: a `measurement` event per record, and a
/// comment line when there was no news for [`KEEP_ALIVE`]; done when the client has gone.
struct Events {
    after: u64,
    tx: mpsc::Sender<Result<Bytes, std::io::Error>>,
}

/// What an event stream waits for besides records.
enum Quiet {
    /// No news for [`KEEP_ALIVE`].
    KeepAlive,
    /// The client has gone.
    Gone,
}

impl Sink for Events {
    type Event = Quiet;

    fn name(&self) -> String {
        "http: event stream".into()
    }

    fn start(&self) -> Start {
        Start::After(self.after)
    }

    async fn deliver(&mut self, record: &Record) -> Next {
        let Ok(data) = serde_json::to_string(record) else {
            return Next::Go;
        };
        let event = format!("id: {}\nevent: measurement\ndata: {data}\n\n", record.id);
        match self.tx.send(Ok(Bytes::from(event))).await {
            Ok(()) => Next::Go,
            Err(_) => Next::End,
        }
    }

    async fn event(&mut self) -> Quiet {
        tokio::select! {
            () = tokio::time::sleep(KEEP_ALIVE) => Quiet::KeepAlive,
            () = self.tx.closed() => Quiet::Gone,
        }
    }

    async fn handle(&mut self, event: Quiet) -> Next {
        match event {
            Quiet::KeepAlive => match self.tx.send(Ok(Bytes::from_static(b": alive\n\n"))).await {
                Ok(()) => Next::Go,
                Err(_) => Next::End,
            },
            Quiet::Gone => Next::End,
        }
    }
}

/// A body sent as it comes: what [`stream_events`] or [`stream_list`] send.
struct Streamed(mpsc::Receiver<Result<Bytes, std::io::Error>>);

impl Body for Streamed {
    type Data = Bytes;
    type Error = std::io::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, std::io::Error>>> {
        self.0.poll_recv(cx).map(|b| b.map(|b| b.map(Frame::data)))
    }
}

/// Whether `segments` name a page or resource (for 405 rather than 404).
fn known(segments: &[&str]) -> bool {
    matches!(
        segments,
        [] | [""]
            | ["api", "measurements"]
            | ["api", "measurements", _]
            | ["api", "measurements", _, _]
            | ["api", "measure"]
            | ["api", "cameras"]
            | ["api", "cameras", _, "color.jpg" | "depth.jpg"]
            | ["api", "station"]
            | ["api", "log", "head"]
            | ["api", "events"]
    )
}

/// A query's items, percent-decoded (`+` a space); an item that is not UTF-8 is refused.
fn query_items(query: &str) -> Result<Vec<String>, String> {
    query
        .split('&')
        .filter(|item| !item.is_empty())
        .map(|item| {
            // `+` is a space in a form's query; an escaped one (%2B) stays a plus.
            coap_net::uri::percent_decode(&item.replace('+', " "))
                .ok_or_else(|| format!("{item}: the query is not percent-encoded UTF-8"))
        })
        .collect()
}

/// 413 for a request whose Content-Length is over [`MAX_BODY`].
fn too_large(request: &Request<Incoming>) -> Option<Answer> {
    let length = request.headers().get(header::CONTENT_LENGTH)?;
    let length: u64 = length.to_str().ok()?.parse().ok()?;
    (length > MAX_BODY as u64).then(body_too_large)
}

fn body_too_large() -> Answer {
    let mut answer = error(
        StatusCode::PAYLOAD_TOO_LARGE,
        &format!("a request's body may have at most {MAX_BODY} bytes"),
    );
    // The rest of the body is not read: the connection cannot go on.
    answer
        .headers_mut()
        .insert(header::CONNECTION, HeaderValue::from_static("close"));
    answer
}

fn proxy_too_large() -> Answer {
    let mut answer = error(
        StatusCode::PAYLOAD_TOO_LARGE,
        &format!(
            "the proxy forwards bodies of at most {} bytes",
            proxy::MAX_REQUEST
        ),
    );
    answer
        .headers_mut()
        .insert(header::CONNECTION, HeaderValue::from_static("close"));
    answer
}

/// A refusal of the results log as its HTTP answer.
fn refusal(refused: &Refusal) -> Answer {
    let status = match refused.kind {
        Kind::BadRequest => StatusCode::BAD_REQUEST,
        Kind::NotFound => StatusCode::NOT_FOUND,
        Kind::Failed => StatusCode::INTERNAL_SERVER_ERROR,
    };
    error(status, &refused.why)
}

fn full(body: Bytes) -> AnswerBody {
    BoxBody::new(Full::new(body).map_err(|never| match never {}))
}

fn empty() -> AnswerBody {
    full(Bytes::new())
}

fn bytes(content_type: &'static str, body: impl Into<Bytes>) -> Answer {
    let mut answer = Response::new(full(body.into()));
    answer
        .headers_mut()
        .insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    answer
}

fn bytes_no_store(content_type: &'static str, body: Bytes) -> Answer {
    let mut answer = bytes(content_type, body);
    answer
        .headers_mut()
        .insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    answer
}

fn json<T: Serialize + ?Sized>(status: StatusCode, value: &T) -> Answer {
    match serde_json::to_vec(value) {
        Ok(body) => {
            let mut answer = bytes("application/json", body);
            *answer.status_mut() = status;
            answer
                .headers_mut()
                .insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
            answer
        }
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &format!("JSON: {e}")),
    }
}

/// `{"error": why}` with `status`.
fn error(status: StatusCode, why: &str) -> Answer {
    let body = serde_json::to_vec(&serde_json::json!({ "error": why }))
        .unwrap_or_else(|_| b"{\"error\":\"?\"}".to_vec());
    let mut answer = bytes("application/json", body);
    *answer.status_mut() = status;
    answer
}

fn page() -> Answer {
    let mut answer = bytes(
        "text/html; charset=utf-8",
        Bytes::from_static(PAGE.as_bytes()),
    );
    answer
        .headers_mut()
        .insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    answer
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn listen_addresses_and_queries() {
        assert_eq!(
            parse_listen("8080"),
            Ok(SocketAddr::from(([127, 0, 0, 1], 8080)))
        );
        assert_eq!(
            parse_listen("0.0.0.0:80"),
            Ok(SocketAddr::from(([0, 0, 0, 0], 80)))
        );
        assert!(parse_listen("localhost").is_err());
        assert_eq!(
            query_items("code=PKG%2D1+x&limit=2&").unwrap(),
            vec!["code=PKG-1 x".to_owned(), "limit=2".to_owned()]
        );
        assert_eq!(query_items("code=A%2BB").unwrap(), ["code=A+B"]);
        assert!(query_items("code=%FF").is_err());
        assert!(query_items("code=%4").is_err());
        assert!(is_local("[::ffff:127.0.0.1]:1".parse().unwrap()));
        assert!(is_local("[::1]:1".parse().unwrap()));
        assert!(!is_local("192.0.2.1:1".parse().unwrap()));
    }
}
