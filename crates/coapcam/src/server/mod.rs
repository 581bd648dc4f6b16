//! A camera server: the resource tree of the thesis (docs/design.md §5) over `coap_net`.
//! [`CameraServer`] assembles one from its configuration ([`Config`]): the `/cams`
//! tree of its cameras (`cams`), files under `/files` (`files`), the group memberships
//! of `/coap-group` (`group`). [`SceneServer`] is the same tree for a
//! synthetic scene on one address inside another program (`demo`, `bench`, tests).
//! [`measure`] is the one way a measurement to record is made; the station, above the
//! server, keeps them ([`measure::Records`]) and adds its own resources and outputs.

mod cams;
mod clock;
mod error;
mod files;
mod group;
pub mod identities;
pub mod measure;

use std::future::Future;
use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use coap::link_format::Filter;
use coap::{Code, EndpointConfig, IncomingRequest, Response};
use coap_net::{Psk, Router, Server, ServerConfig, TcpServer};
use coap_rd::registrant::{Announcement, Registrant, RegistrantConfig};
use rgbd::{CameraHub, Scene, Serial, SyntheticCamera};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio::time::{Instant, MissedTickBehavior};

use crate::backends::{self, Backend, synthetic};
use crate::report::{EdgeQuery, Measurement};
use cams::Cams;
pub use cams::{Busy, CodeColor, EdgeError, LiveLimits};
use clock::ServerClock;
pub use error::{AddressError, StartError};
use files::StaticFiles;
use group::Groups;
pub use identities::{Identities, Role};
use measure::{Records, Rig};

/// How often `/files` looks for new, changed and vanished files.
const RESCAN: Duration = Duration::from_millis(200);

/// What a [`CameraServer`] serves, and where.
pub struct Config {
    /// The addresses to answer on.
    pub binds: Vec<SocketAddr>,
    /// The backends of the cameras under `/cams`, each started in this order; none for a
    /// plain CoAP server (no `/cams`).
    pub cameras: Vec<Box<dyn Backend>>,
    /// Where each camera's configuration is persisted, per serial.
    pub state_dir: PathBuf,
    /// Serve the regular files of this directory at `/files/<name>`.
    pub static_dir: Option<PathBuf>,
    /// Let clients change the files (PUT, POST, DELETE).
    pub writable: bool,
    /// With `writable`: the most bytes the files may hold together.
    pub quota: Option<u64>,
    /// Multicast groups joined at start, on the server's port.
    pub groups: Vec<IpAddr>,
    /// IPv6 interface index for the groups (0: the system's default).
    pub group_interface: u32,
    /// Transmission parameters and limits of the endpoint.
    pub endpoint: EndpointConfig,
    /// Accept configuration changes from any address, not only from this machine
    /// ([`loopback_only`]).
    pub allow_unauthenticated_config: bool,
    /// The memory grabs in progress may take together, in bytes (a grab beyond it
    /// answers 5.03 with Max-Age 1).
    pub grab_memory: u64,
    /// Addresses answered with DTLS (`coaps://`); they need `identities`.
    pub secure_binds: Vec<SocketAddr>,
    /// Addresses answered over TCP (`coap+tcp://`, RFC 8323): the same resources, each
    /// answer in one message (no block-wise transfer or Observe over TCP yet), requests
    /// of up to [`coap_net::tcp::DEFAULT_MAX_MESSAGE_SIZE`], within the default
    /// [`coap_net::tcp::StreamLimits`] (64 connections per address, released after 60 s
    /// idle).
    pub tcp_binds: Vec<SocketAddr>,
    /// Addresses answered over WebSockets (`coap+ws://`, RFC 8323 §4, at
    /// [`coap_net::tcp::WS_PATH`]): as `tcp_binds`, with the same bounds.
    pub ws_binds: Vec<SocketAddr>,
    /// Addresses answered over TLS (`coaps+tcp://`): as `tcp_binds`, each client with a
    /// pre-shared key of `identities` (which they need), its requests with its identity
    /// as over DTLS.
    pub tls_binds: Vec<SocketAddr>,
    /// Addresses answered over WebSockets over TLS (`coaps+ws://`): as `ws_binds`, with
    /// the keys of `identities` as `tls_binds`.
    pub wss_binds: Vec<SocketAddr>,
    /// The DTLS (and TLS) identities with their keys and roles; with them, configuration changes
    /// need an identity of the `configure` role (or this machine).
    pub identities: Option<Arc<Identities>>,
    /// Shift the server's clock as its clients see it (the times it stamps into answers
    /// and its frames' capture times) by this many µs (`--clock-offset-ms`: a server whose
    /// clock is off, for tests); 0 for the system's clock.
    pub clock_offset_us: i64,
    /// The bounds of the live streams (`/cams/<sn>/<stream>/live`).
    pub live: LiveLimits,
}

