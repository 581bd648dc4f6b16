//! `coap+tcp://` and `coap+ws://` (RFC 8323), and their TLS twins `coaps+tcp://` and
//! `coaps+ws://`: serving, a listener whose every connection
//! is a [`coap::connection::Connection`], its requests handed to the same [`Router`] the
//! UDP [`Server`](crate::Server) uses; and the client side, [`TcpClient`], which keeps
//! one connection per server. Over WebSockets ([`TcpServer::bind_ws`],
//! [`TcpClient::websocket`]) the same runs over a WebSocket on the TCP stream, each of
//! its messages one frame (the carrier is `link.rs`'s). With TLS ([`TcpServer::bind_tls`],
//! [`TcpServer::bind_wss`], [`TcpClient::tls`], [`TcpClient::wss`]) OpenSSL's TLS with a
//! pre-shared key runs on the TCP stream first (`tls.rs`), and a server's requests carry
//! the client's PSK identity as DTLS ones do. Nothing here decides protocol behaviour: the connection
//! answers signalling, frames messages and matches responses; this moves bytes, runs
//! handlers and hands responses to whoever waits for them.
//!
//! One task per connection owns its `Connection`. On a server, handlers run as spawned
//! tasks, as the UDP server's do, at most [`MAX_IN_FLIGHT`] per connection, and send
//! their answers back to it. Observe (RFC 7641 as RFC 8323 §7 has it): a server's
//! connection keeps the observations registered on it (`observers.rs`), notifies them of
//! the paths its router is told changed ([`Router::changed`], which
//! [`Server::notify`](crate::Server::notify) calls) and ends them with itself; a
//! connection with observations is never idle. A [`TcpClient`] registers over its
//! connection ([`crate::Client::observe`]) and deregisters with a GET with Observe 1.
//! What the connection does not do yet (block-wise transfer, Pings to keep it alive)
//! neither side does either, but for one thing: a [`TcpClient`] follows an answer to a
//! GET or FETCH that a server sends in Block2 blocks (aiocoap does over streams) and
//! returns it whole.
//!
//! A server's bounds ([`StreamLimits`], per listening address): at most
//! [`DEFAULT_MAX_CONNECTIONS`] connections open, a further one turned away with a
//! Release that says why; a connection idle for [`DEFAULT_IDLE_TIMEOUT`] (nothing came,
//! no request of its being handled, no observation) released and closed; at most 64
//! observations per connection (a registration beyond them answered as a plain GET); messages of up to
//! [`DEFAULT_MAX_MESSAGE_SIZE`]. The TLS and WebSocket handshakes must be done within the
//! idle timeout; a connection whose handshake fails or takes longer is closed.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
use coap::connection::{Connection, ConnectionEvent, DEFAULT_RESPONSE_TIMEOUT};
use coap::{
    BlockOpt, Code, IncomingId, IncomingRequest, ObservationId, OptionNumber, Request,
    RequestError, Response, Token,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Semaphore, broadcast, mpsc, oneshot, watch};
use tokio_tungstenite::tungstenite::http::StatusCode;

use crate::Error;
use crate::driver::StreamItem;
use crate::dtls::Psk;
pub use crate::link::WS_PATH;
use crate::link::{self, Link, Stream};
use crate::observers::{Due, Observers};
use crate::router::Router;
use crate::tls::Tls;

/// The Max-Message-Size a [`TcpServer`] announces unless told otherwise: a request of up
/// to 1 MiB, whole (there is no block-wise transfer over TCP yet).
pub const DEFAULT_MAX_MESSAGE_SIZE: u32 = 1 << 20;

/// The Max-Message-Size a [`TcpClient`] announces: 16 MiB. Without block-wise transfer
/// over TCP a body comes in one message, so this is the largest body a client can fetch
/// over `coap+tcp`: a 1280x720 color frame (2,764,810 bytes), its depth (1,843,210) and
/// the point cloud of all its pixels (12 + 12 x 921,600 = 11,059,212) each fit, with
/// room. It is also the most one connection buffers of a message, whatever the body
/// limit; bodies over [`coap::Limits::client_body_bytes`] fail once they have come.
pub const CLIENT_MAX_MESSAGE_SIZE: u32 = 16 << 20;

/// How many of a connection's requests its handlers may work on at once. At the limit the
/// connection reads no more until one is answered, so a peer that sends faster than the
/// handlers answer is held back by TCP's flow control, not queued here.
pub const MAX_IN_FLIGHT: usize = 32;

/// How many connections a [`TcpServer`] keeps open unless told otherwise: 64. A camera
/// server has a handful of clients, each of our commands one connection to it; the bound
/// is what peers can pin of the server's memory, since each connection may hold a
/// message of up to its Max-Message-Size being received (1 MiB by default, about 68 MiB
/// for 64 connections with their read buffers) and [`MAX_IN_FLIGHT`] handlers.
pub const DEFAULT_MAX_CONNECTIONS: usize = 64;

