//! The `/cams` resource tree (thesis Table 3.1, docs/design.md §5): creation resources,
//! per-camera grab and configuration resources that follow the [`CameraHub`], and
//! `/cams/pointclouds`, and `/cams/dimensions` (measurement at the edge, an extension).

mod answer;
mod budget;
mod edge;
mod grab;
mod live;
mod merge;
mod state;
#[cfg(test)]
mod tests;

use std::collections::BTreeMap;
use std::hash::{Hash as _, Hasher as _};
use std::path::Path;
use std::sync::{Arc, Mutex, MutexGuard, OnceLock, PoisonError};
use std::time::Instant;

use bytes::Bytes;
use coap::link_format::Filter;
use coap::{Code, ContentFormat, IncomingRequest, OptionNumber, Response};
use coap_net::{Resource, Router, handler};
use geometry::{Point3, PointCloud, Transformation};
use rgbd::{
    AdvancedConfig, AdvancedMode, Camera, CameraError, CameraHub, ColorSettings, DepthSettings,
    FilterError, HubEvent, PostProcessing, Serial,
};
use tokio::sync::mpsc;

use super::measure::{self, Records, Rig, RigCamera, Shot};
use crate::api::record::{CameraPose, Change, Event, Trigger, parameters_sha256, sha256_hex};
use crate::report::{self, EdgeQuery, Measurement};
use crate::repr::{self, CloudSource, Stream, Subject, raster};
use crate::vision::calibration::pose_transformation;
use crate::vision::codes;

use super::clock::ServerClock;
use crate::documents::AppConfig;
use crate::timesync::{self, FrameHistory, FrameTime, Limits};
use answer::{content, encode, frame_etag, representation_etag, set_cf, subject, with_no_depth};
pub use budget::Busy;
pub use edge::EdgeError;
use grab::{Frame, GrabError};
pub use live::LiveLimits;
use merge::{Merged, register_and_merge};
use state::StateDir;

/// JSON configuration resources of a camera; the last, [`ADVANCED`], only of a camera
/// with the advanced mode.
const CONFIGS: [&str; 5] = [
    "color-settings",
    "depth-settings",
    "application-config",
    "3d-transformation",
    ADVANCED,
];

/// The advanced-config resource: the camera's [`AdvancedMode`], a D400's.
const ADVANCED: &str = "advanced-config";

/// The names of `camera`'s resources: the grabs and the configuration documents it has.
fn names(camera: &dyn Camera) -> impl Iterator<Item = &'static str> {
    let advanced = camera.advanced_mode().is_some();
    (Stream::ALL.iter().map(|s| s.name()))
        .chain(CONFIGS)
        .chain(live::NAMES)
        .filter(move |name| advanced || *name != ADVANCED)
}

/// Why a camera without the advanced mode has no advanced-config.
fn no_advanced_mode(sn: &Serial) -> String {
    format!("camera {sn} has no advanced-config: it has no advanced mode (a D400's)")
}

/// The documents of a camera that hold legally relevant parameters (docs/station.md,
/// "The audit trail"): its 3d-transformation, and its application-config (the regions of
/// interest and the depth filters). A `PUT` or `DELETE` of one is an event of the
/// results log.
const LEGAL: [&str; 2] = ["application-config", "3d-transformation"];

/// Who sent `request`, as an event names them: `coap://ADDR`, or `coaps://ADDR
/// psk-identity NAME` when DTLS or TLS (`coaps+tcp`, `coaps+ws`) authenticated it; followed by `for http://ADDR` when it
/// came over loopback from the station's HTTP-CoAP proxy, which names its client
/// ([`crate::api::paths::FORWARDED_FOR`]).
fn sender(request: &IncomingRequest) -> String {
    let mut by = match &request.identity {
        Some(identity) => format!("coaps://{} psk-identity {identity}", request.peer),
        None => format!("coap://{}", request.peer),
    };
    let forwarded = request
        .options
        .first(crate::api::paths::FORWARDED_FOR)
        .and_then(|v| std::str::from_utf8(v).ok())
        .filter(|v| v.len() <= 64 && v.starts_with("http://") && !v.contains(char::is_whitespace));
    if request.loopback
        && let Some(client) = forwarded
    {
        by.push_str(" for ");
        by.push_str(client);
    }
    by
}

/// A camera's own configuration, before the server changed any of it.
struct Defaults {
    color: ColorSettings,
    depth: DepthSettings,
    /// Read when first needed: before a saved document is applied, or at the first PUT
    /// (reading it may take a real camera a while).
    advanced: Mutex<Option<AdvancedConfig>>,
}

/// The 3d-transformation a camera starts with: the pose a synthetic scene gives it
/// (`calibrated = true`, the default), else the identity (a real camera, a recording).
fn default_transformation(camera: &dyn Camera) -> Transformation {
    camera
        .true_pose()
        .map_or_else(Transformation::identity, |p| pose_transformation(&p))
}

/// A grabbed frame with its ETag.
type Stored = Arc<(Frame, [u8; 8])>;

/// One connected camera and the server's state for it.
struct CamState {
    camera: Arc<dyn Camera>,
    app: Mutex<AppConfig>,
    transformation: Mutex<Transformation>,
    latest: Mutex<[Option<Stored>; 3]>,
    /// What a DELETE of a configuration document goes back to: the camera's settings as
    /// it connected, before any saved ones were applied.
    defaults: Defaults,
    /// Held through a PUT's validation, change and persisting: PUTs of one camera take
    /// effect one after the other, in memory and on disk in the same order.
    writes: Mutex<()>,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// The resource tree, shared by its handlers and the hub listener.
pub(crate) struct Cams {
    hub: Arc<CameraHub>,
    router: Arc<Router>,
    state: StateDir,
    /// By serial: `/cams/pointclouds` merges in this order, which decides what ICP
    /// registers onto what.
    cams: Mutex<BTreeMap<Serial, Arc<CamState>>>,
    /// Paths with a new representation, for Observe notifications.
    changed: mpsc::UnboundedSender<String>,
    /// `/cams/dimensions`: the latest measurement at the edge.
    measured: Mutex<edge::Latest>,
    /// The memory grabs in progress may take together.
    budget: Arc<budget::Budget>,
    /// Where measurements are kept (the station's results log), once it is set.
    records: OnceLock<Arc<dyn Records>>,
    /// The server's clock: frames' capture times are shifted onto it.
    clock: Arc<ServerClock>,
    /// The last frame of each camera measured at the edge: a camera that serves it again
    /// is stale.
    frames: Mutex<FrameHistory>,
    /// The live streams (`/cams/<sn>/<stream>/live`).
    live: live::Live,
}

impl Cams {
    /// Registers `/cams`, `/cams/pointclouds` and the creation resources on `router`,
    /// then follows `hub` on a thread of its own: per-camera resources appear when a
    /// camera connects (with its persisted configuration re-applied) and vanish when it
    /// disconnects.
    pub(crate) fn start(
        hub: Arc<CameraHub>,
        router: Arc<Router>,
        state_dir: &Path,
        changed: mpsc::UnboundedSender<String>,
        clock: Arc<ServerClock>,
    ) -> std::io::Result<Arc<Self>> {
        let state = StateDir::new(state_dir);
        let removed = state.remove_leftovers();
        if removed > 0 {
            tracing::info!(
                removed,
                "removed the temporary files of writes a stopped server did not finish"
            );
        }
        let me = Arc::new(Self {
            hub,
            router,
            state,
            cams: Mutex::default(),
            changed,
            measured: Mutex::default(),
            budget: budget::Budget::new(budget::DEFAULT_BYTES),
            records: OnceLock::new(),
            clock,
            frames: Mutex::default(),
            live: live::Live::default(),
        });
        me.register_fixed();
        let events = me.hub.subscribe();
        let weak = Arc::downgrade(&me);
        std::thread::Builder::new()
            .name("camera-hub".to_string())
            .spawn(move || {
                for event in events {
                    let Some(cams) = weak.upgrade() else { break };
                    match event {
                        HubEvent::Added(sn) => cams.connected(sn),
                        HubEvent::Removed(sn) => cams.disconnected(sn),
                    }
                }
            })?;
        Ok(me)
    }