/// The policy of a server without security configured: configuration changes (PUT and
/// DELETE, and POST to `/coap-group`, `/files` and the creation resources `/cams/<name>`)
/// come from this machine only (a request that arrived over the loopback interface,
/// whatever its source address says); anything else answers 4.03. The answer is the
/// refusal, `None` letting the request through.
pub fn loopback_only(request: &IncomingRequest) -> Option<Response> {
    if request.loopback {
        return None;
    }
    Some(Response::diagnostic(
        Code::FORBIDDEN,
        "configuration changes are accepted only from the server's own machine (its operator can allow them with serve --allow-unauthenticated-config)",
    ))
}

/// A running camera server: bound, its cameras routed, its groups joined.
pub struct CameraServer {
    server: Server,
    /// The `coap+tcp` listeners, on the same router.
    tcp: Vec<TcpServer>,
    /// The `coap+ws` listeners, on the same router.
    ws: Vec<TcpServer>,
    /// The `coaps+tcp` listeners, on the same router.
    tls: Vec<TcpServer>,
    /// The `coaps+ws` listeners, on the same router.
    wss: Vec<TcpServer>,
    /// The `/coap-group` memberships (what `register_with` announces).
    groups: Arc<Groups>,
    files: Option<StaticFiles>,
    changed: mpsc::UnboundedReceiver<String>,
    /// The sending side of `changed`, for paths changed outside the server.
    changes: mpsc::UnboundedSender<String>,
    memberships: mpsc::UnboundedReceiver<group::MembershipChange>,
    group_interface: u32,
    cameras: Option<CameraTree>,
}

impl CameraServer {
    /// Measures with every camera of this server, in process, as `POST /cams/dimensions`
    /// does (and keeps it as its latest measurement); see [`SceneServer::measure_now`].
    pub async fn measure_now(&self, query: &EdgeQuery) -> Result<Measurement, EdgeError> {
        match &self.cameras {
            Some(tree) => tree.cams.measure_now(query).await,
            None => Err(EdgeError::NoCamera),
        }
    }

    /// Builds the resource tree of `config`, binds every address and joins the groups.
    pub async fn start(config: Config) -> Result<Self, StartError> {
        let router = Router::new();
        match (&config.identities, config.allow_unauthenticated_config) {
            (Some(ids), _) => router.set_policy(Arc::new(identities::by_role(ids.clone()))),
            (None, false) => router.set_policy(Arc::new(loopback_only)),
            (None, true) => {}
        }
        let (changed_tx, changed) = mpsc::unbounded_channel::<String>();
        let (membership_tx, memberships) = mpsc::unbounded_channel();
        let groups = Groups::register(&router, membership_tx);
        let clock = Arc::new(ServerClock::default());
        clock.set_offset_us(config.clock_offset_us);
        clock.install(&router);
        let files = match &config.static_dir {
            Some(dir) => Some(StaticFiles::load(
                dir,
                &router,
                config.writable,
                config.quota,
                changed_tx.clone(),
            )?),
            None => None,
        };
        let cameras = if config.cameras.is_empty() {
            None
        } else {
            Some(start_cameras(
                config.cameras,
                &config.state_dir,
                &router,
                &clock,
                changed_tx.clone(),
                (config.grab_memory, config.live),
            )?)
        };
        let binds = &config.binds;
        let server = Server::bind(
            binds,
            ServerConfig {
                endpoint: config.endpoint,
                secure: config.secure_binds.clone(),
                psk: config.identities.as_ref().map(Identities::keys),
            },
            router,
        )
        .map_err(|source| StartError::Bind {
            binds: binds.clone(),
            source,
        })?;
        let keys = config.identities.as_ref().map(Identities::keys);
        let secured = [&config.tls_binds, &config.wss_binds];
        if keys.is_none()
            && let Some(binds) = secured.into_iter().find(|b| !b.is_empty())
        {
            let why = "TLS (coaps+tcp, coaps+ws) needs the identities of a --psk-file";
            return Err(StartError::Bind {
                binds: binds.clone(),
                source: std::io::Error::new(std::io::ErrorKind::InvalidInput, why),
            });
        }
        let router = server.router();
        let tcp = stream_listeners(&config.tcp_binds, router, false, None).await?;
        let ws = stream_listeners(&config.ws_binds, router, true, None).await?;
        let tls = stream_listeners(&config.tls_binds, router, false, keys.as_ref()).await?;
        let wss = stream_listeners(&config.wss_binds, router, true, keys.as_ref()).await?;
        groups
            .start(&server, &config.groups, config.group_interface)
            .await?;
        Ok(Self {
            server,
            tcp,
            ws,
            tls,
            wss,
            groups,
            files,
            changed,
            changes: changed_tx,
            memberships,
            group_interface: config.group_interface,
            cameras,
        })
    }

