//! Resources by path, added and removed at run time, with async per-method handlers and
//! link attributes that feed `/.well-known/core` (RFC 6690).

use std::collections::HashMap;
use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, RwLock};

use tokio::sync::broadcast;

use coap::link_format::{self, Filter, Link};
use coap::{Code, ContentFormat, IncomingRequest, ObservationId, OptionNumber, Response};

/// A request as a handler sees it: the received request plus the values of the path
/// pattern's `{name}` segments.
#[derive(Debug, Clone)]
pub struct Ctx {
    /// The request (body already assembled).
    pub request: IncomingRequest,
    /// Pattern parameters, e.g. `sn` for `/cams/{sn}/color`.
    pub params: HashMap<String, String>,
}

impl Ctx {
    /// A pattern parameter.
    pub fn param(&self, name: &str) -> Option<&str> {
        self.params.get(name).map(String::as_str)
    }
}

/// A boxed handler future.
pub type BoxFuture = Pin<Box<dyn Future<Output = Response> + Send>>;
/// A handler: an async function from request to response.
pub type Handler = Arc<dyn Fn(Ctx) -> BoxFuture + Send + Sync>;

/// Told that an observation of a resource ended ([`Resource::on_observation_end`]): the
/// observer's address and the observation, as the registration's
/// [`IncomingRequest::observe`] named it.
pub type ObservationEnd = Arc<dyn Fn(std::net::SocketAddr, ObservationId) + Send + Sync>;

/// Wraps an async closure as a [`Handler`].
pub fn handler<F, Fut>(f: F) -> Handler
where
    F: Fn(Ctx) -> Fut + Send + Sync + 'static,
    Fut: Future<Output = Response> + Send + 'static,
{
    Arc::new(move |ctx| Box::pin(f(ctx)))
}

/// One resource: its handlers per method and its link attributes.
#[derive(Clone, Default)]
pub struct Resource {
    methods: Vec<(Code, Handler)>,
    attrs: Vec<(String, Option<String>)>,
    observable: bool,
    /// Methods that change the server's configuration ([`Router::set_policy`]).
    configuring: Vec<Code>,
    /// Told when an observation of the resource ends.
    ended: Option<ObservationEnd>,
}

impl std::fmt::Debug for Resource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Resource")
            .field(
                "methods",
                &self.methods.iter().map(|(c, _)| *c).collect::<Vec<_>>(),
            )
            .field("attrs", &self.attrs)
            .field("observable", &self.observable)
            .finish()
    }
}

impl Resource {
    /// A resource without methods (every method answers 4.05 until one is added).
    pub fn new() -> Self {
        Self::default()
    }

    /// Handles `method`.
    pub fn on(mut self, method: Code, h: Handler) -> Self {
        self.methods.retain(|(c, _)| *c != method);
        self.methods.push((method, h));
        self
    }

    /// Handles GET.
    pub fn get(self, h: Handler) -> Self {
        self.on(Code::GET, h)
    }

    /// Handles POST.
    pub fn post(self, h: Handler) -> Self {
        self.on(Code::POST, h)
    }

    /// Handles PUT.
    pub fn put(self, h: Handler) -> Self {
        self.on(Code::PUT, h)
    }

    /// Handles DELETE.
    pub fn delete(self, h: Handler) -> Self {
        self.on(Code::DELETE, h)
    }

    /// A link attribute for `/.well-known/core` (e.g. `rt`, `if`, `ct`, `title`).
    pub fn attr(mut self, name: &str, value: impl Into<String>) -> Self {
        self.attrs.push((name.to_string(), Some(value.into())));
        self
    }

    /// Marks the resource observable (RFC 7641): GET registrations are accepted and the
    /// link carries `obs`.
    pub fn observable(mut self) -> Self {
        self.observable = true;
        self
    }

    /// Calls `ended` when an observation of the resource ends: the observer deregistered
    /// or rejected a notification, a confirmable notification went unacknowledged, or a
    /// notification was an error. A handler that keeps something per observer (its
    /// registration's [`IncomingRequest::observe`]) lets it go then.
    pub fn on_observation_end(mut self, ended: ObservationEnd) -> Self {
        self.ended = Some(ended);
        self
    }

    /// What is told when an observation of the resource ends, if anything.
    pub fn observation_end(&self) -> Option<&ObservationEnd> {
        self.ended.as_ref()
    }

    /// Whether the resource is observable.
    pub fn is_observable(&self) -> bool {
        self.observable
    }

    /// Marks `methods` as changing the server's configuration: the router's policy
    /// ([`Router::set_policy`]) decides who may use them.
    pub fn configuring(mut self, methods: &[Code]) -> Self {
        self.configuring.extend_from_slice(methods);
        self
    }

