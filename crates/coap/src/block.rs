//! Server-side block-wise state (RFC 7959): Block1 bodies being assembled, and Block2
//! representations stored so that later blocks are served without asking the application
//! again. Both are bounded in bytes and expire by the caller's `now`.

use std::collections::BTreeMap;
use std::fmt;
use std::net::SocketAddr;
use std::ops::Range;
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::Bytes;
use smallvec::SmallVec;

use crate::config::{EndpointConfig, Limits};
use crate::msg::{BlockHead, BlockOpt, Code, OptionNumber, Options};
use crate::peer_key::FastMap;

/// Identifies the request a block belongs to: the peer and the request's method and
/// options without the block options ([`Options::block_key`]).
#[derive(Debug, Clone)]
pub(crate) struct BlockKey {
    pub(crate) peer: SocketAddr,
    pub(crate) method: Code,
    /// The request's options as [`Options::block_key`] encodes them: a path of a few
    /// segments fits without an allocation.
    pub(crate) options: SmallVec<[u8; 64]>,
}

impl BlockKey {
    /// The bytes the key holds: itself, and its options when they spilled to the heap.
    pub(crate) fn held(&self) -> usize {
        size_of::<Self>()
            + if self.options.spilled() {
                self.options.capacity()
            } else {
                0
            }
    }

    /// The key under which a response to a request sent to a group is stored: the
    /// client's port without its address. The client asks for the other blocks by
    /// unicast (RFC 7959 §2.8), and the kernel may send those from another of its
    /// addresses than the group request (the source address is chosen per destination).
    pub(crate) fn for_group(&self) -> Self {
        let any = match self.peer {
            SocketAddr::V4(_) => std::net::IpAddr::from(std::net::Ipv4Addr::UNSPECIFIED),
            SocketAddr::V6(_) => std::net::IpAddr::from(std::net::Ipv6Addr::UNSPECIFIED),
        };
        Self {
            peer: SocketAddr::new(any, self.peer.port()),
            method: self.method,
            options: self.options.clone(),
        }
    }

    /// The address as integers, which order faster than `SocketAddr`'s field-by-field
    /// comparison; every part that tells two addresses apart is kept (family, address,
    /// port, flow label, scope).
    fn addr_bits(&self) -> (u128, u64, u64) {
        match self.peer {
            SocketAddr::V4(a) => (u128::from(a.ip().to_bits()), u64::from(a.port()), 0),
            SocketAddr::V6(a) => (
                a.ip().to_bits(),
                u64::from(a.port()) << 32 | u64::from(a.scope_id()),
                1 << 32 | u64::from(a.flowinfo()),
            ),
        }
    }
}

impl PartialEq for BlockKey {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other).is_eq()
    }
}

impl Eq for BlockKey {}

impl PartialOrd for BlockKey {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for BlockKey {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.addr_bits()
            .cmp(&other.addr_bits())
            .then(self.method.cmp(&other.method))
            .then_with(|| self.options.cmp(&other.options))
    }
}

/// What the server answers to one Block1 request.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Block1Outcome {
    /// More blocks expected: answer 2.31 Continue with this Block1 option.
    Continue(BlockOpt),
    /// The body is complete; the final Block1 option is echoed in the response.
    Complete(Bytes, BlockOpt),
    /// Refused with this code and diagnostic, plus Size1 for 4.13.
    Refuse {
        code: Code,
        diagnostic: &'static str,
        size1: Option<u32>,
    },
}

struct Assembly {
    body: Vec<u8>,
    last_used: Instant,
}

/// What an entry of a map keyed by [`BlockKey`] costs beyond its key and value: the
/// tree's node share and the allocator's headers, rounded up.
const ENTRY_OVERHEAD: usize = 64;

/// The bytes an assembly holds: its key, its body's allocation, the entry.
fn held(key: &BlockKey, a: &Assembly) -> usize {
    key.held() + ENTRY_OVERHEAD + a.body.capacity()
}

/// Block1 bodies in assembly, bounded per peer and in total.
pub(crate) struct Block1Assembler {
    assemblies: BTreeMap<BlockKey, Assembly>,
    /// The bytes held in all: keys, bodies' allocations, entries.
    total_bytes: usize,
    /// The body bytes per peer, kept as bodies grow and go (no scan per request).
    peer_bytes: FastMap<SocketAddr, usize>,
    /// When idle assemblies were last looked for.
    swept: Option<Instant>,
}

/// How often [`Block1Assembler::expire`] looks through every assembly: once a second at
/// most, not once per request (an assembly may outlive the lifetime by that much).
const SWEEP_EVERY: Duration = Duration::from_secs(1);

