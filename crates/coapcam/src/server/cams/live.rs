//! Live streams (an extension): `/cams/<sn>/<stream>/live`, observed (RFC 7641) at the
//! rate a client asks for (`?fps=N`, at most the camera's), in the compact forms: color as
//! JPEG, depth as RVL+zstd or RVL, the point cloud as the compact cloud.
//!
//! A *feed* grabs and encodes the frames of one camera, stream and representation at the
//! highest rate its observers ask for, once per frame for all of them, and keeps only the
//! newest. Each frame becomes a notification through the server's Observe machinery
//! (`coap_net::Server::notify`, which runs the GET handler per observer): an observer
//! whose rate is lower is handed the frame it already has until its period has passed,
//! which the server does not send again. Nothing queues per observer: the endpoint holds
//! at most one newer notification behind an unacknowledged one, and a body larger than a
//! block goes as block 0 in the notification and the rest from the store (RFC 7959 §2.6),
//! where a newer frame waits behind the one a client is partway through and replaces it
//! once that is fetched. A client or a link that falls behind thus skips to the newest
//! frame. Every notification carries the frame's capture time
//! ([`crate::timesync::CAPTURE_TIME`]).
//!
//! Streams are bounded per client address and in all ([`LiveLimits`]); the next is
//! refused with 4.29 (per client) or 5.03 (in all). A feed ends when its last observer's
//! observation does (the resource is told: `coap_net::Resource::on_observation_end`), and
//! with its camera.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;

use coap::{Code, ContentFormat, IncomingRequest, ObservationId, OptionNumber, Response};
use rgbd::Serial;
use serde::Serialize;
use tokio::sync::watch;

use super::answer::{
    content, encode, frame_etag, representation_etag, set_cf, subject, with_no_depth,
};
use super::grab::Frame;
use crate::repr::{self, Stream, raster};
use crate::timesync::{CAPTURE_TIME, capture_time_value};

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// What the feeds need of the camera server.
pub(super) trait Cameras: Send + Sync + 'static {
    /// Its live streams.
    fn live(&self) -> &Live;
    /// The frame rate of camera `sn`'s `kind`, `None` when it is not connected.
    fn rate(&self, sn: Serial, kind: Stream) -> Option<u32>;
    /// A new frame of camera `sn`'s `kind`, its capture time on the server's clock, or
    /// why not (blocking: off the executor).
    fn grab(&self, sn: Serial, kind: Stream) -> Result<Frame, String>;
    /// The representation of `path` changed: its observers are to be notified.
    fn changed(&self, path: &str);
}

/// The live resources' names under `/cams/<sn>/`, one per stream.
pub(super) const NAMES: [&str; 3] = ["color/live", "depth/live", "pointcloud/live"];

/// The stream of live resource `name` (one of [`NAMES`]).
pub(super) fn stream_of(name: &str) -> Option<Stream> {
    Stream::of(name.strip_suffix("/live")?)
}

/// How long a new observer waits for the first frame of a feed before its registration
/// is refused (5.03).
const FIRST_FRAME: Duration = Duration::from_secs(10);

/// The representations a live stream is offered in, the default first: the compact ones.
pub(super) fn formats(kind: Stream) -> &'static [ContentFormat] {
    match kind {
        Stream::Color => &[ContentFormat::IMAGE_JPEG],
        Stream::Depth => &[repr::RVL_ZSTD, repr::RVL],
        Stream::Pointcloud => &[repr::DEPTH_CLOUD],
    }
}

/// The bounds of live streams: an observation of a live resource is one stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct LiveLimits {
    /// Streams of one client address (4 by default); the next answers 4.29.
    pub per_client: usize,
    /// Streams in all (32 by default); the next answers 5.03.
    pub total: usize,
}

impl Default for LiveLimits {
    fn default() -> Self {
        Self {
            per_client: 4,
            total: 32,
        }
    }
}

