//! OPC UA (`serve --opcua opc.tcp://ADDR:PORT`): an OPC UA server (async-opcua's) that
//! shows the station to PLCs and SCADA systems. Under the Objects folder, the object
//! `Station` of the namespace [`NAMESPACE`] holds
//! - `Identity`: `StationName`, `SoftwareName`, `SoftwareVersion`, `SoftwareSha256`;
//! - `Cameras`: a folder with an object per connected camera (its browse name its
//!   serial) holding `Serial`, `Model`, `Calibrated`, and its streams' settings as the
//!   camera server has them now (`ColorFormat`, `ColorWidth`, `ColorHeight`, `ColorFps`,
//!   and the same four of depth); a camera connected or set otherwise shows within
//!   [`CAMERAS_EVERY`];
//! - `LatestResult`: the newest record of the results log (`RecordId`, `Time`,
//!   `LengthMm`, `WidthMm`, `HeightMm`, `DivisionMm`, `Shape`, `Codes`, `Status`,
//!   `Trigger`, and `Photo`: its photo, the JPEG the log keeps, as a ByteString, null
//!   when the log keeps none), updated from the log's follower as each record is appended
//!   (a client's subscription sees each change);
//! - the method `MeasureNow`: measures with every camera as `POST /cams/dimensions` does
//!   and records it; it answers the new record's id and `recorded` (0 and why, when the
//!   table was empty), or a Bad status when measuring failed;
//! - the methods `GetResultById(RecordId)` (a record of the log, as `LatestResult` shows
//!   one; `BadNotFound` without) and `GetResultsSince(AfterId, Since, MaxResults)` (the
//!   records after an id, measured at a time or later, oldest first, an array per
//!   field): results by id and by time from the log, as OPC 40001-101's result
//!   management keeps them;
//! - events: the object is an event notifier, and every record appended while the server
//!   runs is an event of type `NewResultEventType` (a subtype of `BaseEventType` whose
//!   `Message` starts with `record ID` and `Time` is the record's time, with the fields
//!   `RecordId`, `LengthMm`, `WidthMm`, `HeightMm`, `Status` and `Codes`), from `Station`
//!   and from the standard `Server` object. async-opcua 0.19's event filters do not
//!   compare node ids, so a where clause on `EventType` matches nothing: clients
//!   subscribe without one (asyncua: `where_clause_generation=False`).
//!
//! Security: without users, the endpoint takes security mode None and anonymous users,
//! so it is served on a loopback address only (`serve` refuses any other); with
//! `--opcua-users`, its one endpoint is Basic256Sha256 SignAndEncrypt to those user names,
//! on any address, with the station's certificate (made by the library in [`PKI_DIR`] at
//! the first start) and the clients' certificates trusted there by an operator.
//!
//! The names follow what OPC 40210 (Geometrical Measuring Systems) asks of a station (its
//! identity, the latest result, results by id and by time, an event per result, a method
//! to measure), but the nodes are not typed with that specification's types.

use std::convert::Infallible;
use std::future::Future;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use opcua::nodes::BaseEventType;
use opcua::server::address_space::{
    AddressSpace, EventNotifier, MethodBuilder, ObjectBuilder, ObjectTypeBuilder, VariableBuilder,
};
use opcua::server::diagnostics::NamespaceMetadata;
use opcua::server::node_manager::memory::{InMemoryNodeManager, InMemoryNodeManagerImpl};
use opcua::server::node_manager::{MethodCall, RequestContext, ServerContext};
use opcua::server::{
    ANONYMOUS_USER_TOKEN_ID, ServerBuilder, ServerEndpoint, ServerHandle, ServerUserToken,
};
use opcua::sync::RwLock;
use opcua::types::{
    Argument, BuildInfo, ByteString, DataTypeId, DataValue, DateTime, LocalizedText, NodeClass,
    NodeId, ObjectId, ObjectTypeId, QualifiedName, StatusCode, UAString, VariableTypeId, Variant,
};
use tokio::net::TcpListener;
use tokio::task::JoinHandle;

use super::follow::{
    self, CameraView, Cameras, Feed, MeasureNow, Next, Output, OutputId, Sink, Start,
};
use super::log::{LogError, ResultsLog};
use super::reads::{self, Kind, Refusal};
use crate::api::record::{Record, UtcTime};
use crate::api::results::MAX_LIST;
use crate::report::Found;

/// The namespace of the station's nodes.
pub const NAMESPACE: &str = "urn:coapcam:station";

/// The folder of the state directory the OPC UA server keeps its certificate store in:
/// `own/` and `private/` (the station's), `trusted/` and `rejected/` (clients').
pub const PKI_DIR: &str = "opcua-pki";

/// How long stopping the server may take.
const STOP: Duration = Duration::from_secs(5);

/// How often the `Cameras` folder is compared with the cameras the server has.
pub const CAMERAS_EVERY: Duration = Duration::from_secs(1);

/// The largest photo `LatestResult.Photo` carries (a ByteString; a larger one is not
/// served, and the variable is null). The library's default, 65,535 bytes, is less than
/// the default scene's photo.
const PHOTO_MAX: usize = 8 << 20;

/// The largest message the server sends or takes: the photo and the rest of a response.
const MESSAGE_MAX: usize = PHOTO_MAX + (1 << 20);

/// The OPC UA server could not start.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// Its address could not be listened on.
    #[error("listening for OPC UA clients on {addr}")]
    Listen {
        /// The address.
        addr: SocketAddr,
        /// Why.
        source: std::io::Error,
    },
    /// The users' file could not be read.
    #[error("the OPC UA users' file {}: {why}", path.display())]
    Users {
        /// The file.
        path: PathBuf,
        /// Why.
        why: String,
    },
    /// The library refused the configuration.
    #[error("the OPC UA server on {addr}: {why}")]
    Server {
        /// The address.
        addr: SocketAddr,
        /// What the library said.
        why: String,
    },
}