/// How long a [`TcpServer`] keeps a connection on which nothing came and none of whose
/// requests is being handled, unless told otherwise: 60 s.
pub const DEFAULT_IDLE_TIMEOUT: Duration = Duration::from_secs(60);

/// The Hold-Off of the Release that turns a connection away at the connection limit: how
/// many seconds its client should wait before it tries again.
const FULL_HOLD_OFF_S: u32 = 5;

/// How long the listener waits after a failed accept (out of file descriptors, say)
/// before it tries again.
const ACCEPT_RETRY: Duration = Duration::from_millis(100);

/// How long a connection turned away may take: the Release written, then what the
/// client still sends read and dropped until it closes (so that it gets the Release,
/// not a reset for bytes of its left unread).
const REFUSAL_TIME: Duration = Duration::from_secs(1);

/// The most often the listener logs that it turns connections away.
const FULL_LOG_INTERVAL: Duration = Duration::from_secs(60);

/// The bounds of a stream server's connections.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StreamLimits {
    /// The largest message taken, announced as the server's Max-Message-Size; one whose
    /// header says it is larger aborts its connection.
    pub max_message_size: u32,
    /// Open connections at most. One accepted beyond them gets the server's CSM and a
    /// Release (with a Hold-Off of 5 s and a diagnostic saying why) and is closed.
    pub max_connections: usize,
    /// A connection on which nothing came for this long while none of its requests was
    /// being handled and it had no observation is released (RFC 8323 §5.5 lets either
    /// side close) and closed.
    pub idle_timeout: Duration,
}

impl Default for StreamLimits {
    /// [`DEFAULT_MAX_MESSAGE_SIZE`], [`DEFAULT_MAX_CONNECTIONS`] and
    /// [`DEFAULT_IDLE_TIMEOUT`].
    fn default() -> Self {
        Self {
            max_message_size: DEFAULT_MAX_MESSAGE_SIZE,
            max_connections: DEFAULT_MAX_CONNECTIONS,
            idle_timeout: DEFAULT_IDLE_TIMEOUT,
        }
    }
}

/// A running `coap+tcp` server; dropped, it stops listening and closes its connections.
#[derive(Debug)]
pub struct TcpServer {
    local_addr: SocketAddr,
    /// Dropped with the server: the listener and every connection see it and end.
    _stop: watch::Sender<()>,
}

impl TcpServer {
    /// Listens on `addr` and serves `router` on every connection, within `limits`.
    pub async fn bind(
        addr: SocketAddr,
        router: Arc<Router>,
        limits: StreamLimits,
    ) -> std::io::Result<Self> {
        Self::start(addr, router, limits, Door::default()).await
    }

    /// Listens on `addr` for TLS connections (`coaps+tcp`) with the identities of `keys`
    /// (a [`Psk::Server`]) and serves `router` on each, within `limits`: a client must
    /// finish its TLS handshake with a key `keys` knows within `limits.idle_timeout`.
    /// Beyond `limits.max_connections` a client gets its handshake, the CSM and a Release
    /// saying why. Requests carry the client's PSK identity
    /// ([`coap::IncomingRequest::identity`]).
    pub async fn bind_tls(
        addr: SocketAddr,
        router: Arc<Router>,
        limits: StreamLimits,
        keys: &Psk,
    ) -> std::io::Result<Self> {
        let tls = Some(server_tls(keys, true)?);
        let door = Door {
            websocket: false,
            tls,
        };
        Self::start(addr, router, limits, door).await
    }

    /// Listens on `addr` for WebSockets over TLS (`coaps+ws`, a `wss` endpoint at
    /// [`WS_PATH`]) with the identities of `keys`, as [`TcpServer::bind_ws`] does over TCP
    /// and [`TcpServer::bind_tls`] with TLS: both handshakes within
    /// `limits.idle_timeout`.
    pub async fn bind_wss(
        addr: SocketAddr,
        router: Arc<Router>,
        limits: StreamLimits,
        keys: &Psk,
    ) -> std::io::Result<Self> {
        let tls = Some(server_tls(keys, false)?);
        let door = Door {
            websocket: true,
            tls,
        };
        Self::start(addr, router, limits, door).await
    }

    /// Listens on `addr` for WebSocket connections and serves `router` on each (RFC 8323
    /// §4, `coap+ws`): the WebSocket endpoint is [`WS_PATH`], the subprotocol `coap`.
    /// Beyond `limits.max_connections` a handshake is answered 503, saying why; one that
    /// has not finished within `limits.idle_timeout` is dropped.
    pub async fn bind_ws(
        addr: SocketAddr,
        router: Arc<Router>,
        limits: StreamLimits,
    ) -> std::io::Result<Self> {
        let door = Door {
            websocket: true,
            tls: None,
        };
        Self::start(addr, router, limits, door).await
    }

