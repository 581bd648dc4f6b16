//! Transmission parameters (RFC 7252 §4.8) and the limits on every piece of state that
//! input can grow. Every value is configurable; the defaults are the RFC's.

use std::time::Duration;

/// RFC 7252 §4.8 transmission parameters plus coapcam's resource limits.
#[derive(Debug, Clone)]
pub struct EndpointConfig {
    /// ACK_TIMEOUT: the initial retransmission timeout before jitter (RFC 7252: 2 s).
    pub ack_timeout: Duration,
    /// ACK_RANDOM_FACTOR: the initial timeout is `ack_timeout * U[1, factor]` (RFC: 1.5).
    pub ack_random_factor: f64,
    /// MAX_RETRANSMIT: retransmissions after the first transmission (RFC: 4).
    pub max_retransmit: u8,
    /// NSTART: outstanding interactions per peer (RFC: 1).
    pub nstart: usize,
    /// EXCHANGE_LIFETIME: how long a CON message ID is remembered (RFC: 247 s).
    pub exchange_lifetime: Duration,
    /// NON_LIFETIME: how long a NON message ID is remembered (RFC: 145 s).
    pub non_lifetime: Duration,
    /// How long a client waits for a separate response after an empty ACK, and for the
    /// response to a NON request before resending it. Default MAX_TRANSMIT_WAIT (93 s).
    pub response_timeout: Duration,
    /// How long the server waits for the application's response before it sends an empty
    /// ACK and answers separately (RFC 7252 §5.2.2). Default 1 s, well inside ACK_TIMEOUT.
    pub separate_ack_delay: Duration,
    /// Token length for new requests, 0-8 bytes.
    pub token_len: usize,
    /// Seed of the endpoint's random generator (message IDs, tokens, jitter, ETags).
    pub rng_seed: u64,
    /// Largest block size exponent this endpoint sends or asks for (6 = 1024 bytes).
    pub max_block_szx: u8,
    /// Consecutive failed exchanges of one block (or one block-wise step) after which a
    /// block-wise transfer gives up. Each resume sends the block the transfer lacks again,
    /// never restarts from the beginning.
    pub block_retries: u8,
    /// Every this many notifications of an observation, one is sent as CON to learn
    /// whether the client is still there (RFC 7641 §4.5); 0 sends only NON.
    pub notify_con_interval: u32,
    /// How requests fetch responses that come in blocks, unless a request says
    /// ([`Request::transfer`](crate::Request::transfer)); windowed by default.
    pub transfer: Transfer,
    /// The congestion controller of each peer's windowed transfers: BBR by default.
    pub congestion: Congestion,
    /// Whether each path's congestion controller records every round trip (rate samples,
    /// app-limited marks, pacing rate, window, requests in flight, late sends), for
    /// [`Endpoint::poll_round_trace`](crate::Endpoint::poll_round_trace). Off by default:
    /// then nothing is recorded.
    pub trace_congestion: bool,
    /// MAX_PAYLOADS (RFC 9177 §7.2): the payloads of a Q-Block body sent in one burst,
    /// one *set*, before the sender waits for the receiver's 'Continue' (RFC: 10; both
    /// ends must use the same value).
    pub max_payloads: u32,
    /// RFC 9175 §2.4 amplification mitigation: a peer not on loopback whose address is
    /// not verified gets at most three times what it sent. Its unicast requests get an
    /// Echo challenge (4.01) before any work; a GET or FETCH it sent to a group is worked
    /// on (within [`Limits::unverified_group_work`]) and answered if the answer fits
    /// that budget in one block, silently if it is an error, else with the challenge.
    /// On by default.
    pub verify_addresses: bool,
    /// Leisure (RFC 7252 §8.2, RFC 7390 §2.5): the answer to a multicast request leaves
    /// at a random instant within this long of the request's arrival (drawn from the
    /// endpoint's generator), or as soon as the application answers if later, so that
    /// the members of a group do not all answer at once. RFC 7252 suggests 5 s for
    /// unknown constrained networks; coapcam's endpoints sit on a LAN and a user waits
    /// for the answer: 500 ms. Zero answers at once.
    pub leisure: Duration,
    /// Limits on state that peers can make grow.
    pub limits: Limits,
}

