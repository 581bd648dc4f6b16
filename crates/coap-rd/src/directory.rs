//! The directory itself, sans-IO: registrations in, lookups out, every call given the
//! time (`now`, milliseconds since the UNIX epoch, so lifetimes survive a restart).
//!
//! RFC 9176 in this module's terms:
//! - [`Directory::register`] is the registration interface (§5.3): `ep`, `d`, `lt`,
//!   `base` and any other parameter (stored as an endpoint attribute, `et` among them);
//!   the same (`ep`, `d`) again replaces the links and keeps the location.
//! - [`Directory::register_simple`] is simple registration (§5.1): the links come from
//!   the endpoint's own `/.well-known/core`, fetched by the caller; `base` is refused.
//! - [`Directory::update`] and [`Directory::remove`] are the operations on a
//!   registration resource (§5.3.1, §5.3.2).
//! - [`Directory::lookup`] is endpoint and resource lookup (§6) with the criteria of
//!   §6.2 (every criterion must match; a resource link matches a criterion its endpoint
//!   matches, an endpoint one that any of its resource links matches) and `page`/`count`.
//! - [`Directory::expire`] drops registrations whose lifetime ended; lookups never show
//!   them even before that.
//!
//! Bounds: the number of registrations and the bytes they take, in total and per client
//! (an IPv4 address, or an IPv6 /64: one host picks addresses from its /64 at will)
//! ([`Limits`]); a registration's document has a maximum size; a lifetime is at most
//! [`MAX_LIFETIME_S`]. Operations on a registration are accepted only from the IP
//! address that made it (the service first makes the sender prove that address with a
//! fresh Echo value, `freshness`); an update never moves the base of a registration made
//! without one. A location is `/rd/<random 64-bit number>`, not guessable from others.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::fmt::Write as _;
use std::hash::{BuildHasher, RandomState};
use std::net::{IpAddr, Ipv6Addr, SocketAddr};

use coap::Code;
use coap::link_format::{self, Filter, Link};
use serde::{Deserialize, Serialize};

/// RFC 9176 §5.3: the lifetime of a registration that gives none, in seconds (25 h).
pub const DEFAULT_LIFETIME_S: u32 = 90_000;

/// The longest lifetime kept, in seconds (25 h, the default): a longer `lt` is taken as
/// this. A registrant renews well before it (at three quarters of its own lifetime, when
/// that is up to 33 h), and nothing registered stays for years.
pub const MAX_LIFETIME_S: u32 = DEFAULT_LIFETIME_S;

/// RFC 9176 §5.3: the most bytes of an endpoint name or a sector name.
pub const MAX_NAME_BYTES: usize = 63;

/// The resource type of an endpoint link in endpoint lookup (RFC 9176 §6.3).
pub const RT_ENDPOINT: &str = "core.rd-ep";

/// What the directory accepts, in total and from one client ([`client_of`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Registrations held at once.
    pub max_registrations: usize,
    /// Bytes the registrations take together (as [`Registration::cost`] counts them).
    pub max_bytes: usize,
    /// Registrations one client may hold.
    pub per_peer: usize,
    /// Bytes one client's registrations may take.
    pub per_peer_bytes: usize,
    /// The largest link-format document of one registration.
    pub max_document: usize,
}

impl Default for Limits {
    /// 20,000 registrations in 128 MiB; 64 registrations and 1 MiB per client; a
    /// document of at most 32 KiB (a station with eight cameras registers about 6 KiB).
    fn default() -> Self {
        Self {
            max_registrations: 20_000,
            max_bytes: 128 << 20,
            per_peer: 64,
            per_peer_bytes: 1 << 20,
            max_document: 32 << 10,
        }
    }
}

/// Why a request to the directory was refused; [`RdError::code`] is its CoAP answer.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum RdError {
    /// A parameter is missing, repeated or malformed, or the document does not parse.
    #[error("{0}")]
    BadRequest(String),
    /// The request came from another address than the registration's.
    #[error("this registration was made from another address")]
    NotOwner,
    /// No registration at that location.
    #[error("no such registration")]
    NotFound,
    /// The document is larger than [`Limits::max_document`].
    #[error("the link-format document has {0} bytes; the most one registration may have is {1}")]
    DocumentTooLarge(usize, usize),
    /// The client (its IPv4 address or IPv6 /64) holds as many registrations or bytes
    /// as it may.
    #[error(
        "this client (an IPv4 address, an IPv6 /64) holds {held} registrations ({bytes} bytes); the most one may hold is {max} ({max_bytes} bytes)"
    )]
    PeerLimit {
        /// Registrations it holds.
        held: usize,
        /// Their bytes.
        bytes: usize,
        /// [`Limits::per_peer`].
        max: usize,
        /// [`Limits::per_peer_bytes`].
        max_bytes: usize,
    },
    /// The directory holds as many registrations or bytes as it may.
    #[error("the directory is full ({0} registrations)")]
    Full(usize),
    /// An update gave a base to a registration made without one (its base is the
    /// address that registered).
    #[error(
        "this registration was made without a base; an update cannot give it one (register again)"
    )]
    BaseFixed,
}

impl RdError {
    /// The response code that says it (one mapping, in one place).
    #[must_use]
    pub fn code(&self) -> Code {
        match self {
            Self::BadRequest(_) => Code::BAD_REQUEST,
            Self::NotOwner | Self::PeerLimit { .. } | Self::BaseFixed => Code::FORBIDDEN,
            Self::NotFound => Code::NOT_FOUND,
            Self::DocumentTooLarge(..) => Code::REQUEST_ENTITY_TOO_LARGE,
            Self::Full(_) => Code::SERVICE_UNAVAILABLE,
        }
    }
}