impl Block1Assembler {
    pub(crate) fn new() -> Self {
        Self {
            assemblies: BTreeMap::new(),
            total_bytes: 0,
            peer_bytes: FastMap::default(),
            swept: None,
        }
    }

    fn peer_bytes(&self, peer: SocketAddr) -> usize {
        self.peer_bytes.get(&peer).copied().unwrap_or(0)
    }

    /// Counts `body` more (`grew`) or fewer body bytes of `peer`, and `held` more or fewer
    /// bytes held in all.
    fn account(&mut self, peer: SocketAddr, body: usize, held: usize, grew: bool) {
        let bytes = self.peer_bytes.entry(peer).or_default();
        if grew {
            self.total_bytes += held;
            *bytes += body;
        } else {
            self.total_bytes -= held;
            *bytes -= body;
            if *bytes == 0 {
                self.peer_bytes.remove(&peer);
            }
        }
    }

    /// Drops assemblies idle for longer than the lifetime.
    pub(crate) fn expire(&mut self, now: Instant, limits: &Limits) {
        if self
            .swept
            .is_some_and(|at| now.saturating_duration_since(at) < SWEEP_EVERY)
        {
            return;
        }
        self.swept = Some(now);
        let mut gone = Vec::new();
        self.assemblies.retain(|k, a| {
            let keep = now.saturating_duration_since(a.last_used) < limits.blockwise_lifetime;
            if !keep {
                gone.push((k.peer, a.body.len(), held(k, a)));
            }
            keep
        });
        for (peer, body, held) in gone {
            self.account(peer, body, held, false);
        }
    }

    /// Drops every assembly idle for longer than the lifetime, now.
    pub(crate) fn expire_all(&mut self, now: Instant, limits: &Limits) {
        self.swept = None;
        self.expire(now, limits);
    }

    /// When the assembly idle longest was last used.
    pub(crate) fn oldest(&self) -> Option<Instant> {
        self.assemblies.values().map(|a| a.last_used).min()
    }

    /// Takes one Block1 request (RFC 7959 §2.3). `size1` is the request's Size1 option;
    /// `max_szx` the block size this server prefers.
    pub(crate) fn handle(
        &mut self,
        now: Instant,
        key: BlockKey,
        block: BlockOpt,
        size1: Option<u32>,
        payload: &[u8],
        config: &EndpointConfig,
    ) -> Block1Outcome {
        let (limits, max_szx) = (&config.limits, config.max_block_szx);
        self.expire(now, limits);
        let peer_limit = u32::try_from(limits.block1_peer_bytes).unwrap_or(u32::MAX);
        let too_large = Block1Outcome::Refuse {
            code: Code::REQUEST_ENTITY_TOO_LARGE,
            diagnostic: "request body exceeds this server's limit (see Size1)",
            size1: Some(peer_limit),
        };
        if block.more && payload.len() != block.size() {
            return Block1Outcome::Refuse {
                code: Code::BAD_REQUEST,
                diagnostic: "Block1 payload size does not match its SZX",
                size1: None,
            };
        }
        if block.num == 0 {
            self.drop_key(&key);
            if size1.is_some_and(|s| s > peer_limit) {
                return too_large;
            }
        }
        let offset = block.offset();
        let current = self.assemblies.get(&key).map_or(0, |a| a.body.len());
        if block.num > 0 && !self.assemblies.contains_key(&key) {
            return Block1Outcome::Refuse {
                code: Code::REQUEST_ENTITY_INCOMPLETE,
                diagnostic: "Block1 without the preceding blocks",
                size1: None,
            };
        }
        let reply_szx = block.szx.min(max_szx);
        if offset + payload.len() <= current && block.more {
            // A block we already have, sent again after our 2.31 was lost: idempotent.
            if let Some(a) = self.assemblies.get_mut(&key) {
                a.last_used = now;
            }
            return Block1Outcome::Continue(BlockOpt {
                szx: reply_szx,
                ..block
            });
        }
        if offset != current {
            return Block1Outcome::Refuse {
                code: Code::REQUEST_ENTITY_INCOMPLETE,
                diagnostic: "Block1 out of sequence: a block is missing",
                size1: None,
            };
        }
        let new_len = current + payload.len();
        if new_len > limits.block1_peer_bytes
            || self.peer_bytes(key.peer) + payload.len() > limits.block1_peer_bytes
        {
            self.drop_key(&key);
            return too_large;
        }
        if self.total_bytes + payload.len() > limits.block1_total_bytes {
            self.drop_key(&key);
            return Block1Outcome::Refuse {
                code: Code::SERVICE_UNAVAILABLE,
                diagnostic: "server is assembling too many request bodies; retry later",
                size1: None,
            };
        }
        let mut fresh = false;
        let assembly = self.assemblies.entry(key.clone()).or_insert_with(|| {
            fresh = true;
            Assembly {
                body: Vec::new(),
                last_used: now,
            }
        });
        let before = assembly.body.capacity();
        assembly.body.extend_from_slice(payload);
        assembly.last_used = now;
        let mut grew = assembly.body.capacity() - before;
        if fresh {
            grew += key.held() + ENTRY_OVERHEAD;
        }
        self.account(key.peer, payload.len(), grew, true);
        if block.more {
            Block1Outcome::Continue(BlockOpt {
                szx: reply_szx,
                ..block
            })
        } else {
            let body = self.drop_key(&key).unwrap_or_default();
            Block1Outcome::Complete(Bytes::from(body), block)
        }
    }