    async fn start(
        addr: SocketAddr,
        router: Arc<Router>,
        limits: StreamLimits,
        door: Door,
    ) -> std::io::Result<Self> {
        let listener = TcpListener::bind(addr)
            .await
            .map_err(|e| std::io::Error::new(e.kind(), format!("{addr}: {e}")))?;
        let local_addr = listener.local_addr()?;
        let (stop, stopped) = watch::channel(());
        tokio::spawn(listen(listener, router, limits, door, stopped));
        Ok(Self {
            local_addr,
            _stop: stop,
        })
    }

    /// The bound address.
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }
}

/// The server side of TLS with `keys`, which must be a server's.
fn server_tls(keys: &Psk, alpn: bool) -> std::io::Result<Arc<Tls>> {
    if !matches!(keys, Psk::Server(_)) {
        let why = "a TLS server needs the identities it accepts (Psk::Server)";
        return Err(std::io::Error::new(std::io::ErrorKind::InvalidInput, why));
    }
    Tls::new(keys, alpn)
}

/// What a listener's connections speak: WebSockets or not, TLS or not.
#[derive(Debug, Clone, Default)]
struct Door {
    websocket: bool,
    tls: Option<Arc<Tls>>,
}

impl Door {
    fn scheme(&self) -> &'static str {
        match (self.tls.is_some(), self.websocket) {
            (false, false) => "coap+tcp",
            (false, true) => "coap+ws",
            (true, false) => "coaps+tcp",
            (true, true) => "coaps+ws",
        }
    }

    /// The server's side of a new connection's handshakes (TLS, then WebSocket): its
    /// link and the client's PSK identity.
    async fn open(
        &self,
        stream: TcpStream,
        max_message_size: u32,
    ) -> std::io::Result<(Link, Option<Arc<str>>)> {
        let (stream, identity) = self.secure(stream).await?;
        let link = if self.websocket {
            link::accept_ws(stream, max_message_size).await?
        } else {
            Link::tcp(stream)
        };
        Ok((link, identity))
    }

    /// The TLS handshake when this door has TLS: the stream and the client's identity.
    async fn secure(&self, stream: TcpStream) -> std::io::Result<(Stream, Option<Arc<str>>)> {
        let _ = stream.set_nodelay(true);
        match &self.tls {
            Some(tls) => {
                let (stream, identity) = tls.accept(stream).await?;
                Ok((Stream::Tls(Box::new(stream)), identity))
            }
            None => Ok((Stream::Plain(stream), None)),
        }
    }
}

/// Accepts connections (speaking what `door` says) and starts a task serving each, or
/// turns it away at the limit, until the server is dropped.
async fn listen(
    listener: TcpListener,
    router: Arc<Router>,
    limits: StreamLimits,
    door: Door,
    mut stopped: watch::Receiver<()>,
) {
    let scheme = door.scheme();
    let ids = Arc::new(AtomicU64::new(0));
    // A permit per open connection, held by its task.
    let open = Arc::new(Semaphore::new(limits.max_connections));
    let mut last_full_log: Option<Instant> = None;
    loop {
        tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, peer)) => {
                    let Ok(permit) = open.clone().try_acquire_owned() else {
                        let now = crate::clock::now();
                        if last_full_log.is_none_or(|at| now - at >= FULL_LOG_INTERVAL) {
                            last_full_log = Some(now);
                            let max = limits.max_connections;
                            tracing::warn!(%peer, max, "{scheme} connections at their limit: turning new ones away (logged once a minute)");
                        }
                        tokio::spawn(turn_away(stream, limits, door.clone()));
                        continue;
                    };
                    let (router, ids, stopped) = (router.clone(), ids.clone(), stopped.clone());
                    let door = door.clone();
                    tokio::spawn(async move {
                        let shake = door.open(stream, limits.max_message_size);
                        let (link, identity) = match tokio::time::timeout(limits.idle_timeout, shake).await {
                            Ok(Ok(opened)) => opened,
                            Ok(Err(e)) => {
                                tracing::debug!(%peer, error = %e, "{scheme} handshake failed");
                                return;
                            }
                            Err(_) => {
                                tracing::debug!(%peer, "{scheme} handshake took too long");
                                return;
                            }
                        };
                        let conn = link.connection(limits.max_message_size);
                        let from = Peer { addr: peer, identity };
                        serve(link, from, conn, router, ids, limits.idle_timeout, stopped).await;
                        drop(permit);
                    });
                }
                Err(e) => {
                    tracing::warn!(error = %e, "{scheme} accept failed");
                    tokio::time::sleep(ACCEPT_RETRY).await;
                }
            },
            _ = stopped.changed() => return,
        }
    }
}