fn bad(text: impl Into<String>) -> RdError {
    RdError::BadRequest(text.into())
}

/// One registration as it is kept and persisted.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Record {
    /// Its number: the location is `/rd/<id>`.
    pub id: u64,
    /// The endpoint name (`ep`).
    pub ep: String,
    /// The sector (`d`), if given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub d: Option<String>,
    /// The base URI (given, or made from the source address).
    pub base: String,
    /// Whether `base` was given (else it stays the address that registered).
    pub base_given: bool,
    /// The lifetime in seconds.
    pub lt: u32,
    /// When it expires, milliseconds since the UNIX epoch.
    pub expires_ms: u64,
    /// The other endpoint attributes (`et` and any extra), in the order given.
    pub attrs: Vec<(String, Option<String>)>,
    /// The links as registered, in link-format.
    pub links: String,
    /// The address it was made from: only it may update or remove it.
    pub peer: IpAddr,
    /// Made by simple registration (no location was given out).
    #[serde(default)]
    pub simple: bool,
}

/// A registration with what lookups need ready: its endpoint link and its links
/// resolved against the base.
#[derive(Debug, Clone)]
pub struct Registration {
    record: Record,
    ep_link: Link,
    resolved: Vec<Link>,
    /// The attribute names its links have, as a set of [`name_bit`]s: a criterion on a
    /// name whose bit is not set cannot match any of its links.
    link_attrs: u64,
    cost: usize,
    /// Its place in the order lookups list registrations in (0 until it is held).
    seq: u64,
    /// Changes when what lookups show of it changes (0 until it is held): a
    /// [`Listing`] made before renders it again only while this stays.
    version: u64,
    /// The bytes of its endpoint link's text, and of its resolved links' together
    /// (without commas): a listing of whole registrations is sized without rendering them.
    ep_text: usize,
    links_text: usize,
}

impl Registration {
    /// `links` are the record's, parsed (the record keeps their text, parsed again only
    /// when the base changes).
    fn new(record: Record, links: &[Link]) -> Self {
        let mut r = Self {
            record,
            ep_link: Link::default(),
            resolved: Vec::new(),
            link_attrs: 0,
            cost: 0,
            seq: 0,
            version: 0,
            ep_text: 0,
            links_text: 0,
        };
        r.refresh(links);
        r
    }

    /// Builds the endpoint link and the resolved links and counts the bytes.
    fn refresh(&mut self, links: &[Link]) {
        let r = &self.record;
        let mut ep = Link::new(format!("/rd/{}", r.id)).with_attr("ep", r.ep.clone());
        if let Some(d) = &r.d {
            ep = ep.with_attr("d", d.clone());
        }
        ep = ep.with_attr("base", r.base.clone());
        ep.attrs.extend(r.attrs.iter().cloned());
        self.ep_link = ep.with_rt(RT_ENDPOINT);
        self.resolved = links.iter().map(|l| resolve(&r.base, l)).collect();
        self.link_attrs = (self.resolved.iter())
            .flat_map(|l| l.attrs.iter())
            .fold(0, |bits, (n, _)| bits | name_bit(n));
        self.ep_text = self.ep_link.to_string().len();
        self.links_text = self.resolved.iter().map(|l| l.to_string().len()).sum();
        self.cost = cost_of(self);
    }

    /// Keeps `old`'s version when lookups show both the same (a renewal, say).
    fn keep_version_of(&mut self, old: &Self) {
        if self.ep_link == old.ep_link && self.resolved == old.resolved {
            self.version = old.version;
        }
    }

    /// The record (what is persisted).
    #[must_use]
    pub fn record(&self) -> &Record {
        &self.record
    }

    /// The bytes it is counted for: every allocation that holds it, as the allocator
    /// rounds them, and its share of the directory's indexes.
    #[must_use]
    pub fn cost(&self) -> usize {
        self.cost
    }
}

/// What the allocator takes for a block of `n` bytes: glibc's on 64-bit Linux puts an
/// 8-byte header before each, rounds up to 16 and gives at least 32.
fn heap(n: usize) -> usize {
    if n == 0 {
        0
    } else {
        ((n + 8 + 15) & !15).max(32)
    }
}

fn heap_of_string(s: &String) -> usize {
    heap(s.capacity())
}

/// The attribute pairs of a link or record and their strings.
fn heap_of_attrs(attrs: &Vec<(String, Option<String>)>) -> usize {
    heap(attrs.capacity() * size_of::<(String, Option<String>)>())
        + (attrs.iter())
            .map(|(n, v)| heap_of_string(n) + v.as_ref().map_or(0, heap_of_string))
            .sum::<usize>()
}

/// A link's strings and attributes (not the link itself, which its vector holds).
fn heap_of_link(l: &Link) -> usize {
    heap_of_string(&l.target) + heap_of_attrs(&l.attrs)
}

/// An index entry's share of its table: a hash table's buckets are a power of two at
/// most 7/8 full, so an entry takes up to twice its size (and a control byte); a
/// B-tree's nodes are at least half full, so an entry takes up to twice its size too.
fn entry(size: usize) -> usize {
    2 * size + 1
}

