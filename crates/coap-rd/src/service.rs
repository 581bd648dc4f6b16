//! The directory over CoAP (`coapcam rd`): the [`Directory`] behind a lock, its
//! resources on a `coap_net` router, simple registration's fetch of the endpoint's
//! `/.well-known/core`, every registration persisted in a file of its own, and the sweep
//! of expired ones.
//!
//! Resources (RFC 9176; each listed in `/.well-known/core` with its `rt`, so
//! `?rt=core.rd*` finds them): `/rd` (POST: registration, `rt=core.rd`), `/rd/<id>`
//! (POST: update, DELETE: removal), `/rd-lookup/ep` and `/rd-lookup/res` (GET: lookups,
//! `rt=core.rd-lookup-ep` / `core.rd-lookup-res`), `/.well-known/rd` (POST: simple
//! registration).
//!
//! Every request that makes, changes or removes a registration must carry a fresh Echo
//! value of the directory's own, made for its source address ([`super::freshness`]);
//! without one it is answered 4.01 with a value and nothing else happens. So is a lookup
//! whose first message would be more than three times the request, unless it came over
//! the loopback interface (from this machine) or `coapcam rd --no-address-check` says
//! to answer in full.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use anyhow::Context as _;
use coap::{BlockSource, Code, ContentFormat, IncomingRequest, OptionNumber, Request, Response};
use coap_net::{Client, Ctx, Resource, Router, handler};
use tokio::sync::Semaphore;

use super::directory::{Directory, Limits, Listing, LookupKind, Params, Query, RdError, Record};
use super::freshness::Freshness;

/// The registration resource's path (RFC 9176 §5.3 leaves it to the directory).
pub const REGISTRATION_PATH: &str = "/rd";
/// Endpoint lookup.
pub const LOOKUP_EP_PATH: &str = "/rd-lookup/ep";
/// Resource lookup.
pub const LOOKUP_RES_PATH: &str = "/rd-lookup/res";
/// Simple registration (RFC 9176 §5.1: a fixed path).
pub const SIMPLE_PATH: &str = "/.well-known/rd";

/// Simple registrations whose endpoint is being asked for its links at once; more are
/// answered 5.03 with Max-Age 1.
const SIMPLE_AT_ONCE: usize = 16;

/// How long simple registration waits for the endpoint's `/.well-known/core`.
const SIMPLE_FETCH_TIMEOUT: Duration = Duration::from_secs(10);

/// Bytes of lookup answers the CoAP layer keeps for their block-wise transfer: a listing
/// of every one of 20,000 registrations holds 640 KB and a window of 16 KiB, so about 50
/// full lookups at once (a page of 100 holds 20 KB).
pub const ANSWERS_KEPT: usize = 32 << 20;

/// Bytes of registrations being received in blocks (Block1) over all clients: 512
/// documents of 32 KiB.
pub const UPLOADS: usize = 16 << 20;

/// The CoAP layer's limits for a directory with `limits`: the answers kept for
/// block-wise transfer and the bodies received in blocks sized for it (the defaults are a
/// camera server's, 256 and 64 MiB), and no body larger than a registration's document,
/// neither received nor fetched by simple registration (the default for a fetched one is
/// 256 MiB). With the deduplication store (16 MiB), these stores come to 64 MiB on top
/// of the registrations' count.
#[must_use]
pub fn endpoint_limits(limits: &Limits) -> coap::Limits {
    coap::Limits {
        block2_store_bytes: ANSWERS_KEPT,
        block1_peer_bytes: limits.max_document,
        block1_total_bytes: UPLOADS,
        client_body_bytes: limits.max_document,
        ..coap::Limits::default()
    }
}

/// Milliseconds since the UNIX epoch (the directory's time: lifetimes outlive a restart).
#[must_use]
pub fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}

/// The registrations on disk: `<dir>/<id>.json` each, written to a temporary file, synced
/// and renamed, so a file is the old registration or the new one, never half.
#[derive(Debug, Clone)]
pub struct Store {
    dir: PathBuf,
}