/// Turns away a connection accepted beyond the limit: sends a TCP one the server's CSM
/// and a Release that says why, answers a WebSocket one's handshake 503 with the same
/// sentence, and closes it; over TLS once the TLS handshake is done (all within
/// [`REFUSAL_TIME`]: a client too slow for it just sees the connection close).
async fn turn_away(stream: TcpStream, limits: StreamLimits, door: Door) {
    let max = limits.max_connections;
    let reason = format!("the server has {max} connections open, its limit");
    let refuse = async {
        let (mut stream, _) = door.secure(stream).await?;
        if door.websocket {
            link::refuse_ws(stream, StatusCode::SERVICE_UNAVAILABLE, reason).await;
            return Ok(());
        }
        let mut conn = Connection::new(limits.max_message_size);
        conn.release(&reason, Some(FULL_HOLD_OFF_S));
        let bytes = conn.poll_transmit().unwrap_or_default();
        stream.write_all(&bytes).await?;
        stream.shutdown().await?;
        let mut sink = [0u8; 1024];
        while stream.read(&mut sink).await? > 0 {}
        std::io::Result::Ok(())
    };
    let _ = tokio::time::timeout(REFUSAL_TIME, refuse).await;
}

/// Who is at the other end of a server's connection.
#[derive(Debug)]
struct Peer {
    addr: SocketAddr,
    /// The PSK identity a TLS client presented.
    identity: Option<Arc<str>>,
}

/// What a connection's handlers hand back to its task.
enum Handled {
    /// The answer to the request of `token`; `request` is the request itself when it
    /// registered an observation (boxed: a request keeps its options inline).
    Answer {
        token: Token,
        response: Response,
        request: Option<Box<IncomingRequest>>,
    },
    /// A notification of observation `id` (under `token`), run again.
    Notification {
        token: Token,
        id: ObservationId,
        response: Response,
    },
}

/// Runs a notification of `due` on a spawned task, which hands it to `handled`.
fn run_notification(due: Due, router: &Arc<Router>, handled: &mpsc::UnboundedSender<Handled>) {
    let (router, handled) = (router.clone(), handled.clone());
    tokio::spawn(async move {
        let response = router.dispatch(due.request).await;
        let (token, id) = (due.token, due.id);
        let _ = handled.send(Handled::Notification {
            token,
            id,
            response,
        });
    });
}