/// What a registration is counted for: every allocation it and the directory's indexes
/// hold for it, with the allocator's rounding ([`heap`]), and its entries in the
/// location, order, expiry, name and `ep` indexes.
fn cost_of(reg: &Registration) -> usize {
    let r = &reg.record;
    let record = heap_of_string(&r.ep)
        + r.d.as_ref().map_or(0, heap_of_string)
        + heap_of_string(&r.base)
        + heap_of_attrs(&r.attrs)
        + heap_of_string(&r.links);
    let links = heap_of_link(&reg.ep_link)
        + heap(reg.resolved.capacity() * size_of::<Link>())
        + reg.resolved.iter().map(heap_of_link).sum::<usize>();
    // The name index holds a copy of (d, ep), the `ep` index one of ep and a vector.
    let name_copies = 2 * heap_of_string(&r.ep) + r.d.as_ref().map_or(0, heap_of_string);
    let indexes = entry(size_of::<u64>() + size_of::<Registration>())
        + 2 * entry(2 * size_of::<u64>())
        + entry(size_of::<(Option<String>, String)>() + size_of::<u64>())
        + entry(size_of::<String>() + size_of::<Vec<u64>>())
        + heap(size_of::<u64>())
        + name_copies;
    record + links + indexes
}

/// An attribute name's bit in a registration's set of link attribute names: one of 64
/// by a hash of the name in lower case (FNV-1a).
fn name_bit(name: &str) -> u64 {
    let hash = name.bytes().fold(0xcbf2_9ce4_8422_2325_u64, |h, b| {
        (h ^ u64::from(b.to_ascii_lowercase())).wrapping_mul(0x0100_0000_01b3)
    });
    1 << (hash % 64)
}

/// Whether `target` is a URI (has a scheme) rather than a relative reference.
fn has_scheme(target: &str) -> bool {
    let Some((scheme, _)) = target.split_once(':') else {
        return false;
    };
    let mut bytes = scheme.bytes();
    bytes.next().is_some_and(|b| b.is_ascii_alphabetic())
        && bytes.all(|b| b.is_ascii_alphanumeric() || b"+-.".contains(&b))
}

/// `reference` resolved against a base of the form `scheme://authority` (RFC 3986 §5.2
/// for a base without path, which RFC 9176 §5.3 asks of a base).
fn resolve_ref(base: &str, reference: &str) -> String {
    if has_scheme(reference) {
        reference.to_owned()
    } else if reference.starts_with("//") {
        let scheme = base.split_once(':').map_or("coap", |(s, _)| s);
        format!("{scheme}:{reference}")
    } else if reference.starts_with('/') {
        format!("{base}{reference}")
    } else if reference.is_empty() {
        format!("{base}/")
    } else {
        format!("{base}/{reference}")
    }
}

/// A registered link as resource lookup shows it (RFC 9176 §6.1): target and anchor
/// resolved, the base as the anchor of a link without one.
fn resolve(base: &str, link: &Link) -> Link {
    let mut out = Link::new(resolve_ref(base, &link.target));
    let mut anchored = false;
    for (name, value) in &link.attrs {
        if name.eq_ignore_ascii_case("anchor") {
            anchored = true;
            let value = value.as_deref().map(|v| resolve_ref(base, v));
            out.attrs.push((name.clone(), value));
        } else {
            out.attrs.push((name.clone(), value.clone()));
        }
    }
    if !anchored {
        out.attrs.push(("anchor".to_owned(), Some(base.to_owned())));
    }
    out
}

/// `coap://ADDR[:PORT]` of a source address (RFC 9176 §5.3: scheme, address literal,
/// the port unless the default).
#[must_use]
pub fn base_of(peer: SocketAddr) -> String {
    let host = match peer.ip() {
        IpAddr::V4(ip) => ip.to_string(),
        IpAddr::V6(ip) => match ip.to_ipv4_mapped() {
            Some(v4) => v4.to_string(),
            None => format!("[{ip}]"),
        },
    };
    if peer.port() == coap::group::DEFAULT_PORT {
        format!("coap://{host}")
    } else {
        format!("coap://{host}:{}", peer.port())
    }
}

/// The client an address belongs to, as the per-client limits count: an IPv4 address
/// (also written IPv4-mapped), or the /64 of an IPv6 address.
#[must_use]
pub fn client_of(ip: IpAddr) -> IpAddr {
    match ip.to_canonical() {
        IpAddr::V4(v4) => IpAddr::V4(v4),
        IpAddr::V6(v6) => IpAddr::V6(Ipv6Addr::from(u128::from(v6) & !u128::from(u64::MAX))),
    }
}

/// A name of RFC 9176 §5.3: at most 63 bytes, no control characters.
fn check_name(what: &str, value: &str) -> Result<(), RdError> {
    if value.is_empty() {
        return Err(bad(format!("{what} is empty")));
    }
    if value.len() > MAX_NAME_BYTES {
        return Err(bad(format!(
            "{what} has {} bytes; at most {MAX_NAME_BYTES}",
            value.len()
        )));
    }
    if value
        .chars()
        .any(|c| matches!(u32::from(c), 0..=31 | 127..=159))
    {
        return Err(bad(format!("{what} contains a control character")));
    }
    Ok(())
}