/// The flags of the OPC UA output (`serve --opcua`).
#[derive(Debug, Clone, Default, clap::Args)]
#[group(skip)]
pub struct Args {
    /// Serve the station over OPC UA on this address (opc.tcp://127.0.0.1:4840): its
    /// identity, its cameras, the latest result and its photo, results by id and time,
    /// the method MeasureNow and an event per record (docs/station.md). Without --opcua-users: security mode None and
    /// anonymous clients, on a loopback address only.
    #[arg(long, value_name = "opc.tcp://ADDR:PORT", value_parser = parse_endpoint)]
    opcua: Option<SocketAddr>,
    /// With --opcua: serve it signed and encrypted only (Basic256Sha256, SignAndEncrypt)
    /// to the users of FILE, one NAME:PASSWORD a line, on any address; no anonymous
    /// clients, no security mode None. The server's certificate is made in
    /// STATE/opcua-pki/own at the first start; a client's certificate is trusted once
    /// moved from STATE/opcua-pki/rejected (where its first connection leaves it) to
    /// STATE/opcua-pki/trusted. Keep FILE readable by the station only.
    #[arg(long, value_name = "FILE", requires = "opcua")]
    opcua_users: Option<PathBuf>,
}

impl Args {
    /// Whether `--opcua` is given.
    pub(super) fn configured(&self) -> bool {
        self.opcua.is_some()
    }

    /// Refuses an address off this machine for a server without users (security mode
    /// None, anonymous).
    pub(super) fn check(&self) -> Result<(), String> {
        match self.opcua {
            Some(addr) if !addr.ip().is_loopback() && self.opcua_users.is_none() => Err(format!(
                "--opcua {}: without --opcua-users the OPC UA server takes security mode \
                     None and anonymous clients, so it listens on a loopback address only \
                     (127.0.0.1 or [::1]); with --opcua-users FILE it serves Basic256Sha256 \
                     SignAndEncrypt to those users on any address",
                endpoint_url(addr)
            )),
            _ => Ok(()),
        }
    }

    /// The OPC UA server `--opcua` asks for, listening (it keeps no
    /// cursor: its id only tells it apart).
    pub(super) async fn start(
        &self,
        feed: &Feed<'_>,
        _id: &OutputId,
    ) -> Result<Option<Box<dyn Output>>, StartError> {
        let Some(addr) = self.opcua else {
            return Ok(None);
        };
        self.check()
            .map_err(|why| StartError::Server { addr, why })?;
        let users = match &self.opcua_users {
            Some(path) => Some(read_users(path)?),
            None => None,
        };
        let output = OpcUaOutput::start(addr, feed, users).await?;
        Ok(Some(Box::new(output)))
    }
}

/// The users of `path`: `NAME:PASSWORD` lines (blank lines and `#` comments left out).
fn read_users(path: &Path) -> Result<Vec<(String, String)>, StartError> {
    let bad = |why: String| StartError::Users {
        path: path.to_owned(),
        why,
    };
    let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
    let mut users = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim_end_matches('\r');
        if line.trim().is_empty() || line.starts_with('#') {
            continue;
        }
        match line.split_once(':') {
            Some((name, password)) if !name.is_empty() && !password.is_empty() => {
                users.push((name.to_owned(), password.to_owned()));
            }
            _ => return Err(bad(format!("line {}: not NAME:PASSWORD", i + 1))),
        }
    }
    if users.is_empty() {
        return Err(bad("no NAME:PASSWORD line".into()));
    }
    Ok(users)
}

/// The address of `opc.tcp://ADDR:PORT` (`serve --opcua`; an IPv6 address in brackets).
pub fn parse_endpoint(uri: &str) -> Result<SocketAddr, String> {
    uri.strip_prefix("opc.tcp://")
        .and_then(|a| a.trim_end_matches('/').parse().ok())
        .ok_or_else(|| {
            format!("{uri:?} is not opc.tcp://ADDR:PORT (e.g. opc.tcp://127.0.0.1:4840)")
        })
}

/// The OPC UA server of a station and the follower that keeps its latest result. Dropping
/// it stops both.
pub struct OpcUaOutput {
    addr: SocketAddr,
    handle: ServerHandle,
    server: Option<JoinHandle<()>>,
    follow: JoinHandle<()>,
    cameras: JoinHandle<()>,
}

impl OpcUaOutput {
    /// Listens on `addr` (port 0 picks a free one) and follows `feed.log`.
    /// With `users`, it serves Basic256Sha256 SignAndEncrypt to them only.
    pub(super) async fn start(
        addr: SocketAddr,
        feed: &Feed<'_>,
        users: Option<Vec<(String, String)>>,
    ) -> Result<Self, StartError> {
        let listener = TcpListener::bind(addr)
            .await
            .map_err(|source| StartError::Listen { addr, source })?;
        let addr = listener
            .local_addr()
            .map_err(|source| StartError::Listen { addr, source })?;
        let nodes = Arc::new(Nodes {
            station: feed.station.to_owned(),
            measure: feed.measure.clone(),
            log: feed.log.clone(),
        });
        // The library writes its key as any file; the folder it goes in is the owner's
        // alone before that, and the key too afterwards.
        let pki = feed.state_dir.join(PKI_DIR);
        let (station, state_dir) = (feed.station.to_owned(), feed.state_dir.to_owned());
        let for_server = nodes.clone();
        // With users, the first start makes the server's 2048-bit RSA key (a second or
        // more of arithmetic): on the blocking pool, so that the runtime's threads go on
        // serving meanwhile. (The library's builder cannot be sent to it: it is made there.)
        let (server, handle) = tokio::task::spawn_blocking(move || {
            if users.is_some() {
                owner_only(&pki.join("private"), true);
            }
            let built = builder(addr, &station, &state_dir, for_server, users).build();
            owner_only(&pki.join("private").join("private.pem"), false);
            built
        })
        .await
        .map_err(|e| e.to_string())
        .and_then(|built| built)
        .map_err(|why| StartError::Server { addr, why })?;
        let manager = handle
            .node_managers()
            .get_of_type::<InMemoryNodeManager<StationNodes>>()
            .ok_or_else(|| StartError::Server {
                addr,
                why: "the station's node manager is missing".into(),
            })?;
        let server = tokio::spawn(async move {
            if let Err(e) = server.run_with(listener).await {
                tracing::error!("the OPC UA server on {addr} stopped: {e}");
            }
        });
        let cameras = tokio::spawn(show_cameras(
            feed.cameras.clone(),
            manager.clone(),
            handle.clone(),
        ));
        // The newest record is shown from the start, without an event.
        let log = feed.log.clone();
        let newest = log.newest();
        let publisher = Publisher {
            addr,
            handle: handle.clone(),
            manager,
            nodes,
            quiet_until: newest,
        };
        let follow = tokio::spawn(follow::run(log, publisher));
        Ok(Self {
            addr,
            handle,
            server: Some(server),
            follow,
            cameras,
        })
    }

