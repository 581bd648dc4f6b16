//! The endpoint: one CoAP endpoint (one socket's worth of peers), driven as quinn-proto is.
//!
//! Inputs: [`Endpoint::handle`] (a datagram), [`Endpoint::handle_timeout`],
//! [`Endpoint::request`], [`Endpoint::respond`], [`Endpoint::ping`], [`Endpoint::cancel`].
//! Outputs: [`Endpoint::poll_transmit`], [`Endpoint::poll_timeout`], [`Endpoint::poll_event`].
//!
//! Call order: after any input, drain `poll_transmit` and `poll_event`, then sleep until
//! `poll_timeout` and call `handle_timeout`. A `handle_timeout` before anything is due is a
//! no-op, so spurious wake-ups are harmless.
//!
//! Layers inside: the message layer (message IDs, CON retransmission with exponential
//! back-off, ACK/RST, deduplication); the client request layer (tokens, NSTART per peer,
//! transparent Block1 upload and Block2 reassembly that resumes from the block it lacks);
//! the server request layer (Block1 assembly, Block2 slicing from a stored representation,
//! piggybacked or separate responses).
//!
//! A client request is a sequence of *steps*, one message exchange each; today a request
//! runs one step at a time. Windowed transfers (NSTART > 1 within one transfer, RFC 9177)
//! add concurrent steps to the same request without changing the message layer.

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap, VecDeque};
use std::net::SocketAddr;
use std::time::{Duration, Instant};

use bytes::{Bytes, BytesMut};
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore, SeedableRng};

use crate::block::{
    self, Block1Assembler, Block1Outcome, BlockKey, BlockSource, ServerCache, Slice, Source,
};
use crate::config::{EndpointConfig, Limits};
use crate::dedup::{Dedup, Fingerprint, Seen};
use crate::msg::{
    BlockHead, BlockOpt, Code, Message, OptionNumber, Options, Outgoing, Reaction, Token, Type,
};
use crate::peer_key::{MidKey, PeerKey};

/// Identifies a request this endpoint sent (client side).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct RequestId(pub u64);

/// Identifies a request this endpoint received and must answer with [`Endpoint::respond`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct IncomingId(pub u64);

/// A datagram to send.
#[derive(Debug, Clone, PartialEq, Eq)]
#[must_use]
pub struct Transmit {
    /// Destination.
    pub peer: SocketAddr,
    /// The encoded message.
    pub data: Bytes,
}

/// A request to send. The payload may be any size: bodies larger than one block go out
/// with Block1, and a response sent in blocks is reassembled before it is delivered.
#[derive(Debug, Clone)]
pub struct Request {
    /// Method code.
    pub method: Code,
    /// Options (Uri-Path, Uri-Query, Accept, Content-Format, ...).
    pub options: Options,
    /// Request body.
    pub payload: Bytes,
    /// CON (default) or NON.
    pub confirmable: bool,
    /// Block size exponent to use (and to ask the server for); `None` uses the endpoint's
    /// largest (1024 bytes by default) and asks for nothing.
    pub block_szx: Option<u8>,
    /// Give up after this long in total. For a multicast request: how long to collect
    /// responses (default 5 s).
    pub timeout: Option<Duration>,
    /// Sent to a multicast group (RFC 7390): always NON, never re-sent, and every server's
    /// response arrives as [`Event::MulticastResponse`] until the timeout, then
    /// [`Event::MulticastDone`].
    pub multicast: bool,
    /// Report [`Event::Progress`] during a block-wise transfer.
    pub progress: bool,
    /// Deliver the body of a success response as [`Event::BodyChunk`]s, in order, while
    /// its blocks arrive (64 KiB at a time), instead of reassembling it: the final [`Event::Response`] then has
    /// an empty payload. Chunks are provisional until that response; a failure after some
    /// of them (an ETag that changed mid-transfer, a missing block, a total that does not
    /// match Size2) ends in [`Event::RequestFailed`], and the chunks must be discarded.
    pub stream: bool,
}

impl Request {
    /// A CON request for `path` (e.g. `/cams/pointclouds`) without payload.
    pub fn new(method: Code, path: &str) -> Self {
        let mut options = Options::new();
        options.set_path(path);
        Self {
            method,
            options,
            payload: Bytes::new(),
            confirmable: true,
            block_szx: None,
            timeout: None,
            multicast: false,
            progress: false,
            stream: false,
        }
    }

    /// Sets the payload.
    pub fn with_payload(mut self, payload: impl Into<Bytes>) -> Self {
        self.payload = payload.into();
        self
    }
}

/// A response: to send with [`Endpoint::respond`], or received in
/// [`Event::Response`] with the whole reassembled body.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Response {
    /// Response code.
    pub code: Code,
    /// Options.
    pub options: Options,
    /// Body.
    pub payload: Bytes,
    /// A body read block by block when clients ask for it, in place of `payload` (only in
    /// responses this endpoint sends).
    pub source: Option<Source>,
}

impl Response {
    /// A response with a code and no payload.
    pub fn new(code: Code) -> Self {
        Self::with_parts(code, Options::new(), Bytes::new())
    }

    /// A response of these parts.
    pub fn with_parts(code: Code, options: Options, payload: Bytes) -> Self {
        Self {
            code,
            options,
            payload,
            source: None,
        }
    }

    /// An error response with a text/plain diagnostic payload (RFC 7252 §5.5.2).
    pub fn diagnostic(code: Code, text: &str) -> Self {
        Self::with_parts(
            code,
            Options::new(),
            Bytes::copy_from_slice(text.as_bytes()),
        )
    }

    /// Sets the payload.
    pub fn with_payload(mut self, payload: impl Into<Bytes>) -> Self {
        self.payload = payload.into();
        self
    }

    /// Sets a body that is read block by block as clients ask for it (a large file, say),
    /// instead of a payload held in memory.
    pub fn with_source(mut self, source: impl BlockSource + 'static) -> Self {
        self.source = Some(Source::new(source));
        self
    }
}

/// A request received from a peer.
#[derive(Debug, Clone)]
pub struct IncomingRequest {
    /// Answer it with [`Endpoint::respond`].
    pub id: IncomingId,
    /// Who sent it.
    pub peer: SocketAddr,
    /// Method code.
    pub method: Code,
    /// Options (malformed elective options already dropped).
    pub options: Options,
    /// The whole body (Block1 already assembled).
    pub payload: Bytes,
    /// Whether it was sent to a multicast address (error responses are suppressed).
    pub multicast: bool,
    /// Whether it was a CON message.
    pub confirmable: bool,
    /// Set when this is an Observe registration (RFC 7641 §2: GET with Observe 0). The
    /// application accepts it by answering with a success that carries an Observe option
    /// (any value; the endpoint numbers notifications itself); then [`Endpoint::notify`]
    /// sends notifications to it. A response without Observe declines (§4.1).
    pub observe: Option<ObservationId>,
}

/// Identifies an observation this endpoint serves (RFC 7641, server side).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ObservationId(pub u64);

/// Why a request failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum RequestError {
    /// No acknowledgement after MAX_RETRANSMIT retransmissions, no response within the
    /// response timeout, or the request's own timeout expired.
    #[error("timed out")]
    Timeout,
    /// The peer rejected the message with a Reset.
    #[error("reset by peer")]
    Reset,
    /// Nothing listens at the peer's address: its host answered with ICMP "port
    /// unreachable" (reported by the driver, which reads the socket's errors).
    #[error("nothing listens there (ICMP port unreachable)")]
    Unreachable,
    /// The response body exceeds the endpoint's limit.
    #[error("response body larger than {limit} bytes")]
    TooLarge {
        /// The configured limit.
        limit: usize,
    },
    /// The server changed the representation (ETag) during a block-wise transfer more
    /// often than the endpoint retries.
    #[error("representation changed during a block-wise transfer")]
    RepresentationChanged,
    /// The server broke the block-wise protocol.
    #[error("protocol violation: {0}")]
    Protocol(&'static str),
    /// Cancelled by [`Endpoint::cancel`].
    #[error("cancelled")]
    Cancelled,
}