    fn drop_key(&mut self, key: &BlockKey) -> Option<Vec<u8>> {
        let a = self.assemblies.remove(key)?;
        self.account(key.peer, a.body.len(), held(key, &a), false);
        Some(a.body)
    }

    pub(crate) fn total_bytes(&self) -> usize {
        self.total_bytes
    }
}

/// A response body read block by block as clients ask for it, instead of held whole in
/// memory: a file served from disk, say. Handed to the endpoint with
/// [`Response::with_source`](crate::Response::with_source); the Block2 store keeps the
/// source and reads each block from it.
pub trait BlockSource: Send + Sync {
    /// The body's length in bytes. It must not change: a body that changes is a new
    /// representation (a new source, with a new ETag).
    fn len(&self) -> usize;

    /// Whether the body is empty.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The bytes of `range` (within `0..len()`), or `None` when they can no longer be read
    /// as they were when the source was made (the file changed or vanished). The endpoint
    /// then drops the stored representation: a GET is rendered again, and the client sees
    /// the new ETag.
    fn read(&self, range: Range<usize>) -> Option<Bytes>;

    /// Bytes the source keeps in memory (a read-ahead window, say), counted against the
    /// Block2 store's byte limit.
    fn held(&self) -> usize;
}

impl BlockSource for Bytes {
    fn len(&self) -> usize {
        Self::len(self)
    }

    fn read(&self, range: Range<usize>) -> Option<Bytes> {
        Some(self.slice(range))
    }

    fn held(&self) -> usize {
        Self::len(self)
    }
}

/// A shared [`BlockSource`]; equal only to itself.
#[derive(Clone)]
pub struct Source(pub(crate) Arc<dyn BlockSource>);

impl Source {
    /// Wraps a source.
    pub fn new(source: impl BlockSource + 'static) -> Self {
        Self(Arc::new(source))
    }

    /// The body's length ([`BlockSource::len`]).
    #[must_use]
    pub fn len(&self) -> usize {
        self.0.len()
    }

    /// Whether the body is empty.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// Bytes `range` of the body ([`BlockSource::read`]).
    #[must_use]
    pub fn read(&self, range: Range<usize>) -> Option<Bytes> {
        self.0.read(range)
    }

    /// What the source holds, counted against the Block2 store ([`BlockSource::held`]).
    #[must_use]
    pub fn held(&self) -> usize {
        self.0.held()
    }
}

impl PartialEq for Source {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

impl Eq for Source {}

impl fmt::Debug for Source {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Source({} bytes)", self.0.len())
    }
}

/// A representation stored for Block2 continuations.
#[derive(Debug, Clone)]
pub(crate) struct Stored {
    pub(crate) code: Code,
    /// The response options (Content-Format, Max-Age, ETag ...) encoded around Block2,
    /// which each continuation sets.
    pub(crate) head: BlockHead,
    pub(crate) body: Source,
    /// For a body sent with Q-Block2 (RFC 9177), the options of every block (Size2
    /// included), which a Block2 continuation must not be cut from.
    pub(crate) q_options: Option<Options>,
    /// What the entry holds: `body` when it was stored (its [`BlockSource::held`]), its
    /// key, options and bookkeeping; `next`'s not included.
    held: usize,
    last_used: Instant,
    /// A block before the last was the latest served: a client is partway through this
    /// representation.
    partway: bool,
    /// A newer representation a notification brought while a client was partway through
    /// this one ([`Storing::Notification`]).
    next: Option<Box<Self>>,
}

impl Stored {
    fn new(
        now: Instant,
        key: &BlockKey,
        code: Code,
        options: Options,
        body: Source,
        q_block: bool,
    ) -> Self {
        let head = BlockHead::new(&options, OptionNumber::BLOCK2);
        let q_options = q_block.then_some(options);
        // The body, and what the entry holds besides: its key, the options encoded once,
        // the Q-Block options.
        let held = body.0.held()
            + key.held()
            + ENTRY_OVERHEAD
            + size_of::<Self>()
            + head.held()
            + q_options.as_ref().map_or(0, Options::held);
        Self {
            code,
            head,
            q_options,
            body,
            held,
            last_used: now,
            partway: false,
            next: None,
        }
    }