    /// The address it listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }
}

impl Output for OpcUaOutput {
    fn describe(&self) -> String {
        format!("OPC UA server on {}", endpoint_url(self.addr))
    }

    fn stop(mut self: Box<Self>) -> Pin<Box<dyn Future<Output = ()> + Send>> {
        self.follow.abort();
        self.cameras.abort();
        self.handle.cancel();
        let server = self.server.take();
        Box::pin(async move {
            if let Some(server) = server
                && tokio::time::timeout(STOP, server).await.is_err()
            {
                tracing::warn!("the OPC UA server did not stop within {STOP:?}");
            }
        })
    }
}

impl Drop for OpcUaOutput {
    fn drop(&mut self) {
        self.follow.abort();
        self.cameras.abort();
        self.handle.cancel();
        if let Some(server) = &self.server {
            server.abort();
        }
    }
}

/// Makes `path` the owner's alone (a folder 0700, created when `folder` and missing; a
/// file 0600, when it exists); a failure is a warning.
fn owner_only(path: &Path, folder: bool) {
    use std::os::unix::fs::PermissionsExt as _;
    let made = if folder {
        std::fs::create_dir_all(path)
    } else if path.is_file() {
        Ok(())
    } else {
        return;
    };
    let mode = if folder { 0o700 } else { 0o600 };
    if let Err(e) =
        made.and_then(|()| std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode)))
    {
        tracing::warn!("the OPC UA server's {}: {e}", path.display());
    }
}

/// `opc.tcp://ADDR:PORT/`.
fn endpoint_url(addr: SocketAddr) -> String {
    format!("opc.tcp://{addr}/")
}

/// The server: one endpoint, security mode None and anonymous, or Basic256Sha256
/// SignAndEncrypt to `users` (its certificate made at the first start); the core
/// namespace and the station's nodes.
fn builder(
    addr: SocketAddr,
    station: &str,
    state_dir: &Path,
    nodes: Arc<Nodes>,
    users: Option<Vec<(String, String)>>,
) -> ServerBuilder {
    let host = match addr {
        SocketAddr::V4(a) => a.ip().to_string(),
        SocketAddr::V6(a) => format!("[{}]", a.ip()),
    };
    let builder = ServerBuilder::new()
        .application_name(format!("coapcam station {station}"))
        .application_uri(format!("urn:coapcam:{station}"))
        .product_uri("urn:coapcam")
        .build_info(BuildInfo {
            product_uri: "urn:coapcam".into(),
            manufacturer_name: "coapcam".into(),
            product_name: "coapcam".into(),
            software_version: env!("CARGO_PKG_VERSION").into(),
            build_number: crate::identity::SOFTWARE_SHA256.into(),
            build_date: DateTime::null(),
        })
        .host(host)
        .port(addr.port())
        .pki_dir(state_dir.join(PKI_DIR))
        .max_byte_string_length(PHOTO_MAX)
        .max_message_size(MESSAGE_MAX)
        .max_chunk_count(MESSAGE_MAX.div_ceil(opcua::server::constants::SEND_BUFFER_SIZE))
        .create_sample_keypair(users.is_some());
    let builder = match users {
        None => builder.add_endpoint(
            "none",
            ServerEndpoint::new_none("/", &[ANONYMOUS_USER_TOKEN_ID.to_owned()]),
        ),
        Some(users) => {
            let mut builder = builder;
            let mut ids = Vec::new();
            for (i, (name, password)) in users.into_iter().enumerate() {
                let id = format!("user-{i}");
                builder = builder.add_user_token(&id, ServerUserToken::user_pass(name, password));
                ids.push(id);
            }
            builder.add_endpoint(
                "basic256sha256",
                ServerEndpoint::new_basic256sha256_sign_encrypt("/", &ids),
            )
        }
    };
    builder
        .discovery_urls(vec![endpoint_url(addr)])
        .with_node_manager(
            opcua::server::node_manager::memory::InMemoryNodeManagerBuilder::new(
                move |context: ServerContext, space: &mut AddressSpace| {
                    let index = context
                        .type_tree
                        .write()
                        .namespaces_mut()
                        .add_namespace(NAMESPACE);
                    space.add_namespace(NAMESPACE, index);
                    let station = StationNodes { index, nodes };
                    // Here, not in `init`, which runs with the type tree locked.
                    station.event_type(space, &context);
                    station
                },
            ),
        )
}

/// What the station's nodes are made from: its name, how to measure now, and its results
/// log (read by `GetResultById` and `GetResultsSince`, and for the latest photo).
struct Nodes {
    station: String,
    measure: Option<MeasureNow>,
    log: ResultsLog,
}

/// The station's node manager: its nodes, and the method `MeasureNow`.
struct StationNodes {
    index: u16,
    nodes: Arc<Nodes>,
}

/// A variable of `LatestResult`: its name and data type.
const RESULT_FIELDS: [(&str, DataTypeId); 10] = [
    ("RecordId", DataTypeId::UInt64),
    ("Time", DataTypeId::UtcTime),
    ("LengthMm", DataTypeId::Double),
    ("WidthMm", DataTypeId::Double),
    ("HeightMm", DataTypeId::Double),
    ("DivisionMm", DataTypeId::Double),
    ("Shape", DataTypeId::String),
    ("Codes", DataTypeId::String),
    ("Status", DataTypeId::String),
    ("Trigger", DataTypeId::String),
];

/// The variable of `LatestResult` that holds its photo (not one of `GetResultById`'s
/// answers: a photo is large).
const PHOTO: &str = "Photo";