    /// Sets the memory grabs in progress may take together (default 256 MiB); a grab
    /// beyond it answers 5.03 with Max-Age 1.
    pub(crate) fn set_grab_memory(&self, bytes: u64) {
        self.budget.set_limit(bytes);
    }

    /// Sets the bounds of the live streams.
    pub(crate) fn set_live_limits(&self, limits: LiveLimits) {
        self.live.set_limits(limits);
    }

    /// Keeps every measurement made for a client (`POST /cams/dimensions`) in `records`
    /// before answering it; set once.
    pub(crate) fn set_records(&self, records: Arc<dyn Records>) {
        let _ = self.records.set(records);
    }

    /// Reserves the memory of grabbing `kinds` from each of `cams`, or the 5.03 refusal.
    fn reserve(
        &self,
        cams: &[(Serial, Arc<CamState>)],
        kinds: &[Stream],
    ) -> Result<budget::Held, Busy> {
        let cost = cams
            .iter()
            .map(|(_, cam)| {
                let (color, depth) = (cam.camera.color_settings(), cam.camera.depth_settings());
                kinds
                    .iter()
                    .map(|k| budget::cost(*k, &color, &depth))
                    .sum::<u64>()
            })
            .sum();
        self.budget.take(cost)
    }

    fn register_fixed(self: &Arc<Self>) {
        let me = self.clone();
        self.router.add(
            crate::api::paths::CAMS,
            Resource::new()
                .get(handler(move |_ctx| {
                    let links = me
                        .router
                        .links(&Filter::parse("href=/cams/*").unwrap_or_default());
                    async move {
                        let mut r = Response::new(Code::CONTENT).with_payload(links);
                        set_cf(&mut r, ContentFormat::LINK_FORMAT);
                        r
                    }
                }))
                .attr("ct", "40"),
        );
        let me = self.clone();
        self.router.add(
            crate::api::paths::LIVE,
            Resource::new()
                .get(handler(move |_ctx| {
                    let response = live::report(&me.live);
                    async move { response }
                }))
                .attr("rt", "coapcam.live")
                .attr("ct", "50")
                .attr(
                    "title",
                    "extension: the live streams, their bounds and counters",
                ),
        );
        let me = self.clone();
        self.router.add(
            crate::api::paths::POINTCLOUDS,
            Resource::new()
                .post(handler(move |ctx| {
                    let me = me.clone();
                    async move { me.pointclouds(&ctx.request).await }
                }))
                .attr("rt", "rgbd.pointcloud")
                .attr("ct", Stream::Pointcloud.ct()),
        );
        let (post_me, get_me) = (self.clone(), self.clone());
        self.router.add(
            edge::PATH,
            Resource::new()
                .post(handler(move |ctx| {
                    let me = post_me.clone();
                    async move { me.measure(&ctx.request).await }
                }))
                .get(handler(move |ctx| {
                    let response = get_me.latest_measurement(&ctx.request);
                    async move { response }
                }))
                .attr("rt", "coapcam.dimensions")
                .attr("ct", "50 60")
                .attr(
                    "title",
                    "extension: POST measures the parcel with every camera here; GET the latest",
                )
                .observable(),
        );
        for name in Stream::ALL.iter().map(|s| s.name()).chain(CONFIGS) {
            let me = self.clone();
            self.router.add(
                &format!("{}/{name}", crate::api::paths::CAMS),
                Resource::new()
                    .post(handler(move |ctx| {
                        let response = me.create(name, &ctx.request);
                        async move { response }
                    }))
                    .attr(
                        "title",
                        format!("POST a serial to create /cams/<serial>/{name}"),
                    )
                    .configuring(&[Code::POST]),
            );
        }
        // What answers for an advanced-config no camera has (a pattern: literal paths,
        // the cameras' own, come first, and discovery lists none): the reason, when the
        // camera has no advanced mode.
        let me = self.clone();
        let absent = handler(move |ctx| {
            let why = ctx
                .param("sn")
                .and_then(|sn| Serial::parse(sn).ok())
                .filter(|sn| {
                    me.camera(sn)
                        .is_some_and(|cam| cam.camera.advanced_mode().is_none())
                })
                .map_or_else(|| "no such resource".to_owned(), |sn| no_advanced_mode(&sn));
            async move { Response::diagnostic(Code::NOT_FOUND, &why) }
        });
        let mut resource = Resource::new();
        for method in [Code::GET, Code::POST, Code::PUT, Code::DELETE] {
            resource = resource.on(method, absent.clone());
        }
        self.router.add(
            &format!("{}/{{sn}}/{ADVANCED}", crate::api::paths::CAMS),
            resource,
        );
    }

    fn camera(&self, sn: &Serial) -> Option<Arc<CamState>> {
        lock(&self.cams).get(sn).cloned()
    }

    /// A camera connected: its state (persisted documents re-applied) and resources.
    fn connected(self: &Arc<Self>, sn: Serial) {
        let Some(camera) = self.hub.get(&sn) else {
            return;
        };
        let cam = Arc::new(CamState {
            app: Mutex::new(
                self.restore(&sn, "application-config", AppConfig::from_json)
                    .unwrap_or_default(),
            ),
            transformation: Mutex::new(
                self.restore(&sn, "3d-transformation", Transformation::from_json)
                    .unwrap_or_else(|| default_transformation(camera.as_ref())),
            ),
            latest: Mutex::default(),
            defaults: Defaults {
                color: camera.color_settings(),
                depth: camera.depth_settings(),
                advanced: Mutex::default(),
            },
            writes: Mutex::default(),
            camera,
        });
        let modes = cam.camera.stream_modes().clone();
        if let Some(s) = self.restore(&sn, "color-settings", |j| {
            ColorSettings::from_json(j, &modes)
        }) {
            warn_on(&sn, "color-settings", cam.camera.set_color_settings(s));
        }
        if let Some(s) = self.restore(&sn, "depth-settings", |j| {
            DepthSettings::from_json(j, &modes)
        }) {
            warn_on(&sn, "depth-settings", cam.camera.set_depth_settings(s));
        }
        if let Some(advanced) = cam.camera.advanced_mode()
            && let Some(a) = self.restore(&sn, ADVANCED, AdvancedConfig::from_json)
        {
            match advanced.advanced_config() {
                Ok(own) => *lock(&cam.defaults.advanced) = Some(own),
                Err(e) => tracing::warn!(serial = %sn, "reading advanced-config: {e}"),
            }
            warn_on(&sn, ADVANCED, advanced.set_advanced_config(&a));
        }
        let names: Vec<&'static str> = names(cam.camera.as_ref()).collect();
        lock(&self.cams).insert(sn, cam);
        // All at once: a client that finds one of them finds the others.
        self.router
            .add_all(names.into_iter().map(|name| self.resource(sn, name)));
        tracing::info!(serial = %sn, "camera connected: /cams/{sn} added");
    }