    /// What the entry holds with the representation waiting behind it.
    fn held_with_next(&self) -> usize {
        self.held + self.next.as_ref().map_or(0, |n| n.held)
    }
}

/// How [`ServerCache::insert`] stores a representation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Storing {
    /// A response's, sent with Block2: it replaces the one stored before at once.
    Block2,
    /// A response's, sent with Q-Block2 (RFC 9177): it replaces at once too.
    QBlock2,
    /// A notification's, sent with Block2: it may wait behind the one a client is partway
    /// through (paused no longer than `pause`).
    Notification { pause: Duration },
}

/// Block2 representations keyed by request, bounded in bytes, least recently used out
/// first, expired after an idle lifetime.
pub(crate) struct ServerCache {
    entries: BTreeMap<BlockKey, Stored>,
    bytes: usize,
}

impl ServerCache {
    pub(crate) fn new() -> Self {
        Self {
            entries: BTreeMap::new(),
            bytes: 0,
        }
    }

    pub(crate) fn expire(&mut self, now: Instant, limits: &Limits) {
        let bytes = &mut self.bytes;
        self.entries.retain(|_, s| {
            let keep = now.saturating_duration_since(s.last_used) < limits.blockwise_lifetime;
            if !keep {
                *bytes -= s.held_with_next();
            }
            keep
        });
    }

    /// When the representation unused longest was last used.
    pub(crate) fn oldest(&self) -> Option<Instant> {
        self.entries.values().map(|s| s.last_used).min()
    }

    /// Stores a representation, replacing the previous one for the same request and
    /// evicting the least recently used ones to stay within the byte limit. A
    /// representation larger than the whole store is not stored.
    ///
    /// A notification's (RFC 7959 §2.6, [`Storing::Notification`]) waits instead behind the
    /// one stored for the same request when a client has been partway through that within
    /// `pause` and the store has room for both (replacing any that waited before), and
    /// takes its place when the last block has been served or the transfer pauses longer
    /// ([`ServerCache::settle`]): replaced at once, a resource that changes faster than its
    /// blocks arrive could never be fetched whole, and every try costs the client message
    /// IDs.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn insert(
        &mut self,
        now: Instant,
        key: BlockKey,
        code: Code,
        options: Options,
        body: Source,
        how: Storing,
        limits: &Limits,
    ) {
        let q_block = how == Storing::QBlock2;
        let stored = Stored::new(now, &key, code, options, body, q_block);
        if let Storing::Notification { pause } = how {
            let room = limits.block2_store_bytes.saturating_sub(self.bytes);
            if let Some(current) = self.entries.get_mut(&key).filter(|s| {
                s.partway
                    && s.q_options.is_none()
                    && now.saturating_duration_since(s.last_used) < pause
            }) {
                let freed = current.next.as_ref().map_or(0, |n| n.held);
                if stored.held <= room + freed {
                    self.bytes = self.bytes - freed + stored.held;
                    current.next = Some(Box::new(stored));
                    return;
                }
            }
        }
        self.expire(now, limits);
        self.remove(&key);
        let held = stored.held;
        if held > limits.block2_store_bytes {
            return;
        }
        while self.bytes + held > limits.block2_store_bytes {
            let Some(oldest) = self
                .entries
                .iter()
                .min_by_key(|(_, s)| s.last_used)
                .map(|(k, _)| k.clone())
            else {
                break;
            };
            self.remove(&oldest);
        }
        self.bytes += held;
        self.entries.insert(key, stored);
    }

    /// Before a continuation of `key` is served: a representation waiting behind the
    /// stored one takes its place when no block of that was asked for within `pause` (its
    /// client gave up or went on to the newer one).
    pub(crate) fn settle(&mut self, now: Instant, key: &BlockKey, pause: Duration) {
        if let Some(s) = self.entries.get_mut(key)
            && s.next.is_some()
            && now.saturating_duration_since(s.last_used) >= pause
        {
            Self::promote(&mut self.bytes, s, now);
        }
    }

    /// Block `num` (`more` unless the last) of the representation stored for `key` was
    /// served: after the last, the one waiting behind it takes its place.
    pub(crate) fn served(&mut self, now: Instant, key: &BlockKey, num: u32, more: bool) {
        if let Some(s) = self.entries.get_mut(key) {
            s.partway = more && num > 0;
            if !more {
                Self::promote(&mut self.bytes, s, now);
            }
        }
    }

    /// The representation waiting behind `s`, if any, replaces it.
    fn promote(bytes: &mut usize, s: &mut Stored, now: Instant) {
        if let Some(mut next) = s.next.take() {
            *bytes -= s.held;
            next.last_used = now;
            *s = *next;
        }
    }

    /// Drops the representation stored for a request (its source could not be read).
    pub(crate) fn remove(&mut self, key: &BlockKey) {
        if let Some(old) = self.entries.remove(key) {
            self.bytes -= old.held_with_next();
        }
    }

    /// Whether a representation is stored under `key` (expired or not).
    pub(crate) fn contains(&self, key: &BlockKey) -> bool {
        self.entries.contains_key(key)
    }

    /// Calls `f` with the representation stored for a continuation request, refreshing its
    /// lifetime; `None` when none is stored. Only this entry's age is checked here; the
    /// others expire on the next insert, so a block does not walk the whole store.
    pub(crate) fn with_stored<R>(
        &mut self,
        now: Instant,
        key: &BlockKey,
        limits: &Limits,
        f: impl FnOnce(&Stored) -> R,
    ) -> Option<R> {
        let s = self.entries.get_mut(key)?;
        if now.saturating_duration_since(s.last_used) < limits.blockwise_lifetime {
            s.last_used = now;
            return Some(f(s));
        }
        self.remove(key);
        None
    }

    pub(crate) fn bytes(&self) -> usize {
        self.bytes
    }
}