/// The node id's string of the folder of the cameras.
const CAMERAS: &str = "Station.Cameras";

/// A variable of a camera's object: its name and data type.
const CAMERA_FIELDS: [(&str, DataTypeId); 11] = [
    ("Serial", DataTypeId::String),
    ("Model", DataTypeId::String),
    ("Calibrated", DataTypeId::Boolean),
    ("ColorFormat", DataTypeId::String),
    ("ColorWidth", DataTypeId::UInt32),
    ("ColorHeight", DataTypeId::UInt32),
    ("ColorFps", DataTypeId::UInt32),
    ("DepthFormat", DataTypeId::String),
    ("DepthWidth", DataTypeId::UInt32),
    ("DepthHeight", DataTypeId::UInt32),
    ("DepthFps", DataTypeId::UInt32),
];

/// What a camera shows, in the order of [`CAMERA_FIELDS`].
fn camera_values(camera: &CameraView) -> [Variant; 11] {
    let text = |t: &str| Variant::from(UAString::from(t));
    [
        text(&camera.serial),
        text(&camera.model),
        Variant::Boolean(camera.calibrated),
        text(camera.color.format),
        Variant::UInt32(camera.color.width),
        Variant::UInt32(camera.color.height),
        Variant::UInt32(camera.color.fps),
        text(camera.depth.format),
        Variant::UInt32(camera.depth.width),
        Variant::UInt32(camera.depth.height),
        Variant::UInt32(camera.depth.fps),
    ]
}

/// Keeps the `Cameras` folder as the camera server has its cameras: compared every
/// [`CAMERAS_EVERY`], an object added for a camera connected, removed for one gone, and
/// the variables of one whose settings changed set (which a subscription sees).
async fn show_cameras(
    cameras: Cameras,
    manager: Arc<InMemoryNodeManager<StationNodes>>,
    handle: ServerHandle,
) {
    let mut shown: Vec<CameraView> = Vec::new();
    let mut every = tokio::time::interval(CAMERAS_EVERY);
    every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        every.tick().await;
        let now = cameras();
        if now == shown {
            continue;
        }
        let station = manager.inner();
        let is_now = |serial: &str| now.iter().any(|c| c.serial == serial);
        {
            let mut space = manager.address_space().write();
            for gone in shown.iter().filter(|c| !is_now(&c.serial)) {
                let object = station.id(&format!("{CAMERAS}.{}", gone.serial));
                for (name, _) in CAMERA_FIELDS {
                    space.delete(
                        &station.id(&format!("{CAMERAS}.{}.{name}", gone.serial)),
                        true,
                    );
                }
                space.delete(&object, true);
            }
            for new in now
                .iter()
                .filter(|c| !shown.iter().any(|s| s.serial == c.serial))
            {
                station.camera(&mut space, new);
            }
        }
        for camera in now
            .iter()
            .filter(|c| shown.iter().any(|s| s != *c && s.serial == c.serial))
        {
            let ids: Vec<NodeId> = CAMERA_FIELDS
                .iter()
                .map(|(name, _)| station.id(&format!("{CAMERAS}.{}.{name}", camera.serial)))
                .collect();
            let values = camera_values(camera).map(DataValue::new_now);
            if let Err(status) = manager.set_values(
                handle.subscriptions(),
                ids.iter().zip(values).map(|(id, v)| (id, None, v)),
            ) {
                tracing::warn!("OPC UA: showing camera {}: {status}", camera.serial);
            }
        }
        shown = now;
    }
}

/// The browse name of the event type of a new record, and its node id's string.
const EVENT_TYPE: &str = "NewResultEventType";

/// The fields [`NewResultEvent`] adds to `BaseEventType`, as the type's properties.
const EVENT_FIELDS: [(&str, DataTypeId); 6] = [
    ("RecordId", DataTypeId::UInt64),
    ("LengthMm", DataTypeId::Double),
    ("WidthMm", DataTypeId::Double),
    ("HeightMm", DataTypeId::Double),
    ("Status", DataTypeId::String),
    ("Codes", DataTypeId::String),
];

/// The event of a new record (`NewResultEventType`, a subtype of `BaseEventType`): its id,
/// its dimensions (null without), its status and its codes, so that a client needs no
/// read after the event, however fast records follow each other.
#[derive(opcua::Event)]
#[opcua(identifier = "s=NewResultEventType", namespace = "urn:coapcam:station")]
struct NewResultEvent {
    base: BaseEventType,
    own_namespace_index: u16,
    record_id: u64,
    length_mm: Option<f64>,
    width_mm: Option<f64>,
    height_mm: Option<f64>,
    status: UAString,
    codes: Vec<UAString>,
}

/// The node id of `path` (`Station.LatestResult.RecordId`) in namespace `index`.
fn id(index: u16, path: &str) -> NodeId {
    NodeId::new(index, path)
}

impl StationNodes {
    fn id(&self, path: &str) -> NodeId {
        id(self.index, path)
    }

    fn name(&self, name: &str) -> QualifiedName {
        QualifiedName::new(self.index, name)
    }

    /// An object `path` (its last part its name), a component of `parent`.
    fn object(&self, space: &mut AddressSpace, path: &str, parent: &NodeId, description: &str) {
        let name = path.rsplit('.').next().unwrap_or(path);
        ObjectBuilder::new(&self.id(path), self.name(name), name)
            .description(description)
            .has_type_definition(ObjectTypeId::BaseObjectType)
            .component_of(parent.clone())
            .insert(space);
    }

    /// `NewResultEventType` under `BaseEventType`, with a property per field, in the
    /// address space (for clients that browse it to select the fields) and in the type
    /// tree (for the server's event filters).
    fn event_type(&self, space: &mut AddressSpace, context: &ServerContext) {
        let base: NodeId = ObjectTypeId::BaseEventType.into();
        let type_id = self.id(EVENT_TYPE);
        ObjectTypeBuilder::new(&type_id, self.name(EVENT_TYPE), EVENT_TYPE)
            .description("A record appended to the station's results log")
            .subtype_of(base.clone())
            .insert(space);
        let mut tree = context.type_tree.write();
        tree.add_type_node(&type_id, &base, NodeClass::ObjectType);
        for (name, data_type) in EVENT_FIELDS {
            let id = self.id(&format!("{EVENT_TYPE}.{name}"));
            let mut builder = VariableBuilder::new(&id, self.name(name), name)
                .data_type(data_type)
                .has_type_definition(VariableTypeId::PropertyType)
                .has_modelling_rule(ObjectId::ModellingRule_Mandatory)
                .property_of(type_id.clone());
            if name == "Codes" {
                builder = builder.value_rank(1);
            }
            builder.insert(space);
            tree.add_type_property(&id, &type_id, &[&self.name(name)], NodeClass::Variable);
        }
    }