impl Store {
    /// The store in `dir` (created if missing).
    ///
    /// # Errors
    ///
    /// When the directory cannot be created.
    pub fn open(dir: &Path) -> anyhow::Result<Self> {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        Ok(Self {
            dir: dir.to_owned(),
        })
    }

    fn path(&self, id: u64) -> PathBuf {
        self.dir.join(format!("{id}.json"))
    }

    /// Every registration file that parses; one that does not is set aside as
    /// `<name>.bad` with a warning.
    ///
    /// # Errors
    ///
    /// When the directory cannot be read.
    pub fn load(&self) -> anyhow::Result<Vec<Record>> {
        let mut records = Vec::new();
        let entries = std::fs::read_dir(&self.dir)
            .with_context(|| format!("reading {}", self.dir.display()))?;
        for entry in entries {
            let path = entry?.path();
            if path.extension().and_then(|e| e.to_str()) != Some("json") {
                continue;
            }
            let parsed = std::fs::read(&path)
                .map_err(anyhow::Error::from)
                .and_then(|b| Ok(serde_json::from_slice::<Record>(&b)?));
            match parsed {
                Ok(r) => records.push(r),
                Err(e) => {
                    let aside = path.with_extension("json.bad");
                    tracing::warn!(path = %path.display(), error = %e, "a registration file does not parse; set aside");
                    let _ = std::fs::rename(&path, aside);
                }
            }
        }
        Ok(records)
    }

    /// Writes `record`.
    ///
    /// # Errors
    ///
    /// When it cannot be written, synced or renamed.
    pub fn save(&self, record: &Record) -> std::io::Result<()> {
        let path = self.path(record.id);
        let tmp = self.dir.join(format!(".{}.json.tmp", record.id));
        let mut file = std::fs::File::create(&tmp)?;
        file.write_all(&serde_json::to_vec(record).map_err(std::io::Error::other)?)?;
        file.sync_all()?;
        std::fs::rename(&tmp, &path)
    }

    /// Removes registration `id`'s file (none is fine).
    ///
    /// # Errors
    ///
    /// When it exists and cannot be removed.
    pub fn delete(&self, id: u64) -> std::io::Result<()> {
        match std::fs::remove_file(self.path(id)) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e),
            _ => Ok(()),
        }
    }
}

/// The directory a server answers from: the [`Directory`], its store, and the client
/// simple registration fetches with.
pub struct Service {
    directory: Mutex<Directory>,
    store: Option<Store>,
    /// Held while a registration's file is written, so the last write is of the newest
    /// state.
    writing: tokio::sync::Mutex<()>,
    fetcher: Client,
    fetching: Semaphore,
    fresh: Freshness,
    /// Whether a lookup from off this machine needs a fresh Echo value when its answer
    /// is more than three times the request.
    verify_lookups: bool,
}

impl std::fmt::Debug for Service {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Service")
            .field("store", &self.store)
            .finish()
    }
}

impl Service {
    /// A directory with `limits`, persisted in `store` when given (its registrations are
    /// read back first, the expired ones left out and their files removed). Simple
    /// registration fetches through `fetcher`. `verify_lookups`: large lookup answers
    /// go off this machine only to a sender that returned a fresh Echo value.
    ///
    /// # Errors
    ///
    /// When the store cannot be read.
    pub fn new(
        limits: Limits,
        store: Option<Store>,
        fetcher: Client,
        verify_lookups: bool,
    ) -> anyhow::Result<Arc<Self>> {
        let mut directory = Directory::new(limits);
        if let Some(store) = &store {
            let records = store.load()?;
            let now = now_ms();
            let stale: Vec<u64> = records
                .iter()
                .filter(|r| r.expires_ms <= now)
                .map(|r| r.id)
                .collect();
            let n = directory.restore(now, records);
            for id in stale {
                let _ = store.delete(id);
            }
            if n > 0 {
                tracing::info!(registrations = n, "registrations restored");
            }
        }
        Ok(Arc::new(Self {
            directory: Mutex::new(directory),
            store,
            writing: tokio::sync::Mutex::new(()),
            fetcher,
            fetching: Semaphore::new(SIMPLE_AT_ONCE),
            fresh: Freshness::new(),
            verify_lookups,
        }))
    }