/// What a feed produces: one camera's stream in one representation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
struct FeedKey {
    sn: Serial,
    kind: Stream,
    cf: ContentFormat,
    /// The JPEG quality (color only; 0 otherwise).
    quality: u8,
}

/// One frame, encoded once for every observer: the answer (Content-Format, ETag,
/// Capture-Time, the body) and when it was captured.
struct Encoded {
    response: Response,
    captured_us: u64,
}

/// A running feed.
struct Feed {
    path: String,
    latest: watch::Sender<Option<Arc<Encoded>>>,
    /// Frames grabbed and encoded (one encoding each, whatever the observers).
    encoded: AtomicU64,
    /// Grabs or encodings that failed.
    failed: AtomicU64,
    /// Frames handed to observers (registrations and notifications).
    served: AtomicU64,
}

/// An observation of a live resource.
struct Subscriber {
    key: FeedKey,
    fps: u32,
    /// The frame it was handed last.
    last: Option<Arc<Encoded>>,
}

#[derive(Default)]
struct State {
    feeds: HashMap<FeedKey, Arc<Feed>>,
    /// By the observer's address and observation.
    subscribers: HashMap<(SocketAddr, ObservationId), Subscriber>,
}

/// The live streams of a camera server.
#[derive(Default)]
pub(super) struct Live {
    limits: Mutex<LiveLimits>,
    state: Mutex<State>,
}

/// `/cams/live`: the bounds and each feed with its counters.
#[derive(Serialize)]
struct Report {
    limits: LiveLimits,
    streams: usize,
    feeds: Vec<FeedReport>,
}

#[derive(Serialize)]
struct FeedReport {
    path: String,
    content_format: u16,
    #[serde(skip_serializing_if = "Option::is_none")]
    quality: Option<u8>,
    /// The rate it grabs at: the highest its observers ask for.
    fps: u32,
    observers: usize,
    encoded: u64,
    served: u64,
    failed: u64,
}

impl Live {
    pub(super) fn set_limits(&self, limits: LiveLimits) {
        *lock(&self.limits) = limits;
    }

    /// The document of `/cams/live`.
    pub(super) fn report(&self) -> String {
        let state = lock(&self.state);
        let mut feeds: Vec<FeedReport> = state
            .feeds
            .iter()
            .map(|(key, feed)| {
                let observers = state.subscribers.values().filter(|s| s.key == *key);
                FeedReport {
                    path: feed.path.clone(),
                    content_format: key.cf.0,
                    quality: (key.kind == Stream::Color).then_some(key.quality),
                    fps: observers.clone().map(|s| s.fps).max().unwrap_or(0),
                    observers: observers.count(),
                    encoded: feed.encoded.load(Ordering::Relaxed),
                    served: feed.served.load(Ordering::Relaxed),
                    failed: feed.failed.load(Ordering::Relaxed),
                }
            })
            .collect();
        feeds.sort_by(|a, b| (&a.path, a.content_format).cmp(&(&b.path, b.content_format)));
        let report = Report {
            limits: *lock(&self.limits),
            streams: state.subscribers.len(),
            feeds,
        };
        serde_json::to_string(&report).unwrap_or_default()
    }