/// A base URI as RFC 9176 §5.3 wants it: a scheme and an authority, no query or
/// fragment, no path (relative links could not be resolved with one).
fn check_base(base: &str) -> Result<(), RdError> {
    let Some((scheme, rest)) = base.split_once("://") else {
        return Err(bad(format!("base {base:?} is not scheme://authority")));
    };
    if !has_scheme(&format!("{scheme}:")) || rest.is_empty() {
        return Err(bad(format!("base {base:?} is not scheme://authority")));
    }
    if rest.contains(['/', '?', '#']) {
        return Err(bad(format!(
            "base {base:?} has a path, query or fragment; give scheme://authority"
        )));
    }
    if rest.contains('%') && rest.starts_with('[') {
        return Err(bad(format!("base {base:?} has a zone identifier")));
    }
    Ok(())
}

/// The registration parameters of a request's query (RFC 9176 §5.3).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Params {
    /// `ep`.
    pub ep: Option<String>,
    /// `d`.
    pub d: Option<String>,
    /// `lt`.
    pub lt: Option<u32>,
    /// `base`.
    pub base: Option<String>,
    /// Every other parameter, in order (`et` among them).
    pub extra: Vec<(String, Option<String>)>,
}

impl Params {
    /// Reads the Uri-Query items of a registration or an update.
    ///
    /// # Errors
    ///
    /// [`RdError::BadRequest`] for a repeated `ep`, `d`, `lt` or `base`, a bad lifetime,
    /// name or base, or a parameter without a name.
    pub fn parse<'a>(items: impl IntoIterator<Item = &'a str>) -> Result<Self, RdError> {
        let mut p = Self::default();
        for item in items {
            let (name, value) = match item.split_once('=') {
                Some((n, v)) => (n, Some(v)),
                None => (item, None),
            };
            if name.is_empty() {
                return Err(bad(format!("query parameter {item:?} has no name")));
            }
            let once = |slot: &Option<String>| {
                if slot.is_some() {
                    Err(bad(format!("{name} is given twice")))
                } else {
                    Ok(())
                }
            };
            let value_of = || {
                value
                    .map(str::to_owned)
                    .ok_or_else(|| bad(format!("{name} needs a value")))
            };
            match name {
                "ep" => {
                    once(&p.ep)?;
                    let v = value_of()?;
                    check_name("ep", &v)?;
                    p.ep = Some(v);
                }
                "d" => {
                    once(&p.d)?;
                    let v = value_of()?;
                    check_name("d", &v)?;
                    p.d = Some(v);
                }
                "base" => {
                    once(&p.base)?;
                    let v = value_of()?;
                    check_base(&v)?;
                    p.base = Some(v);
                }
                "lt" => {
                    if p.lt.is_some() {
                        return Err(bad("lt is given twice"));
                    }
                    let v = value_of()?;
                    let lt = v
                        .parse::<u32>()
                        .ok()
                        .filter(|lt| *lt >= 1)
                        .ok_or_else(|| bad(format!("lt {v:?} is not 1-4294967295 seconds")))?;
                    p.lt = Some(lt);
                }
                _ => {
                    if !name
                        .bytes()
                        .all(|b| b.is_ascii_alphanumeric() || b"!#$&+-.^_`|~".contains(&b))
                    {
                        return Err(bad(format!("{name:?} is not a link attribute name")));
                    }
                    p.extra.push((name.to_owned(), value.map(str::to_owned)));
                }
            }
        }
        Ok(p)
    }
}

/// Which lookup interface (RFC 9176 §6).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LookupKind {
    /// Endpoint lookup: one link per registration (`core.rd-lookup-ep`).
    Endpoints,
    /// Resource lookup: the registered links, resolved (`core.rd-lookup-res`).
    Resources,
}

/// A lookup's criteria and page.
#[derive(Debug, Clone, Default)]
pub struct Query {
    terms: Vec<Term>,
    page: usize,
    count: Option<usize>,
}

/// One criterion: its filter, and what the indexes need to know of it.
#[derive(Debug, Clone)]
struct Term {
    filter: Filter,
    /// The attribute's name, lower case; empty when it was percent-encoded (then no
    /// index is used for it).
    name: String,
    /// The value when it is matched exactly and was not percent-encoded.
    exact: Option<String>,
    /// The bytes of the criterion as given.
    given: usize,
}

impl Term {
    fn parse(item: &str) -> Result<Self, RdError> {
        let filter = Filter::parse(item).map_err(|e| bad(e.to_string()))?;
        let (name, value) = item.split_once('=').unwrap_or((item, ""));
        let plain = |t: &str| !t.contains('%');
        Ok(Self {
            filter,
            name: if plain(name) {
                name.to_ascii_lowercase()
            } else {
                String::new()
            },
            exact: (plain(value) && !value.ends_with('*') && item.contains('='))
                .then(|| value.to_owned()),
            given: item.len(),
        })
    }

    /// What its strings hold, and its filter's (a name and a value, at most
    /// the criterion's bytes each, in a vector of one).
    fn held(&self) -> usize {
        heap_of_string(&self.name)
            + self.exact.as_ref().map_or(0, heap_of_string)
            + heap(64)
            + 2 * heap(self.given)
    }

    /// Whether it can match any of `reg`'s links: only if one of them has the attribute
    /// (or it is `href`).
    fn may_match_links(&self, reg: &Registration) -> bool {
        self.name.is_empty() || self.name == "href" || reg.link_attrs & name_bit(&self.name) != 0
    }
}