    fn handler(&self, method: Code) -> Option<&Handler> {
        self.methods
            .iter()
            .find(|(c, _)| *c == method)
            .map(|(_, h)| h)
    }
}

#[derive(Debug, Clone, PartialEq, Eq)]
enum Segment {
    Literal(String),
    Param(String),
}

fn parse_pattern(pattern: &str) -> Vec<Segment> {
    pattern
        .split('/')
        .filter(|s| !s.is_empty())
        .map(
            |s| match s.strip_prefix('{').and_then(|s| s.strip_suffix('}')) {
                Some(name) => Segment::Param(name.to_string()),
                None => Segment::Literal(s.to_string()),
            },
        )
        .collect()
}

fn match_pattern(pattern: &[Segment], path: &[String]) -> Option<HashMap<String, String>> {
    if pattern.len() != path.len() {
        return None;
    }
    let mut params = HashMap::new();
    for (seg, part) in pattern.iter().zip(path) {
        match seg {
            Segment::Literal(l) if l == part => {}
            Segment::Literal(_) => return None,
            Segment::Param(name) => {
                params.insert(name.clone(), part.clone());
            }
        }
    }
    Some(params)
}

struct Entry {
    pattern: String,
    segments: Vec<Segment>,
    resource: Resource,
}

/// The resource table. Shared (`Arc<Router>`) between the server and whoever adds and
/// removes resources at run time.
#[derive(Default)]
pub struct Router {
    entries: RwLock<Vec<Entry>>,
    policy: RwLock<Option<Policy>>,
    around: RwLock<Option<Around>>,
    changes: Changes,
}

/// How many changed paths wait for a stream connection that has not taken them yet; one
/// that falls further behind takes every path it observes for changed
/// ([`Router::changes`]).
const CHANGES_BUFFER: usize = 64;

/// The paths [`Router::changed`] was told of, for every stream connection serving the
/// router.
struct Changes(broadcast::Sender<Arc<str>>);

impl Default for Changes {
    fn default() -> Self {
        Self(broadcast::channel(CHANGES_BUFFER).0)
    }
}

/// Who may change the configuration: the answer to a request it refuses, `None` for one
/// it lets through.
pub type Policy = Arc<dyn Fn(&IncomingRequest) -> Option<Response> + Send + Sync>;

/// What the application does around every answer ([`Router::set_around`]): called with
/// the request before anything answers it; the function it returns is called with the
/// answer, whoever made it, just before the router hands it on.
pub type Around =
    Arc<dyn Fn(&IncomingRequest) -> Box<dyn FnOnce(&mut Response) + Send> + Send + Sync>;

impl std::fmt::Debug for Router {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Router")
            .field("patterns", &self.patterns())
            .finish()
    }
}

/// A pattern's segments and its canonical text (`/a/{b}`), the key entries are stored by.
fn normalized(pattern: &str) -> (String, Vec<Segment>) {
    let segments = parse_pattern(pattern);
    let text = format!(
        "/{}",
        segments.iter().map(seg_str).collect::<Vec<_>>().join("/")
    );
    (text, segments)
}

impl Router {
    /// An empty router (it still answers `/.well-known/core`).
    pub fn new() -> Arc<Self> {
        Arc::new(Self::default())
    }

    /// Sets who may use the methods resources mark as [`Resource::configuring`]; without a
    /// policy anyone may.
    pub fn set_policy(&self, policy: Policy) {
        *self
            .policy
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = Some(policy);
    }

    /// Sets what is done around every answer (e.g. stamping the times of the exchange
    /// into it); by default nothing.
    pub fn set_around(&self, around: Around) {
        *self
            .around
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = Some(around);
    }

    /// Tells the connections that serve this router over streams (a
    /// [`TcpServer`](crate::TcpServer)'s) that the representation of `path` changed: each
    /// notifies its observers of `path`, as [`Server::notify`](crate::Server::notify), which
    /// calls this, does those over UDP. Over a stream an observation lives in its
    /// connection, so the connection keeps it rather than the server.
    pub fn changed(&self, path: &str) {
        // No receiver (no stream connection open) is no error.
        let _ = self.changes.0.send(Arc::from(path));
    }

    /// The paths [`Router::changed`] is told of from now on. A receiver more than
    /// 64 paths behind loses the oldest and is told it lagged.
    pub(crate) fn changes(&self) -> broadcast::Receiver<Arc<str>> {
        self.changes.0.subscribe()
    }

    /// Adds or replaces the resource at `pattern` (`/files/a.bin`, `/cams/{sn}/color`).
    /// Literal paths are matched before patterns with parameters.
    pub fn add(&self, pattern: &str, resource: Resource) {
        self.add_all([(pattern, resource)]);
    }