/// Bounds on endpoint state. Past a bound the endpoint refuses (4.13, 5.03) or evicts the
/// oldest entry; it never grows without limit.
#[derive(Debug, Clone)]
pub struct Limits {
    /// Deduplication entries (message IDs remembered with their reply).
    pub dedup_entries: usize,
    /// Bytes of cached replies in the deduplication store.
    pub dedup_bytes: usize,
    /// Largest Block1 body the server assembles from one peer (4.13 with Size1 above).
    pub block1_peer_bytes: usize,
    /// Bytes of Block1 bodies being assembled over all peers (5.03 above).
    pub block1_total_bytes: usize,
    /// Bytes of stored Block2 representations over all peers; the least recently used
    /// ones are dropped first.
    pub block2_store_bytes: usize,
    /// Idle lifetime of an unfinished Block1 assembly or a stored Block2 representation.
    pub blockwise_lifetime: Duration,
    /// Largest response body a client reassembles.
    pub client_body_bytes: usize,
    /// Requests handed to the application and not answered yet (5.03 above).
    pub pending_requests: usize,
    /// Observations served at once; further registrations are answered as plain GETs.
    pub observations: usize,
    /// Peers whose address an Echo round trip verified, remembered at once; beyond it the
    /// one proved longest ago is forgotten (and must answer an Echo challenge again).
    pub verified_peers: usize,
    /// How long a verified peer stays verified after the Echo value that proved it (other
    /// requests, which anyone could send in its name, do not extend it).
    pub verified_lifetime: Duration,
    /// The application's time that GETs and FETCHes sent to a group by peers whose
    /// address is not verified may take, per second over all peers (from the request's
    /// hand-over to its answer; one at a time). Their answer is known only once made, and
    /// an error one must stay silent (RFC 7390 §2.7), so they are worked on first; past
    /// this share they are challenged before any work, as unicast requests always are.
    /// Such requests come only from inside the group's scope (a link or a site).
    pub unverified_group_work: Duration,
}

impl Default for EndpointConfig {
    fn default() -> Self {
        Self {
            ack_timeout: Duration::from_secs(2),
            ack_random_factor: 1.5,
            max_retransmit: 4,
            nstart: 1,
            exchange_lifetime: Duration::from_secs(247),
            non_lifetime: Duration::from_secs(145),
            response_timeout: Duration::from_secs(93),
            separate_ack_delay: Duration::from_secs(1),
            token_len: 4,
            rng_seed: 0,
            max_block_szx: 6,
            block_retries: 4,
            notify_con_interval: 5,
            transfer: Transfer::default(),
            congestion: Congestion::default(),
            trace_congestion: false,
            max_payloads: 10,
            verify_addresses: true,
            leisure: Duration::from_millis(500),
            limits: Limits::default(),
        }
    }
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            dedup_entries: 8192,
            dedup_bytes: 16 << 20,
            block1_peer_bytes: 8 << 20,
            block1_total_bytes: 64 << 20,
            block2_store_bytes: 256 << 20,
            blockwise_lifetime: Duration::from_secs(247),
            client_body_bytes: 256 << 20,
            pending_requests: 1024,
            observations: 1024,
            verified_peers: 16384,
            verified_lifetime: Duration::from_secs(600),
            unverified_group_work: Duration::from_millis(50),
        }
    }
}

impl EndpointConfig {
    /// The blocks of one Q-Block set: [`EndpointConfig::max_payloads`], at least 1.
    pub(crate) fn payloads_per_set(&self) -> u32 {
        self.max_payloads.max(1)
    }

    /// MAX_TRANSMIT_SPAN (RFC 7252 §4.8.2).
    pub fn max_transmit_span(&self) -> Duration {
        self.ack_timeout
            .mul_f64(f64::from((1u32 << self.max_retransmit) - 1) * self.ack_random_factor)
    }
}

/// How a client fetches a response that comes in blocks (RFC 7959 Block2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Hash)]
pub enum Transfer {
    /// One block at a time, each asked for when the one before arrived (RFC 7959's
    /// stop-and-wait, NSTART 1).
    StopAndWait,
    /// After block 0, many blocks in flight at once as NON requests, admitted and paced
    /// by the peer's congestion controller, lost ones asked for again within about a
    /// round trip. Needs Size2 in block 0's response (the first request asks for it) and
    /// a server that serves any block on request (RFC 7959 §2.4); otherwise, or when the
    /// server refuses a block, the transfer goes on stop-and-wait.
    #[default]
    Window,
    /// RFC 9177 Q-Block2 for responses and Q-Block1 for request bodies, with NON
    /// messages: the server sends MAX_PAYLOADS blocks at a time, the client confirms
    /// each whole set ('Continue') and asks for missing blocks. The first exchange with
    /// a peer is a CON that finds out whether it speaks Q-Block; with peers that do not,
    /// the transfer is RFC 7959 stop-and-wait.
    QBlock,
}

/// The congestion controller of a peer's windowed transfers ([`Transfer::Window`]): it
/// admits and paces their block requests, one controller per peer shared by them all.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Hash)]
pub enum Congestion {
    /// BBR: a window of twice the bandwidth-delay product and a pacing rate, both from
    /// the delivery rate and the smallest round trip measured. Random loss does not
    /// shrink it.
    #[default]
    Bbr,
    /// RFC 7252's NSTART (§4.7): at most [`EndpointConfig::nstart`] block requests in
    /// flight, unpaced; each loss found by the window is asked for again.
    Nstart,
}
