//! `coapcam serve`: the CoAP server. Today it serves files (`--static DIR`); the camera
//! resource tree joins it with the resource-server issue.

use std::collections::HashMap;
use std::hash::{Hash as _, Hasher as _};
use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::{Arc, RwLock};
use std::time::{Duration, SystemTime};

use anyhow::{Context as _, bail};
use bytes::Bytes;
use clap::Args;
use coap::{Code, ContentFormat, OptionNumber, Response};
use coap_net::{Resource, Router, Server, ServerConfig, handler};

/// Flags of `serve`.
#[derive(Debug, Args)]
pub(crate) struct ServeArgs {
    /// Address to listen on; repeat for several (default 0.0.0.0:5683 and [::]:5683).
    #[arg(long, value_name = "ADDR:PORT")]
    bind: Vec<SocketAddr>,
    /// Serve no cameras (a plain CoAP server, e.g. with --static).
    #[arg(long)]
    no_cameras: bool,
    /// Serve the regular files of DIR read-only at /files/<name> (observable: changes are
    /// notified).
    #[arg(long = "static", value_name = "DIR")]
    static_dir: Option<PathBuf>,
    /// Join this multicast group on start (e.g. 224.0.1.187 or ff02::fd); repeatable.
    #[arg(long, value_name = "MCAST_ADDR")]
    group: Vec<IpAddr>,
    /// IPv6 interface index for --group (0: the system's default).
    #[arg(long, value_name = "INDEX", default_value_t = 0)]
    group_interface: u32,
    /// Stop after this many seconds (default: run until interrupted).
    #[arg(long, value_name = "SECONDS")]
    duration: Option<f64>,
}

pub(crate) async fn run(args: ServeArgs) -> anyhow::Result<()> {
    if !args.no_cameras {
        bail!(
            "camera resources are not served yet (they come with the resource-server issue); \
             run `coapcam serve --no-cameras --static DIR` for a file server"
        );
    }
    let binds = if args.bind.is_empty() {
        vec![
            SocketAddr::from(([0, 0, 0, 0], 5683)),
            SocketAddr::from(([0u16; 8], 5683)),
        ]
    } else {
        args.bind.clone()
    };
    let router = Router::new();
    let files = match &args.static_dir {
        Some(dir) => Some(StaticFiles::load(dir.clone(), &router)?),
        None => None,
    };
    let server = Server::bind(&binds, ServerConfig::default(), router)
        .with_context(|| format!("binding {binds:?}"))?;
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
    let mut tick = tokio::time::interval(Duration::from_millis(200));
    loop {
        tokio::select! {
            _ = tokio::signal::ctrl_c() => break,
            () = &mut stop => break,
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

#[derive(Clone)]
struct File {
    body: Bytes,
    etag: [u8; 8],
    modified: Option<SystemTime>,
}

/// The files of a directory, reloaded when they change.
struct StaticFiles {
    dir: PathBuf,
    files: Arc<RwLock<HashMap<String, File>>>,
}

impl StaticFiles {
    fn load(dir: PathBuf, router: &Router) -> anyhow::Result<Self> {
        if !dir.is_dir() {
            bail!("--static {}: not a directory", dir.display());
        }
        let me = Self {
            dir,
            files: Arc::new(RwLock::new(HashMap::new())),
        };
        me.rescan(router);
        Ok(me)
    }

    /// Reads new and changed files, drops vanished ones, and returns the paths whose
    /// content changed (for notifications).
    fn rescan(&self, router: &Router) -> Vec<String> {
        let mut changed = Vec::new();
        let Ok(entries) = std::fs::read_dir(&self.dir) else {
            return changed;
        };
        let mut present = Vec::new();
        for entry in entries.flatten() {
            let Ok(meta) = entry.metadata() else { continue };
            let Some(name) = entry.file_name().to_str().map(str::to_string) else {
                continue;
            };
            if !meta.is_file() {
                continue;
            }
            present.push(name.clone());
            let modified = meta.modified().ok();
            let known = self
                .read()
                .get(&name)
                .map(|f| (f.modified, f.body.len() as u64));
            if known == Some((modified, meta.len())) {
                continue;
            }
            let Ok(body) = std::fs::read(entry.path()) else {
                continue;
            };
            let file = File {
                etag: etag(&body),
                body: Bytes::from(body),
                modified,
            };
            let is_new = known.is_none();
            self.files
                .write()
                .unwrap_or_else(std::sync::PoisonError::into_inner)
                .insert(name.clone(), file);
            let path = format!("/files/{name}");
            if is_new {
                router.add(&path, self.resource(&name));
            } else {
                changed.push(path);
            }
        }
        let mut files = self
            .files
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        files.retain(|name, _| {
            let keep = present.contains(name);
            if !keep {
                router.remove(&format!("/files/{name}"));
            }
            keep
        });
        changed
    }

    fn read(&self) -> std::sync::RwLockReadGuard<'_, HashMap<String, File>> {
        self.files
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn resource(&self, name: &str) -> Resource {
        let files = self.files.clone();
        let key = name.to_string();
        let cf = content_format_of(Path::new(name));
        let size = self.read().get(name).map_or(0, |f| f.body.len());
        Resource::new()
            .get(handler(move |_| {
                let file = files
                    .read()
                    .unwrap_or_else(std::sync::PoisonError::into_inner)
                    .get(&key)
                    .cloned();
                async move {
                    let Some(file) = file else {
                        return Response::diagnostic(Code::NOT_FOUND, "file removed");
                    };
                    let mut r = Response::new(Code::CONTENT).with_payload(file.body);
                    r.options
                        .set_uint(OptionNumber::CONTENT_FORMAT, u32::from(cf.0));
                    r.options.set(OptionNumber::ETAG, file.etag.to_vec());
                    r
                }
            }))
            .attr("ct", cf.0.to_string())
            .attr("sz", size.to_string())
            .attr("title", name)
            .observable()
    }
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