impl Query {
    /// Reads the Uri-Query items of a lookup: `page`, `count` and the criteria (each
    /// matched as RFC 6690 §4.1 says, `*` at the end a prefix).
    ///
    /// # Errors
    ///
    /// [`RdError::BadRequest`] for `page` without `count`, a number that is not one, or a
    /// criterion that is not a valid filter.
    pub fn parse<'a>(items: impl IntoIterator<Item = &'a str>) -> Result<Self, RdError> {
        let mut q = Self::default();
        let mut page = None;
        for item in items {
            let number = |v: &str, what: &str| {
                v.parse::<usize>()
                    .map_err(|_| bad(format!("{what} {v:?} is not a whole number")))
            };
            if let Some(v) = item.strip_prefix("page=") {
                page = Some(number(v, "page")?);
            } else if let Some(v) = item.strip_prefix("count=") {
                q.count = Some(number(v, "count")?);
            } else if !item.is_empty() {
                q.terms.push(Term::parse(item)?);
            }
        }
        if let Some(page) = page {
            if q.count.is_none() {
                return Err(bad("page needs count (RFC 9176 §6.2)"));
            }
            q.page = page;
        }
        Ok(q)
    }
}

/// A lookup's answer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Found {
    /// The links of the page, as a link-format document.
    pub document: String,
    /// How many links it holds.
    pub links: usize,
}

/// The directory: registrations by location, by (sector, name), by expiry and by client.
#[derive(Debug, Default)]
pub struct Directory {
    limits: Limits,
    regs: BTreeMap<u64, Registration>,
    names: HashMap<(Option<String>, String), u64>,
    /// Registrations by endpoint name (in every sector), for `ep=NAME` lookups.
    by_ep: HashMap<String, Vec<u64>>,
    /// How many registrations have links with an `ep` attribute themselves (then an
    /// `ep=NAME` lookup must look at every registration).
    ep_in_links: usize,
    expiry: BTreeSet<(u64, u64)>,
    /// Registrations and bytes by client ([`client_of`]).
    peers: HashMap<IpAddr, (usize, usize)>,
    bytes: usize,
    /// Locations are a keyed hash (SipHash, the key from the OS) of a counter.
    ids: RandomState,
    counter: u64,
    /// Registrations in the order they were made (a registration made again keeps its
    /// place), so pages stay in place as others come and go.
    order: BTreeMap<u64, u64>,
    next_seq: u64,
    next_version: u64,
}

/// What a registration did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Registered {
    /// The registration's number (location `/rd/<id>`), random.
    pub id: u64,
    /// A new registration (else the one of the same `ep` and `d` was replaced).
    pub created: bool,
}

impl Directory {
    /// An empty directory with these limits.
    #[must_use]
    pub fn new(limits: Limits) -> Self {
        Self {
            limits,
            ..Self::default()
        }
    }

    /// A number for a new registration: unpredictable, not 0, not one held.
    fn new_id(&mut self) -> u64 {
        loop {
            self.counter += 1;
            let id = self.ids.hash_one(self.counter);
            if id != 0 && !self.regs.contains_key(&id) {
                return id;
            }
        }
    }

    /// Registrations held (expired ones included until [`Directory::expire`]).
    #[must_use]
    pub fn len(&self) -> usize {
        self.regs.len()
    }