    /// The router: what the station adds to the server (its resources) goes on it.
    pub fn router(&self) -> &Arc<Router> {
        self.server.router()
    }

    /// The cameras, to measure through (none without cameras).
    pub(crate) fn rig(&self) -> Option<Arc<impl Rig>> {
        self.cameras.as_ref().map(|tree| tree.cams.clone())
    }

    /// Whether the server serves cameras (`/cams`).
    pub fn has_cameras(&self) -> bool {
        self.cameras.is_some()
    }

    /// Keeps every measurement made for a client (`POST /cams/dimensions`) in `records`
    /// before answering it, with its photo and annotated picture; set once, and nothing
    /// without cameras.
    pub fn set_records(&self, records: Arc<dyn Records>) {
        if let Some(tree) = &self.cameras {
            tree.cams.set_records(records);
        }
    }

    /// Where to send the path of a resource that changed outside the server (the
    /// station's): its observers are notified, once for all the sends meanwhile.
    pub fn changes(&self) -> mpsc::UnboundedSender<String> {
        self.changes.clone()
    }

    /// Sets every camera's color stream to the resolution the codes need and says what
    /// each reads ([`CodeColor`]); none without cameras.
    pub fn color_for_codes(&self) -> Vec<CodeColor> {
        self.cameras
            .as_ref()
            .map(|tree| tree.cams.color_for_codes())
            .unwrap_or_default()
    }

    /// The addresses it answers on (over UDP, then with DTLS).
    pub fn local_addrs(&self) -> Vec<SocketAddr> {
        self.server.local_addrs()
    }

    /// The addresses it answers on over TCP.
    pub fn tcp_addrs(&self) -> Vec<SocketAddr> {
        self.tcp.iter().map(TcpServer::local_addr).collect()
    }

    /// The addresses it answers on over WebSockets.
    pub fn ws_addrs(&self) -> Vec<SocketAddr> {
        self.ws.iter().map(TcpServer::local_addr).collect()
    }

    /// The addresses it answers on over TLS (`coaps+tcp`).
    pub fn tls_addrs(&self) -> Vec<SocketAddr> {
        self.tls.iter().map(TcpServer::local_addr).collect()
    }

    /// The addresses it answers on over WebSockets over TLS (`coaps+ws`).
    pub fn wss_addrs(&self) -> Vec<SocketAddr> {
        self.wss.iter().map(TcpServer::local_addr).collect()
    }

    /// Registers this server with a resource directory and keeps the registration alive
    /// (`serve --register`; [`coap_rd::registrant`]): its typed links (those with an
    /// `rt`: the cameras' resources, `/cams/pointclouds`, `/coap-group`, ...) and the
    /// groups it joined, sent from its own socket so the directory sees its address.
    /// The registration follows cameras that come and go and groups joined or left.
    ///
    /// # Errors
    ///
    /// When the server has no address of the directory's family.
    pub fn register_with(&self, config: RegistrantConfig) -> Result<Registrant, AddressError> {
        let client = self
            .server
            .client_for(config.rd)
            .ok_or(AddressError::ForDirectory { rd: config.rd })?;
        let router = Arc::clone(self.server.router());
        let groups = Arc::clone(&self.groups);
        Ok(Registrant::spawn(config, client, move || {
            let router = Arc::clone(&router);
            let groups = Arc::clone(&groups);
            async move {
                let typed = Filter::parse("rt").unwrap_or_default();
                Announcement {
                    links: router.links(&typed),
                    groups: groups
                        .addrs()
                        .await
                        .iter()
                        .map(|a| coap_rd::registrant::group_key(*a))
                        .collect(),
                }
            }
        }))
    }