    /// A persisted document that still parses; a broken one is logged and ignored.
    fn restore<T, E: std::fmt::Display>(
        &self,
        sn: &Serial,
        name: &str,
        parse: impl FnOnce(&[u8]) -> Result<T, E>,
    ) -> Option<T> {
        match self.state.load(sn, name) {
            Ok(Some(bytes)) => match parse(&bytes) {
                Ok(v) => Some(v),
                Err(e) => {
                    // Kept for a person to look at; defaults are served meanwhile.
                    match self.state.set_aside(sn, name) {
                        Ok(aside) => tracing::warn!(
                            serial = %sn,
                            name,
                            "the persisted document is not valid ({e}); moved it to {} and serve the defaults",
                            aside.display()
                        ),
                        Err(moving) => tracing::warn!(
                            serial = %sn,
                            name,
                            "the persisted document is not valid ({e}) and could not be moved aside ({moving}); serving the defaults"
                        ),
                    }
                    None
                }
            },
            Ok(None) => None,
            Err(e) => {
                tracing::warn!(serial = %sn, name, "reading persisted document: {e}");
                None
            }
        }
    }

    fn disconnected(&self, sn: Serial) {
        lock(&self.cams).remove(&sn);
        self.live.forget_camera(sn);
        let names = (Stream::ALL.iter().map(|s| s.name()))
            .chain(CONFIGS)
            .chain(live::NAMES);
        self.router
            .remove_all(names.map(|name| crate::api::paths::camera(sn, name)));
        tracing::info!(serial = %sn, "camera disconnected: /cams/{sn} removed");
    }

    /// Adds `/cams/<sn>/<name>`.
    fn add_resource(self: &Arc<Self>, sn: Serial, name: &'static str) {
        let (path, resource) = self.resource(sn, name);
        self.router.add(&path, resource);
    }

    /// The path `/cams/<sn>/<name>` and its resource.
    fn resource(self: &Arc<Self>, sn: Serial, name: &'static str) -> (String, Resource) {
        let path = crate::api::paths::camera(sn, name);
        let delete = {
            let (me, path) = (self.clone(), path.clone());
            handler(move |ctx| {
                let (me, path) = (me.clone(), path.clone());
                let by = sender(&ctx.request);
                async move {
                    if CONFIGS.contains(&name) {
                        let reset = me.clone();
                        let outcome =
                            tokio::task::spawn_blocking(move || reset.reset(sn, name, &by)).await;
                        match outcome {
                            Ok(Ok(())) => {}
                            Ok(Err((code, why))) => return Response::diagnostic(code, &why),
                            Err(e) => {
                                return Response::diagnostic(
                                    Code::INTERNAL_SERVER_ERROR,
                                    &format!("{name}: {e}"),
                                );
                            }
                        }
                    }
                    me.router.remove(&path);
                    Response::new(Code::DELETED)
                }
            })
        };
        let resource = if let Some(kind) = live::stream_of(name) {
            let me = self.clone();
            let weak = Arc::downgrade(self);
            let ct: Vec<String> = live::formats(kind)
                .iter()
                .map(|cf| cf.0.to_string())
                .collect();
            Resource::new()
                .get(handler(move |ctx| {
                    let me = me.clone();
                    async move { live::answer(&me, sn, kind, &ctx.request).await }
                }))
                .attr("rt", format!("{}.live", kind.resource_type()))
                .attr("ct", ct.join(" "))
                .attr(
                    "title",
                    "extension: observe for frames as they are captured, ?fps=N",
                )
                .observable()
                .on_observation_end(Arc::new(move |peer, id| {
                    if let Some(me) = weak.upgrade() {
                        me.live.leave((peer, id));
                    }
                }))
        } else if let Some(kind) = Stream::of(name) {
            let rt = kind.resource_type();
            let (get_me, post_me, post_path) = (self.clone(), self.clone(), path.clone());
            Resource::new()
                .get(handler(move |ctx| {
                    let response = get_me.latest(sn, kind, &ctx.request);
                    async move { response }
                }))
                .post(handler(move |ctx| {
                    let (me, path) = (post_me.clone(), post_path.clone());
                    async move { me.grab(sn, kind, &path, &ctx.request).await }
                }))
                .delete(delete)
                .attr("rt", rt)
                .attr("if", "core.p")
                .attr("ct", kind.ct())
                .observable()
                .configuring(&[Code::DELETE])
        } else {
            let (get_me, put_me) = (self.clone(), self.clone());
            Resource::new()
                .get(handler(move |_ctx| {
                    let me = get_me.clone();
                    async move { me.get_config(sn, name).await }
                }))
                .put(handler(move |ctx| {
                    let me = put_me.clone();
                    let by = sender(&ctx.request);
                    async move { me.put_config(sn, name, ctx.request.payload, by).await }
                }))
                .delete(delete)
                .attr("rt", "rgbd.config")
                .attr("if", "core.p")
                .attr("ct", "50")
                .configuring(&[Code::PUT, Code::DELETE])
        };
        (path, resource)
    }

    /// `POST /cams/<name>` with a serial: (re)creates `/cams/<serial>/<name>`.
    fn create(self: &Arc<Self>, name: &'static str, request: &IncomingRequest) -> Response {
        let text = String::from_utf8_lossy(&request.payload);
        let sn = match Serial::parse(text.trim()) {
            Ok(sn) => sn,
            Err(e) => {
                return Response::diagnostic(
                    Code::BAD_REQUEST,
                    &format!("the payload must be a camera's serial number: {e}"),
                );
            }
        };
        let Some(cam) = self.camera(&sn) else {
            return Response::diagnostic(
                Code::BAD_REQUEST,
                &format!("no camera with serial {sn} is connected"),
            );
        };
        if !names(cam.camera.as_ref()).any(|n| n == name) {
            return Response::diagnostic(Code::BAD_REQUEST, &no_advanced_mode(&sn));
        }
        self.add_resource(sn, name);
        let mut r = Response::new(Code::CREATED);
        for seg in ["cams", sn.as_str(), name] {
            r.options.push(OptionNumber::LOCATION_PATH, seg.as_bytes());
        }
        r
    }

    /// `POST /cams/<sn>/<grab>`: a new frame.
    async fn grab(
        &self,
        sn: Serial,
        kind: Stream,
        path: &str,
        request: &IncomingRequest,
    ) -> Response {
        if let Err(refused) = negotiate(kind, request) {
            return refused;
        }
        let Some(cam) = self.camera(&sn) else {
            return Response::diagnostic(Code::NOT_FOUND, &format!("camera {sn} is disconnected"));
        };
        let _held = match self.reserve(&[(sn, cam.clone())], &[kind]) {
            Ok(held) => held,
            Err(busy) => return busy.response(),
        };
        let app = lock(&cam.app).clone();
        let transformation = *lock(&cam.transformation);
        let camera = cam.camera.clone();
        let grabbed = tokio::task::spawn_blocking(move || match kind {
            Stream::Color => grab::color(camera.as_ref(), &app),
            Stream::Depth => grab::depth(camera.as_ref(), &app),
            Stream::Pointcloud => grab::cloud(camera.as_ref(), &app, &transformation),
        })
        .await;
        let frame = match grabbed {
            Ok(Ok(frame)) => frame.on_clock(&self.clock),
            Ok(Err(e)) => return grab_error(&sn, &e),
            Err(e) => {
                return Response::diagnostic(
                    Code::INTERNAL_SERVER_ERROR,
                    &format!("grab task: {e}"),
                );
            }
        };
        let etag = frame_etag(&sn, kind, &frame);
        let stored = Arc::new((frame, etag));
        lock(&cam.latest)[kind.index()] = Some(stored.clone());
        let _ = self.changed.send(path.to_string());
        represent(&sn, kind, &stored.0, etag, request)
    }