/// Moves one connection's bytes between its stream and its `Connection`, and its
/// requests to the router, until either side ends it or it is idle for `idle_timeout`.
/// It keeps the observations registered on it (`observers.rs`) and notifies them of the
/// paths the router is told changed; they end with it.
async fn serve(
    mut link: Link,
    from: Peer,
    mut conn: Connection,
    router: Arc<Router>,
    ids: Arc<AtomicU64>,
    idle_timeout: Duration,
    mut stopped: watch::Receiver<()>,
) {
    let (scheme, peer) = (link.scheme(), from.addr);
    let (handled_tx, mut handled) = mpsc::unbounded_channel::<Handled>();
    let mut changes = router.changes();
    let mut observers = Observers::new(peer);
    let mut in_flight = 0;
    // When the connection last showed life: bytes came, or an answer went.
    let mut active = tokio::time::Instant::now();
    loop {
        let mut closing = false;
        while in_flight < MAX_IN_FLIGHT
            && let Some(event) = conn.poll_event()
        {
            match event {
                ConnectionEvent::Request(request) => {
                    let request = *request;
                    in_flight += 1;
                    let registers = request.method == Code::GET
                        && request.options.uint(OptionNumber::OBSERVE) == Some(0);
                    let observe = observers.request(request.token, registers);
                    let id = IncomingId(ids.fetch_add(1, Ordering::Relaxed));
                    let incoming = IncomingRequest {
                        id,
                        peer,
                        method: request.method,
                        options: request.options,
                        payload: request.payload,
                        multicast: false,
                        // Reliable, as a CON is.
                        confirmable: true,
                        observe,
                        identity: from.identity.clone(),
                        // TCP's handshake proves the peer's address, so one on
                        // loopback is this machine (as the HTTP side decides).
                        loopback: peer.ip().to_canonical().is_loopback(),
                    };
                    let registration = observe.is_some().then(|| Box::new(incoming.clone()));
                    let (router, handled, token) =
                        (router.clone(), handled_tx.clone(), request.token);
                    tokio::spawn(async move {
                        let (method, path) = (incoming.method, incoming.options.path_string());
                        let response = router.dispatch(incoming).await;
                        tracing::debug!(%peer, %method, ?path, code = %response.code, "{scheme} request");
                        let _ = handled.send(Handled::Answer {
                            token,
                            response,
                            request: registration,
                        });
                    });
                }
                ConnectionEvent::Closed(why) => {
                    tracing::debug!(%peer, ?why, "{scheme} connection closed");
                    closing = true;
                }
                // The server sends no requests or Pings of its own.
                ConnectionEvent::Response(..)
                | ConnectionEvent::Failed(..)
                | ConnectionEvent::Pong(_) => {}
            }
        }
        while let Some(bytes) = conn.poll_transmit() {
            if link.send(bytes).await.is_err() {
                return;
            }
        }
        if closing {
            link.close().await;
            return;
        }
        let idle = tokio::time::sleep_until(active + idle_timeout);
        tokio::select! {
            bytes = link.recv(), if in_flight < MAX_IN_FLIGHT => match bytes {
                None => return,
                Some(bytes) => {
                    active = tokio::time::Instant::now();
                    conn.handle(bytes);
                }
            },
            Some(done) = handled.recv() => {
                active = tokio::time::Instant::now();
                match done {
                    Handled::Answer { token, mut response, request } => {
                        in_flight -= 1;
                        if let Some(request) = request {
                            observers.answered(&router, token, *request, &mut response);
                        } else {
                            response.options.remove(OptionNumber::OBSERVE);
                        }
                        conn.respond(token, &response);
                    }
                    Handled::Notification { token, id, response } => {
                        let (send, again) = observers.notified(token, id, response);
                        if let Some(notification) = send {
                            conn.respond(token, &notification);
                        }
                        if let Some(due) = again {
                            run_notification(due, &router, &handled_tx);
                        }
                    }
                }
            }
            changed = changes.recv(), if !observers.is_empty() => {
                let paths = match changed {
                    Ok(path) => vec![path.to_string()],
                    // Changes were lost: every observed path may have changed.
                    Err(broadcast::error::RecvError::Lagged(_)) => observers.paths(),
                    Err(broadcast::error::RecvError::Closed) => Vec::new(),
                };
                for path in paths {
                    for due in observers.changed(&path) {
                        run_notification(due, &router, &handled_tx);
                    }
                }
            }
            // An observed connection is not idle: its notifications are what it waits
            // for, however rarely the resource changes.
            () = idle, if in_flight == 0 && observers.is_empty() => {
                let secs = idle_timeout.as_secs_f64();
                conn.release(&format!("idle for {secs} s"), None);
            }
            _ = stopped.changed() => return,
        }
    }
}

/// A `coap+tcp` client: one connection per server, opened by the first request to it
/// and again by the first after it closed, on which requests go side by side. Cheap to
/// clone; clones share the connections. Dropped with its last clone, its connections
/// close.
#[derive(Clone, Debug)]
pub struct TcpClient {
    /// The largest response body taken ([`coap::Limits::client_body_bytes`]).
    body_limit: usize,
    /// Over WebSockets (`coap+ws`) or plain TCP, with TLS under it or not.
    door: Door,
    /// The command channel of each server's connection task.
    connections: Arc<Mutex<HashMap<SocketAddr, mpsc::UnboundedSender<ToConnection>>>>,
}

/// What a [`TcpClient`] asks of a connection's task.
#[derive(Debug)]
enum ToConnection {
    /// Send a request, sent by the caller at `sent`, and answer on `reply` (boxed: a
    /// request keeps its options inline).
    Request {
        request: Box<Request>,
        sent: Instant,
        reply: oneshot::Sender<Result<Response, Error>>,
    },
    /// Send a Ping and answer on `reply` when its Pong comes.
    Ping {
        timeout: Duration,
        reply: oneshot::Sender<Result<(), Error>>,
    },
    /// Send a registration (a GET with Observe 0), tell its token on `token` once it is
    /// sent, and hand its answer and every notification to `items`.
    Observe {
        request: Box<Request>,
        sent: Instant,
        token: oneshot::Sender<Result<Token, Error>>,
        items: mpsc::UnboundedSender<StreamItem>,
    },
    /// End the observation of this token (a GET with Observe 1 under it).
    Cancel(Token),
}

impl ToConnection {
    /// Answers with `error`.
    fn fail(self, error: Error) {
        match self {
            Self::Request { reply, .. } => drop(reply.send(Err(error))),
            Self::Ping { reply, .. } => drop(reply.send(Err(error))),
            Self::Observe { token, .. } => drop(token.send(Err(error))),
            Self::Cancel(_) => {}
        }
    }
}