/// Block `num` of a body, cut by [`slice`].
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Slice {
    Block(Bytes, BlockOpt),
    /// The block starts past the end (RFC 7959 §2.2: the server answers 4.02 then).
    PastEnd,
    /// The source could not be read ([`BlockSource::read`]).
    Unreadable,
}

/// Cuts block `num` of size `2^(szx+4)` out of `body`.
pub(crate) fn slice(body: &dyn BlockSource, num: u32, szx: u8) -> Slice {
    let size = BlockOpt::size_of(szx);
    let len = body.len();
    let start = num as usize * size;
    if start >= len && !(start == 0 && len == 0) {
        return Slice::PastEnd;
    }
    let end = (start + size).min(len);
    match body.read(start..end) {
        Some(bytes) => Slice::Block(
            bytes,
            BlockOpt {
                num,
                more: end < len,
                szx,
            },
        ),
        None => Slice::Unreadable,
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    fn key(port: u16) -> BlockKey {
        BlockKey {
            peer: SocketAddr::from(([127, 0, 0, 1], port)),
            method: Code::PUT,
            options: SmallVec::new(),
        }
    }

    #[test]
    fn keys_order_every_address_apart() {
        let addrs = [
            "1.2.3.4:5683",
            "1.2.3.4:5684",
            "[::1.2.3.4]:5683",
            "[::ffff:1.2.3.4]:5683",
            "[fe80::1%1]:5683",
            "[fe80::1%2]:5683",
        ];
        let mut keys: Vec<BlockKey> = addrs
            .iter()
            .map(|a| BlockKey {
                peer: a.parse().unwrap(),
                ..key(0)
            })
            .collect();
        let mut flow = std::net::SocketAddrV6::new("fe80::1".parse().unwrap(), 5683, 0, 1);
        flow.set_flowinfo(7);
        keys.push(BlockKey {
            peer: flow.into(),
            ..key(0)
        });
        for (i, a) in keys.iter().enumerate() {
            for (j, b) in keys.iter().enumerate() {
                assert_eq!(a == b, i == j, "{a:?} {b:?}");
                assert_eq!(a.cmp(b), b.cmp(a).reverse());
            }
        }
    }

    fn cfg(max_block_szx: u8, limits: Limits) -> EndpointConfig {
        EndpointConfig {
            max_block_szx,
            limits,
            ..EndpointConfig::default()
        }
    }

    fn b(num: u32, more: bool, szx: u8) -> BlockOpt {
        BlockOpt { num, more, szx }
    }

    #[test]
    fn rfc7959_2_3_block1_in_order_assembles() {
        let now = crate::test_epoch();
        let l = Limits::default();
        let c = cfg(6, l);
        let mut a = Block1Assembler::new();
        assert_eq!(
            a.handle(now, key(1), b(0, true, 0), None, &[1; 16], &c),
            Block1Outcome::Continue(b(0, true, 0))
        );
        let Block1Outcome::Complete(body, echo) =
            a.handle(now, key(1), b(1, false, 0), None, &[2; 5], &c)
        else {
            panic!("not complete");
        };
        assert_eq!(body.len(), 21);
        assert_eq!(echo, b(1, false, 0));
        assert_eq!(a.total_bytes(), 0);
    }

    #[test]
    fn rfc7959_2_9_2_block1_gap_gives_4_08() {
        let now = crate::test_epoch();
        let l = Limits::default();
        let c = cfg(6, l);
        let mut a = Block1Assembler::new();
        let r = a.handle(now, key(1), b(2, true, 0), None, &[1; 16], &c);
        assert!(matches!(
            r,
            Block1Outcome::Refuse {
                code: Code::REQUEST_ENTITY_INCOMPLETE,
                ..
            }
        ));
        a.handle(now, key(1), b(0, true, 0), None, &[1; 16], &c);
        let r = a.handle(now, key(1), b(2, true, 0), None, &[1; 16], &c);
        assert!(matches!(
            r,
            Block1Outcome::Refuse {
                code: Code::REQUEST_ENTITY_INCOMPLETE,
                ..
            }
        ));
    }

    #[test]
    fn rfc7959_2_9_3_block1_size1_over_limit_gives_4_13_with_size1() {
        let now = crate::test_epoch();
        let l = Limits {
            block1_peer_bytes: 64,
            ..Limits::default()
        };
        let mut a = Block1Assembler::new();
        let c = cfg(6, l);
        let r = a.handle(now, key(1), b(0, true, 0), Some(65), &[1; 16], &c);
        assert_eq!(
            r,
            Block1Outcome::Refuse {
                code: Code::REQUEST_ENTITY_TOO_LARGE,
                diagnostic: "request body exceeds this server's limit (see Size1)",
                size1: Some(64)
            }
        );
        for n in 0..4 {
            assert!(matches!(
                a.handle(now, key(1), b(n, true, 0), None, &[1; 16], &c),
                Block1Outcome::Continue(_)
            ));
        }
        let r = a.handle(now, key(1), b(4, true, 0), None, &[1; 16], &c);
        assert!(matches!(
            r,
            Block1Outcome::Refuse {
                code: Code::REQUEST_ENTITY_TOO_LARGE,
                size1: Some(64),
                ..
            }
        ));
        assert_eq!(a.total_bytes(), 0, "a refused body is dropped");
    }

    #[test]
    fn block1_total_limit_gives_5_03() {
        let now = crate::test_epoch();
        let l = Limits {
            block1_total_bytes: 40,
            ..Limits::default()
        };
        let mut a = Block1Assembler::new();
        let c = cfg(6, l);
        a.handle(now, key(1), b(0, true, 0), None, &[1; 16], &c);
        a.handle(now, key(2), b(0, true, 0), None, &[1; 16], &c);
        let r = a.handle(now, key(3), b(0, true, 0), None, &[1; 16], &c);
        assert!(matches!(
            r,
            Block1Outcome::Refuse {
                code: Code::SERVICE_UNAVAILABLE,
                ..
            }
        ));
    }

    #[test]
    fn rfc7959_2_3_server_asks_for_smaller_blocks() {
        let now = crate::test_epoch();
        let mut a = Block1Assembler::new();
        let r = a.handle(
            now,
            key(1),
            b(0, true, 6),
            None,
            &[1; 1024],
            &cfg(3, Limits::default()),
        );
        assert_eq!(r, Block1Outcome::Continue(b(0, true, 3)));
        // The client continues at offset 1024 in 128-byte blocks: num 8.
        let r = a.handle(
            now,
            key(1),
            b(8, false, 3),
            None,
            &[2; 100],
            &cfg(3, Limits::default()),
        );
        assert!(matches!(r, Block1Outcome::Complete(body, _) if body.len() == 1124));
    }

    #[test]
    fn block1_assembly_expires_by_now() {
        let now = crate::test_epoch();
        let l = Limits::default();
        let c = cfg(6, l);
        let mut a = Block1Assembler::new();
        a.handle(now, key(1), b(0, true, 0), None, &[1; 16], &c);
        let later = now + c.limits.blockwise_lifetime + Duration::from_secs(1);
        let r = a.handle(later, key(1), b(1, false, 0), None, &[1; 3], &c);
        assert!(matches!(
            r,
            Block1Outcome::Refuse {
                code: Code::REQUEST_ENTITY_INCOMPLETE,
                ..
            }
        ));
        assert_eq!(a.total_bytes(), 0);
    }

    #[test]
    fn block1_bytes_per_peer_follow_the_assemblies() {
        let now = crate::test_epoch();
        let l = Limits {
            block1_peer_bytes: 64,
            ..Limits::default()
        };
        let c = cfg(6, l);
        let mut a = Block1Assembler::new();
        // Peer 1: two bodies of 32 bytes so far (two requests); peer 3: one of 16.
        let mut two = key(1);
        two.options.extend_from_slice(b"other");
        for k in [key(1), two.clone()] {
            a.handle(now, k.clone(), b(0, true, 0), None, &[1; 16], &c);
            a.handle(now, k, b(1, true, 0), None, &[1; 16], &c);
        }
        a.handle(now, key(3), b(0, true, 0), None, &[1; 16], &c);
        assert_eq!(
            (a.peer_bytes(key(1).peer), a.peer_bytes(key(3).peer)),
            (64, 16)
        );
        // In all, what the bodies' allocations, the keys and the entries hold.
        let held_now: usize = a.assemblies.iter().map(|(k, x)| held(k, x)).sum();
        assert_eq!(a.total_bytes(), held_now);
        assert!(held_now >= 80 + 3 * (key(1).held() + ENTRY_OVERHEAD));
        // A third block for peer 1 passes its 64 bytes: that body is dropped.
        let r = a.handle(now, key(1), b(2, true, 0), None, &[1; 16], &c);
        assert!(matches!(
            r,
            Block1Outcome::Refuse {
                code: Code::REQUEST_ENTITY_TOO_LARGE,
                ..
            }
        ));
        assert_eq!(a.peer_bytes(key(1).peer), 32);
        // Completed and expired bodies are no longer counted.
        assert!(matches!(
            a.handle(now, two, b(2, false, 0), None, &[1; 4], &c),
            Block1Outcome::Complete(..)
        ));
        assert_eq!(a.peer_bytes(key(1).peer), 0);
        let later = now + c.limits.blockwise_lifetime + Duration::from_secs(1);
        a.expire(later, &c.limits);
        assert_eq!((a.peer_bytes(key(3).peer), a.total_bytes()), (0, 0));
        assert!(a.peer_bytes.is_empty());
    }

    /// A key whose request carried `len` bytes of Uri-Query.
    fn long_key(port: u16, len: usize) -> BlockKey {
        let mut k = key(port);
        k.options.extend(std::iter::repeat_n(b'q', len));
        k
    }

    #[test]
    fn stores_count_the_bytes_their_keys_hold() {
        // 100 requests, each with 51 KB of Uri-Query and a small body: the keys are what
        // fills memory, and what the limits must count.
        let now = crate::test_epoch();
        let l = Limits {
            block2_store_bytes: 1 << 20,
            block1_total_bytes: 1 << 20,
            ..Limits::default()
        };
        let mut store = ServerCache::new();
        let mut uploads = Block1Assembler::new();
        let c = cfg(6, l.clone());
        let mut refused = 0;
        for n in 0..100 {
            let body = Source::new(Bytes::from(vec![0; 2000]));
            store.insert(
                now,
                long_key(n, 51_000),
                Code::CONTENT,
                Options::new(),
                body,
                Storing::Block2,
                &l,
            );
            let r = uploads.handle(now, long_key(n, 51_000), b(0, true, 0), None, &[1; 16], &c);
            refused += usize::from(!matches!(r, Block1Outcome::Continue(_)));
        }
        assert!(store.bytes() <= 1 << 20, "{} bytes", store.bytes());
        assert!(store.entries.len() <= 20, "{} kept", store.entries.len());
        assert!(uploads.total_bytes() <= (1 << 20) + 52_000);
        assert!(refused >= 80, "{refused} refused");
    }

    /// What a stored entry of `key(n)` with no options holds besides its body.
    fn stored_overhead() -> usize {
        key(1).held()
            + ENTRY_OVERHEAD
            + size_of::<Stored>()
            + BlockHead::new(&Options::new(), OptionNumber::BLOCK2).held()
    }

    #[test]
    fn block2_store_is_bounded_and_expires() {
        let now = crate::test_epoch();
        let o = stored_overhead();
        let l = Limits {
            block2_store_bytes: 100 + o,
            ..Limits::default()
        };
        let mut c = ServerCache::new();
        c.insert(
            now,
            key(1),
            Code::CONTENT,
            Options::new(),
            Source::new(Bytes::from(vec![0; 60])),
            Storing::Block2,
            &l,
        );
        c.insert(
            now + Duration::from_secs(1),
            key(2),
            Code::CONTENT,
            Options::new(),
            Source::new(Bytes::from(vec![0; 60])),
            Storing::Block2,
            &l,
        );
        assert!(
            c.with_stored(now, &key(1), &l, |_| ()).is_none(),
            "oldest evicted"
        );
        assert_eq!(c.bytes(), 60 + o, "the body, the key, the entry");
        let later = now + l.blockwise_lifetime + Duration::from_secs(2);
        assert!(c.with_stored(later, &key(2), &l, |_| ()).is_none());
        assert_eq!(c.bytes(), 0);
    }

    /// A notification's representation waiting behind one a client is partway through
    /// counts against the store until it takes that one's place; then only it does.
    #[test]
    fn a_waiting_notification_is_counted_and_takes_the_place_after_the_last_block() {
        let now = crate::test_epoch();
        let o = stored_overhead();
        let l = Limits {
            block2_store_bytes: 200 + 2 * o,
            ..Limits::default()
        };
        let pause = Duration::from_secs(3);
        let body = |n: u8, len: usize| Source::new(Bytes::from(vec![n; len]));
        // A notification of `len` bytes, each `n`.
        let notify = |c: &mut ServerCache, n: u8, len: usize| {
            let options = Options::new();
            let how = Storing::Notification { pause };
            c.insert(now, key(1), Code::CONTENT, options, body(n, len), how, &l);
        };
        let first_byte = |c: &mut ServerCache| {
            c.with_stored(now, &key(1), &l, |s| s.body.0.read(0..1))
                .flatten()
                .map(|b| b[0])
        };
        let mut c = ServerCache::new();
        c.insert(
            now,
            key(1),
            Code::CONTENT,
            Options::new(),
            body(1, 60),
            Storing::Block2,
            &l,
        );
        c.served(now, &key(1), 1, true);
        notify(&mut c, 2, 80);
        assert_eq!(c.bytes(), 140 + 2 * o, "both held");
        assert_eq!(first_byte(&mut c), Some(1), "the one partway through stays");
        // A third replaces the one waiting, not the one partway through.
        notify(&mut c, 3, 90);
        assert_eq!(c.bytes(), 150 + 2 * o);
        // No room for a fourth beside it: it replaces at once.
        notify(&mut c, 4, 150);
        assert_eq!((first_byte(&mut c), c.bytes()), (Some(4), 150 + o));
        c.served(now, &key(1), 1, true);
        notify(&mut c, 5, 40);
        c.served(now, &key(1), 2, false);
        assert_eq!(
            (first_byte(&mut c), c.bytes()),
            (Some(5), 40 + o),
            "after the last"
        );
        // A transfer that pauses longer: the waiting one takes its place before a block.
        c.served(now, &key(1), 1, true);
        notify(&mut c, 6, 50);
        c.settle(now + pause / 2, &key(1), pause);
        assert_eq!(first_byte(&mut c), Some(5));
        c.settle(now + pause * 2, &key(1), pause);
        assert_eq!((first_byte(&mut c), c.bytes()), (Some(6), 50 + o));
        c.remove(&key(1));
        assert_eq!(c.bytes(), 0);
    }

    #[test]
    fn rfc7959_2_2_slice_blocks() {
        let body = Bytes::from((0..100u8).collect::<Vec<_>>());
        let Slice::Block(p, o) = slice(&body, 0, 1) else {
            panic!("block 0")
        };
        assert_eq!((p.len(), o.more), (32, true));
        let Slice::Block(p, o) = slice(&body, 3, 1) else {
            panic!("block 3")
        };
        assert_eq!((p.len(), o.more, p[0]), (4, false, 96));
        assert_eq!(slice(&body, 4, 1), Slice::PastEnd);
    }

    /// A body of `len` bytes (byte i is i % 256) that holds `held` bytes and can be read
    /// until `gone` is set.
    struct Counting {
        len: usize,
        held: usize,
        gone: std::sync::atomic::AtomicBool,
    }

    impl BlockSource for Counting {
        fn len(&self) -> usize {
            self.len
        }

        fn read(&self, range: Range<usize>) -> Option<Bytes> {
            (!self.gone.load(std::sync::atomic::Ordering::Relaxed))
                .then(|| range.map(|i| i as u8).collect())
        }

        fn held(&self) -> usize {
            self.held
        }
    }

    #[test]
    fn a_source_is_read_per_block_and_counts_what_it_holds() {
        let now = crate::test_epoch();
        let o = stored_overhead();
        let l = Limits {
            block2_store_bytes: 100 + o,
            ..Limits::default()
        };
        let source = Arc::new(Counting {
            len: 1000,
            held: 40,
            gone: false.into(),
        });
        let mut c = ServerCache::new();
        c.insert(
            now,
            key(1),
            Code::CONTENT,
            Options::new(),
            Source(source.clone()),
            Storing::Block2,
            &l,
        );
        assert_eq!(
            c.bytes(),
            40 + o,
            "a 1000-byte body counts what its source holds"
        );
        let body = c
            .with_stored(now, &key(1), &l, |s| s.body.clone())
            .expect("stored");
        let Slice::Block(p, o) = slice(&*body.0, 31, 1) else {
            panic!("block 31")
        };
        assert_eq!((p.len(), o.more, p[0]), (8, false, (992 % 256) as u8));
        source
            .gone
            .store(true, std::sync::atomic::Ordering::Relaxed);
        assert_eq!(slice(&*body.0, 0, 1), Slice::Unreadable);
        c.remove(&key(1));
        assert_eq!(c.bytes(), 0);
    }
}