    /// `GET /cams/<sn>/<grab>`: the latest frame.
    fn latest(&self, sn: Serial, kind: Stream, request: &IncomingRequest) -> Response {
        if let Err(refused) = negotiate(kind, request) {
            return refused;
        }
        let stored = self
            .camera(&sn)
            .and_then(|cam| lock(&cam.latest)[kind.index()].clone());
        match stored {
            Some(s) => represent(&sn, kind, &s.0, s.1, request),
            None => Response::diagnostic(Code::NOT_FOUND, "no frame grabbed yet: POST grabs one"),
        }
    }

    async fn get_config(&self, sn: Serial, name: &'static str) -> Response {
        let Some(cam) = self.camera(&sn) else {
            return Response::diagnostic(Code::NOT_FOUND, &format!("camera {sn} is disconnected"));
        };
        let doc = match name {
            "color-settings" => Ok(cam.camera.color_settings().to_json()),
            "depth-settings" => Ok(cam.camera.depth_settings().to_json()),
            "application-config" => Ok(lock(&cam.app).to_json()),
            "3d-transformation" => Ok(lock(&cam.transformation).to_json()),
            _ => {
                let camera = cam.camera.clone();
                let read = move || camera.advanced_mode().map(AdvancedMode::advanced_config);
                match tokio::task::spawn_blocking(read).await {
                    Ok(Some(Ok(a))) => Ok(a.to_json()),
                    Ok(Some(Err(e))) => Err(e.to_string()),
                    Ok(None) => {
                        return Response::diagnostic(Code::NOT_FOUND, &no_advanced_mode(&sn));
                    }
                    Err(e) => Err(e.to_string()),
                }
            }
        };
        match doc {
            Ok(doc) => {
                let mut r = Response::new(Code::CONTENT).with_payload(doc);
                set_cf(&mut r, ContentFormat::JSON);
                r
            }
            Err(e) => Response::diagnostic(Code::SERVICE_UNAVAILABLE, &format!("{name}: {e}")),
        }
    }