/// What the endpoint reports to its owner.
#[derive(Debug, Clone)]
#[must_use]
pub enum Event {
    /// A request to answer with [`Endpoint::respond`].
    Request(IncomingRequest),
    /// The complete response to a request.
    Response {
        /// The request.
        id: RequestId,
        /// The response with its whole body.
        response: Response,
    },
    /// A request failed.
    RequestFailed {
        /// The request.
        id: RequestId,
        /// Why.
        error: RequestError,
    },
    /// The peer answered a CoAP ping (RFC 7252 §4.3).
    Pong {
        /// The ping.
        id: RequestId,
    },
    /// A notification of an observed resource (RFC 7641), after the first response.
    Notification {
        /// The Observe request.
        id: RequestId,
        /// The notification.
        response: Response,
    },
    /// One server's response to a multicast request.
    MulticastResponse {
        /// The request.
        id: RequestId,
        /// The server that answered.
        peer: SocketAddr,
        /// Its response.
        response: Response,
    },
    /// A block-wise transfer passed another 64 KiB, or ended (only for requests with
    /// [`Request::progress`]).
    Progress {
        /// The request.
        id: RequestId,
        /// Bytes transferred so far.
        done: usize,
        /// The whole size, when known (Size1 of an upload, Size2 of a download).
        total: Option<usize>,
    },
    /// The next piece of a response body, for requests with [`Request::stream`]: 64 KiB
    /// or more (several blocks), the last one shorter. Pieces come in order without gaps;
    /// the request's [`Event::Response`] or
    /// [`Event::RequestFailed`] follows the last one.
    BodyChunk {
        /// The request.
        id: RequestId,
        /// Where the piece starts in the body.
        offset: usize,
        /// The bytes.
        data: Bytes,
        /// The whole size, when the server announced it (Size2).
        total: Option<usize>,
    },
    /// A multicast request stopped collecting responses.
    MulticastDone {
        /// The request.
        id: RequestId,
    },
    /// An observation ended: the client deregistered, rejected a notification with a
    /// Reset, or did not acknowledge a confirmable one (RFC 7641 §3.6, §4.5); or the
    /// application declined the registration or sent a non-success notification.
    ObservationEnded {
        /// The observation.
        id: ObservationId,
    },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum TimerKind {
    Retransmit {
        peer: SocketAddr,
        mid: u16,
        tx: u8,
    },
    /// The retransmission check of a request's CON, armed at `at` (see
    /// [`ClientRequest::ack_timer`]).
    RequestAck {
        id: u64,
        at: Instant,
    },
    Step {
        id: u64,
        generation: u32,
    },
    Deadline {
        id: u64,
    },
    SeparateAck {
        id: u64,
    },
}

#[derive(Debug, Clone, Copy)]
enum Purpose {
    Request(u64),
    Ping(u64),
    SeparateResponse,
    Notification(u64),
}

/// A CON message waiting for its ACK (RFC 7252 §4.2).
struct OutCon {
    /// The datagram to send again. A request's step keeps none: its message is built
    /// again from the request (same message ID, token, options and payload), so the
    /// block-by-block path sends each CON from the shared chunk, without an allocation.
    data: Option<Bytes>,
    /// Retransmissions so far.
    tx: u8,
    timeout: Duration,
    /// When it is sent again (or given up) unless acknowledged.
    at: Instant,
    purpose: Purpose,
}

/// One exchange of a client request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Step {
    /// The whole payload in one message.
    Whole,
    /// Block1 upload of the block at this byte offset.
    Upload { offset: usize },
    /// Block2 request for block `num` of size `2^(szx+4)`.
    Download { num: u32, szx: u8 },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Waiting {
    /// Not started (queued behind NSTART).
    Queued,
    /// CON sent, no ACK yet.
    Ack(u16),
    /// ACKed empty; waiting for the separate response. Or a NON sent, waiting for the
    /// response (carrying the NON's transmission count).
    Response { non_tx: Option<u8>, mid: u16 },
    /// Observing (RFC 7641): the first response arrived, notifications follow; carries
    /// the last Observe sequence number.
    Observing(u32),
    /// A multicast request collecting responses until its deadline.
    Collecting,
}

struct ClientRequest {
    peer: SocketAddr,
    req: Request,
    token: Token,
    szx1: u8,
    step: Step,
    waiting: Waiting,
    generation: u32,
    failures: u8,
    restarts: u8,
    /// Block2 reassembly: body so far (empty when streamed), the bytes received, the
    /// ETag, the first block's options.
    body: Vec<u8>,
    received: usize,
    etag: Option<Vec<u8>>,
    first_options: Option<Options>,
    /// The user set Block2 in the request: random access, no reassembly.
    user_block2: bool,
    /// The request carries Observe 0 (a registration).
    observe: bool,
    /// When its armed [`TimerKind::RequestAck`] fires. Each block's CON does not push a
    /// timer of its own: the armed one fires, finds the CON then awaited and re-arms for
    /// its due time. So a transfer arms about one timer per ACK_TIMEOUT instead of one per
    /// block, and retransmissions still go out exactly when due.
    ack_timer: Option<Instant>,
    /// The request's options encoded around Block2, for the blocks of a download.
    block_head: Option<BlockHead>,
}

impl ClientRequest {
    /// Sends the message of the current step with message ID `mid`: the request's options
    /// with the step's block option (and Size1 on an upload's first block) set over them,
    /// encoded from the request in place.
    fn send_step(&mut self, mid: u16, outbox: &mut Outbox) {
        let block = |num, more, szx| BlockOpt { num, more, szx }.as_uint();
        let ty = if self.req.confirmable {
            Type::Con
        } else {
            Type::Non
        };
        let mut uints = [(OptionNumber(0), 0); 2];
        let mut set = 0;
        let payload: &[u8] = match self.step {
            Step::Download { num, szx } => {
                // Every block of a download is the same request but for Block2.
                let options = &self.req.options;
                let head = self
                    .block_head
                    .get_or_insert_with(|| BlockHead::new(options, OptionNumber::BLOCK2));
                let header = (ty, self.req.method, mid, self.token);
                let value = block(num, false, szx);
                outbox.send_with(self.peer, 0, |out| {
                    head.encode_into(out, header, value, &[])
                });
                return;
            }
            Step::Whole => {
                if let (Some(szx), false) = (self.req.block_szx, self.user_block2) {
                    uints[0] = (OptionNumber::BLOCK2, block(0, false, szx));
                    set = 1;
                }
                &self.req.payload
            }
            Step::Upload { offset } => {
                let size = BlockOpt::size_of(self.szx1);
                let end = (offset + size).min(self.req.payload.len());
                let more = end < self.req.payload.len();
                uints[0] = (
                    OptionNumber::BLOCK1,
                    block((offset / size) as u32, more, self.szx1),
                );
                set = 1;
                if offset == 0 {
                    // RFC 7959 §4: Size1 tells the server the whole size up front.
                    uints[1] = (OptionNumber::SIZE1, self.req.payload.len() as u32);
                    set = 2;
                }
                &self.req.payload[offset.min(end)..end]
            }
        };
        let msg = Outgoing {
            ty,
            code: self.req.method,
            message_id: mid,
            token: self.token,
            options: &self.req.options,
            uints: &uints[..set],
            payload,
        };
        outbox.send(self.peer, &msg);
    }

    fn step_has_block_option(&self) -> bool {
        match self.step {
            Step::Whole => self.req.block_szx.is_some() || self.user_block2,
            Step::Upload { .. } | Step::Download { .. } => true,
        }
    }
}

/// A received request waiting for the application's response.
struct Pending {
    peer: SocketAddr,
    mid: u16,
    token: Token,
    confirmable: bool,
    acked: bool,
    multicast: bool,
    block2: Option<BlockOpt>,
    block1_echo: Option<BlockOpt>,
    key: BlockKey,
    observation: Option<u64>,
}

/// An observation this endpoint serves.
struct Observation {
    peer: SocketAddr,
    token: Token,
    key: BlockKey,
    established: bool,
    seq: u32,
    sent: u32,
    /// Message ID of the last NON notification, so a Reset to it ends the observation.
    last_mid: Option<u16>,
}

/// Streamed bodies are handed over in pieces of at least this many bytes (the last one
/// may be shorter).
const STREAM_PIECE: usize = 64 << 10;

/// Bytes of the chunk that messages sent once are encoded into ([`Outbox::send`]).
const ENCODE_CHUNK: usize = 16 << 10;

/// A map keyed by what this endpoint chose itself (request and observation ids, its own
/// tokens and message IDs, the peers it sends to): a fast seeded hash is enough there.
/// The deduplication store, keyed by message IDs that peers choose, keeps SipHash.
type FastMap<K, V> = HashMap<K, V, foldhash::fast::RandomState>;

#[derive(Default)]
struct Peer {
    active: usize,
    queue: VecDeque<u64>,
}

/// The datagrams waiting for [`Endpoint::poll_transmit`].
#[derive(Default)]
struct Outbox {
    queue: VecDeque<Transmit>,
    /// Where [`Outbox::send`] encodes.
    chunk: BytesMut,
}

impl Outbox {
    /// Queues a message that goes out once and is not kept (not a CON that keeps its
    /// encoding until its ACK). It is encoded into a chunk shared with the messages before
    /// it, so a block costs no allocation of its own; once they are all sent and dropped,
    /// the chunk is used again from its start (so a caller that keeps a [`Transmit`]
    /// keeps its whole chunk).
    fn send(&mut self, peer: SocketAddr, msg: &Outgoing<'_>) {
        self.send_with(peer, msg.payload.len(), |out| msg.encode_into(out));
    }

