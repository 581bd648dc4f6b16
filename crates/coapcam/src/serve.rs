//! `coapcam serve`: the CoAP server: the `/cams` tree of the cameras of a scene (the
//! built-in synthetic one by default) or of librealsense recordings (`--bag`), and
//! files with `--static DIR`.

use std::collections::HashMap;
use std::hash::{Hash as _, Hasher as _};
use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::{Arc, PoisonError, RwLock};
use std::time::{Duration, SystemTime};

use anyhow::{Context as _, bail};
use bytes::Bytes;
use clap::Args;
use coap::{Code, ContentFormat, IncomingRequest, OptionNumber, Response};
use coap_net::router::check_preconditions;
use coap_net::{Ctx, Resource, Router, Server, ServerConfig, handler};
use tokio::sync::mpsc;

use rgbd::backend::playback::PlaybackCamera;
use rgbd::{Camera as _, CameraHub, Scene, SyntheticCamera};

use crate::cams::Cams;
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
    /// Play a librealsense recording (.bag or .db3) as cameras, one per recorded
    /// device, instead of synthetic ones; repeatable.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["scene", "no_cameras"])]
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
    /// Join this multicast group on start (e.g. 224.0.1.187 or ff02::fd); repeatable.
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
    for g in &args.group {
        server
            .join(*g, args.group_interface)
            .await
            .with_context(|| format!("joining {g}"))?;
    }
    for a in server.local_addrs() {
        eprintln!("coapcam: serving on {a}");
    }
    let stop = async {
        match args.duration {
            Some(s) => {
                tokio::time::sleep(Duration::try_from_secs_f64(s).unwrap_or(Duration::MAX)).await
            }
            None => std::future::pending().await,
        }
    };
    tokio::pin!(stop);
    let mut terminate = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .context("installing the SIGTERM handler")?;
    let mut tick = tokio::time::interval(Duration::from_millis(200));
    // The camera tree lives as long as the server.
    let _cameras = cameras;
    loop {
        tokio::select! {
            _ = tokio::signal::ctrl_c() => break,
            _ = terminate.recv() => break,
            () = &mut stop => break,
            Some(path) = changed_rx.recv() => {
                server.notify(&path).await;
            }
            _ = tick.tick() => {
                if let Some(files) = &files {
                    for path in files.rescan(server.router()) {
                        server.notify(&path).await;
                    }
                }
            }
        }
    }
    Ok(())
}