    /// `PUT`: validate completely, apply, persist; a refused document changes nothing.
    #[expect(
        clippy::result_large_err,
        reason = "a refusal is the Response sent; it keeps its options inline"
    )]
    async fn put_config(
        self: &Arc<Self>,
        sn: Serial,
        name: &'static str,
        body: Bytes,
        by: String,
    ) -> Response {
        let Some(cam) = self.camera(&sn) else {
            return Response::diagnostic(Code::NOT_FOUND, &format!("camera {sn} is disconnected"));
        };
        let me = self.clone();
        match tokio::task::spawn_blocking(move || me.replace(&sn, &cam, name, &body, &by)).await {
            Ok(Ok(())) => {
                tracing::info!(serial = %sn, "{name} of camera {sn} changed");
                Response::new(Code::CHANGED)
            }
            Ok(Err(r)) => r,
            Err(e) => Response::diagnostic(Code::INTERNAL_SERVER_ERROR, &format!("{name}: {e}")),
        }
    }

    #[expect(
        clippy::result_large_err,
        reason = "a refusal is the Response sent; it keeps its options inline"
    )]
    fn replace(
        &self,
        sn: &Serial,
        cam: &CamState,
        name: &str,
        body: &[u8],
        by: &str,
    ) -> Result<(), Response> {
        let bad = |e: &dyn std::fmt::Display| {
            Response::diagnostic(Code::BAD_REQUEST, &format!("{name}: {e}"))
        };
        let _one_at_a_time = lock(&cam.writes);
        let audited = self.audited(sn, cam, name)?;
        let camera = &cam.camera;
        let modes = camera.stream_modes();
        // Validate, and keep what undoes the change if persisting fails.
        let (stored, undo): (String, Box<dyn FnOnce() + '_>) = match name {
            "color-settings" => {
                let new = ColorSettings::from_json(body, modes).map_err(|e| bad(&e))?;
                let frames = [("color", new.width, new.height)];
                lock(&cam.app).check_frames(&frames).map_err(|e| bad(&e))?;
                let old = camera.color_settings();
                camera.set_color_settings(new).map_err(|e| bad(&e))?;
                (
                    new.to_json(),
                    Box::new(move || warn_on(sn, name, camera.set_color_settings(old))),
                )
            }
            "depth-settings" => {
                let new = DepthSettings::from_json(body, modes).map_err(|e| bad(&e))?;
                let frames = [("depth", new.width, new.height)];
                lock(&cam.app).check_frames(&frames).map_err(|e| bad(&e))?;
                let old = camera.depth_settings();
                camera.set_depth_settings(new).map_err(|e| bad(&e))?;
                (
                    new.to_json(),
                    Box::new(move || warn_on(sn, name, camera.set_depth_settings(old))),
                )
            }
            "application-config" => {
                let new = AppConfig::from_json(body).map_err(|e| bad(&e))?;
                let (color, depth) = (camera.color_settings(), camera.depth_settings());
                new.check_frames(&[
                    ("color", color.width, color.height),
                    ("depth", depth.width, depth.height),
                ])
                .map_err(|e| bad(&e))?;
                // The filters this camera can run: the spatial filter needs a stereo pair.
                let baseline_mm = camera.stereo_baseline_m().map(|b| b * 1000.0);
                PostProcessing::new(&new.postprocessing, baseline_mm).map_err(|e| bad(&e))?;
                let json = new.to_json();
                let old = std::mem::replace(&mut *lock(&cam.app), new);
                (json, Box::new(move || *lock(&cam.app) = old))
            }
            "3d-transformation" => {
                let new = Transformation::from_json(body).map_err(|e| bad(&e))?;
                new.to_transform().map_err(|e| bad(&e))?;
                let old = std::mem::replace(&mut *lock(&cam.transformation), new);
                (
                    new.to_json(),
                    Box::new(move || *lock(&cam.transformation) = old),
                )
            }
            _ => {
                let advanced = camera
                    .advanced_mode()
                    .ok_or_else(|| Response::diagnostic(Code::NOT_FOUND, &no_advanced_mode(sn)))?;
                let new = AdvancedConfig::from_json(body).map_err(|e| bad(&e))?;
                let old = advanced
                    .advanced_config()
                    .map_err(|e| camera_error(sn, &e))?;
                lock(&cam.defaults.advanced).get_or_insert_with(|| old.clone());
                advanced.set_advanced_config(&new).map_err(|e| bad(&e))?;
                let full = advanced
                    .advanced_config()
                    .map_err(|e| camera_error(sn, &e))?;
                (
                    full.to_json(),
                    Box::new(move || warn_on(sn, name, advanced.set_advanced_config(&old))),
                )
            }
        };
        if let Err(e) = self.state.store(sn, name, stored.as_bytes()) {
            tracing::warn!(serial = %sn, name, "persisting: {e}");
            undo();
            return Err(Response::diagnostic(
                Code::INTERNAL_SERVER_ERROR,
                &format!("{name}: cannot persist the document ({e}); nothing was changed"),
            ));
        }
        if let Some(before) = audited
            && let Err(why) = self.record_change(sn, name, Change::Put, &before, by)
        {
            undo();
            return Err(self.unrecorded(sn, name, &before, &why));
        }
        Ok(())
    }

    /// What an event of a change to `name` needs from before it: the document as `GET`
    /// serves it, and as the state directory holds it; `None` when `name` holds no legally
    /// relevant parameter or no results log is set.
    #[expect(
        clippy::result_large_err,
        reason = "a refusal is the Response sent; it keeps its options inline"
    )]
    fn audited(&self, sn: &Serial, cam: &CamState, name: &str) -> Result<Option<Before>, Response> {
        if !LEGAL.contains(&name) || self.records.get().is_none() {
            return Ok(None);
        }
        let stored = self.state.load(sn, name).map_err(|e| {
            Response::diagnostic(
                Code::INTERNAL_SERVER_ERROR,
                &format!("{name}: reading the document kept: {e}; nothing was changed"),
            )
        })?;
        Ok(Some(Before {
            served: legal_document(cam, name),
            stored,
            app: lock(&cam.app).clone(),
            transformation: *lock(&cam.transformation),
        }))
    }

    /// Records the change of `name` (made, `before` it) in the results log: which
    /// document, the SHA-256 of its content before and after, `by` whom, and the
    /// parameters in force now.
    fn record_change(
        &self,
        sn: &Serial,
        name: &str,
        change: Change,
        before: &Before,
        by: &str,
    ) -> Result<(), String> {
        let Some(records) = self.records.get() else {
            return Ok(());
        };
        let Some(cam) = self.camera(sn) else {
            return Err(format!("camera {sn} is disconnected"));
        };
        let after = legal_document(&cam, name);
        records.change(Event {
            document: crate::api::paths::camera(*sn, name),
            change,
            old_sha256: sha256_hex(before.served.as_bytes()),
            new_sha256: sha256_hex(after.as_bytes()),
            by: by.to_owned(),
            parameters_sha256: Rig::parameters_sha256(self),
        })
    }

    /// The refusal of a change that could not be recorded, after putting back in the
    /// state directory what it held `before` (the caller has undone the change in memory).
    fn unrecorded(&self, sn: &Serial, name: &str, before: &Before, why: &str) -> Response {
        let restored = match &before.stored {
            Some(bytes) => self.state.store(sn, name, bytes),
            None => self.state.remove(sn, name),
        };
        if let Err(e) = restored {
            tracing::error!(serial = %sn, name, "putting the kept document back: {e}");
        }
        // 5.03, as a measurement that cannot be recorded: no change without its event.
        Response::diagnostic(
            Code::SERVICE_UNAVAILABLE,
            &format!("{name}: the change could not be recorded ({why}); nothing was changed"),
        )
    }

    /// `DELETE` of a configuration document: the camera's own (its defaults) again, at
    /// once in memory, on the camera and in the state directory (so a restart or a
    /// re-created resource does not bring the old one back).
    /// A refusal is its code and diagnostic.
    fn reset(&self, sn: Serial, name: &str, by: &str) -> Result<(), (Code, String)> {
        let Some(cam) = self.camera(&sn) else {
            return Err((Code::NOT_FOUND, format!("camera {sn} is disconnected")));
        };
        let _one_at_a_time = lock(&cam.writes);
        let audited = self
            .audited(&sn, &cam, name)
            .map_err(|r| (r.code, String::from_utf8_lossy(&r.payload).into_owned()))?;
        let failed = |e: &dyn std::fmt::Display| {
            (
                Code::INTERNAL_SERVER_ERROR,
                format!("{name}: going back to the defaults: {e}"),
            )
        };
        let camera = &cam.camera;
        match name {
            "color-settings" => camera
                .set_color_settings(cam.defaults.color)
                .map_err(|e| failed(&e))?,
            "depth-settings" => camera
                .set_depth_settings(cam.defaults.depth)
                .map_err(|e| failed(&e))?,
            "application-config" => *lock(&cam.app) = AppConfig::default(),
            "3d-transformation" => {
                *lock(&cam.transformation) = default_transformation(camera.as_ref());
            }
            _ => {
                if let Some(advanced) = camera.advanced_mode()
                    && let Some(own) = lock(&cam.defaults.advanced).clone()
                {
                    advanced.set_advanced_config(&own).map_err(|e| failed(&e))?;
                }
            }
        }
        self.state.remove(&sn, name).map_err(|e| failed(&e))?;
        if let Some(before) = audited
            && let Err(why) = self.record_change(&sn, name, Change::Delete, &before, by)
        {
            *lock(&cam.app) = before.app.clone();
            *lock(&cam.transformation) = before.transformation;
            let refused = self.unrecorded(&sn, name, &before, &why);
            return Err((
                refused.code,
                String::from_utf8_lossy(&refused.payload).into_owned(),
            ));
        }
        tracing::info!(serial = %sn, "{name} of camera {sn} back to the defaults");
        Ok(())
    }

    /// `POST /cams/pointclouds`: every camera's cloud in the common frame, merged.
    async fn pointclouds(&self, request: &IncomingRequest) -> Response {
        let cf = match negotiate(Stream::Pointcloud, request) {
            Ok(cf) => cf,
            Err(refused) => return refused,
        };
        let cams = self.snapshot();
        let _held = match self.reserve(&cams, &[Stream::Pointcloud]) {
            Ok(held) => held,
            Err(busy) => return busy.response(),
        };
        let merged = self.grab_merged(cams).await;
        if cf == repr::DEPTH_CLOUD && merged.parts.is_empty() {
            // The compact cloud is made of cameras' depth: without one there is nothing
            // to send in it (the other formats send an empty cloud).
            return no_cloud(&merged.failed);
        }
        let source = CloudSource::Merged {
            serials: &merged.serials,
        };
        let subject = Subject::Cloud {
            points: &merged.cloud.points,
            timestamp_us: merged.timestamp_us,
            source,
            parts: &merged.parts,
        };
        let body = encode(cf, &subject);
        let body = match body {
            Ok(body) => body,
            Err(e) => return Response::diagnostic(Code::INTERNAL_SERVER_ERROR, &e.to_string()),
        };
        let mut h = std::collections::hash_map::DefaultHasher::new();
        body.hash(&mut h);
        with_no_depth(
            content(body, cf, h.finish().to_be_bytes()),
            &merged.no_depth,
        )
    }

    /// The connected cameras, in merge order.
    fn snapshot(&self) -> Vec<(Serial, Arc<CamState>)> {
        lock(&self.cams)
            .iter()
            .map(|(sn, c)| (*sn, c.clone()))
            .collect()
    }

    /// A new cloud of each of `cams`, each in the common frame, merged (cameras with `icp`
    /// registered onto those before them); a camera whose grab fails is left out, with
    /// the reason in `failed`.
    async fn grab_merged(&self, cams: Vec<(Serial, Arc<CamState>)>) -> Merged {
        let tasks: Vec<_> = cams
            .into_iter()
            .map(|(sn, cam)| {
                let app = lock(&cam.app).clone();
                let transformation = *lock(&cam.transformation);
                let icp = app.icp;
                let task = tokio::task::spawn_blocking(move || {
                    grab::cloud(cam.camera.as_ref(), &app, &transformation)
                });
                (sn, icp, task)
            })
            .collect();
        let mut parts = Vec::new();
        let mut floors = Vec::new();
        let mut no_depth = Vec::new();
        let mut failed = Vec::new();
        for (sn, icp, task) in tasks {
            match task.await {
                Ok(Ok(Frame::Cloud {
                    points,
                    mut part,
                    floor_m,
                    no_depth: blind,
                })) => {
                    part.depth.timestamp_us = self.clock.shift(part.depth.timestamp_us);
                    floors.push((Some(sn.to_string()), floor_m));
                    no_depth.extend(blind);
                    parts.push((sn, icp, points, part));
                }
                Ok(Ok(_)) => {}
                Ok(Err(e)) => {
                    tracing::warn!(serial = %sn, "pointclouds: {e}");
                    failed.push(format!("camera {sn}: {e}"));
                }
                Err(e) => {
                    tracing::warn!(serial = %sn, "pointclouds: grab task: {e}");
                    failed.push(format!("camera {sn}: grab task: {e}"));
                }
            }
        }
        let mut serials: Vec<Serial> = parts.iter().map(|(sn, ..)| *sn).collect();
        let mut frames_us: Vec<u64> = parts
            .iter()
            .map(|(.., part)| part.depth.timestamp_us)
            .collect();
        let timestamp_us = frames_us
            .iter()
            .copied()
            .max()
            .unwrap_or_else(|| u64::try_from(self.clock.now_us()).unwrap_or(0));
        let (cloud, parts) =
            match tokio::task::spawn_blocking(move || register_and_merge(parts)).await {
                Ok(merged) => merged,
                Err(e) => {
                    failed.push(format!("merging the clouds: {e}"));
                    serials.clear();
                    frames_us.clear();
                    (PointCloud::default(), Vec::new())
                }
            };
        Merged {
            cloud,
            parts,
            serials,
            frames_us,
            timestamp_us,
            floors,
            no_depth,
            failed,
        }
    }

    /// `POST /cams/dimensions`: a new measurement with every camera of this server (see
    /// [`Cams::measure_now`]), in the format the request accepts.
    async fn measure(&self, request: &IncomingRequest) -> Response {
        let cf = match edge::negotiate(request) {
            Ok(cf) => cf,
            Err(refused) => return refused,
        };
        let query = match EdgeQuery::parse(request.options.uri_query()) {
            Ok(q) => q,
            Err(why) => return Response::diagnostic(Code::BAD_REQUEST, &why),
        };
        // Its own measurement, not the latest: another may have ended meanwhile. With a
        // results log it comes with the photo and the annotated picture to record.
        let records = self.records.get();
        let measured =
            match measure::measure(self, &query, Trigger::Request, records.is_some()).await {
                Ok(measured) => measured,
                Err(e) => return e.response(),
            };
        let m = measured.measurement.clone();
        // Kept before it is answered: an answered measurement is in the log. One that
        // found no parcel (an empty table, e.g. `measure --prepare` while setting up) is
        // no result: not kept, as the automatic measurement keeps none either.
        let found = m.parcel != report::Found::Nothing;
        if !found && records.is_some() {
            tracing::info!("POST /cams/dimensions found no parcel: not recorded");
        }
        if found
            && let Some(records) = records
            && let Err(why) = records.keep(measured).await
        {
            // 5.03: the station gives no result without its record, for now (the log may
            // write again: a new file after a removed one, a disk with room again).
            let why = format!("measured, but the measurement could not be recorded: {why}");
            return Response::diagnostic(Code::SERVICE_UNAVAILABLE, &why);
        }
        match edge::stored(m) {
            Ok(stored) => measurement(&stored, cf),
            Err(e) => EdgeError::from(e).response(),
        }
    }

    /// The serial and 3d-transformation of each camera of `serials` still connected.
    pub(crate) fn poses(&self, serials: &[String]) -> Vec<CameraPose> {
        let cams = lock(&self.cams);
        serials
            .iter()
            .filter_map(|sn| {
                let cam = cams.iter().find(|(s, _)| s.to_string() == *sn)?.1;
                Some(CameraPose {
                    serial: sn.clone(),
                    transformation: *lock(&cam.transformation),
                })
            })
            .collect()
    }

    /// Sets every camera's color stream to its largest resolution (the frame rate kept
    /// where it is offered there, else the highest one that is), where a code's modules
    /// span the most pixels: the codes the station reads (`?codes`, `--auto-measure`, the
    /// page) decide the color mode, not a setting someone must remember. What each camera
    /// reads at its distance from the table, one entry per camera.
    pub(crate) fn color_for_codes(&self) -> Vec<CodeColor> {
        self.snapshot()
            .into_iter()
            .map(|(sn, cam)| {
                let camera = &cam.camera;
                let old = camera.color_settings();
                let largest = camera.stream_modes().color.first().map(|m| ColorSettings {
                    width: m.width,
                    height: m.height,
                    fps: if m.fps.contains(&old.fps) {
                        old.fps
                    } else {
                        m.fps
                            .iter()
                            .copied()
                            .filter(|&f| f <= old.fps)
                            .max()
                            .or_else(|| m.fps.first().copied())
                            .unwrap_or(old.fps)
                    },
                    ..old
                });
                let mut changed = None;
                let mut failed = None;
                if let Some(new) = largest
                    && (new.width, new.height) != (old.width, old.height)
                {
                    match camera.set_color_settings(new) {
                        Ok(()) => changed = Some((old.width, old.height)),
                        Err(e) => failed = Some(e.to_string()),
                    }
                }
                let now = camera.color_settings();
                let distance_m = table_distance_m(&lock(&cam.transformation));
                let fx = camera.color_intrinsics().ok().map(|i| f64::from(i.fx));
                CodeColor {
                    serial: sn.to_string(),
                    from: changed,
                    to: (now.width, now.height),
                    failed,
                    distance_m,
                    narrowest_mm: fx
                        .zip(distance_m)
                        .map(|(fx, d)| codes::narrowest_module_mm(fx, d)),
                    logistic_reach_m: fx.map(|fx| codes::farthest_m(fx, codes::LOGISTIC_MODULE_MM)),
                }
            })
            .collect()
    }

    /// Measures with every camera of this server, as `query` asks ([`edge`]): grabs and
    /// merges their clouds (reading the codes from new color images meanwhile when asked),
    /// measures the largest parcel, and keeps the result as the latest measurement
    /// (`GET /cams/dimensions`, whose observers are notified). The measurement has the
    /// server's fields: no `servers`, `cycle_ms` or `received_bytes`.
    pub(crate) async fn measure_now(&self, query: &EdgeQuery) -> Result<Measurement, EdgeError> {
        let cams = self.snapshot();
        if cams.is_empty() {
            return Err(EdgeError::NoCamera);
        }
        if query.codes {
            for c in self.color_for_codes() {
                if c.from.is_some() || c.failed.is_some() {
                    tracing::info!("{c}");
                }
            }
        }
        let kinds: &[Stream] = if query.codes {
            &[Stream::Pointcloud, Stream::Color]
        } else {
            &[Stream::Pointcloud]
        };
        let _held = self.reserve(&cams, kinds)?;
        let started = Instant::now();
        let asked_us = self.clock.now_us();
        let rates: BTreeMap<Serial, u32> = cams
            .iter()
            .map(|(sn, cam)| (*sn, cam.camera.depth_settings().fps))
            .collect();
        // The color images for the codes are grabbed and read while the clouds are.
        let codes = query.codes.then(|| {
            let cameras = cams
                .iter()
                .map(|(sn, cam)| (*sn, cam.camera.clone(), lock(&cam.app).clone()))
                .collect();
            edge::read_codes(cameras, started)
        });
        let uncalibrated: Vec<String> = cams
            .iter()
            .filter(|(_, cam)| *lock(&cam.transformation) == Transformation::identity())
            .map(|(sn, _)| sn.to_string())
            .collect();
        let merged = self.grab_merged(cams).await;
        if merged.parts.is_empty() {
            return Err(EdgeError::NoCloud(merged.failed));
        }
        let grab = started.elapsed();
        // One host, one clock: only staleness is checked (its grabs start together).
        let frames: Vec<FrameTime> = merged
            .parts
            .iter()
            .map(|part| FrameTime {
                camera: part.serial.clone(),
                server: None,
                frame_number: part.depth.frame_number,
                captured_unix_us: i64::try_from(part.depth.timestamp_us).unwrap_or(i64::MAX),
                requested_unix_us: Some(asked_us),
                clock: None,
                fps: Serial::parse(&part.serial)
                    .ok()
                    .and_then(|sn| rates.get(&sn).copied()),
            })
            .collect();
        let limits = Limits {
            max_skew_us: None,
            skew: false,
        };
        let stale = timesync::check_frames(&frames, &limits, &mut lock(&self.frames));
        if !stale.is_empty() {
            let reasons: Vec<String> = stale.iter().map(ToString::to_string).collect();
            let mut m = Measurement::new(
                &report::Parcel::Nothing { points: 0 },
                &query.billing,
                0,
                merged.serials.iter().map(ToString::to_string).collect(),
                merged.frames_us,
                grab,
            );
            m.parcel = report::Found::Unsynced {
                reason: reasons.join("; "),
            };
            m.frames = frames;
            m.warnings = reasons;
            m.warnings.extend(merged.failed);
            if let Some(task) = codes {
                task.abort();
            }
            m.measure_ms = Some(report::ms(started.elapsed()));
            let stored = Arc::new(edge::stored(m.clone())?);
            *lock(&self.measured) = Some(stored);
            let _ = self.changed.send(edge::PATH.to_string());
            return Ok(m);
        }
        let config = query.config;
        let (table, merged) =
            tokio::task::spawn_blocking(move || (merged.table(&config), merged)).await?;
        let mut m = Measurement::of_table(
            &table?,
            &query.billing,
            config.min_coverage,
            merged.cloud.len(),
            merged.serials.iter().map(ToString::to_string).collect(),
            merged.frames_us,
            grab,
        );
        m.frames = frames;
        m.warnings = report::calibration_warnings(&uncalibrated, &merged.floors);
        m.withhold_uncalibrated(&uncalibrated);
        m.warnings.extend(merged.failed);
        if let Some(task) = codes {
            match task.await {
                Ok((seen, failed, took)) => {
                    m.set_codes(seen, took);
                    m.warnings.extend(failed);
                }
                Err(e) => m.warnings.push(format!("code reading: {e}")),
            }
        }
        m.measure_ms = Some(report::ms(started.elapsed()));
        let stored = Arc::new(edge::stored(m.clone())?);
        *lock(&self.measured) = Some(stored);
        let _ = self.changed.send(edge::PATH.to_string());
        Ok(m)
    }

    /// `GET /cams/dimensions`: the latest measurement.
    fn latest_measurement(&self, request: &IncomingRequest) -> Response {
        let cf = match edge::negotiate(request) {
            Ok(cf) => cf,
            Err(refused) => return refused,
        };
        match lock(&self.measured).clone() {
            Some(stored) => measurement(&stored, cf),
            None => Response::diagnostic(Code::NOT_FOUND, "no measurement yet: POST measures"),
        }
    }
}