    /// Queues the message that `encode` appends to the chunk (as [`Outbox::send`]).
    fn send_with(&mut self, peer: SocketAddr, payload: usize, encode: impl FnOnce(&mut BytesMut)) {
        // Room for the payload and usual header and options, without counting them
        // first; a message with more options grows the chunk as it is written.
        let room = payload + 128;
        // Back to the front of the chunk when every datagram cut from it is gone (the
        // usual case: each is sent before the next is encoded), so that block after block
        // is written to the same cache lines.
        let _ = self.chunk.try_reclaim(ENCODE_CHUNK);
        if self.chunk.capacity() < room {
            self.chunk.reserve(room.max(ENCODE_CHUNK));
        }
        encode(&mut self.chunk);
        let data = self.chunk.split().freeze();
        self.queue.push_back(Transmit { peer, data });
    }
}

/// A CoAP endpoint. See the module documentation for the driving protocol.
pub struct Endpoint {
    config: EndpointConfig,
    rng: ChaCha8Rng,
    next_mid: u16,
    next_id: u64,
    timer_seq: u64,
    timers: BinaryHeap<Reverse<(Instant, u64, TimerKind)>>,
    outbox: Outbox,
    events: VecDeque<Event>,
    exchanges: FastMap<MidKey, OutCon>,
    dedup: Dedup,
    requests: FastMap<u64, ClientRequest>,
    by_token: FastMap<Token, u64>,
    peers: FastMap<PeerKey, Peer>,
    pending: FastMap<u64, Pending>,
    block1: Block1Assembler,
    block2: ServerCache,
    observations: FastMap<u64, Observation>,
}

impl Endpoint {
    /// A new endpoint. All randomness comes from `config.rng_seed`.
    pub fn new(config: EndpointConfig) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(config.rng_seed);
        let next_mid = rng.next_u32() as u16;
        Self {
            config,
            rng,
            next_mid,
            next_id: 1,
            timer_seq: 0,
            timers: BinaryHeap::new(),
            outbox: Outbox::default(),
            events: VecDeque::new(),
            exchanges: FastMap::default(),
            dedup: Dedup::new(),
            requests: FastMap::default(),
            by_token: FastMap::default(),
            peers: FastMap::default(),
            pending: FastMap::default(),
            block1: Block1Assembler::new(),
            block2: ServerCache::new(),
            observations: FastMap::default(),
        }
    }

    /// The configuration.
    pub fn config(&self) -> &EndpointConfig {
        &self.config
    }

    /// The next datagram to send.
    pub fn poll_transmit(&mut self) -> Option<Transmit> {
        self.outbox.queue.pop_front()
    }

    /// When [`Endpoint::handle_timeout`] should be called next. Timers that would do
    /// nothing when they fire (the retransmission of a message already acknowledged, the
    /// step of a request that moved on) are dropped first, so a long transfer does not
    /// wake its owner once more per block, ACK_TIMEOUT after each acknowledgement.
    pub fn poll_timeout(&mut self) -> Option<Instant> {
        while let Some(Reverse((at, _, kind))) = self.timers.peek().copied() {
            if self.timer_is_live(kind) {
                return Some(at);
            }
            self.timers.pop();
        }
        None
    }

    /// Whether firing this timer now would do anything (the handlers' own checks).
    fn timer_is_live(&self, kind: TimerKind) -> bool {
        match kind {
            TimerKind::Retransmit { peer, mid, tx } => self
                .exchanges
                .get(&MidKey(peer, mid))
                .is_some_and(|x| x.tx == tx),
            TimerKind::RequestAck { id, at } => self
                .requests
                .get(&id)
                .is_some_and(|r| r.ack_timer == Some(at)),
            TimerKind::Step { id, generation } => self
                .requests
                .get(&id)
                .is_some_and(|r| r.generation == generation),
            TimerKind::Deadline { id } => self.requests.contains_key(&id),
            TimerKind::SeparateAck { id } => self
                .pending
                .get(&id)
                .is_some_and(|p| !p.acked && p.confirmable),
        }
    }

    /// The next event.
    pub fn poll_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    /// Requests in progress or queued (client side).
    pub fn requests_in_flight(&self) -> usize {
        self.requests.len()
    }

    /// Fires every timer due at `now`.
    pub fn handle_timeout(&mut self, now: Instant) {
        while let Some(Reverse((at, _, kind))) = self.timers.peek().copied() {
            if at > now {
                break;
            }
            self.timers.pop();
            match kind {
                TimerKind::Retransmit { peer, mid, tx } => {
                    self.on_retransmit_timer(now, peer, mid, tx)
                }
                TimerKind::RequestAck { id, at } => self.on_request_ack_timer(now, id, at),
                TimerKind::Step { id, generation } => self.on_step_timer(now, id, generation),
                TimerKind::Deadline { id } => match self.requests.get(&id).map(|r| r.waiting) {
                    Some(Waiting::Collecting) => {
                        self.finish(now, id);
                        self.events
                            .push_back(Event::MulticastDone { id: RequestId(id) });
                    }
                    Some(_) => self.fail(now, id, RequestError::Timeout),
                    None => {}
                },
                TimerKind::SeparateAck { id } => self.on_separate_ack_timer(now, id),
            }
        }
    }

    /// Takes one received datagram. `multicast` says it was addressed to a multicast group
    /// (then no error responses and no Resets are sent, RFC 7390 §2.7).
    pub fn handle(&mut self, now: Instant, peer: SocketAddr, data: &[u8], multicast: bool) {
        let mut msg = Message::empty(Type::Con, 0);
        let payload = match msg.decode_in_place(data) {
            Ok(payload) => payload,
            Err(e) => {
                if let (Reaction::Reset(mid), false) = (Reaction::from(&e), multicast) {
                    self.send(peer, &Message::empty(Type::Rst, mid));
                }
                return;
            }
        };
        match msg.ty {
            // Passed on by reference: a message with its inline options is a few hundred
            // bytes, and each move would copy them. A response's payload stays in the
            // datagram until it is copied where it goes (into a body being reassembled).
            Type::Ack | Type::Rst => self.on_ack_or_reset(now, peer, &mut msg, payload),
            Type::Con if msg.code.is_empty() => {
                // CoAP ping (RFC 7252 §4.3): an empty CON is answered with a Reset.
                if !multicast {
                    self.send(peer, &Message::empty(Type::Rst, msg.message_id));
                }
            }
            Type::Con | Type::Non if msg.code.is_request() => {
                self.on_request(now, peer, msg, payload, multicast);
            }
            Type::Con | Type::Non if msg.code.is_response() => {
                self.on_separate_response(now, peer, &mut msg, payload)
            }
            // An empty NON is a format error (§4.3); unknown code classes are ignored.
            Type::Con | Type::Non => {}
        }
    }

    // ---------------------------------------------------------------- message layer

    fn next_mid(&mut self) -> u16 {
        self.next_mid = self.next_mid.wrapping_add(1);
        self.next_mid
    }

    fn new_id(&mut self) -> u64 {
        self.next_id += 1;
        self.next_id
    }

    fn schedule(&mut self, at: Instant, kind: TimerKind) {
        self.timer_seq += 1;
        self.timers.push(Reverse((at, self.timer_seq, kind)));
    }