/// Who waits for what a connection's task was asked, by token.
#[derive(Debug)]
enum Waiter {
    Response(oneshot::Sender<Result<Response, Error>>),
    Pong(oneshot::Sender<Result<(), Error>>),
    /// An observation: its registration (sent again with Observe 1 to cancel it) and
    /// where its answer and notifications go.
    Observe(Box<Request>, mpsc::UnboundedSender<StreamItem>),
}

impl TcpClient {
    /// A client whose responses may carry bodies of up to `body_limit` bytes (the
    /// endpoint's [`coap::Limits::client_body_bytes`]); larger ones fail with
    /// [`RequestError::TooLarge`].
    pub fn new(body_limit: usize) -> Self {
        Self {
            body_limit,
            door: Door::default(),
            connections: Arc::default(),
        }
    }

    /// The same over TLS (`coaps+tcp`) with `key` (a [`Psk::Client`]: its identity and
    /// key), offering the ALPN protocol `coap`. A server that does not know the key
    /// fails the handshake, and each request with it.
    pub fn tls(body_limit: usize, key: &Psk) -> std::io::Result<Self> {
        let door = Door {
            websocket: false,
            tls: Some(client_tls(key, true)?),
        };
        Ok(Self {
            door,
            ..Self::new(body_limit)
        })
    }

    /// WebSockets over TLS (`coaps+ws`, a `wss` connection to the server's [`WS_PATH`])
    /// with `key`, as [`TcpClient::tls`].
    pub fn wss(body_limit: usize, key: &Psk) -> std::io::Result<Self> {
        let door = Door {
            websocket: true,
            tls: Some(client_tls(key, false)?),
        };
        Ok(Self {
            door,
            ..Self::new(body_limit)
        })
    }

    /// The same over WebSockets (`coap+ws`, RFC 8323 §4): each connection is a WebSocket
    /// to the server's [`WS_PATH`] with the subprotocol `coap`.
    pub fn websocket(body_limit: usize) -> Self {
        let door = Door {
            websocket: true,
            tls: None,
        };
        Self {
            door,
            ..Self::new(body_limit)
        }
    }

    /// The channel to `peer`'s connection task, started when there is none or the last
    /// one ended.
    fn connection(&self, peer: SocketAddr) -> mpsc::UnboundedSender<ToConnection> {
        let mut connections = self
            .connections
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(tx) = connections.get(&peer).filter(|tx| !tx.is_closed()) {
            return tx.clone();
        }
        let (tx, rx) = mpsc::unbounded_channel();
        tokio::spawn(drive(peer, self.body_limit, self.door.clone(), rx));
        connections.insert(peer, tx.clone());
        tx
    }

    /// Sends `request` to `peer` over its connection and waits for the response, at most
    /// the request's timeout ([`DEFAULT_RESPONSE_TIMEOUT`] without one) in all, connecting
    /// included. A request that never left because its connection closed first is sent
    /// once more on a new one. An answer to a GET or FETCH that comes in Block2 blocks
    /// (RFC 7959 §2.4: a server may send them over a stream too; aiocoap does whenever its
    /// peer announces no Block-Wise-Transfer) is followed, block after block, and
    /// returned whole; one to another method fails, rather than come back cut.
    pub async fn send(&self, peer: SocketAddr, request: Request) -> Result<Response, Error> {
        let timeout = request.timeout.unwrap_or(DEFAULT_RESPONSE_TIMEOUT);
        tokio::time::timeout(timeout, self.send_following_block2(peer, request))
            .await
            .unwrap_or(Err(Error::Request(RequestError::Timeout)))
    }

    /// [`TcpClient::send`] without its timeout.
    async fn send_following_block2(
        &self,
        peer: SocketAddr,
        request: Request,
    ) -> Result<Response, Error> {
        let mut response = self.exchange(peer, &request).await?;
        let Some(first) = response.options.block2() else {
            return Ok(response);
        };
        if !first.more {
            return Ok(response);
        }
        if !matches!(request.method, Code::GET | Code::FETCH) {
            return Err(Error::Unsupported(
                "a block-wise answer to a request other than GET or FETCH",
            ));
        }
        if first.num != 0 {
            return Err(RequestError::Protocol("the first Block2 block is not block 0").into());
        }
        let etag = response
            .options
            .first(OptionNumber::ETAG)
            .map(<[u8]>::to_vec);
        let mut body = response.payload.to_vec();
        let mut block = first;
        while block.more {
            let next = BlockOpt {
                num: block.num + 1,
                more: false,
                szx: block.szx,
            };
            let mut more = request.clone();
            more.options.set_block(OptionNumber::BLOCK2, next);
            let answer = self.exchange(peer, &more).await?;
            if !answer.code.is_success() {
                return Ok(answer);
            }
            if answer.options.first(OptionNumber::ETAG).map(<[u8]>::to_vec) != etag {
                return Err(RequestError::RepresentationChanged.into());
            }
            block = answer.options.block2().ok_or(RequestError::Protocol(
                "a later block of a Block2 answer has no Block2 option",
            ))?;
            if block.offset() != body.len() {
                return Err(
                    RequestError::Protocol("a Block2 block does not follow the last one").into(),
                );
            }
            body.extend_from_slice(&answer.payload);
            if body.len() > self.body_limit {
                return Err(RequestError::TooLarge {
                    limit: self.body_limit,
                }
                .into());
            }
        }
        response.options.remove(OptionNumber::BLOCK2);
        response.payload = Bytes::from(body);
        Ok(response)
    }