    /// Adds or replaces several resources at once: a request finds all of them or none
    /// (a camera's resources appear together).
    pub fn add_all<P: AsRef<str>>(&self, resources: impl IntoIterator<Item = (P, Resource)>) {
        let added: Vec<Entry> = resources
            .into_iter()
            .map(|(pattern, resource)| {
                let (pattern, segments) = normalized(pattern.as_ref());
                Entry {
                    pattern,
                    segments,
                    resource,
                }
            })
            .collect();
        let mut entries = self
            .entries
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        for entry in added {
            entries.retain(|e| e.pattern != entry.pattern);
            entries.push(entry);
        }
        entries.sort_by_key(|e| {
            e.segments
                .iter()
                .filter(|s| matches!(s, Segment::Param(_)))
                .count()
        });
    }

    /// Removes the resource at `pattern`; returns whether there was one.
    pub fn remove(&self, pattern: &str) -> bool {
        self.remove_all([pattern]) > 0
    }

    /// Removes several resources at once (see [`Router::add_all`]); returns how many
    /// there were.
    pub fn remove_all<P: AsRef<str>>(&self, patterns: impl IntoIterator<Item = P>) -> usize {
        let gone: Vec<String> = patterns
            .into_iter()
            .map(|p| normalized(p.as_ref()).0)
            .collect();
        let mut entries = self
            .entries
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let before = entries.len();
        entries.retain(|e| !gone.contains(&e.pattern));
        before - entries.len()
    }

    /// The registered patterns.
    pub fn patterns(&self) -> Vec<String> {
        let entries = self
            .entries
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        entries.iter().map(|e| e.pattern.clone()).collect()
    }

    /// The resource for a concrete path, with its parameters.
    pub fn find(&self, path: &[String]) -> Option<(Resource, HashMap<String, String>)> {
        let entries = self
            .entries
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        entries
            .iter()
            .find_map(|e| match_pattern(&e.segments, path).map(|p| (e.resource.clone(), p)))
    }

    /// The `/.well-known/core` document (RFC 6690 §4): every resource whose path has no
    /// parameters, with its attributes, filtered by the query.
    pub fn links(&self, filter: &Filter) -> String {
        let entries = self
            .entries
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let links: Vec<Link> = entries
            .iter()
            .filter(|e| e.segments.iter().all(|s| matches!(s, Segment::Literal(_))))
            .map(|e| {
                let mut link = Link {
                    target: e.pattern.clone(),
                    attrs: e.resource.attrs.clone(),
                };
                if e.resource.observable {
                    link.attrs.push(("obs".to_string(), None));
                }
                link
            })
            .filter(|l| filter.matches(l))
            .collect();
        link_format::write_links(&links)
    }

    /// Answers a request: `/.well-known/core`, the resource's handler, 4.04 for an unknown
    /// path, 4.05 for a method the resource lacks. A GET whose ETag option names the
    /// representation the handler produced is answered 2.03 Valid (RFC 7252 §5.10.6.1).
    /// What [`Router::set_around`] set is done around it.
    pub async fn dispatch(&self, request: IncomingRequest) -> Response {
        let around = (self.around.read())
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone();
        let after = around.map(|around| around(&request));
        let mut response = self.answer(request).await;
        if let Some(after) = after {
            after(&mut response);
        }
        response
    }

    async fn answer(&self, request: IncomingRequest) -> Response {
        let path: Vec<String> = request.options.uri_path().map(|s| s.into_owned()).collect();
        if path == [".well-known", "core"] {
            if request.method != Code::GET {
                return Response::diagnostic(Code::METHOD_NOT_ALLOWED, "GET only");
            }
            let query: Vec<String> = request
                .options
                .uri_query()
                .map(|q| q.into_owned())
                .collect();
            let filter = match Filter::parse(&query.join("&")) {
                Ok(f) => f,
                Err(e) => return Response::diagnostic(Code::BAD_REQUEST, &e.to_string()),
            };
            let mut r = Response::new(Code::CONTENT).with_payload(self.links(&filter));
            r.options.set_uint(
                OptionNumber::CONTENT_FORMAT,
                u32::from(ContentFormat::LINK_FORMAT.0),
            );
            return r;
        }
        let Some((resource, params)) = self.find(&path) else {
            return Response::diagnostic(Code::NOT_FOUND, "no such resource");
        };
        let Some(h) = resource.handler(request.method).cloned() else {
            return Response::diagnostic(
                Code::METHOD_NOT_ALLOWED,
                "method not allowed on this resource",
            );
        };
        if resource.configuring.contains(&request.method) {
            let policy = (self.policy.read())
                .unwrap_or_else(std::sync::PoisonError::into_inner)
                .clone();
            if let Some(refused) = policy.and_then(|refuses| refuses(&request)) {
                return refused;
            }
        }
        let etags: Vec<Vec<u8>> = request
            .options
            .values(OptionNumber::ETAG)
            .map(<[u8]>::to_vec)
            .collect();
        let method = request.method;
        let observable = resource.observable;
        let observe = request.observe.is_some();
        let mut response = h(Ctx { request, params }).await;
        if method == Code::GET
            && response.code == Code::CONTENT
            && response
                .options
                .etag()
                .is_some_and(|t| etags.iter().any(|e| e == t))
        {
            // The client's copy is current: 2.03 with the ETag, no payload.
            response.code = Code::VALID;
            response.payload = bytes::Bytes::new();
        }
        if observable && observe && response.code.is_success() {
            // Accept the registration (the endpoint numbers the notifications).
            response.options.set_uint(OptionNumber::OBSERVE, 0);
        }
        response
    }
}