impl live::Cameras for Cams {
    fn live(&self) -> &live::Live {
        &self.live
    }

    fn rate(&self, sn: Serial, kind: Stream) -> Option<u32> {
        let cam = self.camera(&sn)?;
        Some(match kind {
            Stream::Color => cam.camera.color_settings().fps,
            Stream::Depth | Stream::Pointcloud => cam.camera.depth_settings().fps,
        })
    }

    fn grab(&self, sn: Serial, kind: Stream) -> Result<Frame, String> {
        let cam = self
            .camera(&sn)
            .ok_or_else(|| format!("camera {sn} is disconnected"))?;
        let _held = self
            .reserve(&[(sn, cam.clone())], &[kind])
            .map_err(|busy| busy.to_string())?;
        let app = lock(&cam.app).clone();
        let transformation = *lock(&cam.transformation);
        let camera = cam.camera.as_ref();
        let frame = match kind {
            Stream::Color => grab::color(camera, &app),
            Stream::Depth => grab::depth(camera, &app),
            Stream::Pointcloud => grab::cloud(camera, &app, &transformation),
        };
        frame
            .map(|f| f.on_clock(&self.clock))
            .map_err(|e| e.to_string())
    }

    fn changed(&self, path: &str) {
        let _ = self.changed.send(path.to_owned());
    }
}