    /// The object of `camera` in the `Cameras` folder, its variables set.
    fn camera(&self, space: &mut AddressSpace, camera: &CameraView) {
        let path = format!("{CAMERAS}.{}", camera.serial);
        ObjectBuilder::new(
            &self.id(&path),
            self.name(&camera.serial),
            format!("{} {}", camera.model, camera.serial),
        )
        .description("A camera of the station")
        .has_type_definition(ObjectTypeId::BaseObjectType)
        .organized_by(self.id(CAMERAS))
        .insert(space);
        for ((name, data_type), value) in CAMERA_FIELDS.into_iter().zip(camera_values(camera)) {
            self.variable(space, &path, name, data_type, value);
        }
    }

    /// A read-only variable `parent.name`.
    fn variable(
        &self,
        space: &mut AddressSpace,
        parent: &str,
        name: &str,
        data_type: DataTypeId,
        value: Variant,
    ) {
        let mut builder =
            VariableBuilder::new(&self.id(&format!("{parent}.{name}")), self.name(name), name)
                .data_type(data_type)
                .value(value)
                .has_type_definition(VariableTypeId::BaseDataVariableType)
                .component_of(self.id(parent));
        if name == "Codes" {
            builder = builder.value_rank(1);
        }
        builder.insert(space);
    }
}

#[async_trait]
impl InMemoryNodeManagerImpl for StationNodes {
    async fn init(&self, space: &mut AddressSpace, _context: ServerContext) {
        let objects: NodeId = ObjectId::ObjectsFolder.into();
        let station = self.id("Station");
        ObjectBuilder::new(&station, self.name("Station"), self.nodes.station.as_str())
            .description("A parcel-dimensioning station (coapcam)")
            .has_type_definition(ObjectTypeId::BaseObjectType)
            .event_notifier(EventNotifier::SUBSCRIBE_TO_EVENTS)
            .organized_by(objects)
            .insert(space);
        self.object(
            space,
            "Station.Identity",
            &station,
            "The station and its software",
        );
        let identity = [
            ("StationName", self.nodes.station.clone()),
            ("SoftwareName", "coapcam".to_owned()),
            ("SoftwareVersion", env!("CARGO_PKG_VERSION").to_owned()),
            (
                "SoftwareSha256",
                crate::identity::SOFTWARE_SHA256.to_owned(),
            ),
        ];
        for (name, value) in identity {
            self.variable(
                space,
                "Station.Identity",
                name,
                DataTypeId::String,
                UAString::from(value).into(),
            );
        }
        self.object(
            space,
            "Station.LatestResult",
            &station,
            "The newest record of the results log (RecordId 0: none yet)",
        );
        for (name, data_type) in RESULT_FIELDS {
            let empty = match name {
                "RecordId" => Variant::UInt64(0),
                "Status" => UAString::from("none").into(),
                _ => Variant::Empty,
            };
            self.variable(space, "Station.LatestResult", name, data_type, empty);
        }
        self.variable(
            space,
            "Station.LatestResult",
            PHOTO,
            DataTypeId::ByteString,
            ByteString::null().into(),
        );
        ObjectBuilder::new(&self.id(CAMERAS), self.name("Cameras"), "Cameras")
            .description("The cameras connected now, an object each (its name its serial)")
            .has_type_definition(ObjectTypeId::FolderType)
            .component_of(self.id("Station"))
            .insert(space);
        MethodBuilder::new(
            &self.id("Station.MeasureNow"),
            self.name("MeasureNow"),
            "MeasureNow",
        )
        .description(
            "Measures with every camera and records it: the new record's id and \
             \"recorded\", or 0 and why nothing was recorded",
        )
        .component_of(station)
        .output_args(
            space,
            &self.id("Station.MeasureNow.OutputArguments"),
            &[
                ("RecordId", DataTypeId::UInt64).into(),
                ("Outcome", DataTypeId::String).into(),
            ],
        )
        .executable(self.nodes.measure.is_some())
        .user_executable(self.nodes.measure.is_some())
        .insert(space);
        let result_outputs: Vec<Argument> = RESULT_FIELDS
            .iter()
            .map(|&(name, data_type)| argument(name, data_type, name == "Codes"))
            .collect();
        MethodBuilder::new(
            &self.id("Station.GetResultById"),
            self.name("GetResultById"),
            "GetResultById",
        )
        .description(
            "The record of this id in the results log, as LatestResult shows one \
             (BadNotFound: no such record)",
        )
        .component_of(self.id("Station"))
        .input_args(
            space,
            &self.id("Station.GetResultById.InputArguments"),
            &[argument("RecordId", DataTypeId::UInt64, false)],
        )
        .output_args(
            space,
            &self.id("Station.GetResultById.OutputArguments"),
            &result_outputs,
        )
        .executable(true)
        .user_executable(true)
        .insert(space);
        let since_outputs: Vec<Argument> = SINCE_FIELDS
            .iter()
            .map(|&(name, data_type)| argument(name, data_type, true))
            .collect();
        MethodBuilder::new(
            &self.id("Station.GetResultsSince"),
            self.name("GetResultsSince"),
            "GetResultsSince",
        )
        .description(
            "The records after AfterId measured at Since or later (a null Since: at any \
             time), oldest first, at most MaxResults (0: 1000): an array per field, \
             NaN where nothing was measured",
        )
        .component_of(self.id("Station"))
        .input_args(
            space,
            &self.id("Station.GetResultsSince.InputArguments"),
            &[
                argument("AfterId", DataTypeId::UInt64, false),
                argument("Since", DataTypeId::UtcTime, false),
                argument("MaxResults", DataTypeId::UInt32, false),
            ],
        )
        .output_args(
            space,
            &self.id("Station.GetResultsSince.OutputArguments"),
            &since_outputs,
        )
        .executable(true)
        .user_executable(true)
        .insert(space);
    }

