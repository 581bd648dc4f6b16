//! [`Station`]: the camera server and what the station adds to it, composed in one place.
//! The camera server starts first (its cameras, files, groups, the bind); then, when it
//! has cameras, the results log (its CoAP resources on the server's router, the server
//! keeping what it measures for clients in it), the outputs that follow it (the list in
//! `outputs.rs`), the HTTP side and the watcher of `--auto-measure`.

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use coap_rd::registrant::{Registrant, RegistrantConfig};
use tokio::task::JoinHandle;

use super::follow::{CameraView, Cameras, Feed, MeasureNow, Output, StreamView};
use super::log::{LogError, ResultsLog};
use super::outputs::OutputError;
use super::signing::StationKey;
use super::writer::{WriterError, WriterLock};
use super::{Config, Recorder, http, last_id_path, resources, watch};
use crate::api::paths;
use crate::report::{EdgeQuery, Measurement};
use crate::server::measure::Rig;
use crate::server::{self, CameraServer, CodeColor, EdgeError};

/// A station could not start: its camera server, its results log, an output or the HTTP
/// side.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StartError {
    /// The camera server did not start.
    #[error(transparent)]
    Server(#[from] server::StartError),
    /// The station key (`--signing-key`) is missing or not kept secret (its words).
    #[error("{0}")]
    Key(String),
    /// Another station writes the results log, or its lock could not be taken.
    #[error(transparent)]
    Writer(#[from] WriterError),
    /// The results log could not be opened.
    #[error("opening the results log {}", path.display())]
    Log {
        /// The log's file.
        path: PathBuf,
        /// Why.
        source: LogError,
    },
    /// The results log cannot sign with the station key.
    #[error(transparent)]
    Signing(LogError),
    /// `--results` names no file (without cameras, the log is only read).
    #[error("no results log at {}", .0.display())]
    NoLog(PathBuf),
    /// Outputs asked for without cameras.
    #[error("the outputs of the results log need cameras (and so a results log)")]
    OutputsNeedCameras,
    /// An output did not start.
    #[error(transparent)]
    Output(#[from] OutputError),
    /// `--http` asked for without cameras.
    #[error("--http needs cameras (and so a results log)")]
    HttpNeedsCameras,
    /// The HTTP address could not be listened on.
    #[error("listening for HTTP on {addr}")]
    Http {
        /// The address.
        addr: SocketAddr,
        /// Why.
        source: std::io::Error,
    },
}

/// A running station: its camera server, and with cameras the outputs of its results log.
pub struct Station {
    server: CameraServer,
    /// The outputs that follow the log, in the order of their list.
    outputs: Vec<Box<dyn Output>>,
    /// The page and the HTTP API (`--http`).
    http: Option<http::HttpServer>,
    /// The lock of the results log this station writes: one log, one writer.
    _writer: Option<WriterLock>,
    /// The tasks that end with the station: the one that tells the server of each new
    /// record (the observers of `/station/measurements/latest`), and `--auto-measure`'s
    /// watcher.
    _tasks: Tasks,
}

/// Tasks aborted when this is dropped.
struct Tasks(Vec<JoinHandle<()>>);

impl Drop for Tasks {
    fn drop(&mut self) {
        for task in &self.0 {
            task.abort();
        }
    }
}

impl Station {
    /// Starts the camera server of `server` and what `config` adds to it.
    pub async fn start(server: server::Config, config: Config) -> Result<Self, StartError> {
        let open = server.allow_unauthenticated_config;
        let state_dir = server.state_dir.clone();
        let server = CameraServer::start(server).await?;
        // Aborted on an early return too.
        let mut tasks = Tasks(Vec::new());
        let mut writer = None;
        let recorder = match server.rig() {
            Some(_) => {
                let path = config.results_path(&state_dir);
                let key = match &config.signing_key {
                    Some(file) => Some(StationKey::load(file).map_err(StartError::Key)?),
                    None => None,
                };
                // Before the log opens: a second station on it refuses to start.
                let mut lock = WriterLock::take(&path)?;
                let addrs: Vec<String> = server
                    .local_addrs()
                    .iter()
                    .map(ToString::to_string)
                    .collect();
                lock.write(&format!("coap {}", addrs.join(" ")))?;
                writer = Some(lock);
                let last_id = last_id_path(&state_dir, &path);
                let log = ResultsLog::open_station(&path, config.retention, &last_id).map_err(
                    |source| StartError::Log {
                        path: path.clone(),
                        source,
                    },
                )?;
                if let Some(key) = key {
                    tracing::info!(
                        "results log {}: every record is signed with the station key {}",
                        path.display(),
                        key.public()
                    );
                    log.sign_with(key).map_err(StartError::Signing)?;
                }
                let parameters: Option<resources::Parameters> = server
                    .rig()
                    .map(|rig| Arc::new(move || rig.parameters_sha256()) as resources::Parameters);
                resources::register(server.router(), &log, &config.name, parameters);
                let recorder = Recorder::new(log.clone(), config.name.clone());
                server.set_records(Arc::new(recorder.clone()));
                // One notification per new record: appends that come faster than
                // notifications go out are told once, with the newest.
                let (mut newest, changes) = (log.subscribe(), server.changes());
                tasks.0.push(tokio::spawn(async move {
                    while newest.changed().await.is_ok()
                        && changes.send(paths::LATEST.to_owned()).is_ok()
                    {}
                }));
                // The head moves with events too.
                let (mut head, changes) = (log.subscribe_head(), server.changes());
                tasks.0.push(tokio::spawn(async move {
                    while head.changed().await.is_ok()
                        && changes.send(paths::HEAD.to_owned()).is_ok()
                    {}
                }));
                Some(recorder)
            }
            None => {
                // Without cameras (`serve --no-cameras --results FILE`) an archived log is
                // served to read, as it is: nothing records into it or prunes it.
                if let Some(path) = &config.results {
                    if !path.is_file() {
                        return Err(StartError::NoLog(path.clone()));
                    }
                    let log = ResultsLog::open(path).map_err(|source| StartError::Log {
                        path: path.clone(),
                        source,
                    })?;
                    resources::register(server.router(), &log, &config.name, None);
                }
                None
            }
        };
        let outputs = match &recorder {
            Some(recorder) => {
                let feed = Feed {
                    log: recorder.log(),
                    station: &config.name,
                    state_dir: &state_dir,
                    measure: server
                        .rig()
                        .map(|rig| measure_now(rig, recorder.clone(), config.auto_measure)),
                    cameras: match server.rig() {
                        Some(rig) => cameras(rig),
                        None => Arc::new(Vec::new),
                    },
                };
                config.outputs.start(&feed).await?
            }
            None if config.outputs.any() => {
                return Err(StartError::OutputsNeedCameras);
            }
            None => Vec::new(),
        };
        let http = start_http(&config, &server, recorder.as_ref(), open).await?;
        // The station watches the table once the server answers.
        if let (Some(rig), Some(recorder), Some(auto)) =
            (server.rig(), recorder.clone(), config.auto_measure)
        {
            tasks.0.push(watch::spawn(rig, recorder, auto));
        }
        Ok(Self {
            server,
            outputs,
            http,
            _writer: writer,
            _tasks: tasks,
        })
    }

    /// Measures with every camera, in process, as `POST /cams/dimensions` does (and
    /// keeps it as the latest measurement).
    pub async fn measure_now(&self, query: &EdgeQuery) -> Result<Measurement, EdgeError> {
        self.server.measure_now(query).await
    }

    /// Sets every camera's color stream to the resolution the codes need and says what
    /// each reads; none without cameras.
    pub fn color_for_codes(&self) -> Vec<CodeColor> {
        self.server.color_for_codes()
    }

    /// What each output does (`line output on ADDR`), in the order of their list.
    pub fn outputs(&self) -> Vec<String> {
        self.outputs.iter().map(|o| o.describe()).collect()
    }

    /// Where the page and the HTTP API are served (`--http`).
    pub fn http_addr(&self) -> Option<SocketAddr> {
        self.http.as_ref().map(http::HttpServer::local_addr)
    }

    /// The addresses the camera server answers on.
    pub fn local_addrs(&self) -> Vec<SocketAddr> {
        self.server.local_addrs()
    }

    /// The addresses the camera server answers on over TCP (`coap+tcp://`).
    pub fn tcp_addrs(&self) -> Vec<SocketAddr> {
        self.server.tcp_addrs()
    }

    /// The addresses the camera server answers on over WebSockets (`coap+ws://`).
    pub fn ws_addrs(&self) -> Vec<SocketAddr> {
        self.server.ws_addrs()
    }

    /// The addresses the camera server answers on over TLS (`coaps+tcp://`).
    pub fn tls_addrs(&self) -> Vec<SocketAddr> {
        self.server.tls_addrs()
    }

    /// The addresses the camera server answers on over WebSockets over TLS
    /// (`coaps+ws://`).
    pub fn wss_addrs(&self) -> Vec<SocketAddr> {
        self.server.wss_addrs()
    }

    /// Registers the camera server with a resource directory
    /// ([`CameraServer::register_with`]).
    ///
    /// # Errors
    ///
    /// When the server has no address of the directory's family.
    pub fn register_with(
        &self,
        config: RegistrantConfig,
    ) -> Result<Registrant, server::AddressError> {
        self.server.register_with(config)
    }

    /// Serves until `stop` completes ([`CameraServer::run`]), then stops the outputs
    /// (the MQTT publisher says `offline` on its status topic, within a bounded time).
    pub async fn run(self, stop: impl Future<Output = ()>) {
        // The HTTP side and the tasks live until the end (`..` keeps them in `self`).
        let Self {
            server, outputs, ..
        } = self;
        server.run(stop).await;
        for output in outputs {
            output.stop().await;
        }
    }
}

/// The HTTP server, as `config` asks; `open`: anyone may measure over HTTP
/// (`--allow-unauthenticated-config`). The proxy reaches the camera server's
/// addresses besides the hosts of `--proxy-allow`.
async fn start_http(
    config: &Config,
    server: &CameraServer,
    recorder: Option<&Recorder>,
    open: bool,
) -> Result<Option<http::HttpServer>, StartError> {
    let (Some(rig), Some(recorder)) = (server.rig(), recorder) else {
        if config.http.is_some() {
            return Err(StartError::HttpNeedsCameras);
        }
        return Ok(None);
    };
    Ok(match config.http {
        Some(addr) => Some(
            http::HttpServer::start(
                addr,
                rig,
                recorder.clone(),
                open,
                http::proxy::Reach {
                    own: server.local_addrs(),
                    allowed: config.proxy_allow.clone(),
                },
            )
            .await
            .map_err(|source| StartError::Http { addr, source })?,
        ),
        None => None,
    })
}

/// Measuring now for an output (OPC UA's `MeasureNow`): with `rig`, recorded by
/// `recorder`, as `--auto-measure`'s measurements ask (the codes, the thresholds, the
/// billing), or with the codes and the defaults without it.
fn measure_now(
    rig: Arc<impl Rig>,
    recorder: Recorder,
    auto: Option<watch::AutoConfig>,
) -> MeasureNow {
    let query = auto.unwrap_or_default().query;
    Arc::new(move || {
        let (rig, recorder) = (rig.clone(), recorder.clone());
        Box::pin(async move {
            recorder
                .measure_now(rig.as_ref(), &query)
                .await
                .map(|record| record.map(|r| r.id))
        })
    })
}

/// The cameras of `rig` as an output shows them (OPC UA's `Cameras`), read at each call.
fn cameras(rig: Arc<impl Rig>) -> Cameras {
    Arc::new(move || {
        rig.cameras()
            .into_iter()
            .map(|cam| {
                let (color, depth) = (cam.camera.color_settings(), cam.camera.depth_settings());
                CameraView {
                    serial: cam.serial.to_string(),
                    model: cam.camera.model().to_owned(),
                    calibrated: cam.transformation != geometry::Transformation::identity(),
                    color: StreamView {
                        format: color.format.name(),
                        fps: color.fps,
                        width: color.width,
                        height: color.height,
                    },
                    depth: StreamView {
                        format: depth.format.name(),
                        fps: depth.fps,
                        width: depth.width,
                        height: depth.height,
                    },
                }
            })
            .collect()
    })
}
