//! The client side of a resource directory: a server's registration kept alive
//! (`serve --register`) and the lookups of `discover --rd` and `measure --group --rd`.
//!
//! [`Schedule`] is the registration's state, sans-IO (instants in, the next action
//! out): register, renew at three quarters of the lifetime, register again when the
//! announced links or groups changed or the directory lost the registration, retry a
//! failure after 1 s, doubling up to an eighth of the lifetime. [`Registrant`] drives
//! it from a task over a `coap_net::Client` that sends from the server's own socket
//! (so the directory's base is the server's address), and removes the registration
//! when stopped.

use std::future::Future;
use std::net::SocketAddr;
use std::time::Duration;

use anyhow::{Context as _, bail};
use coap::link_format::{self, Link};
use coap::{Code, ContentFormat, OptionNumber, Request};
use coap_net::{Client, Uri};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tokio::time::Instant;

use super::service::REGISTRATION_PATH;

/// The endpoint type coapcam's servers register with (`et`).
pub const STATION_ET: &str = "coapcam.station";

/// The endpoint attribute naming a group the server joined (`grp=ADDR:PORT`, once per
/// group).
pub const GROUP_ATTR: &str = "grp";

/// How a group is named in `grp`: its address and port (`224.0.1.188:5683`,
/// `[ff02::fd]:5683`), without an IPv6 zone.
#[must_use]
pub fn group_key(group: SocketAddr) -> String {
    SocketAddr::new(group.ip(), group.port()).to_string()
}

/// How often the task looks whether the links or groups changed.
const LOOK: Duration = Duration::from_secs(1);

/// What a server announces: its links (its `/.well-known/core` document) and the groups
/// it joined (`ADDR:PORT`, IPv6 in brackets).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Announcement {
    /// The link-format document to register.
    pub links: String,
    /// The groups, each as `ADDR:PORT`.
    pub groups: Vec<String>,
}

/// What to do next.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Action {
    /// Register (again): POST the links to the registration resource.
    Register,
    /// Renew: POST to the registration's location.
    Update(String),
    /// Nothing before this instant (unless the announcement changes).
    Wait(Instant),
}

#[derive(Debug, Clone)]
enum State {
    Unregistered {
        retry_at: Instant,
    },
    Registered {
        location: String,
        announced: Announcement,
        renew_at: Instant,
    },
}

/// A registration's schedule, sans-IO.
#[derive(Debug, Clone)]
pub struct Schedule {
    lifetime: Duration,
    state: State,
    backoff: Duration,
}

impl Schedule {
    /// A schedule for a registration of `lifetime`, to register at `now`.
    #[must_use]
    pub fn new(now: Instant, lifetime: Duration) -> Self {
        Self {
            lifetime,
            state: State::Unregistered { retry_at: now },
            backoff: Duration::from_secs(1),
        }
    }

    /// The location of the registration, when registered.
    #[must_use]
    pub fn location(&self) -> Option<&str> {
        match &self.state {
            State::Registered { location, .. } => Some(location),
            State::Unregistered { .. } => None,
        }
    }

    /// What to do at `now`, the server announcing `current`.
    #[must_use]
    pub fn next(&self, now: Instant, current: &Announcement) -> Action {
        match &self.state {
            State::Unregistered { retry_at } if *retry_at <= now => Action::Register,
            State::Unregistered { retry_at } => Action::Wait(*retry_at),
            State::Registered { announced, .. } if announced != current => Action::Register,
            State::Registered {
                location, renew_at, ..
            } if *renew_at <= now => Action::Update(location.clone()),
            State::Registered { renew_at, .. } => Action::Wait(*renew_at),
        }
    }

    /// The directory took the registration (or its renewal) at `now`.
    pub fn registered(&mut self, now: Instant, location: String, announced: Announcement) {
        self.backoff = Duration::from_secs(1);
        self.state = State::Registered {
            location,
            announced,
            renew_at: now + self.lifetime * 3 / 4,
        };
    }

    /// A renewal was answered 2.04 at `now`.
    pub fn renewed(&mut self, now: Instant) {
        self.backoff = Duration::from_secs(1);
        if let State::Registered { renew_at, .. } = &mut self.state {
            *renew_at = now + self.lifetime * 3 / 4;
        }
    }