impl Rig for Cams {
    type Error = EdgeError;

    async fn measure(&self, query: &EdgeQuery) -> Result<Measurement, EdgeError> {
        self.measure_now(query).await
    }

    async fn shot(&self, serial: Serial) -> Result<Shot, String> {
        let cam = self
            .camera(&serial)
            .ok_or_else(|| format!("camera {serial} is not connected"))?;
        let app = lock(&cam.app).clone();
        let transformation = *lock(&cam.transformation);
        let grabbed = tokio::task::spawn_blocking(move || grab::color(cam.camera.as_ref(), &app))
            .await
            .map_err(|e| format!("camera {serial}: color grab task: {e}"))?;
        match grabbed.map(|f| f.on_clock(&self.clock)) {
            Ok(Frame::Color(frame, intrinsics, depth_to_color)) => Ok(Shot {
                frame,
                intrinsics,
                depth_to_color,
                transformation,
            }),
            Ok(_) => Err(format!(
                "camera {serial}: the color grab gave no color frame"
            )),
            Err(e) => Err(format!("camera {serial}: color: {e}")),
        }
    }

    fn poses(&self, serials: &[String]) -> Vec<CameraPose> {
        Self::poses(self, serials)
    }

    fn cameras(&self) -> Vec<RigCamera> {
        self.snapshot()
            .into_iter()
            .map(|(serial, cam)| RigCamera {
                serial,
                camera: cam.camera.clone(),
                transformation: *lock(&cam.transformation),
            })
            .collect()
    }

    fn parameters_sha256(&self) -> String {
        let documents: Vec<(String, String)> = self
            .snapshot()
            .into_iter()
            .flat_map(|(sn, cam)| {
                LEGAL.map(|name| {
                    (
                        crate::api::paths::camera(sn, name),
                        legal_document(&cam, name),
                    )
                })
            })
            .collect();
        parameters_sha256(
            documents
                .iter()
                .map(|(path, doc)| (path.clone(), doc.as_bytes())),
        )
    }
}

/// A camera's document of legally relevant parameters `name` (one of [`LEGAL`]) as `GET`
/// serves it.
fn legal_document(cam: &CamState, name: &str) -> String {
    if name == "application-config" {
        lock(&cam.app).to_json()
    } else {
        lock(&cam.transformation).to_json()
    }
}

/// What a change of legally relevant parameters needs from before it, to record it and
/// to undo it when it cannot be recorded.
struct Before {
    /// The document as `GET` served it.
    served: String,
    /// The document as the state directory held it (`None`: none, the camera's own).
    stored: Option<Vec<u8>>,
    /// The camera's application-config.
    app: AppConfig,
    /// The camera's 3d-transformation.
    transformation: Transformation,
}

/// 5.03 for a request that needs a camera's cloud when no camera gave one, with why.
fn no_cloud(failed: &[String]) -> Response {
    let why = if failed.is_empty() {
        "no camera is connected".to_string()
    } else {
        format!("no camera gave a cloud: {}", failed.join("; "))
    };
    Response::diagnostic(Code::SERVICE_UNAVAILABLE, &why)
}