    /// Serves until `stop` completes: notifies observers of changed resources, applies
    /// group changes, rescans the files.
    pub async fn run(mut self, stop: impl Future<Output = ()>) {
        let server = &self.server;
        tokio::pin!(stop);
        // The files were scanned at load. A rescan hashes new and changed files, as long as
        // that takes: it runs on the blocking pool, one at a time, so requests, notifications
        // and signals are not held up behind it.
        let mut tick = tokio::time::interval_at(Instant::now() + RESCAN, RESCAN);
        tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
        let mut scan: Option<JoinHandle<Vec<String>>> = None;
        loop {
            tokio::select! {
                () = &mut stop => break,
                Some(path) = self.changed.recv() => {
                    notify_changed(server, path, &mut self.changed).await;
                }
                Some(change) = self.memberships.recv() => {
                    group::apply(server, change, self.group_interface).await;
                }
                _ = tick.tick(), if scan.is_none() => {
                    if let Some(files) = self.files.clone() {
                        let router = Arc::clone(server.router());
                        scan = Some(tokio::task::spawn_blocking(move || files.rescan(&router)));
                    }
                }
                done = async { scan.as_mut().expect("guarded by is_some").await }, if scan.is_some() => {
                    scan = None;
                    match done {
                        Ok(paths) => {
                            for path in paths {
                                server.notify(&path).await;
                            }
                        }
                        Err(e) => tracing::warn!(error = %e, "rescanning the files failed"),
                    }
                }
            }
        }
        // A rescan under way ends at its next window instead of hashing on: the runtime
        // waits for its blocking work when it shuts down.
        if let Some(files) = &self.files {
            files.stop();
        }
        if let Some(scan) = scan {
            let _ = scan.await;
        }
    }
}

/// Notifies the observers of `first` and of every other path changed meanwhile, each
/// once: a resource that changed many times while the last round of notifications went
/// out is notified once, with its newest state.
async fn notify_changed(
    server: &Server,
    first: String,
    changed: &mut mpsc::UnboundedReceiver<String>,
) {
    let mut paths = vec![first];
    while let Ok(path) = changed.try_recv() {
        if !paths.contains(&path) {
            paths.push(path);
        }
    }
    for path in paths {
        server.notify(&path).await;
    }
}

/// A server of a scene's synthetic cameras on one address, answering until dropped
/// (`demo`, `bench accuracy`); [`SceneServer::load`] swaps the scene's cameras.
pub struct SceneServer {
    server: Arc<Server>,
    hub: Arc<CameraHub>,
    cams: Arc<Cams>,
    clock: Arc<ServerClock>,
    notifier: JoinHandle<()>,
}

impl SceneServer {
    /// Serves `scene` on `bind` (port 0 picks a free one), persisting configuration in
    /// `state_dir`.
    pub async fn start(
        scene: &Scene,
        state_dir: &Path,
        bind: SocketAddr,
    ) -> Result<Self, StartError> {
        let router = Router::new();
        router.set_policy(Arc::new(loopback_only));
        let (changed_tx, mut changed_rx) = mpsc::unbounded_channel::<String>();
        let clock = Arc::new(ServerClock::default());
        clock.install(&router);
        let (hub, cams) = start_hub(state_dir, &router, changed_tx, &clock)?;
        load_scene(&hub, &router, scene)?;
        let server = Arc::new(
            Server::bind(&[bind], ServerConfig::default(), router).map_err(|source| {
                StartError::Bind {
                    binds: vec![bind],
                    source,
                }
            })?,
        );
        let notify = server.clone();
        let notifier = tokio::spawn(async move {
            while let Some(path) = changed_rx.recv().await {
                notify_changed(&notify, path, &mut changed_rx).await;
            }
        });
        Ok(Self {
            server,
            hub,
            cams,
            clock,
            notifier,
        })
    }

    /// Replaces the cameras with those of `scene` (they disconnect and connect, as when
    /// cameras are unplugged and plugged in).
    pub fn load(&self, scene: &Scene) -> Result<(), StartError> {
        load_scene(&self.hub, self.server.router(), scene)
    }

    /// Measures with every camera of this server, in process, as `POST /cams/dimensions`
    /// does: the server's edge measurement (no `servers`, `cycle_ms` or
    /// `received_bytes`), kept as the latest (`GET /cams/dimensions` and its observers).
    pub async fn measure_now(&self, query: &EdgeQuery) -> Result<Measurement, EdgeError> {
        self.cams.measure_now(query).await
    }

    /// Shifts the server's clock as its clients see it by `offset_us` (see
    /// [`Config::clock_offset_us`]).
    pub fn set_clock_offset_us(&self, offset_us: i64) {
        self.clock.set_offset_us(offset_us);
    }

    /// Requests answered so far; a Block2 continuation, answered from the endpoint's
    /// store, is not one.
    pub fn requests_answered(&self) -> u64 {
        self.clock.answered()
    }