    /// Admits observation `who` of `key` at `fps`, with its feed (and whether that is new,
    /// to be started), or the refusal beyond the bounds.
    #[expect(
        clippy::result_large_err,
        reason = "a refusal is the Response sent; it keeps its options inline"
    )]
    fn admit(
        &self,
        who: (SocketAddr, ObservationId),
        key: FeedKey,
        fps: u32,
        path: &str,
    ) -> Result<(Arc<Feed>, bool), Response> {
        let limits = *lock(&self.limits);
        let mut state = lock(&self.state);
        // The same registration again (its peer and token) is no new stream.
        let known = state.subscribers.contains_key(&who);
        let ip = who.0.ip();
        let mine = state
            .subscribers
            .keys()
            .filter(|(p, _)| p.ip() == ip)
            .count();
        if !known && mine >= limits.per_client {
            let why = format!(
                "at most {} live streams per client ({ip} has {mine}): end one first (serve --live-streams-per-client)",
                limits.per_client
            );
            return Err(retry_later(Code::TOO_MANY_REQUESTS, &why));
        }
        if !known && state.subscribers.len() >= limits.total {
            let why = format!(
                "at most {} live streams in all, and as many run: retry later (serve --live-streams)",
                limits.total
            );
            return Err(retry_later(Code::SERVICE_UNAVAILABLE, &why));
        }
        state.subscribers.insert(
            who,
            Subscriber {
                key,
                fps,
                last: None,
            },
        );
        if let Some(feed) = state.feeds.get(&key) {
            return Ok((feed.clone(), false));
        }
        let (latest, _) = watch::channel(None);
        let feed = Arc::new(Feed {
            path: path.to_owned(),
            latest,
            encoded: AtomicU64::new(0),
            failed: AtomicU64::new(0),
            served: AtomicU64::new(0),
        });
        state.feeds.insert(key, feed.clone());
        Ok((feed, true))
    }

    /// Observation `who` ended (or was never established).
    pub(super) fn leave(&self, who: (SocketAddr, ObservationId)) {
        lock(&self.state).subscribers.remove(&who);
    }

    /// Camera `sn` disconnected: its streams end with it.
    pub(super) fn forget_camera(&self, sn: Serial) {
        let mut state = lock(&self.state);
        state.subscribers.retain(|_, s| s.key.sn != sn);
        state.feeds.retain(|k, _| k.sn != sn);
    }

    /// The rate feed `key` grabs at now (the highest its observers ask for); `None`, and
    /// the feed is gone, when it has none left.
    fn rate(&self, key: &FeedKey) -> Option<u32> {
        let mut state = lock(&self.state);
        let fps = (state.subscribers.values())
            .filter(|s| s.key == *key)
            .map(|s| s.fps)
            .max();
        if fps.is_none() {
            state.feeds.remove(key);
        }
        fps
    }

    /// For a known observation `who` (a notification, or the same registration again):
    /// the newest frame when its period has passed since the frame it was handed last
    /// (within half a frame of the camera, `slack_us`), else that frame again, which the
    /// server does not send twice. `None` for an observation it does not know.
    fn notification(&self, who: &(SocketAddr, ObservationId), slack_us: u64) -> Option<Response> {
        let mut state = lock(&self.state);
        let key = state.subscribers.get(who)?.key;
        let feed = state.feeds.get(&key)?.clone();
        let newest = feed.latest.borrow().clone()?;
        let sub = state.subscribers.get_mut(who)?;
        let period_us = 1_000_000 / u64::from(sub.fps.max(1));
        let due = sub.last.as_ref().is_none_or(|last| {
            newest.captured_us + slack_us >= last.captured_us + period_us
                && newest.captured_us > last.captured_us
        });
        if due {
            sub.last = Some(newest.clone());
            feed.served.fetch_add(1, Ordering::Relaxed);
            return Some(newest.response.clone());
        }
        sub.last.as_ref().map(|last| last.response.clone())
    }

    /// Hands `frame` to observation `who` as its first.
    fn first(&self, who: &(SocketAddr, ObservationId), feed: &Feed, frame: &Arc<Encoded>) {
        if let Some(sub) = lock(&self.state).subscribers.get_mut(who) {
            sub.last = Some(frame.clone());
            feed.served.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// The newest frame of a running feed of `key`.
    fn newest(&self, key: &FeedKey) -> Option<Arc<Encoded>> {
        let feed = lock(&self.state).feeds.get(key)?.clone();
        feed.latest.borrow().clone()
    }
}

/// A refusal to try again later: `code` with Max-Age 5 (RFC 8516 §3 for 4.29).
fn retry_later(code: Code, why: &str) -> Response {
    let mut r = Response::diagnostic(code, why);
    r.options.set_uint(OptionNumber::MAX_AGE, 5);
    r
}

/// What a live request asks for besides its representation: the rate and the JPEG
/// quality.
struct LiveQuery {
    fps: Option<u32>,
    quality: Option<u8>,
}

impl LiveQuery {
    fn parse(request: &IncomingRequest, cf: ContentFormat) -> Result<Self, String> {
        let mut query = Self {
            fps: None,
            quality: None,
        };
        for item in request.options.uri_query() {
            if let Some(v) = item.strip_prefix("fps=") {
                match v.parse::<u32>() {
                    Ok(n @ 1..=1000) => query.fps = Some(n),
                    _ => {
                        return Err(format!(
                            "fps={v}: the frame rate is a whole number from 1 to 1000 (more than the camera's is its rate)"
                        ));
                    }
                }
            } else if let Some(v) = item.strip_prefix("q=") {
                if cf != ContentFormat::IMAGE_JPEG {
                    return Err("q (the JPEG quality) is for color as image/jpeg (22)".to_owned());
                }
                match v.parse::<u8>() {
                    Ok(n @ 1..=100) => query.quality = Some(n),
                    _ => {
                        return Err(format!(
                            "q={v}: the JPEG quality is a whole number from 1 to 100"
                        ));
                    }
                }
            } else {
                return Err(format!(
                    "unknown query item {item:?}: a live stream takes fps=N and, for color, q=N"
                ));
            }
        }
        Ok(query)
    }
}

/// The representation a live request accepts (the stream's default without Accept), or
/// 4.06 naming the live formats.
#[expect(
    clippy::result_large_err,
    reason = "a refusal is the Response sent; it keeps its options inline"
)]
fn negotiate(kind: Stream, request: &IncomingRequest) -> Result<ContentFormat, Response> {
    let offered = formats(kind);
    let cf = request.options.accept().unwrap_or(offered[0]);
    if offered.contains(&cf) {
        return Ok(cf);
    }
    let names: Vec<String> = offered
        .iter()
        .map(|cf| format!("{} ({})", repr::Format::describe(*cf), cf.0))
        .collect();
    Err(Response::diagnostic(
        Code::NOT_ACCEPTABLE,
        &format!(
            "a live {} stream is served as {}",
            kind.name(),
            names.join(" or ")
        ),
    ))
}