    /// The directory no longer knows the registration (4.04 to a renewal): register again.
    pub fn lost(&mut self, now: Instant) {
        self.state = State::Unregistered { retry_at: now };
    }

    /// A registration or renewal failed at `now` (no answer, an error): try again after
    /// the back-off, 1 s doubling up to an eighth of the lifetime (at least 1 s).
    pub fn failed(&mut self, now: Instant) {
        let cap = (self.lifetime / 8).max(Duration::from_secs(1));
        let wait = self.backoff.min(cap);
        self.backoff = (self.backoff * 2).min(cap);
        match &mut self.state {
            State::Unregistered { retry_at } => *retry_at = now + wait,
            State::Registered { renew_at, .. } => *renew_at = now + wait,
        }
    }
}

/// Where and how a server registers.
#[derive(Debug, Clone)]
pub struct RegistrantConfig {
    /// The directory's address.
    pub rd: SocketAddr,
    /// The registration resource's path when the URI gave one; else it is discovered
    /// (`/.well-known/core?rt=core.rd`), `/rd` when discovery finds none.
    pub path: Option<String>,
    /// The endpoint name.
    pub ep: String,
    /// The sector, if any.
    pub d: Option<String>,
    /// The lifetime in seconds.
    pub lt: u32,
}

impl RegistrantConfig {
    /// From a `coap://HOST[:PORT][/PATH]` URI (resolved).
    ///
    /// # Errors
    ///
    /// A URI that does not parse or resolve, or `coaps://` or `coap+tcp://` (not
    /// supported here).
    pub async fn from_uri(
        uri: &str,
        ep: String,
        d: Option<String>,
        lt: u32,
    ) -> anyhow::Result<Self> {
        let parsed = Uri::parse(uri)?;
        if parsed.secure || parsed.tcp || parsed.ws {
            bail!(
                "{uri}: registering over coaps://, coap+tcp:// or coap+ws:// is not supported; give coap://"
            );
        }
        let rd = parsed
            .resolve()
            .await
            .with_context(|| format!("resolving {uri}"))?;
        let path = (!parsed.path.is_empty()).then(|| parsed.path_string());
        Ok(Self {
            rd,
            path,
            ep,
            d,
            lt,
        })
    }
}

/// A registration kept alive by a task until [`Registrant::remove`].
#[derive(Debug)]
pub struct Registrant {
    stop: Option<oneshot::Sender<()>>,
    task: JoinHandle<()>,
}

impl Registrant {
    /// Starts the task: `client` sends (from the server's socket), `announce` says what
    /// the server offers now.
    pub fn spawn<F, Fut>(config: RegistrantConfig, client: Client, announce: F) -> Self
    where
        F: Fn() -> Fut + Send + 'static,
        Fut: Future<Output = Announcement> + Send + 'static,
    {
        let (stop, stopped) = oneshot::channel();
        let task = tokio::spawn(keep(config, client, announce, stopped));
        Self {
            stop: Some(stop),
            task,
        }
    }

    /// Removes the registration from the directory (DELETE, waited for up to about 5 s)
    /// and ends the task.
    pub async fn remove(mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        let _ = (&mut self.task).await;
    }
}

impl Drop for Registrant {
    fn drop(&mut self) {
        if self.stop.is_some() {
            self.task.abort();
        }
    }
}

/// The registration resource's path: the configured one, else the first `rt=core.rd`
/// link of the directory's `/.well-known/core`, else `/rd`.
pub async fn registration_path(client: &Client, config: &RegistrantConfig) -> String {
    if let Some(p) = &config.path {
        return p.clone();
    }
    find_resource(client, config.rd, "core.rd", Duration::from_secs(5))
        .await
        .ok()
        .flatten()
        .unwrap_or_else(|| REGISTRATION_PATH.to_owned())
}

