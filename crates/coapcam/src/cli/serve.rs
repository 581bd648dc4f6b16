//! `coapcam serve`: the CoAP server: the `/cams` tree of the cameras of a scene (the
//! built-in synthetic one by default) or of librealsense recordings (`--bag`), and
//! files with `--static DIR`.

use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context as _, bail};
use clap::Args;
use coap_net::{Router, Server, ServerConfig};
use tokio::signal::unix::{SignalKind, signal};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio::time::{Instant, MissedTickBehavior};

use rgbd::backend::playback::PlaybackCamera;
use rgbd::{Camera as _, CameraHub, Scene, Serial, SyntheticCamera};

use crate::cams::Cams;
use crate::files::StaticFiles;
use crate::group::Groups;
use crate::transmission::TransmissionArgs;

/// Flags of `serve`.
#[derive(Debug, Args)]
pub(crate) struct ServeArgs {
    /// Address to listen on; repeat for several (default 0.0.0.0:5683 and [::]:5683).
    #[arg(long, value_name = "ADDR:PORT")]
    bind: Vec<SocketAddr>,
    /// Serve no cameras (a plain CoAP server, e.g. with --static).
    #[arg(long, conflicts_with = "scene")]
    no_cameras: bool,
    /// Synthetic cameras of this scene file (default: the built-in single-camera scene).
    #[arg(long, value_name = "FILE")]
    scene: Option<PathBuf>,
    /// Serve the Intel RealSense D400 cameras librealsense2 finds (loaded at run time;
    /// hot-plug followed) instead of synthetic ones.
    #[arg(long, conflicts_with = "no_cameras")]
    realsense: bool,
    /// The librealsense2 library for --realsense (default: $LIBREALSENSE2_PATH, then
    /// librealsense2.so.2.* / librealsense2.so on the system library path).
    #[arg(long, value_name = "PATH", requires = "realsense")]
    librealsense: Option<PathBuf>,
    /// A library to load globally before librealsense2 (repeatable), e.g. the libpython
    /// a pyrealsense2 wheel's module needs when that module is --librealsense.
    #[arg(long, value_name = "PATH", requires = "realsense")]
    librealsense_preload: Vec<PathBuf>,
    /// With --realsense: keep the sensors streaming and serve the newest frame, instead
    /// of opening and closing a sensor per grab.
    #[arg(long, requires = "realsense")]
    realsense_streaming: bool,
    /// With --realsense: also put a virtual D415 per camera of the scene into
    /// librealsense (a software device fed by the synthetic renderer), served through
    /// the same librealsense code path as a real camera. For testing without hardware.
    #[arg(long, requires = "realsense")]
    realsense_software: bool,
    /// Play a librealsense recording (.bag or .db3) as cameras, one per recorded
    /// device, instead of synthetic ones; repeatable.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["scene", "no_cameras", "realsense"])]
    bag: Vec<PathBuf>,
    /// Where camera configuration is persisted per serial (default:
    /// $XDG_STATE_HOME/coapcam, ~/.local/state/coapcam, else ./coapcam-state).
    #[arg(long, value_name = "DIR")]
    state_dir: Option<PathBuf>,
    /// Serve the regular files of DIR at /files/<name>, read-only unless --writable.
    /// The resources are observable: a changed file is notified to its observers.
    #[arg(long = "static", value_name = "DIR")]
    static_dir: Option<PathBuf>,
    /// Let clients change --static DIR: PUT /files/<name> creates or replaces a file
    /// (If-Match and If-None-Match honoured), POST /files creates one under a new name
    /// (2.01 with Location-Path), DELETE removes one.
    #[arg(long, requires = "static_dir")]
    writable: bool,
    /// Join this multicast group on start (e.g. 224.0.1.187 or ff02::fd), on the server's
    /// port; repeatable. Listed in /coap-group, where clients add and remove memberships.
    #[arg(long, value_name = "MCAST_ADDR")]
    group: Vec<IpAddr>,
    /// IPv6 interface index for --group (0: the system's default).
    #[arg(long, value_name = "INDEX", default_value_t = 0)]
    group_interface: u32,
    /// Stop after this many seconds (default: run until interrupted).
    #[arg(long, value_name = "SECONDS")]
    duration: Option<f64>,
    #[command(flatten)]
    transmission: TransmissionArgs,
}