    /// Whether `request` carries a fresh Echo value the directory made for its sender.
    fn proved(&self, request: &IncomingRequest) -> bool {
        let echo = request.options.first(OptionNumber::ECHO);
        self.fresh.is_fresh(now_ms(), request.peer, echo)
    }

    /// 4.01 with a new Echo value for the sender (RFC 9175 §2.3): the client sends the
    /// request again with it. 4 bytes, the token and 19 for the option.
    fn challenge(&self, request: &IncomingRequest) -> Response {
        let mut r = Response::new(Code::UNAUTHORIZED);
        let value = self.fresh.value(now_ms(), request.peer);
        r.options.set(OptionNumber::ECHO, value);
        r
    }

    /// The directory, locked.
    pub fn directory(&self) -> std::sync::MutexGuard<'_, Directory> {
        self.directory
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }

    /// Adds the directory's resources to `router`.
    pub fn route(self: &Arc<Self>, router: &Router) {
        let ct = ContentFormat::LINK_FORMAT.0.to_string();
        let me = self.clone();
        router.add(
            REGISTRATION_PATH,
            Resource::new()
                .post(handler(move |ctx| {
                    let me = me.clone();
                    async move { me.register(&ctx.request).await }
                }))
                .attr("rt", "core.rd")
                .attr("ct", ct.clone()),
        );
        let (update, delete) = (self.clone(), self.clone());
        router.add(
            "/rd/{id}",
            Resource::new()
                .post(handler(move |ctx| {
                    let me = update.clone();
                    async move { me.update(&ctx).await }
                }))
                .delete(handler(move |ctx| {
                    let me = delete.clone();
                    async move { me.remove(&ctx).await }
                })),
        );
        for (path, kind, rt) in [
            (LOOKUP_EP_PATH, LookupKind::Endpoints, "core.rd-lookup-ep"),
            (LOOKUP_RES_PATH, LookupKind::Resources, "core.rd-lookup-res"),
        ] {
            let me = self.clone();
            router.add(
                path,
                Resource::new()
                    .get(handler(move |ctx| {
                        let me = me.clone();
                        async move { Self::lookup(&me, kind, &ctx.request) }
                    }))
                    .attr("rt", rt)
                    .attr("ct", ct.clone()),
            );
        }
        let me = self.clone();
        router.add(
            SIMPLE_PATH,
            Resource::new().post(handler(move |ctx| {
                let me = me.clone();
                async move { me.register_simple(&ctx.request).await }
            })),
        );
    }

    /// Drops the registrations whose lifetime ended, and their files.
    pub async fn sweep(&self) {
        let gone = self.directory().expire(now_ms());
        for id in gone {
            self.persist(id).await;
        }
    }

    /// Writes registration `id`'s file as the directory now holds it (or removes it).
    async fn persist(&self, id: u64) -> Option<std::io::Error> {
        let store = self.store.clone()?;
        let _writing = self.writing.lock().await;
        let record = self.directory().get(id).map(|r| r.record().clone());
        let done = tokio::task::spawn_blocking(move || match record {
            Some(r) => store.save(&r),
            None => store.delete(id),
        })
        .await
        .unwrap_or_else(|e| Err(std::io::Error::other(e)));
        done.err().inspect(|e| {
            tracing::warn!(id, error = %e, "a registration could not be written");
        })
    }

    /// The answer once `id` changed: `ok`, or 5.00 when it could not be written.
    async fn persisted(&self, id: u64, ok: Response) -> Response {
        match self.persist(id).await {
            None => ok,
            Some(e) => Response::diagnostic(
                Code::INTERNAL_SERVER_ERROR,
                &format!("the registration could not be stored: {e}"),
            ),
        }
    }

    async fn register(&self, request: &IncomingRequest) -> Response {
        if !self.proved(request) {
            return self.challenge(request);
        }
        if let Some(refused) = link_format_only(request) {
            return refused;
        }
        let Ok(document) = std::str::from_utf8(&request.payload) else {
            return Response::diagnostic(Code::BAD_REQUEST, "the document is not UTF-8");
        };
        let registered = parse_params(request).and_then(|params| {
            self.directory()
                .register(now_ms(), request.peer, params, document)
        });
        match registered {
            Ok(r) => {
                let mut created = Response::new(Code::CREATED);
                created.options.push(OptionNumber::LOCATION_PATH, "rd");
                created
                    .options
                    .push(OptionNumber::LOCATION_PATH, r.id.to_string());
                self.persisted(r.id, created).await
            }
            Err(e) => refusal(&e),
        }
    }

    async fn register_simple(&self, request: &IncomingRequest) -> Response {
        if !self.proved(request) {
            return self.challenge(request);
        }
        if !request.payload.is_empty() {
            return Response::diagnostic(
                Code::BAD_REQUEST,
                "simple registration has an empty payload (RFC 9176 §5.1)",
            );
        }
        let params = match parse_params(request) {
            Ok(p) if p.base.is_some() => {
                return Response::diagnostic(
                    Code::BAD_REQUEST,
                    "simple registration takes no base (RFC 9176 §5.1)",
                );
            }
            Ok(p) => p,
            Err(e) => return refusal(&e),
        };
        let Ok(_permit) = self.fetching.try_acquire() else {
            let mut busy = Response::diagnostic(
                Code::SERVICE_UNAVAILABLE,
                "too many simple registrations under way",
            );
            busy.options.set_uint(OptionNumber::MAX_AGE, 1);
            return busy;
        };
        let peer = request.peer;
        let mut get = Request::new(Code::GET, "/.well-known/core");
        get.timeout = Some(SIMPLE_FETCH_TIMEOUT);
        let document = match self.fetcher.send(peer, get).await {
            Ok(r) if r.code == Code::CONTENT => r.payload,
            Ok(r) => {
                return Response::diagnostic(
                    Code::BAD_GATEWAY,
                    &format!("GET /.well-known/core of {peer} answered {}", r.code),
                );
            }
            Err(coap_net::Error::Request(coap::RequestError::TooLarge { limit })) => {
                return Response::diagnostic(
                    Code::REQUEST_ENTITY_TOO_LARGE,
                    &format!(
                        "the /.well-known/core of {peer} has more than {limit} bytes, the most one registration may have"
                    ),
                );
            }
            Err(e) => {
                return Response::diagnostic(
                    Code::GATEWAY_TIMEOUT,
                    &format!("GET /.well-known/core of {peer}: {e}"),
                );
            }
        };
        let Ok(document) = std::str::from_utf8(&document) else {
            return Response::diagnostic(
                Code::BAD_GATEWAY,
                "the endpoint's /.well-known/core is not UTF-8",
            );
        };
        let registered = self
            .directory()
            .register_simple(now_ms(), peer, params, document);
        match registered {
            Ok(r) => self.persisted(r.id, Response::new(Code::CHANGED)).await,
            Err(e) => refusal(&e),
        }
    }

    async fn update(&self, ctx: &Ctx) -> Response {
        if !self.proved(&ctx.request) {
            return self.challenge(&ctx.request);
        }
        let Some(id) = ctx.param("id").and_then(|s| s.parse::<u64>().ok()) else {
            return Response::diagnostic(Code::NOT_FOUND, "no such registration");
        };
        if !ctx.request.payload.is_empty() {
            return Response::diagnostic(
                Code::BAD_REQUEST,
                "an update has an empty payload (RFC 9176 §5.3.1); register again to change the links",
            );
        }
        let updated = parse_params(&ctx.request).and_then(|params| {
            self.directory()
                .update(now_ms(), ctx.request.peer, id, params)
        });
        match updated {
            Ok(()) => self.persisted(id, Response::new(Code::CHANGED)).await,
            Err(e) => refusal(&e),
        }
    }

    async fn remove(&self, ctx: &Ctx) -> Response {
        if !self.proved(&ctx.request) {
            return self.challenge(&ctx.request);
        }
        let Some(id) = ctx.param("id").and_then(|s| s.parse::<u64>().ok()) else {
            return Response::diagnostic(Code::NOT_FOUND, "no such registration");
        };
        let removed = self.directory().remove(ctx.request.peer, id);
        match removed {
            Ok(()) => self.persisted(id, Response::new(Code::DELETED)).await,
            Err(e) => refusal(&e),
        }
    }

    /// A lookup's answer: a source that renders each block from the registrations it
    /// lists when a client asks for it ([`Directory::listing`], a window of 16 KiB at a
    /// time), so the CoAP layer keeps 32 bytes per registration listed and the window for
    /// the block-wise transfer, not the document (17.3 MB for every link of 14,896
    /// stations, kept whole for each client before).
    fn lookup(me: &Arc<Self>, kind: LookupKind, request: &IncomingRequest) -> Response {
        let items: Vec<String> = request
            .options
            .uri_query()
            .map(|q| q.into_owned())
            .collect();
        let query = match Query::parse(items.iter().map(String::as_str)) {
            Ok(q) => q,
            Err(e) => return refusal(&e),
        };
        let listing = me.directory().listing(now_ms(), kind, &query);
        if me.verify_lookups
            && !request.loopback
            && first_message_len(request, listing.len()) > 3 * request_len(request)
            && !me.proved(request)
        {
            return me.challenge(request);
        }
        let answer = Answer {
            service: Arc::clone(me),
            listing,
            window: Mutex::new((0, bytes::Bytes::new())),
        };
        let mut r = Response::new(Code::CONTENT).with_source(answer);
        r.options.set_uint(
            OptionNumber::CONTENT_FORMAT,
            u32::from(ContentFormat::LINK_FORMAT.0),
        );
        r
    }
}