    /// One request and its response, sent once more on a new connection if its
    /// connection closed before it left.
    async fn exchange(&self, peer: SocketAddr, request: &Request) -> Result<Response, Error> {
        let sent = crate::clock::now();
        for _ in 0..2 {
            let (reply, answer) = oneshot::channel();
            let request = Box::new(request.clone());
            let command = ToConnection::Request {
                request,
                sent,
                reply,
            };
            if self.connection(peer).send(command).is_err() {
                continue;
            }
            // No answer at all: the task ended before it took the request.
            if let Ok(answer) = answer.await {
                return answer;
            }
        }
        Err(Error::Closed)
    }

    /// A CoAP Ping over `peer`'s connection (RFC 8323 §5.4), connecting first if need
    /// be: `Ok` when its Pong comes within `timeout`.
    pub async fn ping(&self, peer: SocketAddr, timeout: Duration) -> Result<(), Error> {
        let exchange = async {
            let (reply, answer) = oneshot::channel();
            let command = ToConnection::Ping { timeout, reply };
            self.connection(peer)
                .send(command)
                .map_err(|_| Error::Closed)?;
            answer.await.map_err(|_| Error::Closed)?
        };
        tokio::time::timeout(timeout, exchange)
            .await
            .unwrap_or(Err(Error::Request(RequestError::Timeout)))
    }

    /// Registers `request` (a GET with Observe 0) on `peer` over its connection,
    /// connecting first if need be: its answer and then each notification come on the
    /// returned receiver (RFC 7641 over RFC 8323 §7), which ends when the observation
    /// does (an answer without Observe, an error, the connection's end).
    /// [`TcpObservation::cancel`] ends it from this side. Fails when the connection
    /// cannot be opened.
    pub(crate) async fn observe(
        &self,
        peer: SocketAddr,
        request: Request,
    ) -> Result<(TcpObservation, mpsc::UnboundedReceiver<StreamItem>), Error> {
        let sent = crate::clock::now();
        for _ in 0..2 {
            let (items, rx) = mpsc::unbounded_channel();
            let (token_tx, token) = oneshot::channel();
            let commands = self.connection(peer);
            let command = ToConnection::Observe {
                request: Box::new(request.clone()),
                sent,
                token: token_tx,
                items,
            };
            if commands.send(command).is_err() {
                continue;
            }
            // No answer at all: the task ended before it took the registration.
            if let Ok(token) = token.await {
                let token = token?;
                return Ok((TcpObservation { commands, token }, rx));
            }
        }
        Err(Error::Closed)
    }
}

/// This side's end of an observation over a stream ([`TcpClient::observe`]).
#[derive(Debug)]
pub(crate) struct TcpObservation {
    commands: mpsc::UnboundedSender<ToConnection>,
    token: Token,
}

impl TcpObservation {
    /// Deregisters (RFC 7641 §3.6: a GET with Observe 1 under the observation's token,
    /// the only way over a stream, RFC 8323 §7.4), unless it already ended; whatever
    /// comes for it after is dropped.
    pub(crate) fn cancel(&self) {
        let _ = self.commands.send(ToConnection::Cancel(self.token));
    }
}