    /// Whether it holds none.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.regs.is_empty()
    }

    /// The bytes its registrations are counted for.
    #[must_use]
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// The registration at `/rd/<id>`.
    #[must_use]
    pub fn get(&self, id: u64) -> Option<&Registration> {
        self.regs.get(&id)
    }

    /// The registration of `ep` in sector `d`.
    #[must_use]
    pub fn find(&self, d: Option<&str>, ep: &str) -> Option<&Registration> {
        let id = self.names.get(&(d.map(str::to_owned), ep.to_owned()))?;
        self.regs.get(id)
    }

    /// The earliest time a registration expires, to set the next sweep.
    #[must_use]
    pub fn next_expiry(&self) -> Option<u64> {
        self.expiry.first().map(|(at, _)| *at)
    }

    /// Registration (RFC 9176 §5.3) of `document` (link-format) by `peer`.
    ///
    /// # Errors
    ///
    /// [`RdError`]: no `ep`, a bad parameter or document, another address's registration
    /// of the same name, or a limit.
    pub fn register(
        &mut self,
        now_ms: u64,
        peer: SocketAddr,
        params: Params,
        document: &str,
    ) -> Result<Registered, RdError> {
        self.insert(now_ms, peer, params, document, false)
    }

    /// Simple registration (RFC 9176 §5.1): `document` is what the endpoint's
    /// `/.well-known/core` answered; the base is its address.
    ///
    /// # Errors
    ///
    /// As [`Directory::register`], and [`RdError::BadRequest`] when `base` is given.
    pub fn register_simple(
        &mut self,
        now_ms: u64,
        peer: SocketAddr,
        params: Params,
        document: &str,
    ) -> Result<Registered, RdError> {
        if params.base.is_some() {
            return Err(bad("simple registration takes no base (RFC 9176 §5.1)"));
        }
        self.insert(now_ms, peer, params, document, true)
    }

    fn insert(
        &mut self,
        now_ms: u64,
        peer: SocketAddr,
        params: Params,
        document: &str,
        simple: bool,
    ) -> Result<Registered, RdError> {
        let Some(ep) = params.ep else {
            return Err(bad("ep (the endpoint name) is missing"));
        };
        if document.len() > self.limits.max_document {
            return Err(RdError::DocumentTooLarge(
                document.len(),
                self.limits.max_document,
            ));
        }
        let links = link_format::parse(document).map_err(|e| bad(e.to_string()))?;
        let key = (params.d.clone(), ep.clone());
        let existing = self.names.get(&key).copied();
        if let Some(id) = existing
            && let Some(old) = self.regs.get(&id)
            && old.record.peer != peer.ip()
            && old.record.expires_ms > now_ms
        {
            return Err(RdError::NotOwner);
        }
        let lt = params.lt.unwrap_or(DEFAULT_LIFETIME_S).min(MAX_LIFETIME_S);
        let base_given = params.base.is_some();
        let record = Record {
            id: match existing {
                Some(id) => id,
                None => self.new_id(),
            },
            ep,
            d: params.d,
            base: params.base.unwrap_or_else(|| base_of(peer)),
            base_given,
            lt,
            expires_ms: now_ms.saturating_add(u64::from(lt) * 1000),
            attrs: params.extra,
            links: document.to_owned(),
            peer: peer.ip(),
            simple,
        };
        let mut reg = Registration::new(record, &links);
        let client = client_of(peer.ip());
        let freed = existing.and_then(|id| self.regs.get(&id)).map(|old| {
            let same_client = client_of(old.record.peer) == client;
            (old.cost, same_client)
        });
        let (held, held_bytes) = self.peers.get(&client).copied().unwrap_or_default();
        let (held, held_bytes) = match freed {
            Some((cost, true)) => (held - 1, held_bytes - cost),
            _ => (held, held_bytes),
        };
        if held + 1 > self.limits.per_peer || held_bytes + reg.cost > self.limits.per_peer_bytes {
            return Err(RdError::PeerLimit {
                held,
                bytes: held_bytes,
                max: self.limits.per_peer,
                max_bytes: self.limits.per_peer_bytes,
            });
        }
        let total = self.bytes - freed.map_or(0, |(c, _)| c);
        let count = self.regs.len() - usize::from(freed.is_some());
        if count + 1 > self.limits.max_registrations || total + reg.cost > self.limits.max_bytes {
            return Err(RdError::Full(self.regs.len()));
        }
        if let Some(old) = existing.and_then(|id| self.take(id)) {
            reg.seq = old.seq;
            reg.keep_version_of(&old);
        }
        let id = reg.record.id;
        self.put(reg);
        Ok(Registered {
            id,
            created: existing.is_none(),
        })
    }

    /// Adds a registration to every index.
    fn put(&mut self, mut reg: Registration) {
        if reg.seq == 0 {
            self.next_seq += 1;
            reg.seq = self.next_seq;
        }
        if reg.version == 0 {
            self.next_version += 1;
            reg.version = self.next_version;
        }
        self.order.insert(reg.seq, reg.record.id);
        let r = &reg.record;
        self.names.insert((r.d.clone(), r.ep.clone()), r.id);
        let ids = self.by_ep.entry(r.ep.clone()).or_default();
        if let Err(at) = ids.binary_search(&r.id) {
            ids.insert(at, r.id);
        }
        self.ep_in_links += usize::from(reg.link_attrs & name_bit("ep") != 0);
        self.expiry.insert((r.expires_ms, r.id));
        let held = self.peers.entry(client_of(r.peer)).or_default();
        held.0 += 1;
        held.1 += reg.cost;
        self.bytes += reg.cost;
        self.regs.insert(r.id, reg);
    }

    /// Removes a registration from every index.
    fn take(&mut self, id: u64) -> Option<Registration> {
        let reg = self.regs.remove(&id)?;
        self.order.remove(&reg.seq);
        let r = &reg.record;
        self.names.remove(&(r.d.clone(), r.ep.clone()));
        if let Some(ids) = self.by_ep.get_mut(&r.ep) {
            ids.retain(|id| *id != r.id);
            if ids.is_empty() {
                self.by_ep.remove(&r.ep);
            }
        }
        self.ep_in_links -= usize::from(reg.link_attrs & name_bit("ep") != 0);
        self.expiry.remove(&(r.expires_ms, r.id));
        let client = client_of(r.peer);
        if let Some(held) = self.peers.get_mut(&client) {
            held.0 -= 1;
            held.1 -= reg.cost;
            if held.0 == 0 {
                self.peers.remove(&client);
            }
        }
        self.bytes -= reg.cost;
        Some(reg)
    }

    /// Registration update (RFC 9176 §5.3.1): a new lifetime (or the last one again),
    /// base or endpoint attributes. The base of a registration made without one stays
    /// the address that registered: neither an update from another port nor a `base`
    /// moves it.
    ///
    /// # Errors
    ///
    /// [`RdError::NotFound`], [`RdError::NotOwner`], [`RdError::BaseFixed`], or a
    /// parameter that may not be updated (`ep`, `d`) or is malformed, or a limit.
    pub fn update(
        &mut self,
        now_ms: u64,
        peer: SocketAddr,
        id: u64,
        params: Params,
    ) -> Result<(), RdError> {
        // A registration whose lifetime ended is gone, swept or not: a late update (a
        // retransmission from a registrant that has since died) does not bring it back.
        let reg = (self.regs.get(&id))
            .filter(|r| r.record.expires_ms > now_ms)
            .ok_or(RdError::NotFound)?;
        if reg.record.peer != peer.ip() {
            return Err(RdError::NotOwner);
        }
        if params.ep.is_some() || params.d.is_some() {
            return Err(bad(
                "ep and d cannot be changed by an update; register again",
            ));
        }
        if params.base.is_some() && !reg.record.base_given {
            return Err(RdError::BaseFixed);
        }
        let mut record = reg.record.clone();
        // Stored only once it parsed.
        let links = link_format::parse(&record.links).unwrap_or_default();
        if let Some(lt) = params.lt {
            record.lt = lt.min(MAX_LIFETIME_S);
        }
        record.expires_ms = now_ms.saturating_add(u64::from(record.lt) * 1000);
        if let Some(base) = params.base {
            record.base = base;
        }
        for (name, value) in params.extra {
            match record.attrs.iter_mut().find(|(n, _)| *n == name) {
                Some(slot) => slot.1 = value,
                None => record.attrs.push((name, value)),
            }
        }
        let mut new = Registration::new(record, &links);
        new.seq = reg.seq;
        new.keep_version_of(reg);
        let (_, held_bytes) = (self.peers.get(&client_of(peer.ip())))
            .copied()
            .unwrap_or_default();
        let old_cost = reg.cost;
        if held_bytes - old_cost + new.cost > self.limits.per_peer_bytes
            || self.bytes - old_cost + new.cost > self.limits.max_bytes
        {
            return Err(RdError::PeerLimit {
                held: 0,
                bytes: held_bytes,
                max: self.limits.per_peer,
                max_bytes: self.limits.per_peer_bytes,
            });
        }
        self.take(id);
        self.put(new);
        Ok(())
    }

    /// Registration removal (RFC 9176 §5.3.2).
    ///
    /// # Errors
    ///
    /// [`RdError::NotFound`] or [`RdError::NotOwner`].
    pub fn remove(&mut self, peer: SocketAddr, id: u64) -> Result<(), RdError> {
        let reg = self.regs.get(&id).ok_or(RdError::NotFound)?;
        if reg.record.peer != peer.ip() {
            return Err(RdError::NotOwner);
        }
        self.take(id);
        Ok(())
    }

    /// Drops every registration whose lifetime has ended; returns their numbers.
    pub fn expire(&mut self, now_ms: u64) -> Vec<u64> {
        let mut gone = Vec::new();
        while let Some(&(at, id)) = self.expiry.first() {
            if at > now_ms {
                break;
            }
            self.take(id);
            gone.push(id);
        }
        gone
    }

    /// Puts back registrations read from storage (those already expired are left out,
    /// and none lives longer than [`MAX_LIFETIME_S`] from `now_ms`: a record written
    /// before the cap keeps no longer); returns how many were put back.
    pub fn restore(&mut self, now_ms: u64, records: impl IntoIterator<Item = Record>) -> usize {
        let mut n = 0;
        for mut record in records {
            if record.expires_ms <= now_ms || self.regs.contains_key(&record.id) {
                continue;
            }
            record.lt = record.lt.min(MAX_LIFETIME_S);
            record.expires_ms =
                (record.expires_ms).min(now_ms.saturating_add(u64::from(MAX_LIFETIME_S) * 1000));
            let Ok(links) = link_format::parse(&record.links) else {
                continue;
            };
            self.put(Registration::new(record, &links));
            n += 1;
        }
        n
    }

    /// Endpoint or resource lookup (RFC 9176 §6): the links that meet every criterion,
    /// the page of them `page` and `count` ask for.
    #[must_use]
    pub fn lookup(&self, now_ms: u64, kind: LookupKind, query: &Query) -> Found {
        let mut document = String::new();
        let mut links = 0;
        for (i, part) in self.select(now_ms, kind, query).iter().enumerate() {
            if let Some(reg) = self.regs.get(&part.id) {
                links += render(reg, kind, query, part, i == 0, &mut document);
            }
        }
        Found { document, links }
    }

    /// The same lookup as [`Directory::lookup`], kept as the registrations it lists
    /// rather than their text: a large answer goes out block by block
    /// ([`Directory::read`]), and the whole of it is never held.
    #[must_use]
    pub fn listing(&self, now_ms: u64, kind: LookupKind, query: &Query) -> Listing {
        let mut parts = self.select(now_ms, kind, query);
        let (mut len, mut links) = (0, 0);
        let mut text = String::new();
        for (i, part) in parts.iter_mut().enumerate() {
            if let Some(reg) = self.regs.get(&part.id) {
                let take = part.take as usize;
                // A comma before every link but the document's first.
                let commas = take - usize::from(i == 0);
                let whole = match kind {
                    LookupKind::Endpoints => Some(reg.ep_text),
                    LookupKind::Resources => (take == reg.resolved.len()).then_some(reg.links_text),
                };
                len += match whole {
                    Some(bytes) => bytes + commas,
                    None => {
                        text.clear();
                        render(reg, kind, query, part, i == 0, &mut text);
                        text.len()
                    }
                };
                links += take;
            }
            part.end = len;
        }
        parts.shrink_to_fit();
        Listing {
            kind,
            query: query.clone(),
            parts,
            len,
            links,
        }
    }

    /// Bytes `range` of `listing`'s document, rendered from the registrations it lists;
    /// `None` when one of them has since changed what lookups show of it or is gone (the
    /// document can no longer be read as it was).
    #[must_use]
    pub fn read(&self, listing: &Listing, range: std::ops::Range<usize>) -> Option<Vec<u8>> {
        let first = listing.parts.partition_point(|p| p.end <= range.start);
        // Where the text rendered from part `first` on begins in the document.
        let base = first
            .checked_sub(1)
            .map_or(0, |before| listing.parts[before].end);
        let mut start = base;
        let mut text = String::new();
        for (i, part) in listing.parts.iter().enumerate().skip(first) {
            if start >= range.end {
                break;
            }
            let reg = self
                .regs
                .get(&part.id)
                .filter(|r| r.version == part.version)?;
            let from = text.len();
            render(reg, listing.kind, &listing.query, part, i == 0, &mut text);
            if text.len() - from != part.end - start {
                return None;
            }
            start = part.end;
        }
        let skip = range.start - base;
        (text.as_bytes())
            .get(skip..skip + range.len())
            .map(<[u8]>::to_vec)
    }

    /// The registrations a lookup lists, in order, each with the range of its links
    /// shown (of those that meet the criteria).
    fn select(&self, now_ms: u64, kind: LookupKind, query: &Query) -> Vec<Part> {
        let mut skip = query.page.saturating_mul(query.count.unwrap_or(0));
        let mut left = query.count.unwrap_or(usize::MAX);
        let mut parts = Vec::new();
        // `ep=NAME` (exactly) looks at that name's registrations only, unless some
        // registration's links carry `ep` themselves.
        let by_name = query
            .terms
            .iter()
            .find(|t| t.name == "ep" && self.ep_in_links == 0)
            .and_then(|t| t.exact.as_ref())
            .map(|name| self.by_ep.get(name).map_or(&[][..], Vec::as_slice));
        let candidates: Box<dyn Iterator<Item = &Registration>> = match by_name {
            Some(ids) => Box::new(ids.iter().filter_map(|id| self.regs.get(id))),
            None => Box::new(self.order.values().filter_map(|id| self.regs.get(id))),
        };
        for reg in candidates {
            if left == 0 {
                break;
            }
            if reg.record.expires_ms <= now_ms {
                continue;
            }
            let matching = match kind {
                LookupKind::Endpoints => usize::from(endpoint_matches(reg, query)),
                LookupKind::Resources => resources_matching(reg, query).count(),
            };
            let shown = matching.saturating_sub(skip).min(left);
            if shown > 0 {
                parts.push(Part {
                    id: reg.record.id,
                    version: reg.version,
                    skip: u32::try_from(matching.min(skip)).unwrap_or(u32::MAX),
                    take: u32::try_from(shown).unwrap_or(u32::MAX),
                    end: 0,
                });
            }
            skip = skip.saturating_sub(matching);
            left -= shown;
        }
        parts
    }
}