/// The cameras of the scene in a hub, and the `/cams` tree following it.
fn start_cameras(
    args: &ServeArgs,
    router: &Arc<Router>,
    changed: mpsc::UnboundedSender<String>,
) -> anyhow::Result<(Arc<CameraHub>, Arc<Cams>)> {
    let scene = match &args.scene {
        Some(path) => {
            Scene::load(path).with_context(|| format!("loading scene {}", path.display()))?
        }
        None => Scene::default_single(),
    };
    let state_dir = args.state_dir.clone().unwrap_or_else(default_state_dir);
    std::fs::create_dir_all(&state_dir)
        .with_context(|| format!("creating state directory {}", state_dir.display()))?;
    let hub = Arc::new(CameraHub::new());
    let cams = Cams::start(hub.clone(), router.clone(), &state_dir, changed)
        .context("starting the camera hub listener")?;
    let mut expected = Vec::new();
    if args.bag.is_empty() {
        for camera in SyntheticCamera::all(&scene).context("building the scene's cameras")? {
            expected.push(format!("/cams/{}/color", camera.serial()));
            hub.add(camera).context("adding a camera")?;
        }
    }
    for path in &args.bag {
        let cameras = PlaybackCamera::open(path)
            .with_context(|| format!("opening recording {}", path.display()))?;
        for camera in cameras {
            expected.push(format!("/cams/{}/color", camera.serial()));
            hub.add(Arc::new(camera))
                .with_context(|| format!("adding the camera of {}", path.display()))?;
        }
    }
    // The hub listener registers per-camera resources on its own thread: announce the
    // server only once every camera of the scene is routed, so a client that starts at
    // "serving on" never sees a 4.04 for a camera that is there.
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while !expected.iter().all(|p| router.patterns().contains(p)) {
        if std::time::Instant::now() > deadline {
            bail!("the scene's camera resources did not appear within 10 s");
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    Ok((hub, cams))
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

#[derive(Clone)]
struct File {
    body: Bytes,
    etag: [u8; 8],
    modified: Option<SystemTime>,
}

/// The files of a directory, reloaded when they change on disk, and (with --writable)
/// changed by clients.
#[derive(Clone)]
struct StaticFiles {
    dir: PathBuf,
    files: Arc<RwLock<HashMap<String, File>>>,
    writable: bool,
    /// Paths changed by clients, for notifications.
    changed: mpsc::UnboundedSender<String>,
}

impl StaticFiles {
    fn load(
        dir: &Path,
        router: &Router,
        writable: bool,
        changed: mpsc::UnboundedSender<String>,
    ) -> anyhow::Result<Self> {
        if !dir.is_dir() {
            bail!("--static {}: not a directory", dir.display());
        }
        let me = Self {
            dir: dir.to_path_buf(),
            files: Arc::default(),
            writable,
            changed,
        };
        me.rescan(router);
        if writable {
            // Names that do not exist yet: PUT creates them; POST /files picks a name.
            router.add("/files/{name}", me.resource(None));
            router.add(
                "/files",
                me.resource(None).attr("title", "POST creates a file"),
            );
        }
        Ok(me)
    }

    fn read(&self) -> std::sync::RwLockReadGuard<'_, HashMap<String, File>> {
        self.files.read().unwrap_or_else(PoisonError::into_inner)
    }

    fn write(&self) -> std::sync::RwLockWriteGuard<'_, HashMap<String, File>> {
        self.files.write().unwrap_or_else(PoisonError::into_inner)
    }

    /// Reads new and changed files, drops vanished ones, keeps the router in step, and
    /// returns the paths whose content changed on disk.
    fn rescan(&self, router: &Router) -> Vec<String> {
        let mut changed = Vec::new();
        let Ok(entries) = std::fs::read_dir(&self.dir) else {
            return changed;
        };
        let mut present = std::collections::HashSet::new();
        let routed: std::collections::HashSet<String> = router.patterns().into_iter().collect();
        for entry in entries.flatten() {
            let Ok(meta) = entry.metadata() else { continue };
            let Some(name) = entry.file_name().to_str().map(str::to_string) else {
                continue;
            };
            if !meta.is_file() || !valid_name(&name) {
                continue;
            }
            present.insert(name.clone());
            let path = format!("/files/{name}");
            let modified = meta.modified().ok();
            let known = self
                .read()
                .get(&name)
                .map(|f| (f.modified, f.body.len() as u64));
            if known != Some((modified, meta.len())) {
                let Ok(body) = std::fs::read(entry.path()) else {
                    continue;
                };
                let file = File {
                    etag: etag(&body),
                    body: Bytes::from(body),
                    modified,
                };
                self.write().insert(name.clone(), file);
                if known.is_some() {
                    changed.push(path.clone());
                }
            }
            if !routed.contains(&path) {
                router.add(
                    &path,
                    self.resource(Some(name))
                        .attr("title", path.trim_start_matches("/files/")),
                );
            }
        }
        self.write().retain(|name, _| {
            let keep = present.contains(name);
            if !keep {
                router.remove(&format!("/files/{name}"));
            }
            keep
        });
        changed
    }

    /// The resource of one file (`Some(name)`), or of the writable patterns (`None`: the
    /// name comes from the path, or POST picks one).
    fn resource(&self, name: Option<String>) -> Resource {
        let (me, fixed) = (self.clone(), name.clone());
        let name_of = move |ctx: &Ctx| {
            fixed
                .clone()
                .or_else(|| ctx.param("name").map(str::to_string))
        };
        let mut r = Resource::new();
        if let Some(n) = &name {
            let cf = content_format_of(Path::new(n));
            let size = self.read().get(n).map_or(0, |f| f.body.len());
            r = r
                .attr("ct", cf.0.to_string())
                .attr("sz", size.to_string())
                .observable();
        }
        let get = (me.clone(), name_of.clone());
        r = r.get(handler(move |ctx| {
            let response = get.0.get(get.1(&ctx));
            async move { response }
        }));
        if !self.writable {
            return r;
        }
        let put = (me.clone(), name_of.clone());
        let delete = (me.clone(), name_of);
        r.put(handler(move |ctx| {
            let response = put.0.put(put.1(&ctx), &ctx.request);
            async move { response }
        }))
        .delete(handler(move |ctx| {
            let response = delete.0.delete(delete.1(&ctx));
            async move { response }
        }))
        .post(handler(move |ctx| {
            let response = me.post(&ctx.request);
            async move { response }
        }))
    }

    fn get(&self, name: Option<String>) -> Response {
        let Some(file) = name.as_ref().and_then(|n| self.read().get(n).cloned()) else {
            return Response::diagnostic(Code::NOT_FOUND, "no such file");
        };
        let cf = content_format_of(Path::new(name.as_deref().unwrap_or_default()));
        let mut r = Response::new(Code::CONTENT).with_payload(file.body);
        r.options
            .set_uint(OptionNumber::CONTENT_FORMAT, u32::from(cf.0));
        r.options.set(OptionNumber::ETAG, file.etag.to_vec());
        r
    }

    /// Writes through a temporary file and a rename, so readers never see half a file.
    fn store(&self, name: &str, body: &Bytes) -> std::io::Result<()> {
        let tmp = self.dir.join(format!(".{name}.tmp"));
        std::fs::write(&tmp, body)?;
        std::fs::rename(&tmp, self.dir.join(name))?;
        let modified = std::fs::metadata(self.dir.join(name))?.modified().ok();
        self.write().insert(
            name.to_string(),
            File {
                body: body.clone(),
                etag: etag(body),
                modified,
            },
        );
        let _ = self.changed.send(format!("/files/{name}"));
        Ok(())
    }

    fn put(&self, name: Option<String>, request: &IncomingRequest) -> Response {
        let Some(name) = name.filter(|n| valid_name(n)) else {
            return Response::diagnostic(
                Code::BAD_REQUEST,
                "a file name must not be empty, start with '.' or contain '/'",
            );
        };
        let current = self.read().get(&name).map(|f| f.etag);
        if let Some(refused) = check_preconditions(request, current.as_ref().map(|e| &e[..])) {
            return refused;
        }
        match self.store(&name, &request.payload) {
            Ok(()) => Response::new(if current.is_some() {
                Code::CHANGED
            } else {
                Code::CREATED
            }),
            Err(e) => {
                Response::diagnostic(Code::INTERNAL_SERVER_ERROR, &format!("writing {name}: {e}"))
            }
        }
    }

    fn post(&self, request: &IncomingRequest) -> Response {
        let stamp = SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        let name = format!("upload-{stamp}.bin");
        match self.store(&name, &request.payload) {
            Ok(()) => {
                let mut r = Response::new(Code::CREATED);
                r.options
                    .push(OptionNumber::LOCATION_PATH, b"files".to_vec());
                r.options
                    .push(OptionNumber::LOCATION_PATH, name.into_bytes());
                r
            }
            Err(e) => {
                Response::diagnostic(Code::INTERNAL_SERVER_ERROR, &format!("writing {name}: {e}"))
            }
        }
    }

    fn delete(&self, name: Option<String>) -> Response {
        let Some(name) = name.filter(|n| valid_name(n)) else {
            return Response::diagnostic(Code::BAD_REQUEST, "bad file name");
        };
        match std::fs::remove_file(self.dir.join(&name)) {
            Ok(()) => {
                self.write().remove(&name);
                Response::new(Code::DELETED)
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                Response::diagnostic(Code::NOT_FOUND, "no such file")
            }
            Err(e) => Response::diagnostic(
                Code::INTERNAL_SERVER_ERROR,
                &format!("deleting {name}: {e}"),
            ),
        }
    }
}

fn valid_name(name: &str) -> bool {
    !name.is_empty() && !name.starts_with('.') && !name.contains(['/', '\\', '\0'])
}

fn etag(body: &[u8]) -> [u8; 8] {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    body.hash(&mut h);
    h.finish().to_be_bytes()
}

fn content_format_of(path: &Path) -> ContentFormat {
    match path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .as_deref()
    {
        Some("txt") => ContentFormat::TEXT_PLAIN,
        Some("json") => ContentFormat::JSON,
        Some("png") => ContentFormat::IMAGE_PNG,
        Some("jpg" | "jpeg") => ContentFormat::IMAGE_JPEG,
        Some("cbor") => ContentFormat::CBOR,
        Some("ply") => ContentFormat::PLY,
        Some("wlnk") => ContentFormat::LINK_FORMAT,
        _ => ContentFormat::OCTET_STREAM,
    }
}