/// How often `--static` looks for new, changed and vanished files.
const RESCAN: Duration = Duration::from_millis(200);

pub(crate) async fn run(args: ServeArgs) -> anyhow::Result<()> {
    let binds = if args.bind.is_empty() {
        vec![
            SocketAddr::from(([0, 0, 0, 0], 5683)),
            SocketAddr::from(([0u16; 8], 5683)),
        ]
    } else {
        args.bind.clone()
    };
    let router = Router::new();
    let (changed_tx, mut changed_rx) = mpsc::unbounded_channel::<String>();
    let (membership_tx, mut membership_rx) = mpsc::unbounded_channel();
    let groups = Groups::register(&router, membership_tx);
    let files = match &args.static_dir {
        Some(dir) => Some(StaticFiles::load(
            dir,
            &router,
            args.writable,
            changed_tx.clone(),
        )?),
        None => None,
    };
    let cameras = if args.no_cameras {
        None
    } else {
        Some(start_cameras(&args, &router, changed_tx.clone())?)
    };
    let config = ServerConfig {
        endpoint: args.transmission.endpoint_config(),
        ..ServerConfig::default()
    };
    let server =
        Server::bind(&binds, config, router).with_context(|| format!("binding {binds:?}"))?;
    groups
        .start(&server, &args.group, args.group_interface)
        .await?;
    let stop = async {
        match args.duration {
            Some(s) => {
                tokio::time::sleep(Duration::try_from_secs_f64(s).unwrap_or(Duration::MAX)).await
            }
            None => std::future::pending().await,
        }
    };
    tokio::pin!(stop);
    // Both handlers are in place before the server announces itself: a signal sent as soon
    // as "serving on" appears stops the server cleanly instead of killing it.
    let mut terminate =
        signal(SignalKind::terminate()).context("installing the SIGTERM handler")?;
    let mut interrupt = signal(SignalKind::interrupt()).context("installing the SIGINT handler")?;
    for a in server.local_addrs() {
        eprintln!("coapcam: serving on {a}");
    }
    // The files were scanned at load. A rescan hashes new and changed files, as long as
    // that takes: it runs on the blocking pool, one at a time, so requests, notifications
    // and signals are not held up behind it.
    let mut tick = tokio::time::interval_at(Instant::now() + RESCAN, RESCAN);
    tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
    let mut scan: Option<JoinHandle<Vec<String>>> = None;
    // The camera tree lives as long as the server.
    let _cameras = cameras;
    loop {
        tokio::select! {
            _ = interrupt.recv() => break,
            _ = terminate.recv() => break,
            () = &mut stop => break,
            Some(path) = changed_rx.recv() => {
                server.notify(&path).await;
            }
            Some(change) = membership_rx.recv() => {
                crate::group::apply(&server, change, args.group_interface).await;
            }
            _ = tick.tick(), if scan.is_none() => {
                if let Some(files) = files.clone() {
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
    if let Some(files) = &files {
        files.stop();
    }
    if let Some(scan) = scan {
        let _ = scan.await;
    }
    Ok(())
}

/// A server of a scene's synthetic cameras on one address, answering until dropped
/// (`demo`, `bench accuracy`); [`SceneServer::load`] swaps the scene's cameras.
pub(crate) struct SceneServer {
    server: Arc<Server>,
    hub: Arc<CameraHub>,
    _cams: Arc<Cams>,
    notifier: JoinHandle<()>,
}

impl SceneServer {
    /// Serves `scene` on `bind` (port 0 picks a free one), persisting configuration in
    /// `state_dir`.
    pub(crate) async fn start(
        scene: &Scene,
        state_dir: &Path,
        bind: SocketAddr,
    ) -> anyhow::Result<Self> {
        let router = Router::new();
        let (changed_tx, mut changed_rx) = mpsc::unbounded_channel::<String>();
        let (hub, cams) = start_hub(state_dir, &router, changed_tx)?;
        load_scene(&hub, &router, scene)?;
        let server = Arc::new(
            Server::bind(&[bind], ServerConfig::default(), router)
                .with_context(|| format!("binding {bind}"))?,
        );
        let notify = server.clone();
        let notifier = tokio::spawn(async move {
            while let Some(path) = changed_rx.recv().await {
                notify.notify(&path).await;
            }
        });
        Ok(Self {
            server,
            hub,
            _cams: cams,
            notifier,
        })
    }

    /// Replaces the cameras with those of `scene` (they disconnect and connect, as when
    /// cameras are unplugged and plugged in).
    pub(crate) fn load(&self, scene: &Scene) -> anyhow::Result<()> {
        load_scene(&self.hub, self.server.router(), scene)
    }

    /// The address the server answers on.
    pub(crate) fn addr(&self) -> anyhow::Result<SocketAddr> {
        self.server
            .local_addrs()
            .into_iter()
            .next()
            .context("the server has no address")
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
) -> anyhow::Result<(Arc<CameraHub>, Arc<Cams>)> {
    std::fs::create_dir_all(state_dir)
        .with_context(|| format!("creating state directory {}", state_dir.display()))?;
    let hub = Arc::new(CameraHub::new());
    let cams = Cams::start(hub.clone(), router.clone(), state_dir, changed)
        .context("starting the camera hub listener")?;
    Ok((hub, cams))
}

/// Replaces the cameras of `hub` with the synthetic cameras of `scene`, and returns once
/// the router follows: the hub listener adds and removes per-camera resources on its own
/// thread, so a client that starts after this (or after "serving on") never sees a 4.04
/// for a camera that is there, nor a resource of one that left.
fn load_scene(hub: &CameraHub, router: &Router, scene: &Scene) -> anyhow::Result<()> {
    let cameras = SyntheticCamera::all(scene).context("building the scene's cameras")?;
    let gone = hub.serials();
    for sn in &gone {
        hub.remove(sn);
    }
    wait_routed(router, &gone, false)?;
    let mut expected = Vec::new();
    for camera in cameras {
        expected.push(camera.serial());
        hub.add(camera).context("adding a camera")?;
    }
    wait_routed(router, &expected, true)
}

/// Waits until `/cams/{sn}/color` of every camera of `serials` is routed (`present`), or
/// of none of them (not `present`).
fn wait_routed(router: &Router, serials: &[Serial], present: bool) -> anyhow::Result<()> {
    let paths: Vec<String> = serials
        .iter()
        .map(|sn| format!("/cams/{sn}/color"))
        .collect();
    let done = || {
        let patterns = router.patterns();
        paths.iter().all(|p| patterns.contains(p) == present)
    };
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while !done() {
        if std::time::Instant::now() > deadline {
            bail!("the cameras' resources did not follow the hub within 10 s");
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    Ok(())
}

/// The cameras (of the scene, or librealsense's with --realsense) in a hub, and the
/// `/cams` tree following it; returns once every camera present at start is routed.
fn start_cameras(
    args: &ServeArgs,
    router: &Arc<Router>,
    changed: mpsc::UnboundedSender<String>,
) -> anyhow::Result<CameraTree> {
    let scene = match &args.scene {
        Some(path) => {
            Scene::load(path).with_context(|| format!("loading scene {}", path.display()))?
        }
        None => Scene::default_single(),
    };
    let state_dir = args.state_dir.clone().unwrap_or_else(default_state_dir);
    let (hub, cams) = start_hub(&state_dir, router, changed)?;
    let mut backend = None;
    if args.realsense {
        let realsense = realsense::start(args, &scene, hub.clone())?;
        wait_routed(router, &realsense.serials, true)?;
        backend = Some(realsense);
    } else if !args.bag.is_empty() {
        let mut expected = Vec::new();
        for path in &args.bag {
            let cameras = PlaybackCamera::open(path)
                .with_context(|| format!("opening recording {}", path.display()))?;
            for camera in cameras {
                expected.push(camera.serial());
                hub.add(Arc::new(camera))
                    .with_context(|| format!("adding the camera of {}", path.display()))?;
            }
        }
        wait_routed(router, &expected, true)?;
    } else {
        load_scene(&hub, router, &scene)?;
    }
    Ok(CameraTree {
        _backend: backend,
        _hub: hub,
        _cams: cams,
    })
}

/// What serves the cameras; kept alive as long as the server.
struct CameraTree {
    _backend: Option<realsense::Backend>,
    _hub: Arc<CameraHub>,
    _cams: Arc<Cams>,
}

/// `--realsense`: librealsense's cameras in the hub.
mod realsense {
    use std::sync::Arc;
    use std::time::Duration;

    use anyhow::Context as _;
    use rgbd::backend::realsense::{
        GrabMode, LibrarySearch, RealSense, RealSenseLibrary, SoftwareD415,
    };
    use rgbd::{CameraHub, Scene, Serial, SyntheticCamera};

    use super::ServeArgs;

    /// How long librealsense gets to announce the first camera.
    const FIRST_CAMERA: Duration = Duration::from_secs(3);

    /// The running backend, its virtual cameras and the serials served at start.
    pub(super) struct Backend {
        pub(super) serials: Vec<Serial>,
        // Dropped before the context: stops injecting.
        _software: Vec<SoftwareD415>,
        _realsense: RealSense,
    }

    pub(super) fn start(
        args: &ServeArgs,
        scene: &Scene,
        hub: Arc<CameraHub>,
    ) -> anyhow::Result<Backend> {
        let library = RealSenseLibrary::load(&LibrarySearch {
            explicit: args.librealsense.clone(),
            preload: args.librealsense_preload.clone(),
        })?;
        let mode = if args.realsense_streaming {
            GrabMode::Streaming
        } else {
            GrabMode::PerRequest
        };
        let realsense = RealSense::start(&library, hub, mode)
            .with_context(|| format!("starting librealsense {}", library.version()))?;
        let mut software = Vec::new();
        if args.realsense_software {
            for camera in SyntheticCamera::all(scene).context("building the scene's cameras")? {
                software.push(
                    realsense
                        .add_software_d415(camera)
                        .context("adding a virtual D415 to librealsense")?,
                );
            }
        }
        let mut serials = realsense.wait_for_cameras(FIRST_CAMERA)?;
        // Every virtual camera is announced on librealsense's thread; wait for all.
        let deadline = std::time::Instant::now() + FIRST_CAMERA;
        while software.iter().any(|s| !serials.contains(&s.serial()))
            && std::time::Instant::now() < deadline
        {
            std::thread::sleep(Duration::from_millis(10));
            serials = realsense.wait_for_cameras(FIRST_CAMERA)?;
        }
        for reason in realsense.rejected() {
            tracing::warn!("librealsense device not served: {reason}");
        }
        Ok(Backend {
            serials,
            _software: software,
            _realsense: realsense,
        })
    }
}

fn default_state_dir() -> PathBuf {
    let base = std::env::var_os("XDG_STATE_HOME")
        .filter(|v| !v.is_empty())
        .map(PathBuf::from)
        .or_else(|| {
            std::env::var_os("HOME")
                .filter(|v| !v.is_empty())
                .map(|h| PathBuf::from(h).join(".local").join("state"))
        });
    base.map_or_else(|| PathBuf::from("coapcam-state"), |b| b.join("coapcam"))
}