    /// The address the server answers on.
    pub fn addr(&self) -> Result<SocketAddr, AddressError> {
        self.server
            .local_addrs()
            .into_iter()
            .next()
            .ok_or(AddressError::None)
    }
}

impl Drop for SceneServer {
    fn drop(&mut self) {
        self.notifier.abort();
    }
}

/// A camera hub and the `/cams` tree following it.
fn start_hub(
    state_dir: &Path,
    router: &Arc<Router>,
    changed: mpsc::UnboundedSender<String>,
    clock: &Arc<ServerClock>,
) -> Result<(Arc<CameraHub>, Arc<Cams>), StartError> {
    std::fs::create_dir_all(state_dir).map_err(|source| StartError::StateDir {
        path: state_dir.to_owned(),
        source,
    })?;
    let hub = Arc::new(CameraHub::new());
    let cams = Cams::start(
        hub.clone(),
        router.clone(),
        state_dir,
        changed,
        clock.clone(),
    )
    .map_err(StartError::HubListener)?;
    Ok((hub, cams))
}

/// Replaces the cameras of `hub` with the synthetic cameras of `scene`, and returns once
/// the router follows: the hub listener adds and removes per-camera resources on its own
/// thread, so a client that starts after this (or after "serving on") never sees a 4.04
/// for a camera that is there, nor a resource of one that left.
fn load_scene(hub: &CameraHub, router: &Router, scene: &Scene) -> Result<(), StartError> {
    // Built before the old cameras go: a scene that cannot be built leaves them served.
    let cameras = SyntheticCamera::all(scene).map_err(backends::StartError::Scene)?;
    let gone = hub.serials();
    for sn in &gone {
        hub.remove(sn);
    }
    wait_routed(router, &gone, false)?;
    let expected = synthetic::add(hub, cameras)?;
    wait_routed(router, &expected, true)
}

/// Waits until `/cams/{sn}/color` of every camera of `serials` is routed (`present`), or
/// of none of them (not `present`).
fn wait_routed(router: &Router, serials: &[Serial], present: bool) -> Result<(), StartError> {
    let paths: Vec<String> = serials
        .iter()
        .map(|sn| crate::api::paths::camera(sn, "color"))
        .collect();
    let done = || {
        let patterns = router.patterns();
        paths.iter().all(|p| patterns.contains(p) == present)
    };
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while !done() {
        if std::time::Instant::now() > deadline {
            return Err(StartError::NotRouted);
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    Ok(())
}

/// The cameras of `backends` in a hub, and the `/cams` tree following it; returns once
/// every camera present at start is routed.
fn start_cameras(
    mut backends: Vec<Box<dyn Backend>>,
    state_dir: &Path,
    router: &Arc<Router>,
    clock: &Arc<ServerClock>,
    changed: mpsc::UnboundedSender<String>,
    (grab_memory, live): (u64, LiveLimits),
) -> Result<CameraTree, StartError> {
    let (hub, cams) = start_hub(state_dir, router, changed, clock)?;
    cams.set_grab_memory(grab_memory);
    cams.set_live_limits(live);
    for backend in &mut backends {
        let serials = backend.start(&hub)?;
        wait_routed(router, &serials, true)?;
    }
    Ok(CameraTree {
        _backends: backends,
        _hub: hub,
        cams,
    })
}

/// What serves the cameras; kept alive as long as the server.
struct CameraTree {
    _backends: Vec<Box<dyn Backend>>,
    _hub: Arc<CameraHub>,
    cams: Arc<Cams>,
}

/// A listener on each of `addrs` serving `router` over TCP, or over WebSockets when `ws`
/// (RFC 8323), with TLS and the identities of `keys` when given, each within the default
/// [`coap_net::tcp::StreamLimits`].
async fn stream_listeners(
    addrs: &[SocketAddr],
    router: &Arc<Router>,
    ws: bool,
    keys: Option<&Psk>,
) -> Result<Vec<TcpServer>, StartError> {
    let mut listeners = Vec::with_capacity(addrs.len());
    for &addr in addrs {
        let (router, limits) = (Arc::clone(router), coap_net::tcp::StreamLimits::default());
        let bound = match (ws, keys) {
            (false, None) => TcpServer::bind(addr, router, limits).await,
            (true, None) => TcpServer::bind_ws(addr, router, limits).await,
            (false, Some(keys)) => TcpServer::bind_tls(addr, router, limits, keys).await,
            (true, Some(keys)) => TcpServer::bind_wss(addr, router, limits, keys).await,
        };
        listeners.push(bound.map_err(|source| StartError::Bind {
            binds: vec![addr],
            source,
        })?);
    }
    Ok(listeners)
}