/// The path of the first link of `rt` in the directory's `/.well-known/core`: `None`
/// when the directory answered but lists no such link.
///
/// # Errors
///
/// No answer within `timeout`, an error answer, or a document that does not parse.
pub async fn find_resource(
    client: &Client,
    rd: SocketAddr,
    rt: &str,
    timeout: Duration,
) -> anyhow::Result<Option<String>> {
    let mut get = Request::new(Code::GET, "/.well-known/core");
    get.options
        .push(OptionNumber::URI_QUERY, format!("rt={rt}"));
    get.timeout = Some(timeout);
    let r = client
        .send(rd, get)
        .await
        .with_context(|| format!("asking {rd} for /.well-known/core?rt={rt}"))?;
    if r.code != Code::CONTENT {
        bail!(
            "{rd} answered /.well-known/core?rt={rt} with {} {}",
            r.code,
            String::from_utf8_lossy(&r.payload)
        );
    }
    let text = std::str::from_utf8(&r.payload)
        .with_context(|| format!("{rd}'s /.well-known/core is not UTF-8"))?;
    let links =
        link_format::parse(text).with_context(|| format!("parsing {rd}'s /.well-known/core"))?;
    Ok(links
        .into_iter()
        .find(|l| l.rt().any(|t| t == rt))
        .map(|l| path_of(&l.target)))
}

/// The path of a link target (`/rd`, or the path of `coap://host/rd`).
fn path_of(target: &str) -> String {
    match target.split_once("://") {
        Some((_, rest)) => rest.find('/').map_or_else(
            || "/".to_owned(),
            |i| rest.get(i..).unwrap_or("/").to_owned(),
        ),
        None => target.to_owned(),
    }
}

/// A request with `path` and the query items. The path's segments are kept as given,
/// an empty last one too: aiocoap's directory is at `/resourcedirectory/`.
fn request(method: Code, path: &str, query: &[String]) -> Request {
    let mut r = Request::new(method, "/");
    let path = path.strip_prefix('/').unwrap_or(path);
    if !path.is_empty() {
        for seg in path.split('/') {
            r.options.push(OptionNumber::URI_PATH, seg.as_bytes());
        }
    }
    for q in query {
        r.options.push(OptionNumber::URI_QUERY, q.as_bytes());
    }
    r.timeout = Some(Duration::from_secs(10));
    r
}

async fn keep<F, Fut>(
    config: RegistrantConfig,
    client: Client,
    announce: F,
    mut stopped: oneshot::Receiver<()>,
) where
    F: Fn() -> Fut,
    Fut: Future<Output = Announcement>,
{
    let lifetime = Duration::from_secs(u64::from(config.lt));
    let mut schedule = Schedule::new(Instant::now(), lifetime);
    let mut path: Option<String> = None;
    // Failures in a row: the first is a warning, the retries that fail the same way
    // are debug lines until one succeeds.
    let mut failures = 0u32;
    loop {
        let current = announce().await;
        let now = Instant::now();
        match schedule.next(now, &current) {
            Action::Register => {
                let p = match &path {
                    Some(p) => p.clone(),
                    None => {
                        let p = registration_path(&client, &config).await;
                        path = Some(p.clone());
                        p
                    }
                };
                match register(&client, &config, &p, &current).await {
                    Ok(location) => {
                        tracing::info!(rd = %config.rd, %location, ep = %config.ep, failures, "registered");
                        failures = 0;
                        schedule.registered(Instant::now(), location, current);
                    }
                    Err(e) => {
                        let error = format!("{e:#}");
                        if failures == 0 {
                            tracing::warn!(rd = %config.rd, %error, "registering with the directory failed; trying again, at longer intervals, without saying so again until it succeeds");
                        } else {
                            tracing::debug!(rd = %config.rd, %error, failures, "registering with the directory failed again");
                        }
                        failures += 1;
                        // The path is looked up again: the directory may have restarted
                        // elsewhere or with other paths.
                        path = None;
                        schedule.failed(Instant::now());
                    }
                }
                continue;
            }
            Action::Update(location) => {
                let r = client
                    .send(config.rd, request(Code::POST, &location, &[]))
                    .await;
                match r {
                    Ok(r) if r.code == Code::CHANGED => schedule.renewed(Instant::now()),
                    Ok(r) if r.code == Code::NOT_FOUND => {
                        tracing::warn!(rd = %config.rd, %location, "the directory lost the registration; registering again");
                        schedule.lost(Instant::now());
                    }
                    Ok(r) => {
                        tracing::warn!(rd = %config.rd, code = %r.code, "renewing the registration was refused; registering again");
                        schedule.lost(Instant::now());
                    }
                    Err(e) => {
                        tracing::warn!(rd = %config.rd, error = %e, "renewing the registration failed; trying again");
                        schedule.failed(Instant::now());
                    }
                }
                continue;
            }
            Action::Wait(until) => {
                let until = until.min(now + LOOK);
                tokio::select! {
                    () = tokio::time::sleep_until(until) => {}
                    _ = &mut stopped => break,
                }
            }
        }
    }
    if let Some(location) = schedule.location() {
        let mut delete = request(Code::DELETE, location, &[]);
        delete.timeout = Some(Duration::from_secs(5));
        match client.send(config.rd, delete).await {
            Ok(r) if r.code.is_success() => {
                tracing::info!(rd = %config.rd, %location, "registration removed");
            }
            Ok(r) => {
                tracing::warn!(rd = %config.rd, code = %r.code, "removing the registration was refused")
            }
            Err(e) => {
                tracing::warn!(rd = %config.rd, error = %e, "removing the registration failed")
            }
        }
    }
}