fn seg_str(s: &Segment) -> String {
    match s {
        Segment::Literal(l) => l.clone(),
        Segment::Param(p) => format!("{{{p}}}"),
    }
}

/// RFC 7252 §5.10.8: checks If-Match and If-None-Match of a request against the current
/// ETag of the target (`None`: the resource does not exist). Returns 4.12 Precondition
/// Failed when a condition fails.
pub fn check_preconditions(request: &IncomingRequest, current: Option<&[u8]>) -> Option<Response> {
    let if_match: Vec<&[u8]> = request.options.values(OptionNumber::IF_MATCH).collect();
    if !if_match.is_empty() {
        // An empty If-Match value matches any existing representation.
        let ok = current.is_some_and(|c| if_match.iter().any(|m| m.is_empty() || *m == c));
        if !ok {
            return Some(Response::diagnostic(
                Code::PRECONDITION_FAILED,
                "If-Match failed",
            ));
        }
    }
    if request.options.contains(OptionNumber::IF_NONE_MATCH) && current.is_some() {
        return Some(Response::diagnostic(
            Code::PRECONDITION_FAILED,
            "If-None-Match: resource exists",
        ));
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resources_added_and_removed_together_replace_and_count() {
        let router = Router::new();
        let titled = |t: &str| Resource::new().attr("title", t);
        router.add("/cams/1/color", titled("old"));
        router.add_all([
            ("/cams/1/color", titled("new")),
            ("/cams/1/depth", titled("d")),
        ]);
        let mut patterns = router.patterns();
        patterns.sort();
        assert_eq!(patterns, ["/cams/1/color", "/cams/1/depth"]);
        let path = |p: &str| p.split('/').skip(1).map(str::to_owned).collect::<Vec<_>>();
        let (found, _) = router.find(&path("/cams/1/color")).expect("color");
        assert_eq!(found.attrs, [("title".to_owned(), Some("new".to_owned()))]);
        assert_eq!(
            router.remove_all(["/cams/1/color", "/cams/1/depth", "/cams/1/x"]),
            2
        );
        assert!(router.patterns().is_empty());
        assert!(!router.remove("/cams/1/color"));
    }

    #[test]
    fn the_policy_decides_only_the_methods_marked_configuring() {
        let router = Router::new();
        let ok = || handler(|_ctx| async { Response::new(Code::CHANGED) });
        router.add(
            "/cfg",
            Resource::new()
                .get(ok())
                .put(ok())
                .post(ok())
                .configuring(&[Code::PUT]),
        );
        // A request from this machine (over loopback) or from elsewhere.
        let request = |method: Code, loopback: bool| IncomingRequest {
            id: coap::IncomingId(1),
            peer: "192.0.2.7:5683".parse().expect("address"),
            method,
            options: coap::Request::new(method, "/cfg").options,
            payload: bytes::Bytes::new(),
            multicast: false,
            confirmable: true,
            observe: None,
            identity: None,
            loopback,
        };
        let code = |method, loopback| {
            let runtime = tokio::runtime::Builder::new_current_thread()
                .build()
                .expect("runtime");
            runtime
                .block_on(router.dispatch(request(method, loopback)))
                .code
        };
        assert_eq!(code(Code::PUT, false), Code::CHANGED, "no policy yet");
        router.set_policy(Arc::new(|r: &IncomingRequest| {
            (!r.loopback).then(|| Response::new(Code::FORBIDDEN))
        }));
        assert_eq!(code(Code::PUT, false), Code::FORBIDDEN);
        assert_eq!(code(Code::PUT, true), Code::CHANGED);
        assert_eq!(code(Code::POST, false), Code::CHANGED, "POST is not marked");
        assert_eq!(code(Code::GET, false), Code::CHANGED);
    }
}