    fn name(&self) -> &str {
        "coapcam station"
    }

    fn namespaces(&self) -> Vec<NamespaceMetadata> {
        vec![NamespaceMetadata {
            namespace_uri: NAMESPACE.to_owned(),
            namespace_index: self.index,
            ..Default::default()
        }]
    }

    async fn call(
        &self,
        _context: &RequestContext,
        _space: &RwLock<AddressSpace>,
        methods: &mut [&mut &mut MethodCall],
    ) -> Result<(), StatusCode> {
        for call in methods {
            let method = call.method_id().clone();
            let answer = if method == self.id("Station.MeasureNow") {
                self.measure_now().await
            } else if method == self.id("Station.GetResultById") {
                self.result_by_id(call.arguments()).await
            } else if method == self.id("Station.GetResultsSince") {
                self.results_since(call.arguments()).await
            } else {
                Err(StatusCode::BadMethodInvalid)
            };
            match answer {
                Ok(outputs) => {
                    call.set_outputs(outputs);
                    call.set_status(StatusCode::Good);
                }
                Err(status) => call.set_status(status),
            }
        }
        Ok(())
    }
}

/// The fields of `GetResultsSince`'s answer, an array each.
const SINCE_FIELDS: [(&str, DataTypeId); 6] = [
    ("RecordIds", DataTypeId::UInt64),
    ("Times", DataTypeId::UtcTime),
    ("LengthMm", DataTypeId::Double),
    ("WidthMm", DataTypeId::Double),
    ("HeightMm", DataTypeId::Double),
    ("Status", DataTypeId::String),
];

/// A method's argument `name` of `data_type`, an array when `array`.
fn argument(name: &str, data_type: DataTypeId, array: bool) -> Argument {
    let mut argument: Argument = (name, data_type).into();
    if array {
        argument.value_rank = 1;
        argument.array_dimensions = Some(vec![0]);
    }
    argument
}

/// An unsigned integer argument.
fn unsigned(value: Option<&Variant>) -> Result<u64, StatusCode> {
    match value {
        Some(Variant::UInt64(v)) => Ok(*v),
        Some(Variant::UInt32(v)) => Ok(u64::from(*v)),
        Some(Variant::UInt16(v)) => Ok(u64::from(*v)),
        Some(Variant::Byte(v)) => Ok(u64::from(*v)),
        Some(Variant::Int64(v)) => u64::try_from(*v).map_err(|_| StatusCode::BadOutOfRange),
        Some(Variant::Int32(v)) => u64::try_from(*v).map_err(|_| StatusCode::BadOutOfRange),
        Some(_) => Err(StatusCode::BadTypeMismatch),
        None => Err(StatusCode::BadArgumentsMissing),
    }
}

impl StationNodes {
    /// `MeasureNow`: the new record's id and `recorded`, or 0 and why nothing was.
    async fn measure_now(&self) -> Result<Vec<Variant>, StatusCode> {
        let measure = self
            .nodes
            .measure
            .as_ref()
            .ok_or(StatusCode::BadNotExecutable)?;
        match measure().await {
            Ok(Some(id)) => Ok(vec![Variant::UInt64(id), UAString::from("recorded").into()]),
            Ok(None) => Ok(vec![
                Variant::UInt64(0),
                UAString::from("nothing on the table: not recorded").into(),
            ]),
            Err(why) => {
                tracing::warn!("OPC UA MeasureNow: {why}");
                Err(StatusCode::BadResourceUnavailable)
            }
        }
    }

    /// `GetResultById(RecordId)`: the record's fields as `LatestResult` shows them.
    async fn result_by_id(&self, arguments: &[Variant]) -> Result<Vec<Variant>, StatusCode> {
        if arguments.len() > 1 {
            return Err(StatusCode::BadTooManyArguments);
        }
        let id = unsigned(arguments.first())?;
        let record = reads::record(&self.nodes.log, id).await.map_err(refused)?;
        Ok(result_values(&record).into())
    }

    /// `GetResultsSince(AfterId, Since, MaxResults)`: the records after `AfterId` measured
    /// at `Since` or later, oldest first, an array per field of [`SINCE_FIELDS`].
    async fn results_since(&self, arguments: &[Variant]) -> Result<Vec<Variant>, StatusCode> {
        if arguments.len() > 3 {
            return Err(StatusCode::BadTooManyArguments);
        }
        let after = unsigned(arguments.first())?;
        let since = match arguments.get(1) {
            Some(Variant::DateTime(t)) if t.is_null() => None,
            Some(Variant::DateTime(t)) => Some(UtcTime {
                unix_ms: t.as_chrono().timestamp_millis(),
            }),
            Some(Variant::Empty) => None,
            Some(_) => return Err(StatusCode::BadTypeMismatch),
            None => return Err(StatusCode::BadArgumentsMissing),
        };
        let max = match unsigned(arguments.get(2))? {
            0 => MAX_LIST,
            n => usize::try_from(n).unwrap_or(MAX_LIST).min(MAX_LIST),
        };
        let records = reads::after(&self.nodes.log, after, since, max)
            .await
            .map_err(refused)?;
        let mm = |pick: fn(&crate::report::Reported) -> f64| -> Variant {
            let values: Vec<f64> = records
                .iter()
                .map(|r| r.measurement.reported().map_or(f64::NAN, pick))
                .collect();
            values.into()
        };
        let ids: Vec<u64> = records.iter().map(|r| r.id).collect();
        let times: Vec<DateTime> = records.iter().map(|r| record_time(r.time)).collect();
        let statuses: Vec<UAString> = records
            .iter()
            .map(|r| UAString::from(status(&r.measurement.parcel)))
            .collect();
        Ok(vec![
            ids.into(),
            times.into(),
            mm(|d| d.length_mm),
            mm(|d| d.width_mm),
            mm(|d| d.height_mm),
            statuses.into(),
        ])
    }
}