/// Whether `reg` meets every criterion of an endpoint lookup: the endpoint itself, or
/// one of its links.
fn endpoint_matches(reg: &Registration, query: &Query) -> bool {
    query.terms.iter().all(|t| {
        t.filter.matches(&reg.ep_link)
            || (t.may_match_links(reg) && reg.resolved.iter().any(|l| t.filter.matches(l)))
    })
}

/// The links of `reg` a resource lookup lists: the criteria the endpoint meets hold for
/// every one of them.
fn resources_matching<'a>(
    reg: &'a Registration,
    query: &'a Query,
) -> Box<dyn Iterator<Item = &'a Link> + 'a> {
    let open: Vec<&Term> = (query.terms.iter())
        .filter(|t| !t.filter.matches(&reg.ep_link))
        .collect();
    if !open.iter().all(|t| t.may_match_links(reg)) {
        return Box::new(std::iter::empty());
    }
    Box::new((reg.resolved.iter()).filter(move |l| open.iter().all(|t| t.filter.matches(l))))
}

/// Appends `part` of a lookup's document to `out` (a comma first unless it is the
/// document's `first`); returns how many links it wrote.
fn render(
    reg: &Registration,
    kind: LookupKind,
    query: &Query,
    part: &Part,
    first: bool,
    out: &mut String,
) -> usize {
    let links: Box<dyn Iterator<Item = &Link>> = match kind {
        LookupKind::Endpoints => Box::new(std::iter::once(&reg.ep_link)),
        LookupKind::Resources => resources_matching(reg, query),
    };
    let mut n = 0;
    for link in links.skip(part.skip as usize).take(part.take as usize) {
        if n > 0 || !first {
            out.push(',');
        }
        let _ = write!(out, "{link}");
        n += 1;
    }
    n
}

/// One registration in a [`Listing`].
#[derive(Debug, Clone)]
struct Part {
    id: u64,
    /// Its [`Registration::version`] when listed.
    version: u64,
    /// Of its links that meet the criteria, those skipped (the page starts in it) and
    /// those shown.
    skip: u32,
    take: u32,
    /// Where its text ends in the document.
    end: usize,
}

/// A lookup's answer as the registrations it lists ([`Directory::listing`]).
#[derive(Debug, Clone)]
pub struct Listing {
    kind: LookupKind,
    query: Query,
    parts: Vec<Part>,
    len: usize,
    links: usize,
}

impl Listing {
    /// The bytes of its document.
    #[must_use]
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether its document is empty (no link met the criteria).
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The links it lists.
    #[must_use]
    pub fn links(&self) -> usize {
        self.links
    }

    /// The bytes it holds: itself, an entry per registration, and its criteria.
    #[must_use]
    pub fn held(&self) -> usize {
        size_of::<Self>()
            + heap(self.parts.capacity() * size_of::<Part>())
            + heap(self.query.terms.capacity() * size_of::<Term>())
            + self.query.terms.iter().map(Term::held).sum::<usize>()
    }
}

#[cfg(test)]
mod tests;