/// The bytes of a lookup's document rendered at once for the blocks that follow (a
/// block's registrations are rendered whole, and one spans blocks).
const WINDOW: usize = 16 << 10;

/// A lookup's document, read from the directory a window at a time.
struct Answer {
    service: Arc<Service>,
    listing: Listing,
    /// The last window read: its offset in the document and its bytes.
    window: Mutex<(usize, bytes::Bytes)>,
}

impl BlockSource for Answer {
    fn len(&self) -> usize {
        self.listing.len()
    }

    fn read(&self, range: std::ops::Range<usize>) -> Option<bytes::Bytes> {
        let mut window = self.window.lock().unwrap_or_else(PoisonError::into_inner);
        let (start, bytes) = &*window;
        if range.start < *start || range.end > start + bytes.len() {
            let end = range.end.max(range.start + WINDOW).min(self.len());
            let text = (self.service.directory()).read(&self.listing, range.start..end)?;
            *window = (range.start, text.into());
        }
        let (start, bytes) = &*window;
        Some(bytes.slice(range.start - start..range.end - start))
    }

    fn held(&self) -> usize {
        self.listing.held() + WINDOW.min(self.len())
    }
}

/// The bytes `request` took on the wire, at least: its header, options and payload (the
/// token is not known here, so a request is counted a little short).
fn request_len(request: &IncomingRequest) -> usize {
    coap::Message {
        ty: coap::Type::Con,
        code: request.method,
        message_id: 0,
        token: coap::Token::EMPTY,
        options: request.options.clone(),
        payload: request.payload.clone(),
    }
    .encoded_len()
}