/// `frame` of camera `sn` encoded as `key` asks, once for every observer.
fn encode_frame(key: &FeedKey, frame: &Frame) -> Result<Encoded, repr::EncodeError> {
    let body = encode(key.cf, &subject(&key.sn, frame, key.quality))?;
    let quality = (key.kind == Stream::Color).then_some(key.quality);
    let etag = representation_etag(frame_etag(&key.sn, key.kind, frame), key.cf, quality);
    let mut response = content(body, key.cf, etag);
    response
        .options
        .set(CAPTURE_TIME, capture_time_value(frame.timestamp_us()));
    if let Frame::Cloud { no_depth, .. } = frame {
        response = with_no_depth(response, no_depth);
    }
    Ok(Encoded {
        response,
        captured_us: frame.timestamp_us(),
    })
}

/// `GET /cams/<sn>/<kind>/live` of `cameras`: with Observe, a new stream (the first
/// frame, then each at the rate asked for) or, for a known one, its next notification;
/// without, the newest frame of a running feed.
pub(super) async fn answer<C: Cameras>(
    cameras: &Arc<C>,
    sn: Serial,
    kind: Stream,
    request: &IncomingRequest,
) -> Response {
    let cf = match negotiate(kind, request) {
        Ok(cf) => cf,
        Err(refused) => return refused,
    };
    let query = match LiveQuery::parse(request, cf) {
        Ok(q) => q,
        Err(why) => return Response::diagnostic(Code::BAD_REQUEST, &why),
    };
    let Some(rate) = cameras.rate(sn, kind) else {
        return Response::diagnostic(Code::NOT_FOUND, &format!("camera {sn} is disconnected"));
    };
    let rate = rate.max(1);
    let key = FeedKey {
        sn,
        kind,
        cf,
        quality: match kind {
            Stream::Color => query.quality.unwrap_or(raster::JPEG_QUALITY),
            Stream::Depth | Stream::Pointcloud => 0,
        },
    };
    let live = cameras.live();
    let Some(id) = request.observe else {
        return match live.newest(&key) {
            Some(frame) => frame.response.clone(),
            None => Response::diagnostic(
                Code::NOT_FOUND,
                "no live stream of this representation runs: observe the resource (GET with Observe) to start one",
            ),
        };
    };
    let who = (request.peer, id);
    let slack_us = 500_000 / u64::from(rate);
    if let Some(next) = live.notification(&who, slack_us) {
        return next;
    }
    let fps = query.fps.map_or(rate, |asked| asked.min(rate));
    let path = format!("{}/live", crate::api::paths::camera(sn, kind.name()));
    let (feed, new) = match live.admit(who, key, fps, &path) {
        Ok(admitted) => admitted,
        Err(refused) => return refused,
    };
    if new {
        tokio::spawn(run_feed(Arc::downgrade(cameras), key, feed.clone()));
    }
    let mut frames = feed.latest.subscribe();
    let first = tokio::time::timeout(FIRST_FRAME, frames.wait_for(Option::is_some)).await;
    let frame = match first {
        Ok(Ok(frame)) => frame.clone(),
        _ => None,
    };
    if let Some(frame) = frame {
        live.first(&who, &feed, &frame);
        return frame.response.clone();
    }
    live.leave(who);
    let why = format!(
        "camera {sn} gave no {} frame within {} s",
        kind.name(),
        FIRST_FRAME.as_secs()
    );
    retry_later(Code::SERVICE_UNAVAILABLE, &why)
}

