//! What the endpoint's owner sees: requests and responses, their ids, the datagrams to
//! send, the events, and the errors of a request.

use std::net::SocketAddr;
use std::time::Duration;

use bytes::Bytes;

use crate::block::{BlockSource, Source};
use crate::config::Transfer;
use crate::msg::{Code, Options};

/// Identifies a request this endpoint sent (client side).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct RequestId(pub u64);

/// Identifies a request this endpoint received and must answer with [`Endpoint::respond`](crate::Endpoint::respond).
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
    /// responses (default 5 s); for an Observe registration, how long to wait for the
    /// first answer (the observation then lasts until it is cancelled or ends).
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
    /// How a response sent in blocks is fetched (see [`Transfer`]); `None` takes the
    /// endpoint's [`EndpointConfig::transfer`](crate::EndpointConfig::transfer).
    pub transfer: Option<Transfer>,
}

/// What the server side of an endpoint holds ([`Endpoint::server_stats`](crate::Endpoint::server_stats)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ServerStats {
    /// Bytes held by request bodies being assembled (Block1), with their keys.
    pub upload_bytes: usize,
    /// Bytes held by representations stored for Block2 continuations, with their keys.
    pub stored_bytes: usize,
    /// Requests handed to the application and not answered yet (or answered and held
    /// for their leisure, RFC 7252 §8.2).
    pub pending: usize,
    /// Observations served.
    pub observations: usize,
}

/// What an endpoint knows of the path to one peer: its round-trip estimate and what its
/// windowed transfers counted ([`Endpoint::path_stats`](crate::Endpoint::path_stats)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct PathStats {
    /// The smoothed round trip (RFC 6298 SRTT), if measured.
    pub srtt: Option<Duration>,
    /// Its variation (RTTVAR).
    pub rttvar: Duration,
    /// The smallest round trip seen.
    pub min_rtt: Option<Duration>,
    /// CON messages sent again after their timeout.
    pub retransmissions: u64,
    /// Block requests of windowed transfers, including those sent again.
    pub block_requests: u64,
    /// Of those, declared lost (the block asked for again).
    pub blocks_lost: u64,
    /// Blocks that arrived after their request had been declared lost.
    pub blocks_late: u64,
    /// Blocks that arrived twice.
    pub blocks_duplicate: u64,
    /// The most block requests in flight at once.
    pub max_window: u64,
    /// Windowed downloads that went on stop-and-wait after three probe timeouts in a
    /// row without a block.
    pub window_fallbacks: u64,
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
            transfer: None,
        }
    }

    /// Sets the payload.
    pub fn with_payload(mut self, payload: impl Into<Bytes>) -> Self {
        self.payload = payload.into();
        self
    }
}

/// A response: to send with [`Endpoint::respond`](crate::Endpoint::respond), or received in
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
    /// Answer it with [`Endpoint::respond`](crate::Endpoint::respond).
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
    /// (any value; the endpoint numbers notifications itself); then [`Endpoint::notify`](crate::Endpoint::notify)
    /// sends notifications to it. A response without Observe declines (§4.1).
    pub observe: Option<ObservationId>,
    /// The peer's authenticated identity (its DTLS PSK identity), set by the transport;
    /// `None` over plain CoAP.
    pub identity: Option<std::sync::Arc<str>>,
    /// Whether it arrived over a loopback interface, that is from a program on this
    /// machine, set by the transport (`false` unless it knows). Never inferred from the
    /// peer's address: a remote sender can forge one that looks like loopback.
    pub loopback: bool,
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
    /// Cancelled by [`Endpoint::cancel`](crate::Endpoint::cancel).
    #[error("cancelled")]
    Cancelled,
    /// The stream connection the request went over closed before its response came
    /// (RFC 8323: a Release or an Abort, or the stream ended).
    #[error("the connection closed before the response came")]
    ConnectionClosed,
    /// The request is larger than the peer takes in one message (its Max-Message-Size,
    /// RFC 8323 §5.3.1), and streams have no block-wise transfer yet.
    #[error("request larger than the peer's Max-Message-Size of {limit} bytes")]
    RequestTooLarge {
        /// The peer's Max-Message-Size.
        limit: usize,
    },
}

/// What the endpoint reports to its owner.
#[derive(Debug, Clone)]
#[must_use]
pub enum Event {
    /// A request to answer with [`Endpoint::respond`](crate::Endpoint::respond).
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