    /// ACK_TIMEOUT scaled by a uniform random factor in [1, ACK_RANDOM_FACTOR].
    fn initial_timeout(&mut self) -> Duration {
        let unit = (self.rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        let spread = (self.config.ack_random_factor - 1.0).max(0.0);
        let jitter = self.config.ack_timeout.as_secs_f64() * 1e9 * spread * unit;
        // Whole nanoseconds added, rather than Duration::mul_f64's checked conversion of
        // the product: this runs for every CON of a transfer.
        self.config.ack_timeout + Duration::from_nanos(jitter as u64)
    }

    /// Sends a message that goes out once ([`Outbox::send`]).
    fn send(&mut self, peer: SocketAddr, msg: &Message) {
        self.outbox.send(peer, &msg.outgoing());
    }

    /// Sends a CON that keeps its own encoding for retransmission.
    fn send_con(&mut self, now: Instant, peer: SocketAddr, msg: &Message, purpose: Purpose) {
        let data = Bytes::from(msg.encode());
        self.outbox.queue.push_back(Transmit {
            peer,
            data: data.clone(),
        });
        self.await_ack(now, peer, msg.message_id, purpose, Some(data));
    }

    /// Records a CON just sent and schedules its retransmission (RFC 7252 §4.2). `data`
    /// is what to send again; `None` for a request's step, which is built again.
    fn await_ack(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        mid: u16,
        purpose: Purpose,
        data: Option<Bytes>,
    ) {
        let timeout = self.initial_timeout();
        let at = now + timeout;
        self.exchanges.insert(
            MidKey(peer, mid),
            OutCon {
                data,
                tx: 0,
                timeout,
                at,
                purpose,
            },
        );
        match purpose {
            Purpose::Request(id) => self.arm_request_ack(id, at),
            _ => self.schedule(at, TimerKind::Retransmit { peer, mid, tx: 0 }),
        }
    }

    /// Makes sure the request's ACK timer fires no later than `at`.
    fn arm_request_ack(&mut self, id: u64, at: Instant) {
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if r.ack_timer.is_some_and(|armed| armed <= at) {
            return;
        }
        r.ack_timer = Some(at);
        self.schedule(at, TimerKind::RequestAck { id, at });
    }

    /// The ACK timer of a request: the CON it waits for is sent again if due (RFC 7252
    /// §4.2, the timeout doubling each time), its step fails after MAX_RETRANSMIT; a CON
    /// due later re-arms the timer for then.
    fn on_request_ack_timer(&mut self, now: Instant, id: u64, at: Instant) {
        let max = self.config.max_retransmit;
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if r.ack_timer != Some(at) {
            return;
        }
        r.ack_timer = None;
        let Waiting::Ack(mid) = r.waiting else {
            return;
        };
        let key = MidKey(r.peer, mid);
        let Some(x) = self.exchanges.get_mut(&key) else {
            return;
        };
        if x.at > now {
            let due = x.at;
            self.arm_request_ack(id, due);
        } else if x.tx < max {
            x.tx += 1;
            x.timeout *= 2;
            x.at = now + x.timeout;
            let due = x.at;
            r.send_step(mid, &mut self.outbox);
            self.arm_request_ack(id, due);
        } else {
            self.exchanges.remove(&key);
            self.step_failed(now, id, RequestError::Timeout);
        }
    }

    fn on_retransmit_timer(&mut self, now: Instant, peer: SocketAddr, mid: u16, tx: u8) {
        let max = self.config.max_retransmit;
        let Some(x) = self.exchanges.get_mut(&MidKey(peer, mid)) else {
            return;
        };
        if x.tx != tx {
            return;
        }
        if x.tx < max {
            // RFC 7252 §4.2: retransmit, doubling the timeout each time.
            // Only a request's CON keeps no datagram, and it has no timer of this kind.
            debug_assert!(x.data.is_some(), "a request's CON has its own ACK timer");
            let Some(data) = x.data.clone() else {
                return;
            };
            x.tx += 1;
            x.timeout *= 2;
            x.at = now + x.timeout;
            let (at, tx) = (x.at, x.tx);
            self.outbox.queue.push_back(Transmit { peer, data });
            self.schedule(at, TimerKind::Retransmit { peer, mid, tx });
            return;
        }
        let Some(x) = self.exchanges.remove(&MidKey(peer, mid)) else {
            return;
        };
        match x.purpose {
            Purpose::Request(id) => self.step_failed(now, id, RequestError::Timeout),
            Purpose::Ping(id) => {
                self.events.push_back(Event::RequestFailed {
                    id: RequestId(id),
                    error: RequestError::Timeout,
                });
            }
            Purpose::SeparateResponse => {}
            Purpose::Notification(obs) => self.end_observation(obs),
        }
    }

    fn on_ack_or_reset(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        msg: &mut Message,
        payload: &[u8],
    ) {
        // ACK and RST are matched by message ID only (RFC 7252 §4.2, §4.3); an unknown one
        // is ignored.
        let Some(x) = self.exchanges.remove(&MidKey(peer, msg.message_id)) else {
            if msg.ty == Type::Rst {
                // A Reset to a NON notification ends the observation (RFC 7641 §3.6).
                let obs = self
                    .observations
                    .iter()
                    .find(|(_, o)| o.peer == peer && o.last_mid == Some(msg.message_id));
                if let Some((&id, _)) = obs {
                    self.end_observation(id);
                }
            }
            return;
        };
        match x.purpose {
            Purpose::Ping(id) => self.events.push_back(Event::Pong { id: RequestId(id) }),
            Purpose::SeparateResponse => {}
            Purpose::Notification(obs) => {
                if msg.ty == Type::Rst {
                    self.end_observation(obs);
                }
            }
            Purpose::Request(id) => {
                if msg.ty == Type::Rst {
                    self.fail(now, id, RequestError::Reset);
                } else if msg.code.is_response()
                    && let Some(r) = self.requests.get_mut(&id).filter(|r| r.token == msg.token)
                {
                    // Piggybacked: the exchange ended with this ACK.
                    r.waiting = Waiting::Response {
                        non_tx: None,
                        mid: msg.message_id,
                    };
                    self.on_response(now, id, msg, payload);
                } else {
                    self.on_empty_ack(now, id);
                }
            }
        }
    }

    /// A CON or NON response (not piggybacked).
    fn on_separate_response(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        msg: &mut Message,
        payload: &[u8],
    ) {
        let limits = self.config.limits.clone();
        let known = self.by_token.get(&msg.token).copied();
        if self.replay_duplicate(now, peer, msg, &limits) {
            return;
        }
        let lifetime = if msg.ty == Type::Con {
            self.config.exchange_lifetime
        } else {
            self.config.non_lifetime
        };
        let seen = match (known, msg.ty) {
            // RFC 7252 §5.3.2: a response we cannot match is rejected with a Reset.
            (None, _) => self.reply_with(peer, Message::empty(Type::Rst, msg.message_id)),
            (Some(_), Type::Con) => {
                self.reply_with(peer, Message::empty(Type::Ack, msg.message_id))
            }
            (Some(_), _) => Seen::Silent,
        };
        self.dedup.insert(
            now,
            (peer, msg.message_id),
            Fingerprint::of(msg),
            now + lifetime,
            seen,
            &limits,
        );
        let Some(id) = known else { return };
        match self.requests.get_mut(&id) {
            Some(r) if r.waiting == Waiting::Collecting => {
                let response = take_response(msg, payload);
                self.events.push_back(Event::MulticastResponse {
                    id: RequestId(id),
                    peer,
                    response,
                });
            }
            Some(r) if r.peer != peer => {}
            Some(r) => {
                if let Waiting::Observing(last) = r.waiting {
                    let seq = msg.options.uint(OptionNumber::OBSERVE);
                    // RFC 7641 §3.4: deliver only notifications newer than the last one.
                    if let Some(seq) = seq.filter(|v| is_newer(last, *v)) {
                        r.waiting = Waiting::Observing(seq);
                        let response = take_response(msg, payload);
                        self.events.push_back(Event::Notification {
                            id: RequestId(id),
                            response,
                        });
                    } else if seq.is_none() {
                        // A final response without Observe ends the observation (§3.2).
                        let response = take_response(msg, payload);
                        self.finish(now, id);
                        self.events.push_back(Event::Notification {
                            id: RequestId(id),
                            response,
                        });
                    }
                    return;
                }
                self.on_response(now, id, msg, payload);
            }
            None => {}
        }
    }

    // ---------------------------------------------------------------- client layer

    /// Starts a request to `peer`. The outcome arrives as [`Event::Response`] or
    /// [`Event::RequestFailed`] with the returned id.
    pub fn request(&mut self, now: Instant, peer: SocketAddr, req: Request) -> RequestId {
        let id = self.new_id();
        let token = self.new_token();
        let szx1 = req
            .block_szx
            .unwrap_or(self.config.max_block_szx)
            .min(self.config.max_block_szx);
        let user_block2 = req.options.contains(OptionNumber::BLOCK2);
        let observe = req.options.uint(OptionNumber::OBSERVE) == Some(0);
        let mut req = req;
        if req.multicast {
            req.confirmable = false;
            req.timeout = Some(req.timeout.unwrap_or(Duration::from_secs(5)));
        }
        if let Some(t) = req.timeout {
            self.schedule(now + t, TimerKind::Deadline { id });
        }
        let step = if req.payload.len() > BlockOpt::size_of(szx1) {
            Step::Upload { offset: 0 }
        } else {
            Step::Whole
        };
        self.requests.insert(
            id,
            ClientRequest {
                peer,
                req,
                token,
                szx1,
                step,
                waiting: Waiting::Queued,
                generation: 0,
                failures: 0,
                restarts: 0,
                body: Vec::new(),
                received: 0,
                etag: None,
                first_options: None,
                user_block2,
                observe,
                ack_timer: None,
                block_head: None,
            },
        );
        self.by_token.insert(token, id);
        self.peers
            .entry(PeerKey(peer))
            .or_default()
            .queue
            .push_back(id);
        self.pump(now, peer);
        RequestId(id)
    }

    /// Sends a CoAP ping (an empty CON, RFC 7252 §4.3): [`Event::Pong`] when the peer
    /// answers with a Reset, [`Event::RequestFailed`] after MAX_RETRANSMIT.
    pub fn ping(&mut self, now: Instant, peer: SocketAddr) -> RequestId {
        let id = self.new_id();
        let mid = self.next_mid();
        self.send_con(
            now,
            peer,
            &Message::empty(Type::Con, mid),
            Purpose::Ping(id),
        );
        RequestId(id)
    }

    /// Abandons a request; [`Event::RequestFailed`] with [`RequestError::Cancelled`]
    /// follows if it was still running.
    pub fn cancel(&mut self, now: Instant, id: RequestId) {
        if self.requests.contains_key(&id.0) {
            self.fail(now, id.0, RequestError::Cancelled);
        }
    }

    fn new_token(&mut self) -> Token {
        let len = self.config.token_len.min(8);
        loop {
            let bytes = self.rng.next_u64().to_be_bytes();
            // NOTE(unwrap): len <= 8.
            let token = Token::new(&bytes[..len]).unwrap_or_default();
            if len == 0 || !self.by_token.contains_key(&token) {
                return token;
            }
        }
    }

    /// Starts queued requests while the peer has fewer than NSTART outstanding.
    fn pump(&mut self, now: Instant, peer: SocketAddr) {
        let nstart = self.config.nstart.max(1);
        loop {
            let Some(p) = self.peers.get_mut(&PeerKey(peer)) else {
                return;
            };
            if p.active >= nstart {
                return;
            }
            let Some(id) = p.queue.pop_front() else {
                if p.active == 0 {
                    self.peers.remove(&PeerKey(peer));
                }
                return;
            };
            p.active += 1;
            self.send_step(now, id);
        }
    }

    fn send_step(&mut self, now: Instant, id: u64) {
        let mid = self.next_mid();
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        r.send_step(mid, &mut self.outbox);
        r.generation += 1;
        let (peer, generation) = (r.peer, r.generation);
        if r.req.multicast {
            // RFC 7390 §2.5: sent once, responses collected until the deadline.
            r.waiting = Waiting::Collecting;
        } else if r.req.confirmable {
            r.waiting = Waiting::Ack(mid);
            self.await_ack(now, peer, mid, Purpose::Request(id), None);
        } else {
            r.waiting = Waiting::Response {
                non_tx: Some(0),
                mid,
            };
            let t = self.initial_timeout();
            self.schedule(now + t, TimerKind::Step { id, generation });
        }
    }

    fn on_empty_ack(&mut self, now: Instant, id: u64) {
        let timeout = self.config.response_timeout;
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if let Waiting::Ack(mid) = r.waiting {
            r.waiting = Waiting::Response { non_tx: None, mid };
            r.generation += 1;
            let generation = r.generation;
            self.schedule(now + timeout, TimerKind::Step { id, generation });
        }
    }

    fn on_step_timer(&mut self, now: Instant, id: u64, generation: u32) {
        let max = self.config.max_retransmit;
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if r.generation != generation {
            return;
        }
        match r.waiting {
            Waiting::Response {
                non_tx: Some(tx), ..
            } if tx < max => {
                // A NON request gets no ACK; resend it (new message ID, same token) on
                // the same back-off schedule a CON would use.
                let mid = self.next_mid();
                let Some(r) = self.requests.get_mut(&id) else {
                    return;
                };
                r.send_step(mid, &mut self.outbox);
                r.waiting = Waiting::Response {
                    non_tx: Some(tx + 1),
                    mid,
                };
                let t = self.initial_timeout() * (1u32 << (tx + 1));
                self.schedule(now + t, TimerKind::Step { id, generation });
            }
            _ => self.step_failed(now, id, RequestError::Timeout),
        }
    }

    /// One exchange failed. A block-wise step is resumed (the same block again) up to
    /// `block_retries` consecutive times; anything else fails the request.
    fn step_failed(&mut self, now: Instant, id: u64, error: RequestError) {
        let retries = self.config.block_retries;
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if r.step_has_block_option() && r.failures < retries {
            r.failures += 1;
            self.send_step(now, id);
        } else {
            self.fail(now, id, error);
        }
    }

    fn fail(&mut self, now: Instant, id: u64, error: RequestError) {
        self.finish(now, id);
        self.events.push_back(Event::RequestFailed {
            id: RequestId(id),
            error,
        });
    }

    /// Removes a finished request and frees its NSTART slot.
    fn finish(&mut self, now: Instant, id: u64) {
        let Some(r) = self.requests.remove(&id) else {
            return;
        };
        self.by_token.remove(&r.token);
        match r.waiting {
            Waiting::Ack(mid) => {
                self.exchanges.remove(&MidKey(r.peer, mid));
            }
            Waiting::Queued => {
                if let Some(p) = self.peers.get_mut(&PeerKey(r.peer)) {
                    p.queue.retain(|q| *q != id);
                }
                return;
            }
            // An observation gave its NSTART slot back when it was established.
            Waiting::Observing(_) => return,
            Waiting::Response { .. } | Waiting::Collecting => {}
        }
        self.release_slot(now, r.peer);
    }

    fn release_slot(&mut self, now: Instant, peer: SocketAddr) {
        if let Some(p) = self.peers.get_mut(&PeerKey(peer)) {
            p.active = p.active.saturating_sub(1);
        }
        self.pump(now, peer);
    }

    /// Delivers the final response of a request. An Observe registration that the server
    /// accepted (a success carrying Observe) stays alive for its notifications and frees
    /// its NSTART slot; anything else is finished.
    fn complete(&mut self, now: Instant, id: u64, response: Response) {
        let seq = response.options.uint(OptionNumber::OBSERVE);
        let observing = self.requests.get_mut(&id).and_then(|r| {
            let seq = seq.filter(|_| r.observe && response.code.is_success())?;
            r.waiting = Waiting::Observing(seq);
            Some(r.peer)
        });
        match observing {
            Some(peer) => self.release_slot(now, peer),
            None => self.finish(now, id),
        }
        self.events.push_back(Event::Response {
            id: RequestId(id),
            response,
        });
    }

    /// A response (piggybacked or separate) matched to request `id` by token.
    fn on_response(&mut self, now: Instant, id: u64, msg: &mut Message, payload: &[u8]) {
        let limit = self.config.limits.client_body_bytes;
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        // Is it the answer to the step in flight? Late answers to earlier steps are dropped.
        let current = match r.step {
            Step::Upload { offset } => msg
                .options
                .block1()
                .is_none_or(|b| b.num as usize == offset / BlockOpt::size_of(r.szx1)),
            Step::Download { num, .. } => msg.options.block2().is_none_or(|b| b.num == num),
            Step::Whole => true,
        };
        if !current || r.waiting == Waiting::Queued {
            if !current && msg.ty == Type::Ack {
                // The ACK of the step's own CON answers another block: that exchange is
                // over, so the block is asked for again rather than waited for.
                return self.step_failed(
                    now,
                    id,
                    RequestError::Protocol("the response is for another block"),
                );
            }
            return;
        }
        // A separate response also acknowledges the request (RFC 7252 §5.2.2).
        if let Waiting::Ack(mid) = r.waiting {
            self.exchanges.remove(&MidKey(r.peer, mid));
        }
        r.generation += 1;
        r.failures = 0;

        if let Step::Upload { offset } = r.step {
            let size = BlockOpt::size_of(r.szx1);
            let sent_end = (offset + size).min(r.req.payload.len());
            if msg.code == Code::CONTINUE {
                let Some(b1) = msg.options.block1() else {
                    return self.fail(
                        now,
                        id,
                        RequestError::Protocol("2.31 Continue without Block1"),
                    );
                };
                if sent_end >= r.req.payload.len() {
                    return self.fail(
                        now,
                        id,
                        RequestError::Protocol("2.31 Continue after the last block"),
                    );
                }
                // RFC 7959 §2.3: continue with the server's block size if it is smaller;
                // the offset stays, so the block number scales.
                r.szx1 = r.szx1.min(b1.szx);
                r.step = Step::Upload { offset: sent_end };
                if r.req.progress && offset >> 16 != sent_end >> 16 {
                    let total = Some(r.req.payload.len());
                    self.events.push_back(Event::Progress {
                        id: RequestId(id),
                        done: sent_end,
                        total,
                    });
                }
                return self.send_step(now, id);
            }
            if msg.code == Code::REQUEST_ENTITY_TOO_LARGE
                && let Some(b1) = msg
                    .options
                    .block1()
                    .filter(|b| b.szx < r.szx1 && r.restarts < 4)
            {
                // RFC 7959 §2.9.3: the server wants smaller blocks; start over with them.
                r.restarts += 1;
                r.szx1 = b1.szx;
                r.step = Step::Upload { offset: 0 };
                return self.send_step(now, id);
            }
        } else if r.step == Step::Whole
            && msg.code == Code::REQUEST_ENTITY_TOO_LARGE
            && !r.req.payload.is_empty()
            && let Some(b1) = msg.options.block1().filter(|_| r.restarts < 4)
        {
            // The body fit one message but not the server: go block-wise at its size.
            r.restarts += 1;
            r.szx1 = b1.szx.min(r.szx1);
            r.step = Step::Upload { offset: 0 };
            return self.send_step(now, id);
        }

        // The request is fully sent; now the response, possibly in blocks.
        let b2 = msg
            .options
            .block2()
            .filter(|_| !r.user_block2 && msg.code.is_success());
        let Some(b2) = b2 else {
            if r.first_options.take().is_some() {
                // Reassembly ended with a block lacking Block2: a broken server.
                return self.fail(
                    now,
                    id,
                    RequestError::Protocol("block-wise response lost its Block2"),
                );
            }
            let mut response = take_response(msg, payload);
            if r.req.stream && response.code.is_success() && !response.payload.is_empty() {
                let data = std::mem::take(&mut response.payload);
                self.events.push_back(Event::BodyChunk {
                    id: RequestId(id),
                    offset: 0,
                    total: Some(data.len()),
                    data,
                });
            }
            return self.complete(now, id, response);
        };
        if r.first_options.is_some() && msg.options.etag() != r.etag.as_deref() {
            // RFC 7959 §2.4: the representation changed. Streamed pieces cannot be taken
            // back, so a streamed request fails; a reassembled one starts over, a few
            // times at most.
            if r.restarts >= 4 || r.req.stream {
                return self.fail(now, id, RequestError::RepresentationChanged);
            }
            r.restarts += 1;
            r.body.clear();
            r.received = 0;
            r.first_options = None;
            r.step = Step::Download {
                num: 0,
                szx: b2.szx,
            };
            return self.send_step(now, id);
        }
        if r.first_options.is_none() {
            if b2.num != 0 {
                return self.fail(
                    now,
                    id,
                    RequestError::Protocol("first Block2 response is not block 0"),
                );
            }
            let mut first = msg.options.clone();
            first.remove(OptionNumber::BLOCK2);
            r.etag = msg.options.etag().map(<[u8]>::to_vec);
            // Room for the first piece of a streamed body, or for the whole body Size2
            // announced (bounded by the limit), not regrown block by block.
            let room = if r.req.stream {
                if b2.more { STREAM_PIECE + b2.size() } else { 0 }
            } else {
                msg.options
                    .uint(OptionNumber::SIZE2)
                    .map_or(0, |size2| (size2 as usize).min(limit))
            };
            r.body.reserve(room);
            r.first_options = Some(first);
        }
        if b2.offset() != r.received {
            // A block we did not ask for at this offset: ask again for the one we lack.
            let size = b2.size();
            r.step = Step::Download {
                num: (r.received / size) as u32,
                szx: b2.szx,
            };
            return self.send_step(now, id);
        }
        if r.received + payload.len() > limit {
            return self.fail(now, id, RequestError::TooLarge { limit });
        }
        if b2.more && payload.len() != b2.size() {
            return self.fail(
                now,
                id,
                RequestError::Protocol("Block2 payload size does not match SZX"),
            );
        }
        let total = r
            .first_options
            .as_ref()
            .and_then(|o| o.uint(OptionNumber::SIZE2))
            .map(|v| v as usize);
        let (stream, progress) = (r.req.stream, r.req.progress);
        let before = r.received;
        r.received += payload.len();
        let done = r.received;
        if stream && !b2.more && total.is_some_and(|t| t != done) {
            return self.fail(
                now,
                id,
                RequestError::Protocol("the body does not have the size Size2 announced"),
            );
        }
        r.body.extend_from_slice(payload);
        // A streamed body leaves in pieces of STREAM_PIECE bytes (and the rest at the end):
        // one hand-over to the reader per piece, not per block.
        if stream && (r.body.len() >= STREAM_PIECE || !b2.more) {
            // The next piece gets its room at once rather than growing block by block.
            let room = if b2.more { STREAM_PIECE + b2.size() } else { 0 };
            let data = Bytes::from(std::mem::replace(&mut r.body, Vec::with_capacity(room)));
            self.events.push_back(Event::BodyChunk {
                id: RequestId(id),
                offset: done - data.len(),
                data,
                total,
            });
        }
        // Progress at most every 64 KiB (and at the end), so watching costs nothing.
        if progress && (before >> 16 != done >> 16 || !b2.more) {
            self.events.push_back(Event::Progress {
                id: RequestId(id),
                done,
                total,
            });
        }
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if b2.more {
            let num = (r.received / b2.size()) as u32;
            r.step = Step::Download { num, szx: b2.szx };
            return self.send_step(now, id);
        }
        let body = Bytes::from(std::mem::take(&mut r.body));
        let options = r.first_options.take().unwrap_or_default();
        let response = Response::with_parts(msg.code, options, body);
        self.complete(now, id, response);
    }

    // ---------------------------------------------------------------- server layer

    /// A request; its `payload` stays in the datagram until it is copied where it goes
    /// (an upload's block into the body being assembled).
    fn on_request(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        mut msg: Message,
        payload: &[u8],
        multicast: bool,
    ) {
        let limits = self.config.limits.clone();
        let con = msg.ty == Type::Con;
        let block2 = msg.options.block2();
        let block1 = msg.options.block1();
        // A Block2 continuation is looked up in the store before deduplication: the store
        // answers a duplicate just as well, and the message ID of a long transfer's
        // continuation may come round again to that of its first block, whose reply the
        // dedup store keeps (the token is the same).
        let continuation = matches!((block2, block1), (Some(b2), None) if b2.num > 0);
        if !continuation && self.replay_duplicate(now, peer, &msg, &limits) {
            return;
        }
        let lifetime = if con {
            self.config.exchange_lifetime
        } else {
            self.config.non_lifetime
        };
        let expires = now + lifetime;

        if let Some(bad) = msg.options.first_bad_critical() {
            if continuation && self.replay_duplicate(now, peer, &msg, &limits) {
                return;
            }
            // RFC 7252 §5.4.1: 4.02 for a CON request; a NON one is rejected.
            let seen = if con {
                let text = format!("unrecognized or malformed critical option {}", bad.0);
                self.reply(
                    peer,
                    &msg,
                    multicast,
                    Response::diagnostic(Code::BAD_OPTION, &text),
                )
            } else if multicast {
                Seen::Silent
            } else {
                self.reply_with(peer, Message::empty(Type::Rst, msg.message_id))
            };
            self.dedup.insert(
                now,
                (peer, msg.message_id),
                Fingerprint::of(&msg),
                expires,
                seen,
                &limits,
            );
            return;
        }
        msg.options.drop_bad_elective();
        let key = BlockKey {
            peer,
            method: msg.code,
            options: msg.options.block_key(),
        };

        // A Block2 continuation is served from the stored representation; the application
        // never sees it (a POST grab must not grab again).
        if let (Some(b2), true) = (block2, continuation) {
            // A GET falls through when nothing is stored: it is safe, so the application
            // renders it again and the block is cut from the new representation (its ETag
            // tells the client whether the blocks still fit).
            let szx = b2.szx.min(self.config.max_block_szx);
            let (ty, mid) = self.reply_header(&msg);
            let stored = self.block2.with_stored(now, &key, &limits, |s| {
                let slice = block::slice(&*s.body.0, b2.num, szx);
                if let Slice::Block(payload, opt) = &slice {
                    // The block goes out as the stored options, encoded once, around this
                    // Block2.
                    let header = (ty, s.code, mid, msg.token);
                    self.outbox.send_with(peer, payload.len(), |out| {
                        s.head.encode_into(out, header, opt.as_uint(), payload);
                    });
                }
                slice
            });
            match stored {
                // Served from the store, which is idempotent (RFC 7252 §4.5 allows
                // relaxing deduplication then): a duplicate is cut again from the same
                // bytes, and a 10 MB transfer leaves no 10,000 dedup entries behind.
                Some(Slice::Block(..)) => return,
                // RFC 7959 §2.2: a block past the end is a bad option.
                Some(Slice::PastEnd) => {
                    if let Some(reply) = self.reply_message(&msg, multicast, past_end()) {
                        self.send(peer, &reply);
                    }
                    return;
                }
                // The stored source can no longer be read as it was: as if nothing were
                // stored.
                Some(Slice::Unreadable) => self.block2.remove(&key),
                None => {}
            }
            if self.replay_duplicate(now, peer, &msg, &limits) {
                return;
            }
            if !matches!(msg.code, Code::GET | Code::FETCH) {
                let response = Response::diagnostic(
                    Code::REQUEST_ENTITY_INCOMPLETE,
                    "the representation is no longer stored; repeat the request from block 0",
                );
                self.answer(now, peer, &msg, multicast, expires, response);
                return;
            }
        }

        let mut assembled = None;
        let mut block1_echo = None;
        if let Some(b1) = block1 {
            let size1 = msg.options.uint(OptionNumber::SIZE1);
            let outcome = self
                .block1
                .handle(now, key.clone(), b1, size1, payload, &self.config);
            let response = match outcome {
                Block1Outcome::Continue(opt) => {
                    let mut r = Response::new(Code::CONTINUE);
                    r.options.set_block(OptionNumber::BLOCK1, opt);
                    Some(r)
                }
                Block1Outcome::Refuse {
                    code,
                    diagnostic,
                    size1,
                } => {
                    let mut r = Response::diagnostic(code, diagnostic);
                    if let Some(s) = size1 {
                        r.options.set_uint(OptionNumber::SIZE1, s);
                    }
                    if code == Code::SERVICE_UNAVAILABLE {
                        r.options.set_uint(OptionNumber::MAX_AGE, 5);
                    }
                    Some(r)
                }
                Block1Outcome::Complete(body, echo) => {
                    assembled = Some(body);
                    block1_echo = Some(echo);
                    None
                }
            };
            if let Some(response) = response {
                self.answer(now, peer, &msg, multicast, expires, response);
                return;
            }
        }

        if self.pending.len() >= limits.pending_requests {
            let r = Response::diagnostic(Code::SERVICE_UNAVAILABLE, "server busy");
            self.answer(now, peer, &msg, multicast, expires, r);
            return;
        }
        let id = self.new_id();
        let observation = self.observe_option(peer, &msg, &key);
        self.pending.insert(
            id,
            Pending {
                peer,
                mid: msg.message_id,
                token: msg.token,
                confirmable: con,
                acked: false,
                multicast,
                block2,
                block1_echo,
                key,
                observation,
            },
        );
        self.dedup.insert(
            now,
            (peer, msg.message_id),
            Fingerprint::of(&msg),
            expires,
            Seen::Pending(id),
            &limits,
        );
        if con {
            self.schedule(
                now + self.config.separate_ack_delay,
                TimerKind::SeparateAck { id },
            );
        }
        self.events.push_back(Event::Request(IncomingRequest {
            id: IncomingId(id),
            peer,
            method: msg.code,
            options: msg.options,
            payload: assembled.unwrap_or_else(|| Bytes::copy_from_slice(payload)),
            multicast,
            confirmable: con,
            observe: observation.map(ObservationId),
        }));
    }

    /// Answers a duplicate message as the first one was answered (RFC 7252 §4.5); whether
    /// `msg` was one.
    fn replay_duplicate(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        msg: &Message,
        limits: &Limits,
    ) -> bool {
        let Some(seen) = self
            .dedup
            .check(now, peer, msg.message_id, Fingerprint::of(msg), limits)
        else {
            return false;
        };
        match seen.clone() {
            Seen::Replied(m) => self.send(peer, &m),
            Seen::Pending(id) if msg.ty == Type::Con => self.ack_pending(id),
            Seen::Pending(_) | Seen::Silent => {}
        }
        true
    }

    /// RFC 7641 §2, §3.6: a GET or FETCH with Observe 0 registers (or re-registers, same
    /// peer and token) an observation; Observe 1 deregisters.
    fn observe_option(&mut self, peer: SocketAddr, msg: &Message, key: &BlockKey) -> Option<u64> {
        if !matches!(msg.code, Code::GET | Code::FETCH) {
            return None;
        }
        let value = msg.options.uint(OptionNumber::OBSERVE)?;
        let existing = self
            .observations
            .iter()
            .find(|(_, o)| o.peer == peer && o.token == msg.token)
            .map(|(id, _)| *id);
        match (value, existing) {
            (0, Some(id)) => Some(id),
            (0, None) if self.observations.len() < self.config.limits.observations => {
                let id = self.new_id();
                let o = Observation {
                    peer,
                    token: msg.token,
                    key: key.clone(),
                    established: false,
                    seq: 0,
                    sent: 0,
                    last_mid: None,
                };
                self.observations.insert(id, o);
                Some(id)
            }
            (1, Some(id)) => {
                self.end_observation(id);
                None
            }
            _ => None,
        }
    }

    fn end_observation(&mut self, id: u64) {
        if self.observations.remove(&id).is_some() {
            self.events.push_back(Event::ObservationEnded {
                id: ObservationId(id),
            });
        }
    }

    /// Sends a notification to an established observation (RFC 7641 §4.2): the Observe
    /// sequence number goes up by one, every `notify_con_interval`-th notification is a CON
    /// (§4.5), and a body larger than one block goes out as Block2 block 0 with the rest
    /// kept for the client's continuations (RFC 7959 §2.6). A non-success response ends
    /// the observation. Returns false when the observation no longer exists, so the
    /// application can forget it.
    pub fn notify(&mut self, now: Instant, id: ObservationId, response: Response) -> bool {
        let limits = self.config.limits.clone();
        let interval = self.config.notify_con_interval;
        let szx = self.config.max_block_szx;
        let Some(o) = self.observations.get_mut(&id.0).filter(|o| o.established) else {
            return false;
        };
        o.seq = (o.seq + 1) & 0x00ff_ffff;
        o.sent += 1;
        let con = interval > 0 && o.sent % interval == 0;
        let (peer, token, key, seq) = (o.peer, o.token, o.key.clone(), o.seq);
        let mut response = self.blockwise_response(now, key, None, response, &limits, szx);
        let success = response.code.is_success();
        if success {
            response.options.set_uint(OptionNumber::OBSERVE, seq);
        }
        let ty = if con { Type::Con } else { Type::Non };
        let msg = Message {
            ty,
            code: response.code,
            message_id: self.next_mid(),
            token,
            options: response.options,
            payload: response.payload,
        };
        if con {
            self.send_con(now, peer, &msg, Purpose::Notification(id.0));
        } else {
            self.send(peer, &msg);
            if let Some(o) = self.observations.get_mut(&id.0) {
                o.last_mid = Some(msg.message_id);
            }
        }
        if !success {
            self.end_observation(id.0);
        }
        true
    }

    /// Cuts a response into its first (or requested) block when it does not fit one, adding
    /// an ETag and storing the representation for the continuations.
    fn blockwise_response(
        &mut self,
        now: Instant,
        key: BlockKey,
        block2: Option<BlockOpt>,
        mut response: Response,
        limits: &Limits,
        max_szx: u8,
    ) -> Response {
        let szx = block2.map_or(max_szx, |b| b.szx.min(max_szx));
        let num = block2.map_or(0, |b| b.num);
        let body = match response.source.take() {
            Some(source) => source,
            None if response.payload.len() <= BlockOpt::size_of(szx) && num == 0 => {
                return response;
            }
            None => Source::new(std::mem::take(&mut response.payload)),
        };
        let len = body.0.len();
        if len <= BlockOpt::size_of(szx) && num == 0 {
            return match body.0.read(0..len) {
                Some(payload) => response.with_payload(payload),
                None => unreadable(),
            };
        }
        // Block numbers have 20 bits (RFC 7959 §2.2) and Size2 at most 4 bytes.
        if len > BlockOpt::size_of(szx) << 20 || u32::try_from(len).is_err() {
            return Response::diagnostic(
                Code::INTERNAL_SERVER_ERROR,
                "the representation is too large for block-wise transfer at this block size",
            );
        }
        if response.options.etag().is_none() {
            let etag = self.rng.next_u32().to_be_bytes();
            response.options.set(OptionNumber::ETAG, etag);
        }
        let Some(mut block) =
            block2_response(response.code, response.options.clone(), &body, num, szx)
        else {
            return unreadable();
        };
        if len > BlockOpt::size_of(szx) {
            self.block2
                .insert(now, key, response.code, response.options, body, limits);
        }
        // The reply is remembered for duplicates for EXCHANGE_LIFETIME; a slice would keep
        // the whole representation (or a source's read-ahead window) alive that long.
        block.payload = Bytes::copy_from_slice(&block.payload);
        block
    }

    /// Answers a request at once and remembers the answer for its duplicates.
    fn answer(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        req: &Message,
        multicast: bool,
        expires: Instant,
        response: Response,
    ) {
        let seen = self.reply(peer, req, multicast, response);
        let limits = &self.config.limits;
        self.dedup.insert(
            now,
            (peer, req.message_id),
            Fingerprint::of(req),
            expires,
            seen,
            limits,
        );
    }

    /// Sends a response to a request right away (piggybacked on the ACK of a CON, or as a
    /// NON to a NON) and returns what to remember for duplicates. Error responses to
    /// multicast requests are suppressed (RFC 7390 §2.7).
    fn reply(
        &mut self,
        peer: SocketAddr,
        req: &Message,
        multicast: bool,
        response: Response,
    ) -> Seen {
        match self.reply_message(req, multicast, response) {
            Some(msg) => self.reply_with(peer, msg),
            None => Seen::Silent,
        }
    }

    /// The type and message ID of a reply to `req`: a piggybacked ACK to a CON, a NON
    /// with a new message ID otherwise.
    fn reply_header(&mut self, req: &Message) -> (Type, u16) {
        match req.ty {
            Type::Con => (Type::Ack, req.message_id),
            _ => (Type::Non, self.next_mid()),
        }
    }

    /// The message that answers `req` right away; `None` when nothing is sent (an error
    /// response to a multicast request).
    fn reply_message(
        &mut self,
        req: &Message,
        multicast: bool,
        response: Response,
    ) -> Option<Message> {
        if multicast && response.code.is_error() {
            return None;
        }
        let (ty, mid) = self.reply_header(req);
        let msg = Message {
            ty,
            code: response.code,
            message_id: mid,
            token: req.token,
            options: response.options,
            payload: response.payload,
        };
        Some(msg)
    }

    /// Sends a reply and keeps the message (not its encoding, which shares a chunk with
    /// other messages) to send again for duplicates.
    fn reply_with(&mut self, peer: SocketAddr, msg: Message) -> Seen {
        self.send(peer, &msg);
        Seen::Replied(Box::new(msg))
    }

    fn on_separate_ack_timer(&mut self, _now: Instant, id: u64) {
        self.ack_pending(id);
    }

    /// Sends the empty ACK of a CON request whose response is not ready (RFC 7252 §5.2.2).
    fn ack_pending(&mut self, id: u64) {
        let Some(p) = self.pending.get_mut(&id) else {
            return;
        };
        if p.acked || !p.confirmable {
            return;
        }
        p.acked = true;
        let (peer, mid) = (p.peer, p.mid);
        let seen = self.reply_with(peer, Message::empty(Type::Ack, mid));
        self.dedup.set_reply(peer, mid, seen);
    }

    /// Answers a request from [`Event::Request`]. A body larger than one block is stored
    /// and sent with Block2 (ETag and Size2 added); later blocks are served from the store.
    /// Answering an unknown or already answered id does nothing.
    pub fn respond(&mut self, now: Instant, id: IncomingId, response: Response) {
        let limits = self.config.limits.clone();
        let Some(p) = self.pending.remove(&id.0) else {
            return;
        };
        let max_szx = self.config.max_block_szx;
        let mut response =
            self.blockwise_response(now, p.key.clone(), p.block2, response, &limits, max_szx);
        if let Some(obs) = p.observation {
            match self.observations.get_mut(&obs) {
                Some(o)
                    if response.code.is_success()
                        && response.options.contains(OptionNumber::OBSERVE) =>
                {
                    o.established = true;
                    o.seq = (o.seq + 1) & 0x00ff_ffff;
                    response.options.set_uint(OptionNumber::OBSERVE, o.seq);
                }
                _ => self.end_observation(obs),
            }
        }
        if let Some(echo) = p.block1_echo {
            response.options.set_block(OptionNumber::BLOCK1, echo);
        }
        if p.multicast && response.code.is_error() {
            self.dedup.set_reply(p.peer, p.mid, Seen::Silent);
            return;
        }
        let (ty, mid) = match (p.confirmable, p.acked) {
            (true, false) => (Type::Ack, p.mid),
            (true, true) => (Type::Con, self.next_mid()),
            (false, _) => (Type::Non, self.next_mid()),
        };
        let msg = Message {
            ty,
            code: response.code,
            message_id: mid,
            token: p.token,
            options: response.options,
            payload: response.payload,
        };
        if ty == Type::Con {
            self.send_con(now, p.peer, &msg, Purpose::SeparateResponse);
        } else {
            let seen = self.reply_with(p.peer, msg);
            self.dedup.set_reply(p.peer, p.mid, seen);
        }
    }
}

/// Block `num` of a representation as a response, with Block2, and Size2 on block 0
/// (RFC 7959 §4); 4.02 when the block starts past the end; `None` when the body's source
/// could not be read.
fn block2_response(
    code: Code,
    options: Options,
    body: &Source,
    num: u32,
    szx: u8,
) -> Option<Response> {
    let (payload, opt) = match block::slice(&*body.0, num, szx) {
        Slice::Block(payload, opt) => (payload, opt),
        Slice::PastEnd => return Some(past_end()),
        Slice::Unreadable => return None,
    };
    let mut options = options;
    options.set_block(OptionNumber::BLOCK2, opt);
    if num == 0 {
        options.set_uint(OptionNumber::SIZE2, body.0.len() as u32);
    }
    Some(Response::with_parts(code, options, payload))
}

/// A received response: the code and options taken out of its message, and a copy of
/// its payload.
fn take_response(msg: &mut Message, payload: &[u8]) -> Response {
    let options = std::mem::take(&mut msg.options);
    Response::with_parts(msg.code, options, Bytes::copy_from_slice(payload))
}

/// The answer to a block that starts past the end of the body (RFC 7959 §2.2).
fn past_end() -> Response {
    Response::diagnostic(
        Code::BAD_OPTION,
        "Block2 number beyond the end of the representation",
    )
}

/// The answer when a body's source cannot be read as it was (the file is changing): try
/// again in a second (RFC 7252 §5.9.3.4).
fn unreadable() -> Response {
    let mut r = Response::diagnostic(
        Code::SERVICE_UNAVAILABLE,
        "the representation changed while it was read; try again",
    );
    r.options.set_uint(OptionNumber::MAX_AGE, 1);
    r
}

/// RFC 7641 §3.4: whether Observe value `v2` is newer than `v1` (24-bit serial arithmetic).
fn is_newer(v1: u32, v2: u32) -> bool {
    const HALF: u32 = 1 << 23;
    (v1 < v2 && v2 - v1 < HALF) || (v1 > v2 && v1 - v2 > HALF)
}