/// `GET /cams/live`: the bounds, the streams, each feed and its counters (JSON).
pub(super) fn report(live: &Live) -> Response {
    let mut r = Response::new(Code::CONTENT).with_payload(live.report());
    set_cf(&mut r, ContentFormat::JSON);
    r
}

/// Grabs and encodes the frames of feed `key` at its observers' rate, each handed to them
/// as it is ready, until it has no observer left or its camera is gone.
async fn run_feed<C: Cameras>(cameras: Weak<C>, key: FeedKey, feed: Arc<Feed>) {
    let mut next = tokio::time::Instant::now();
    loop {
        tokio::time::sleep_until(next).await;
        let Some(me) = cameras.upgrade() else { return };
        let Some(fps) = me.live().rate(&key) else {
            return;
        };
        if me.rate(key.sn, key.kind).is_none() {
            me.live().forget_camera(key.sn);
            return;
        }
        let period = Duration::from_secs_f64(1.0 / f64::from(fps.max(1)));
        next = (next + period).max(tokio::time::Instant::now());
        let grabber = me.clone();
        let work = tokio::task::spawn_blocking(move || {
            let frame = grabber.grab(key.sn, key.kind)?;
            encode_frame(&key, &frame).map_err(|e| e.to_string())
        })
        .await;
        match work {
            Ok(Ok(frame)) => {
                feed.encoded.fetch_add(1, Ordering::Relaxed);
                feed.latest.send_replace(Some(Arc::new(frame)));
                me.changed(&feed.path);
            }
            Ok(Err(why)) => {
                let failed = feed.failed.fetch_add(1, Ordering::Relaxed) + 1;
                // Once, then at the 2nd, 4th, 8th ... failure: a camera that keeps failing
                // does not flood the log.
                if failed.is_power_of_two() {
                    tracing::warn!(path = %feed.path, failed, "live stream: {why}");
                }
            }
            Err(e) => {
                feed.failed.fetch_add(1, Ordering::Relaxed);
                tracing::warn!(path = %feed.path, "live stream: grab task: {e}");
            }
        }
    }
}