/// Connects to `peer` and moves bytes between the stream and a client `Connection`, and
/// commands and answers between it and the callers, until the connection closes or every
/// [`TcpClient`] is gone. Commands it did not take by then are dropped unanswered (their
/// callers try a new connection).
async fn drive(
    peer: SocketAddr,
    body_limit: usize,
    door: Door,
    mut commands: mpsc::UnboundedReceiver<ToConnection>,
) {
    let scheme = door.scheme();
    let mut link = match connect(peer, &door).await {
        Ok(link) => link,
        Err(e) => {
            commands.close();
            while let Some(command) = commands.recv().await {
                let error = std::io::Error::new(e.kind(), format!("{scheme} {peer}: {e}"));
                command.fail(Error::Io(error));
            }
            return;
        }
    };
    let conn = link.connection(CLIENT_MAX_MESSAGE_SIZE);
    let mut conn = conn.with_body_limit(body_limit);
    let mut waiters: HashMap<Token, Waiter> = HashMap::new();
    loop {
        while let Some(event) = conn.poll_event() {
            match event {
                ConnectionEvent::Response(token, response) => match waiters.remove(&token) {
                    Some(Waiter::Response(reply)) => drop(reply.send(Ok(*response))),
                    Some(Waiter::Observe(request, items)) => {
                        let _ = items.send(StreamItem::Response(peer, response));
                        // Kept while the registration holds: its notifications follow.
                        if conn.is_observing(token) {
                            waiters.insert(token, Waiter::Observe(request, items));
                        }
                    }
                    Some(other) => drop(waiters.insert(token, other)),
                    None => {}
                },
                ConnectionEvent::Failed(token, error) => match waiters.remove(&token) {
                    Some(Waiter::Response(reply)) => drop(reply.send(Err(Error::Request(error)))),
                    Some(Waiter::Pong(reply)) => drop(reply.send(Err(Error::Request(error)))),
                    Some(Waiter::Observe(_, items)) => drop(items.send(StreamItem::Failed(error))),
                    None => {}
                },
                ConnectionEvent::Pong(token) => {
                    if let Some(Waiter::Pong(reply)) = waiters.remove(&token) {
                        let _ = reply.send(Ok(()));
                    }
                }
                // A server's request to this client: it serves no resources.
                ConnectionEvent::Request(request) => {
                    let answer = Response::diagnostic(Code::NOT_FOUND, "a client: no resources");
                    conn.respond(request.token, &answer);
                }
                ConnectionEvent::Closed(why) => {
                    tracing::debug!(%peer, ?why, "{scheme} client connection closed");
                }
            }
        }
        if let Some(bytes) = conn.poll_transmit()
            && link.send(bytes).await.is_err()
        {
            // Its requests fail with the events the next turn hands out.
            conn.handle_end();
            continue;
        }
        if conn.is_closed() {
            link.close().await;
            return;
        }
        let due = conn.poll_timeout();
        let at = due.unwrap_or_else(crate::clock::now);
        let sleep = tokio::time::sleep_until(tokio::time::Instant::from_std(at));
        tokio::select! {
            bytes = link.recv() => match bytes {
                None => conn.handle_end(),
                Some(bytes) => conn.handle(bytes),
            },
            command = commands.recv() => match command {
                Some(ToConnection::Request { request, sent, reply }) => {
                    let token = conn.send_request(sent, &request);
                    waiters.insert(token, Waiter::Response(reply));
                }
                Some(ToConnection::Ping { timeout, reply }) => {
                    let token = conn.ping(crate::clock::now(), timeout);
                    waiters.insert(token, Waiter::Pong(reply));
                }
                Some(ToConnection::Observe { request, sent, token, items }) => {
                    let registered = conn.send_request(sent, &request);
                    let _ = token.send(Ok(registered));
                    waiters.insert(registered, Waiter::Observe(request, items));
                }
                Some(ToConnection::Cancel(token)) => {
                    if let Some(Waiter::Observe(request, _)) = waiters.remove(&token) {
                        conn.cancel_observation(token, &request);
                    }
                }
                // Every client is gone.
                None => {
                    link.close().await;
                    return;
                }
            },
            () = sleep, if due.is_some() => conn.handle_timeout(crate::clock::now()),
        }
    }
}

/// The client side of TLS with `key`, which must be a client's.
fn client_tls(key: &Psk, alpn: bool) -> std::io::Result<Arc<Tls>> {
    if !matches!(key, Psk::Client { .. }) {
        let why = "a TLS client needs an identity and its key (Psk::Client)";
        return Err(std::io::Error::new(std::io::ErrorKind::InvalidInput, why));
    }
    Tls::new(key, alpn)
}

/// Opens the connection to `peer`: a TCP one, then the TLS handshake and the WebSocket
/// one over it as `door` says (the handshakes given [`DEFAULT_RESPONSE_TIMEOUT`] at
/// most).
async fn connect(peer: SocketAddr, door: &Door) -> std::io::Result<Link> {
    let stream = TcpStream::connect(peer).await?;
    let _ = stream.set_nodelay(true);
    let shake = async {
        let stream = match &door.tls {
            Some(tls) => Stream::Tls(Box::new(tls.connect(stream).await?)),
            None => Stream::Plain(stream),
        };
        if door.websocket {
            link::connect_ws(stream, peer, CLIENT_MAX_MESSAGE_SIZE).await
        } else {
            Ok(Link::tcp(stream))
        }
    };
    tokio::time::timeout(DEFAULT_RESPONSE_TIMEOUT, shake)
        .await
        .map_err(|_| std::io::Error::new(std::io::ErrorKind::TimedOut, "handshake"))?
}