/// A measurement's document as the answer in `cf`.
fn measurement(stored: &(Measurement, [u8; 8]), cf: ContentFormat) -> Response {
    match edge::body(stored, cf) {
        Ok((body, etag)) => content(body, cf, etag),
        Err(why) => Response::diagnostic(Code::INTERNAL_SERVER_ERROR, &why.to_string()),
    }
}

fn warn_on(sn: &Serial, name: &str, result: Result<(), CameraError>) {
    if let Err(e) = result {
        tracing::warn!(serial = %sn, name, "re-applying: {e}");
    }
}

fn camera_error(sn: &Serial, e: &CameraError) -> Response {
    match e {
        CameraError::Disconnected { .. } => {
            Response::diagnostic(Code::NOT_FOUND, &format!("camera {sn} is disconnected"))
        }
        CameraError::Timeout { timeout_ms } => {
            let mut r = Response::diagnostic(
                Code::SERVICE_UNAVAILABLE,
                &format!("camera {sn}: no frame within {timeout_ms} ms; retry later"),
            );
            let secs = timeout_ms.div_ceil(1000).max(1);
            r.options.set_uint(
                OptionNumber::MAX_AGE,
                u32::try_from(secs).unwrap_or(u32::MAX),
            );
            r
        }
        other => Response::diagnostic(
            Code::INTERNAL_SERVER_ERROR,
            &format!("camera {sn}: {other}"),
        ),
    }
}

fn grab_error(sn: &Serial, e: &GrabError) -> Response {
    tracing::warn!(serial = %sn, "grab: {e}");
    match e {
        GrabError::Camera(c) => camera_error(sn, c),
        GrabError::RoiOutside { .. }
        | GrabError::Transform(_)
        | GrabError::Filter(FilterError::NoStereoPair) => {
            Response::diagnostic(Code::BAD_REQUEST, &e.to_string())
        }
        GrabError::Filter(_) => Response::diagnostic(Code::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
}

/// The content format to answer with, or 4.06 Not Acceptable.
#[expect(
    clippy::result_large_err,
    reason = "a refusal is the Response sent; it keeps its options inline"
)]
fn negotiate(kind: Stream, request: &IncomingRequest) -> Result<ContentFormat, Response> {
    let accept = request
        .options
        .accept()
        .unwrap_or(ContentFormat::OCTET_STREAM);
    if kind.offers(accept) {
        Ok(accept)
    } else {
        Err(Response::diagnostic(
            Code::NOT_ACCEPTABLE,
            &kind.not_acceptable(),
        ))
    }
}

/// A frame in the format the request accepts; the ETag is the frame's, made distinct per
/// content format (RFC 7252 §5.10.6: an entity-tag identifies one representation).
fn represent(
    sn: &Serial,
    kind: Stream,
    frame: &Frame,
    etag: [u8; 8],
    request: &IncomingRequest,
) -> Response {
    let cf = match negotiate(kind, request) {
        Ok(cf) => cf,
        Err(refused) => return refused,
    };
    let quality = match jpeg_quality(request, cf) {
        Ok(q) => q,
        Err(refused) => return refused,
    };
    let subject = subject(sn, frame, quality.unwrap_or(raster::JPEG_QUALITY));
    let body = encode(cf, &subject);
    let response = match body {
        Ok(body) => content(body, cf, representation_etag(etag, cf, quality)),
        Err(e) => return Response::diagnostic(Code::INTERNAL_SERVER_ERROR, &e.to_string()),
    };
    match frame {
        Frame::Cloud { no_depth, .. } => with_no_depth(response, no_depth),
        _ => response,
    }
}

/// The JPEG quality a request asks for with the query `q=N` (1-100), if it does; 4.00 for
/// a bad one or for `q` with another format than JPEG.
#[expect(
    clippy::result_large_err,
    reason = "a refusal is the Response sent; it keeps its options inline"
)]
fn jpeg_quality(request: &IncomingRequest, cf: ContentFormat) -> Result<Option<u8>, Response> {
    let Some(q) = request
        .options
        .uri_query()
        .find_map(|item| item.strip_prefix("q=").map(str::to_owned))
    else {
        return Ok(None);
    };
    if cf != ContentFormat::IMAGE_JPEG {
        let why = "q (the JPEG quality) needs Accept: image/jpeg (22)";
        return Err(Response::diagnostic(Code::BAD_REQUEST, why));
    }
    match q.parse::<u8>() {
        Ok(n @ 1..=100) => Ok(Some(n)),
        _ => Err(Response::diagnostic(
            Code::BAD_REQUEST,
            &format!("q={q}: the JPEG quality is a whole number from 1 to 100"),
        )),
    }
}

/// How far along its optical axis camera's 3d-transformation puts the table (the plane
/// z = 0) in front of it, metres; `None` for an uncalibrated camera (the identity) or
/// one that looks along or above the table.
fn table_distance_m(transformation: &Transformation) -> Option<f64> {
    if *transformation == Transformation::identity() {
        return None;
    }
    let t = transformation.to_transform().ok()?;
    let centre = t.apply(&Point3::new(0.0, 0.0, 0.0));
    let ahead = t.apply(&Point3::new(0.0, 0.0, 1.0));
    let (c, a) = (centre.coords.cast::<f64>(), ahead.coords.cast::<f64>());
    let axis = a - c;
    // The axis must come down towards the table, at least 6 degrees below level.
    (axis.z < -0.1 * axis.norm() && c.z > 0.0).then(|| c.z / -axis.z * axis.norm())
}

/// A camera's color stream as the codes need it (`Cams::color_for_codes`).
#[derive(Debug, Clone, PartialEq)]
pub struct CodeColor {
    /// The camera's serial.
    pub serial: String,
    /// The resolution it had when this changed it; `None` when it was already there.
    pub from: Option<(u32, u32)>,
    /// Its color resolution now.
    pub to: (u32, u32),
    /// Why the camera refused the largest resolution.
    pub failed: Option<String>,
    /// The table's distance along its optical axis, metres; `None` uncalibrated.
    pub distance_m: Option<f64>,
    /// The narrowest module read on the table, millimetres (nearer surfaces, a parcel's
    /// lid, show narrower ones).
    pub narrowest_mm: Option<f64>,
    /// The farthest distance that reads a GS1 logistic label's narrowest module.
    pub logistic_reach_m: Option<f64>,
}

impl CodeColor {
    /// Whether the table is too far for a GS1 logistic label's narrowest module.
    pub fn too_far(&self) -> bool {
        self.narrowest_mm
            .is_some_and(|mm| mm > codes::LOGISTIC_MODULE_MM)
    }
}

impl std::fmt::Display for CodeColor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (w, h) = self.to;
        write!(f, "camera {}: codes read at color {w}x{h}", self.serial)?;
        if let Some((ow, oh)) = self.from {
            write!(f, " (set from {ow}x{oh})")?;
        }
        if let Some(e) = &self.failed {
            write!(f, " (the largest resolution refused: {e})")?;
        }
        match (self.distance_m, self.narrowest_mm) {
            (Some(d), Some(mm)) => write!(
                f,
                "; the table {d:.2} m away: modules from {mm:.2} mm read at 1 px of lens blur ({} px a module)",
                codes::MIN_PX_PER_MODULE
            )?,
            _ => write!(f, "; not calibrated: how far the table is, unknown")?,
        }
        if self.too_far()
            && let Some(reach) = self.logistic_reach_m
        {
            write!(
                f,
                "; a GS1 logistic label's {} mm modules need the camera within {reach:.2} m of the label",
                codes::LOGISTIC_MODULE_MM
            )?;
        }
        Ok(())
    }
}