/// The status of a method whose read of the results log ([`reads`]) was refused: no such
/// record is `BadNotFound`, a log that could not be read `BadResourceUnavailable` (`reads`
/// said why in the server's log).
fn refused(refusal: Refusal) -> StatusCode {
    match refusal.kind {
        Kind::BadRequest => StatusCode::BadInvalidArgument,
        Kind::NotFound => StatusCode::BadNotFound,
        Kind::Failed => StatusCode::BadResourceUnavailable,
    }
}

/// Runs `read` on `log` on the blocking pool: what it read, or why it could not (the log's
/// error, or the task's). For the photo of the record the follower hands the publisher,
/// whose failure `follow::run` says once and retries, where [`reads`] would warn at each
/// retry.
async fn read_log<T: Send + 'static>(
    log: &ResultsLog,
    read: impl FnOnce(&ResultsLog) -> Result<T, LogError> + Send + 'static,
) -> Result<T, String> {
    let log = log.clone();
    match tokio::task::spawn_blocking(move || read(&log)).await {
        Ok(read) => read.map_err(|e| e.to_string()),
        Err(e) => Err(e.to_string()),
    }
}

/// The OPC UA time of a record's time `time` (`LatestResult.Time`, `GetResultsSince`'s
/// `Times`, an event's `Time`): the same instant to the millisecond, within OPC UA's
/// range (1601 to 9999: a time outside is its first or last instant).
fn record_time(time: UtcTime) -> DateTime {
    /// Milliseconds from 1601-01-01, OPC UA's epoch, to 1970-01-01, UNIX's.
    const UNIX_EPOCH_MS: i64 = 11_644_473_600_000;
    /// OPC UA's ticks (100 ns) in a millisecond.
    const TICKS_PER_MS: i64 = 10_000;
    let ticks = time
        .unix_ms
        .saturating_add(UNIX_EPOCH_MS)
        .saturating_mul(TICKS_PER_MS);
    DateTime::from(ticks.clamp(0, DateTime::endtimes_ticks()))
}

/// What a record shows in `LatestResult`, in the order of [`RESULT_FIELDS`].
pub(super) fn result_values(record: &Record) -> [Variant; 10] {
    let reported = record.measurement.reported();
    let mm = |v: Option<f64>| v.map_or(Variant::Empty, Variant::Double);
    let time = Variant::from(record_time(record.time));
    let shape = match reported {
        Some(_) => record
            .measurement
            .parcels
            .first()
            .map_or(Variant::Empty, |p| UAString::from(p.shape.as_str()).into()),
        None => Variant::Empty,
    };
    let codes: Vec<UAString> = record
        .code_texts()
        .into_iter()
        .map(UAString::from)
        .collect();
    [
        Variant::UInt64(record.id),
        time,
        mm(reported.map(|r| r.length_mm)),
        mm(reported.map(|r| r.width_mm)),
        mm(reported.map(|r| r.height_mm)),
        mm(reported.and_then(|r| r.division_mm)),
        shape,
        Variant::from(codes),
        UAString::from(status(&record.measurement.parcel)).into(),
        UAString::from(record.trigger.name()).into(),
    ]
}

/// `measured`, or what else the measurement found (`refused`, ...), as in the record's
/// JSON.
fn status(found: &Found) -> &'static str {
    match found {
        Found::Measured(_) => "measured",
        Found::Nothing => "nothing",
        Found::Uncalibrated { .. } => "uncalibrated",
        Found::Refused { .. } => "refused",
        Found::Unsynced { .. } => "unsynced",
    }
}

/// The OPC UA server as a [`Sink`]: each record becomes the latest result, and, once the
/// records there at the start are shown, an event.
struct Publisher {
    addr: SocketAddr,
    handle: ServerHandle,
    manager: Arc<InMemoryNodeManager<StationNodes>>,
    nodes: Arc<Nodes>,
    /// The newest record when the server started: shown, but no event.
    quiet_until: u64,
}

impl Publisher {
    /// Shows `record` and `photo` (null: none) as the latest result.
    fn show(&self, record: &Record, photo: ByteString) -> Result<(), StatusCode> {
        let index = self.manager.inner().index;
        let ids: Vec<NodeId> = RESULT_FIELDS
            .iter()
            .map(|(name, _)| name)
            .chain([&PHOTO])
            .map(|name| id(index, &format!("Station.LatestResult.{name}")))
            .collect();
        let now = DateTime::now();
        let values = result_values(record)
            .into_iter()
            .chain([Variant::from(photo)])
            .map(|v| {
                let mut value = DataValue::new_at(v, now);
                value.source_timestamp = Some(now);
                value
            });
        self.manager.set_values(
            self.handle.subscriptions(),
            ids.iter().zip(values).map(|(id, v)| (id, None, v)),
        )
    }

    /// The photo of `record` the log keeps, read on the blocking pool; null without one
    /// or when it is larger than [`PHOTO_MAX`].
    async fn photo(&self, record: &Record) -> Result<ByteString, String> {
        if !record.has_photo {
            return Ok(ByteString::null());
        }
        let id = record.id;
        match read_log(&self.nodes.log, move |log| log.photo(id)).await {
            Ok(Some(jpeg)) if jpeg.len() <= PHOTO_MAX => Ok(ByteString::from(jpeg)),
            Ok(Some(jpeg)) => {
                tracing::warn!(
                    "OPC UA: the photo of record {id} ({} bytes) is larger than {PHOTO_MAX}: not shown",
                    jpeg.len()
                );
                Ok(ByteString::null())
            }
            Ok(None) => Ok(ByteString::null()),
            Err(why) => Err(format!("reading the photo of record {id}: {why}")),
        }
    }