/// The most bytes the first message of a lookup's answer takes: the block the request
/// asks for (1,024 bytes when it asks none) or the whole document if smaller, and 32
/// for the header, an 8-byte token, the options (Content-Format, and for a body in
/// blocks ETag, Block2 and Size2) and the payload marker.
fn first_message_len(request: &IncomingRequest, document: usize) -> usize {
    let szx = (request.options.block2()).map_or(coap::BlockOpt::MAX_SZX, |b| {
        b.szx.min(coap::BlockOpt::MAX_SZX)
    });
    let block = coap::BlockOpt::size_of(szx);
    32 + document.min(block)
}

/// The Uri-Query items of `request` as registration parameters.
fn parse_params(request: &IncomingRequest) -> Result<Params, RdError> {
    let items: Vec<String> = request
        .options
        .uri_query()
        .map(|q| q.into_owned())
        .collect();
    Params::parse(items.iter().map(String::as_str))
}

/// 4.15 for a body that is not link-format (none given means link-format).
fn link_format_only(request: &IncomingRequest) -> Option<Response> {
    match request.options.content_format() {
        None => None,
        Some(cf) if cf == ContentFormat::LINK_FORMAT => None,
        Some(cf) => Some(Response::diagnostic(
            Code::UNSUPPORTED_CONTENT_FORMAT,
            &format!(
                "Content-Format {} is not application/link-format (40)",
                cf.0
            ),
        )),
    }
}