/// One registration: the location the directory answered.
async fn register(
    client: &Client,
    config: &RegistrantConfig,
    path: &str,
    announced: &Announcement,
) -> anyhow::Result<String> {
    let mut query = vec![
        format!("ep={}", config.ep),
        format!("lt={}", config.lt),
        format!("et={STATION_ET}"),
    ];
    if let Some(d) = &config.d {
        query.push(format!("d={d}"));
    }
    query.extend(announced.groups.iter().map(|g| format!("{GROUP_ATTR}={g}")));
    let mut post = request(Code::POST, path, &query);
    post.options.set_uint(
        OptionNumber::CONTENT_FORMAT,
        u32::from(ContentFormat::LINK_FORMAT.0),
    );
    post.payload = announced.links.clone().into();
    let r = client.send(config.rd, post).await?;
    if r.code == Code::FORBIDDEN {
        // coapcam's directory refuses a name registered from another address: most often
        // a second server of one host, where every server defaults to the host's name.
        bail!(
            "{} answered {} {}: the endpoint name {:?} may be taken by another server (every server of one host is named after the host unless told otherwise): give each server its own name with serve --rd-ep NAME (or --station-name NAME)",
            config.rd,
            r.code,
            String::from_utf8_lossy(&r.payload),
            config.ep
        );
    }
    if r.code != Code::CREATED && r.code != Code::CHANGED {
        bail!(
            "{} answered {} {}",
            config.rd,
            r.code,
            String::from_utf8_lossy(&r.payload)
        );
    }
    let location: Vec<String> = r
        .options
        .values(OptionNumber::LOCATION_PATH)
        .map(|v| String::from_utf8_lossy(v).into_owned())
        .collect();
    if location.is_empty() {
        bail!("{} answered {} without a Location-Path", config.rd, r.code);
    }
    Ok(format!("/{}", location.join("/")))
}

/// One endpoint a directory lists.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Endpoint {
    /// Its name (`ep`).
    pub ep: String,
    /// Its base URI.
    pub base: String,
    /// The base as a socket address, when it is a `coap://` URI with an address literal.
    pub addr: Option<SocketAddr>,
    /// The endpoint link as the directory gave it.
    pub link: Link,
}