    fn announce(&self, record: &Record) {
        let index = self.manager.inner().index;
        let station = id(index, "Station");
        let time = record_time(record.time);
        let dims = record
            .measurement
            .reported()
            .map_or_else(String::new, |r| format!(": {}", r.dimensions_text()));
        let base = BaseEventType::new(
            id(index, EVENT_TYPE),
            ByteString::from(record.hash.as_bytes().to_vec()),
            LocalizedText::from(format!("record {}{dims}", record.id)),
            time,
        )
        .set_source_node(station.clone())
        .set_source_name(UAString::from(self.nodes.station.as_str()))
        .set_receive_time(DateTime::now())
        .set_severity(100);
        let reported = record.measurement.reported();
        let event = NewResultEvent {
            base,
            own_namespace_index: index,
            record_id: record.id,
            length_mm: reported.map(|r| r.length_mm),
            width_mm: reported.map(|r| r.width_mm),
            height_mm: reported.map(|r| r.height_mm),
            status: status(&record.measurement.parcel).into(),
            codes: record
                .code_texts()
                .into_iter()
                .map(UAString::from)
                .collect(),
        };
        let server: NodeId = ObjectId::Server.into();
        self.handle.subscriptions().notify_events(
            [
                (&event as &dyn opcua::nodes::Event, &station),
                (&event as &dyn opcua::nodes::Event, &server),
            ]
            .into_iter(),
        );
    }
}

impl Sink for Publisher {
    type Event = Infallible;

    fn name(&self) -> String {
        format!("OPC UA server on {}", endpoint_url(self.addr))
    }

    fn start(&self) -> Start {
        Start::After(self.quiet_until.saturating_sub(1))
    }

    async fn deliver(&mut self, record: &Record) -> Next {
        let photo = match self.photo(record).await {
            Ok(photo) => photo,
            Err(why) => return Next::Retry(why),
        };
        if let Err(status) = self.show(record, photo) {
            return Next::Retry(format!("showing record {}: {status}", record.id));
        }
        if record.id > self.quiet_until {
            self.announce(record);
        }
        Next::Go
    }

    async fn handle(&mut self, event: Self::Event) -> Next {
        match event {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_records_time_is_the_same_instant_in_opc_ua_within_its_range() {
        let time = |text: &str| UtcTime::parse(text).expect("a time");
        for text in [
            "2026-11-30T02:40:00.123Z",
            "1970-01-01T00:00:00.000Z",
            "1601-01-01T00:00:00.001Z",
        ] {
            assert_eq!(
                record_time(time(text)),
                DateTime::parse_from_rfc3339(text).expect("RFC 3339"),
                "{text}"
            );
        }
        assert_eq!(
            record_time(time("1600-12-31T23:59:59.999Z")).ticks(),
            0,
            "before 1601"
        );
        assert_eq!(
            record_time(UtcTime { unix_ms: i64::MAX }).ticks(),
            DateTime::endtimes_ticks(),
            "after 9999"
        );
        // LatestResult shows the same time as GetResultsSince and the event.
        let record = crate::api::record::tests::billed_record();
        assert_eq!(
            result_values(&record)[1],
            Variant::from(record_time(record.time))
        );
    }

    /// The first start with users makes the server's RSA key; the one thread of this
    /// runtime keeps running its other tasks meanwhile: a ticker that stood still for the
    /// whole start while the key was made on it.
    #[tokio::test(flavor = "current_thread")]
    async fn making_the_servers_key_leaves_the_runtimes_thread_free() {
        use std::sync::Mutex;
        use std::time::Instant;
        let dir = crate::ScratchDir::new("opcua-key");
        let log = ResultsLog::open(&dir.path().join("log.db")).expect("log");
        let feed = Feed {
            log: &log,
            station: "dock-1",
            state_dir: dir.path(),
            measure: None,
            cameras: Arc::new(Vec::new),
        };
        // When the ticker ticked.
        let ticks = Arc::new(Mutex::new(vec![Instant::now()]));
        let ticker = tokio::spawn({
            let ticks = ticks.clone();
            async move {
                loop {
                    tokio::time::sleep(Duration::from_millis(5)).await;
                    ticks.lock().expect("ticks").push(Instant::now());
                }
            }
        });
        tokio::time::sleep(Duration::from_millis(20)).await;
        let started = Instant::now();
        let users = vec![("operator".to_owned(), "secret".to_owned())];
        let output = OpcUaOutput::start("127.0.0.1:0".parse().expect("addr"), &feed, Some(users))
            .await
            .expect("the server");
        let finished = Instant::now();
        // Until the ticker has ticked after the start.
        for _ in 0..1000 {
            if ticks.lock().expect("ticks").last() > Some(&finished) {
                break;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        ticker.abort();
        let key = dir.path().join(PKI_DIR).join("private").join("private.pem");
        assert!(key.is_file(), "the key was made");
        // The longest part of the start without a tick.
        let ticks = ticks.lock().expect("ticks").clone();
        let still = ticks
            .windows(2)
            .map(|w| {
                w[1].min(finished)
                    .saturating_duration_since(w[0].max(started))
            })
            .max()
            .unwrap_or_default();
        let took = finished - started;
        assert!(
            still * 3 < took,
            "the runtime's thread stood still for {still:?} of the {took:?} the start took"
        );
        drop(output);
    }

    #[test]
    fn only_loopback_endpoints_are_taken_without_users() {
        assert_eq!(
            parse_endpoint("opc.tcp://127.0.0.1:4840"),
            Ok("127.0.0.1:4840".parse().expect("addr"))
        );
        assert_eq!(
            parse_endpoint("opc.tcp://[::1]:4840/"),
            Ok("[::1]:4840".parse().expect("addr"))
        );
        assert!(parse_endpoint("tcp://127.0.0.1:4840").is_err());
        assert!(parse_endpoint("opc.tcp://localhost:4840").is_err());
        let args = |addr: &str, users: bool| Args {
            opcua: Some(parse_endpoint(addr).expect("an endpoint")),
            opcua_users: users.then(|| PathBuf::from("users")),
        };
        assert_eq!(args("opc.tcp://127.0.0.1:4840", false).check(), Ok(()));
        let refused = args("opc.tcp://0.0.0.0:4840", false)
            .check()
            .expect_err("0.0.0.0");
        assert!(refused.contains("loopback"), "{refused}");
        assert!(args("opc.tcp://192.168.1.2:4840", false).check().is_err());
        assert_eq!(args("opc.tcp://0.0.0.0:4840", true).check(), Ok(()));
    }
}