/// The answer to a refused request: its code and the reason as the diagnostic; a full
/// directory says when to try again.
fn refusal(error: &RdError) -> Response {
    let mut r = Response::diagnostic(error.code(), &error.to_string());
    if matches!(error, RdError::Full(_)) {
        r.options.set_uint(OptionNumber::MAX_AGE, 60);
    }
    r
}

/// Runs the sweep of expired registrations every second until dropped (abort the task).
pub fn spawn_sweep(service: Arc<Service>) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(Duration::from_secs(1));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tick.tick().await;
            service.sweep().await;
        }
    })
}

#[cfg(test)]
mod tests {
    use std::net::SocketAddr;

    use coap::{EndpointConfig, IncomingId, Options, Source};

    use super::*;

    /// A GET of every link, from this machine.
    fn full_lookup() -> IncomingRequest {
        let mut options = Options::new();
        options.push(OptionNumber::URI_PATH, "rd-lookup");
        options.push(OptionNumber::URI_PATH, "res");
        IncomingRequest {
            id: IncomingId(1),
            peer: SocketAddr::from(([127, 0, 0, 1], 40_000)),
            method: Code::GET,
            options,
            payload: bytes::Bytes::new(),
            multicast: false,
            confirmable: true,
            observe: None,
            identity: None,
            loopback: true,
        }
    }

    #[tokio::test]
    async fn a_full_lookup_is_read_block_by_block_and_never_kept_whole() {
        let fetcher = Client::bind(
            SocketAddr::from(([127, 0, 0, 1], 0)),
            EndpointConfig::default(),
        )
        .expect("a client");
        let limits = Limits {
            per_peer: 2_000,
            per_peer_bytes: usize::MAX,
            ..Limits::default()
        };
        let service = Service::new(limits, None, fetcher, true).expect("a directory");
        let peer = SocketAddr::from(([10, 0, 0, 1], 5683));
        for i in 0..2_000 {
            let params = Params::parse([format!("ep=station-{i}").as_str()]).expect("params");
            // A camera's three streams and three documents.
            let links = [
                "color",
                "depth",
                "pointcloud",
                "color-settings",
                "depth-settings",
                "3d-transformation",
            ]
            .map(|r| format!(r#"</cams/{i:012}/{r}>;rt="rgbd.{r}";if="core.p";obs"#))
            .join(",");
            (service.directory())
                .register(now_ms(), peer, params, &links)
                .expect("registered");
        }
        let everything = Query::parse(std::iter::empty()).expect("a query");
        let whole = (service.directory())
            .lookup(now_ms(), LookupKind::Resources, &everything)
            .document;
        let r = Service::lookup(&service, LookupKind::Resources, &full_lookup());
        assert_eq!(r.code, Code::CONTENT);
        // What the CoAP layer keeps for the block-wise transfer (before: the whole
        // document as the payload).
        let kept = r.payload.len() + r.source.as_ref().map_or(0, Source::held);
        assert!(
            kept * 8 < whole.len(),
            "{kept} bytes kept for a document of {}",
            whole.len()
        );
        let source = r.source.expect("a source");
        let mut read = Vec::new();
        for start in (0..source.len()).step_by(1024) {
            let end = (start + 1024).min(source.len());
            read.extend_from_slice(&source.read(start..end).expect("readable"));
        }
        assert_eq!(read, whole.as_bytes());
    }
}