/// Endpoint lookup: the endpoints of the directory at `rd` that meet `query` (RFC 9176
/// criteria, e.g. `grp=224.0.1.188:5683`), the lookup path discovered
/// (`rt=core.rd-lookup-ep`).
///
/// # Errors
///
/// No lookup resource, no answer, an error answer, or a document that does not parse.
pub async fn lookup_endpoints(
    client: &Client,
    rd: SocketAddr,
    query: &[String],
    timeout: Duration,
) -> anyhow::Result<Vec<Endpoint>> {
    let path = find_resource(client, rd, "core.rd-lookup-ep", timeout)
        .await?
        .with_context(|| {
            format!("{rd} lists no endpoint lookup (rt=core.rd-lookup-ep) in /.well-known/core")
        })?;
    let mut get = request(Code::GET, &path, query);
    get.timeout = Some(timeout);
    let r = client
        .send(rd, get)
        .await
        .with_context(|| format!("endpoint lookup at {rd}{path}"))?;
    if r.code != Code::CONTENT {
        bail!(
            "endpoint lookup at {rd}{path} answered {} {}",
            r.code,
            String::from_utf8_lossy(&r.payload)
        );
    }
    let text = std::str::from_utf8(&r.payload).context("the lookup's document is not UTF-8")?;
    let links = link_format::parse(text).context("parsing the lookup's document")?;
    Ok(links
        .into_iter()
        .map(|link| {
            let base = link.attr("base").unwrap_or_default().to_owned();
            let addr = Uri::parse(&base)
                .ok()
                .filter(|u| !u.secure && !u.tcp && !u.ws)
                .and_then(|u| u.ip().map(|ip| SocketAddr::new(ip, u.port)));
            Endpoint {
                ep: link.attr("ep").unwrap_or_default().to_owned(),
                base,
                addr,
                link,
            }
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(base: Instant, s: u64) -> Instant {
        base + Duration::from_secs(s)
    }

    #[test]
    fn registers_renews_at_three_quarters_and_again_when_the_announcement_changes() {
        let t = Instant::now();
        let mut s = Schedule::new(t, Duration::from_secs(60));
        let a = Announcement {
            links: "</cams>".into(),
            groups: vec!["224.0.1.188:5683".into()],
        };
        assert_eq!(s.next(t, &a), Action::Register);
        s.registered(t, "/rd/1".into(), a.clone());
        assert_eq!(s.location(), Some("/rd/1"));
        assert_eq!(s.next(at(t, 10), &a), Action::Wait(at(t, 45)));
        assert_eq!(s.next(at(t, 45), &a), Action::Update("/rd/1".into()));
        s.renewed(at(t, 45));
        assert_eq!(s.next(at(t, 46), &a), Action::Wait(at(t, 90)));
        // A camera came: the links changed.
        let b = Announcement {
            links: "</cams>,</cams/1/color>".into(),
            ..a.clone()
        };
        assert_eq!(s.next(at(t, 46), &b), Action::Register);
        // A group left.
        let c = Announcement {
            groups: vec![],
            ..a.clone()
        };
        assert_eq!(s.next(at(t, 46), &c), Action::Register);
        s.lost(at(t, 50));
        assert_eq!(s.location(), None);
        assert_eq!(s.next(at(t, 50), &a), Action::Register);
    }

    #[test]
    fn failures_back_off_doubling_up_to_an_eighth_of_the_lifetime() {
        let t = Instant::now();
        let mut s = Schedule::new(t, Duration::from_secs(40));
        let a = Announcement::default();
        let mut now = t;
        let mut waits = Vec::new();
        for _ in 0..5 {
            s.failed(now);
            let Action::Wait(until) = s.next(now, &a) else {
                panic!("waits after a failure");
            };
            waits.push((until - now).as_secs());
            now = until;
        }
        assert_eq!(waits, [1, 2, 4, 5, 5]);
        assert_eq!(s.next(now, &a), Action::Register);
        s.registered(now, "/rd/2".into(), a.clone());
        s.failed(now);
        assert_eq!(s.next(now, &a), Action::Wait(now + Duration::from_secs(1)));
        // A short lifetime still retries after a second.
        let mut short = Schedule::new(t, Duration::from_secs(2));
        short.failed(t);
        short.failed(t);
        assert_eq!(short.next(t, &a), Action::Wait(at(t, 1)));
    }

    #[test]
    fn link_targets_give_their_path() {
        assert_eq!(path_of("/rd"), "/rd");
        assert_eq!(
            path_of("coap://[::1]:5683/resourcedirectory/"),
            "/resourcedirectory/"
        );
        assert_eq!(path_of("coap://h"), "/");
    }
}
