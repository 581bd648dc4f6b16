//! One thread per socket owns a `coap::Endpoint`: it waits for datagrams in a blocking
//! receive (up to the endpoint's next timeout), moves them between the socket and the
//! endpoint, and exchanges commands and events with the async rest of the program over
//! channels. Nothing here decides protocol behaviour.
//!
//! Why a thread and not a tokio task: in a stop-and-wait transfer every block is one
//! round trip, and the kernel's receive is the only wait on it. Through tokio's poller a
//! datagram costs an `epoll_wait` and a non-blocking receive plus the runtime's wake-up,
//! about half again a blocking ping-pong's time per block on these machines. The thread
//! costs the async callers one thing: a command must wake the receive, which an empty
//! datagram sent to the socket from the endpoint's waker does (at most one is in flight).

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Weak};
use std::time::{Duration, Instant};

use coap::{
    Endpoint, EndpointConfig, Event, IncomingRequest, ObservationId, Request, RequestError,
    RequestId, Response,
};
use tokio::sync::mpsc::error::TryRecvError;
use tokio::sync::{mpsc, oneshot};

use crate::clock;
use crate::dtls::{Dtls, Psk};
use crate::socket::{RECV_BUFFER, Socket};

/// What a request's caller gets back.
pub(crate) enum Reply {
    /// One response (or failure).
    Once(oneshot::Sender<Result<Response, RequestError>>),
    /// One response, and the progress of its block-wise transfer on the way.
    Tracked(
        oneshot::Sender<Result<Response, RequestError>>,
        mpsc::UnboundedSender<Progress>,
    ),
    /// The first response and every notification (Observe), or every server's response
    /// (multicast); the channel closes when the request ends.
    Stream(mpsc::UnboundedSender<StreamItem>),
    /// The pieces of a streamed body, then the response or the failure.
    Body(mpsc::UnboundedSender<BodyItem>),
}

/// One item of a [`Reply::Body`].
#[derive(Debug)]
pub(crate) enum BodyItem {
    /// The next piece of the body, and the whole size when the server announced it.
    Chunk(bytes::Bytes, Option<usize>),
    /// The response (its payload is empty: the body came in the pieces).
    Done(Box<Response>),
    /// The request failed; the pieces so far are not a body.
    Failed(RequestError),
}

/// How far a block-wise transfer has come.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Progress {
    /// Bytes transferred so far.
    pub done: usize,
    /// The whole size, when the peer announced it.
    pub total: Option<usize>,
}

/// One item of a [`Reply::Stream`].
#[derive(Debug)]
pub(crate) enum StreamItem {
    /// A response: the first one or a notification, or one server's answer to a multicast
    /// request.
    Response(SocketAddr, Box<Response>),
    /// The request failed.
    Failed(RequestError),
}

pub(crate) enum Command {
    Request {
        peer: SocketAddr,
        request: Request,
        reply: Reply,
        id_tx: Option<oneshot::Sender<RequestId>>,
    },
    Cancel(RequestId),
    Respond {
        id: coap::IncomingId,
        response: Response,
    },
    Notify {
        id: ObservationId,
        response: Response,
        done: oneshot::Sender<bool>,
    },
    Ping {
        peer: SocketAddr,
        reply: oneshot::Sender<Result<(), RequestError>>,
    },
    PathStats {
        peer: SocketAddr,
        reply: oneshot::Sender<Option<coap::PathStats>>,
    },
    RememberRtt {
        peer: SocketAddr,
        rtt: Duration,
    },
    Membership {
        group: IpAddr,
        interface: u32,
        join: bool,
        done: oneshot::Sender<std::io::Result<()>>,
    },
    /// A datagram a group socket's thread received (`membership` names the socket).
    GroupDatagram {
        membership: u64,
        peer: SocketAddr,
        data: Vec<u8>,
        loopback: bool,
    },
    Shutdown,
}

/// A handle to a running endpoint thread. Cloning it is cheap; the thread ends when every
/// handle and the server side are gone and no request is open.
#[derive(Clone, Debug)]
pub struct EndpointHandle {
    tx: mpsc::UnboundedSender<Command>,
    waker: Arc<Waker>,
    local: SocketAddr,
}

/// Wakes the endpoint thread out of its receive: an empty datagram to the endpoint's
/// socket, from a socket of its own (the thread knows its address). Only one is in flight:
/// the thread clears `pending` before it reads the commands. Without a route to the
/// endpoint's address (an IPv6 wildcard on a host whose loopback has no ::1) there is no
/// socket, and the thread looks for commands every [`POLL_WAIT`] instead.
#[derive(Debug)]
struct Waker {
    socket: Option<UdpSocket>,
    pending: Arc<AtomicBool>,
}

impl Waker {
    /// A waker for the socket bound to `target` (a wildcard bind is woken over loopback).
    fn new(target: SocketAddr) -> Self {
        let socket = Self::connect(target)
            .inspect_err(|e| {
                tracing::warn!(
                    %target,
                    error = %e,
                    "no route to wake the socket's thread; it looks for commands every {POLL_WAIT:?}"
                );
            })
            .ok();
        Self {
            socket,
            pending: Arc::new(AtomicBool::new(false)),
        }
    }

    fn connect(target: SocketAddr) -> std::io::Result<UdpSocket> {
        let mut to = target;
        if to.ip().is_unspecified() {
            to.set_ip(match to {
                SocketAddr::V4(_) => IpAddr::from([127, 0, 0, 1]),
                SocketAddr::V6(_) => IpAddr::from([0u16, 0, 0, 0, 0, 0, 0, 1]),
            });
        }
        let any: SocketAddr = match to {
            SocketAddr::V4(_) => ([0, 0, 0, 0], 0).into(),
            SocketAddr::V6(_) => ([0u16; 8], 0).into(),
        };
        let socket = UdpSocket::bind(any)?;
        socket.connect(to)?;
        Ok(socket)
    }

    /// The address wake-ups come from, if there are any.
    fn source(&self) -> Option<SocketAddr> {
        self.socket.as_ref().and_then(|s| s.local_addr().ok())
    }

    fn wake(&self) {
        let Some(socket) = &self.socket else { return };
        if !self.pending.swap(true, Ordering::AcqRel)
            && let Err(e) = socket.send(&[])
        {
            // The thread still reads the commands at its next datagram or timeout.
            tracing::debug!(error = %e, "wake-up not sent");
            self.pending.store(false, Ordering::Release);
        }
    }
}

impl Drop for Waker {
    /// The last handle is gone: the thread sees the closed channel and ends.
    fn drop(&mut self) {
        if let Some(socket) = &self.socket {
            let _ = socket.send(&[]);
        }
    }
}

/// Requests received by an endpoint that serves, and the end of observations.
///
/// Responses and requests travel boxed through these channels: they keep their options
/// inline, a few hundred bytes each.
pub(crate) enum ServerEvent {
    Request(Box<IncomingRequest>),
    ObservationEnded(ObservationId),
}

impl EndpointHandle {
    /// The socket's local address.
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }

    pub(crate) fn send(&self, cmd: Command) -> Result<(), crate::Error> {
        self.tx.send(cmd).map_err(|_| crate::Error::Closed)?;
        self.waker.wake();
        Ok(())
    }
}

/// The longest a thread sleeps in a receive without a timeout of the endpoint's: a bound
/// on how late a command is read if its wake-up datagram was lost (a full receive buffer).
const MAX_WAIT: Duration = Duration::from_secs(1);

/// Why requests to a peer failed when no DTLS session could be opened with it.
const NO_SESSION: &str = "no DTLS session: the handshake failed or got no answer (a wrong key or identity, or no coaps:// server there)";

/// The same bound for a thread that has no waker.
const POLL_WAIT: Duration = Duration::from_millis(10);

/// Deadlines closer than this are waited for with a high-resolution timer
/// ([`Socket::wait_readable`]): a receive's read timeout counts in the kernel's ticks and
/// ends up to 12 ms late, which a paced window (requests due every few hundred
/// microseconds) cannot afford. Beyond it the lateness is a few percent at most.
const PRECISE_WAIT: Duration = Duration::from_millis(250);

/// The target of the congestion controllers' round-by-round trace
/// (`RUST_LOG=coap_net::congestion=trace`).
const TRACE_TARGET: &str = "coap_net::congestion";

/// Starts the thread for `socket`. Requests go to `server` when given; a client-only
/// endpoint answers them 4.04.
pub(crate) fn spawn(
    socket: Socket,
    config: EndpointConfig,
    server: Option<mpsc::UnboundedSender<ServerEvent>>,
    psk: Option<&Psk>,
) -> std::io::Result<EndpointHandle> {
    let waker = Waker::new(socket.local_addr());
    let dtls = psk.map(Dtls::new).transpose()?;
    start(socket, config, server, waker, dtls)
}

fn start(
    socket: Socket,
    config: EndpointConfig,
    server: Option<mpsc::UnboundedSender<ServerEvent>>,
    waker: Waker,
    dtls: Option<Dtls>,
) -> std::io::Result<EndpointHandle> {
    let (tx, rx) = mpsc::unbounded_channel();
    let local = socket.local_addr();
    let mut config = config;
    config.trace_congestion |= tracing::enabled!(target: TRACE_TARGET, tracing::Level::TRACE);
    let trace = config.trace_congestion.then(clock::now);
    let waker = Arc::new(waker);
    let wake_from = waker.source();
    let thread = Thread {
        socket,
        ep: Endpoint::new(config),
        rx,
        tx: tx.downgrade(),
        waker: Arc::downgrade(&waker),
        server,
        wake_from,
        wake_pending: waker.pending.clone(),
        replies: HashMap::new(),
        pings: HashMap::new(),
        groups: Vec::new(),
        memberships: 0,
        open: true,
        wait: None,
        dtls,
        dtls_tick: None,
        trace,
    };
    std::thread::Builder::new()
        .name(format!("coap {local}"))
        .spawn(move || thread.run())?;
    Ok(EndpointHandle { tx, waker, local })
}

/// A group socket of a server bound to a unicast address: it only receives, on a thread of
/// its own that hands each datagram to the endpoint thread; every answer leaves from the
/// unicast socket (RFC 7390 §2.5: from the unicast address).
struct Group {
    group: IpAddr,
    interface: u32,
    membership: u64,
    socket: Arc<Socket>,
}

impl Drop for Group {
    /// Its thread notices within [`MAX_WAIT`] and ends; datagrams it still hands over
    /// are dropped (their membership is gone).
    fn drop(&mut self) {
        let _ = self.socket.leave(self.group, self.interface);
    }
}

struct Thread {
    socket: Socket,
    ep: Endpoint,
    rx: mpsc::UnboundedReceiver<Command>,
    /// For group sockets' threads (weak: they must not keep the endpoint alive).
    tx: mpsc::WeakUnboundedSender<Command>,
    waker: Weak<Waker>,
    server: Option<mpsc::UnboundedSender<ServerEvent>>,
    /// Where wake-ups come from (`None`: no waker; commands are polled).
    wake_from: Option<SocketAddr>,
    wake_pending: Arc<AtomicBool>,
    replies: HashMap<RequestId, (SocketAddr, Reply)>,
    pings: HashMap<RequestId, oneshot::Sender<Result<(), RequestError>>>,
    groups: Vec<Group>,
    /// Memberships made so far: the last one names the newest group socket.
    memberships: u64,
    /// Whether handles may still send commands.
    open: bool,
    /// The socket's read timeout as last set (`None`: not yet).
    wait: Option<Duration>,
    /// DTLS between the socket and the endpoint (`coaps://`), and when its handshakes
    /// are to be driven next.
    dtls: Option<Dtls>,
    dtls_tick: Option<Instant>,
    /// When the thread started, if the congestion controllers' rounds are traced.
    trace: Option<Instant>,
}

impl Thread {
    fn run(mut self) {
        let mut buf = vec![0u8; RECV_BUFFER];
        loop {
            while let Some(t) = self.ep.poll_transmit() {
                match &mut self.dtls {
                    Some(dtls) => {
                        for d in dtls.send(clock::now(), t.peer, &t.data) {
                            self.send(&d, t.peer);
                        }
                    }
                    None => self.send(&t.data, t.peer),
                }
            }
            // Requests are taken right after the datagram that completed them (below);
            // any other is not known to have come over loopback.
            self.events(false);
            if let Some(start) = self.trace {
                self.trace_rounds(start);
            }
            if !self.open
                && self.replies.is_empty()
                && self.pings.is_empty()
                && self.server.as_ref().is_none_or(|s| s.is_closed())
            {
                return;
            }
            let now = clock::now();
            if let Some(dtls) = &mut self.dtls {
                let mut gave_up = Vec::new();
                if self.dtls_tick.is_some_and(|t| t <= now) {
                    self.dtls_tick = None;
                    let (datagrams, peers) = dtls.handle_timeout(now);
                    gave_up = peers;
                    for (peer, d) in datagrams {
                        if let Err(e) = self.socket.send_to(&d, peer) {
                            tracing::debug!(%peer, error = %e, "send failed");
                        }
                    }
                }
                if self.dtls_tick.is_none() {
                    self.dtls_tick = dtls.poll_timeout(now);
                }
                if self.server.is_none() {
                    for peer in gave_up {
                        self.fail_peer(peer, RequestError::Protocol(NO_SESSION));
                    }
                }
            }
            let deadline = match (self.ep.poll_timeout(), self.dtls_tick) {
                (Some(a), Some(b)) => Some(a.min(b)),
                (a, b) => a.or(b),
            };
            if deadline.is_some_and(|d| d <= now) {
                self.ep.handle_timeout(now);
                continue;
            }
            match deadline.map(|d| d - now) {
                // A near deadline (pacing, a window's loss or probe timer) is waited for
                // with a high-resolution timer; a far one, or none, by the receive's own
                // timeout, whose few milliseconds of lateness do not matter there.
                Some(left) if left < PRECISE_WAIT => match self.socket.wait_readable(left) {
                    Ok(false) => continue,
                    Ok(true) => {}
                    Err(e) => {
                        tracing::debug!(error = %e, "ppoll failed");
                        self.arm(left);
                    }
                },
                left => self.arm(left.unwrap_or_else(|| self.max_wait())),
            }
            match self.socket.recv(&mut buf) {
                Ok(d) => {
                    let now = clock::now();
                    if Some(d.peer) == self.wake_from {
                        self.wake_pending.store(false, Ordering::Release);
                    } else if d.forged_loopback() {
                        tracing::debug!(peer = %d.peer, "dropped: a loopback source from outside");
                    } else {
                        let data = &buf[..d.len];
                        match &mut self.dtls {
                            Some(dtls) => {
                                let out = dtls.receive(now, d.peer, data);
                                for reply in &out.send {
                                    if let Err(e) = self.socket.send_to(reply, d.peer) {
                                        tracing::debug!(peer = %d.peer, error = %e, "send failed");
                                    }
                                }
                                for message in &out.received {
                                    self.ep.handle(now, d.peer, message, false);
                                    self.events(d.loopback == Some(true));
                                }
                                if out.failed && self.server.is_none() {
                                    self.fail_peer(d.peer, RequestError::Protocol(NO_SESSION));
                                }
                            }
                            None => {
                                self.ep.handle(now, d.peer, data, d.multicast);
                                self.events(d.loopback == Some(true));
                            }
                        }
                    }
                }
                Err(e) if timed_out(&e) => {}
                // A queued ICMP error surfaces here: a port that nothing listens on fails
                // the requests to it now, not after every retransmission.
                Err(e) => {
                    tracing::debug!(error = %e, "recv failed");
                    for peer in self.socket.unreachable() {
                        self.fail_peer(peer, RequestError::Unreachable);
                        // And what it observed of a server ends.
                        self.ep.peer_unreachable(peer);
                    }
                    self.events(false);
                }
            }
            // Every turn, not only after a wake-up: a lost wake-up costs no command.
            if self.commands() {
                return;
            }
        }
    }

    /// Logs the rounds the congestion controllers recorded, one line each: rates in
    /// blocks per second, times in milliseconds since the thread started.
    fn trace_rounds(&mut self, start: Instant) {
        let ms = |d: Duration| d.as_secs_f64() * 1000.0;
        while let Some((peer, r)) = self.ep.poll_round_trace() {
            let (sample, sample_app_limited) = r.max_sample.unwrap_or((0.0, false));
            tracing::trace!(
                target: TRACE_TARGET,
                %peer,
                t_ms = format_args!("{:.1}", ms(r.at.saturating_duration_since(start))),
                round = r.round,
                mode = r.mode,
                gain = r.pacing_gain,
                samples = r.samples,
                app_limited_samples = r.app_limited_samples,
                max_sample = format_args!("{sample:.0}"),
                max_sample_app_limited = sample_app_limited,
                bw = format_args!("{:.0}", r.bw.unwrap_or(0.0)),
                pacing_rate = format_args!("{:.0}", r.pacing_rate.unwrap_or(0.0)),
                window = r.window,
                in_flight = r.in_flight,
                max_in_flight = r.max_in_flight,
                min_rtt_ms = format_args!("{:.2}", r.min_rtt.map_or(0.0, ms)),
                sent = r.sent,
                late_sends = r.late_sends,
                lateness_ms = format_args!("{:.2}", ms(r.lateness)),
                delivered = r.delivered,
                lost = r.lost,
                "round"
            );
        }
    }

    fn send(&self, data: &[u8], peer: SocketAddr) {
        if let Err(e) = self.socket.send_to(data, peer) {
            tracing::debug!(%peer, error = %e, "send failed");
        }
    }

    /// Sets the socket's read timeout so the receive returns by `until_deadline` (at most
    /// `max_wait`). A system call only when the wait would end late or far too early:
    /// the retransmission deadline moves with every block of a transfer, the timeout not.
    fn arm(&mut self, until_deadline: Duration) {
        let want = until_deadline
            .min(self.max_wait())
            .max(Duration::from_millis(1));
        let rearm = self.wait.is_none_or(|w| want < w || want > w * 4);
        if rearm {
            // Three quarters: the next deadlines, a little later or earlier, still fit.
            let w = (want * 3 / 4).max(Duration::from_millis(1));
            match self.socket.set_read_timeout(Some(w)) {
                Ok(()) => self.wait = Some(w),
                Err(e) => tracing::debug!(error = %e, "read timeout not set"),
            }
        }
    }

    /// The longest wait in a receive: [`MAX_WAIT`], or [`POLL_WAIT`] without a waker.
    fn max_wait(&self) -> Duration {
        if self.wake_from.is_some() {
            MAX_WAIT
        } else {
            POLL_WAIT
        }
    }

    /// Applies the waiting commands; true when the thread is to end.
    fn commands(&mut self) -> bool {
        while self.open {
            match self.rx.try_recv() {
                Ok(Command::Shutdown) => return true,
                Ok(cmd) => self.apply(cmd),
                Err(TryRecvError::Empty) => break,
                Err(TryRecvError::Disconnected) => self.open = false,
            }
        }
        false
    }

    /// Joins or leaves a group: on the socket itself when it is bound to a wildcard address
    /// (it then receives the group's datagrams too), else through a group socket of its own.
    fn membership(&mut self, group: IpAddr, interface: u32, join: bool) -> std::io::Result<()> {
        if self.socket.local_addr().ip().is_unspecified() {
            return if join {
                self.socket.join(group, interface)
            } else {
                self.socket.leave(group, interface)
            };
        }
        self.groups
            .retain(|g| !(g.group == group && g.interface == interface));
        if join {
            let local = self.socket.local_addr();
            let socket = Arc::new(Socket::bind_group(
                group,
                local.port(),
                interface,
                local.ip(),
            )?);
            self.memberships += 1;
            let membership = self.memberships;
            let (s, tx, waker) = (socket.clone(), self.tx.clone(), self.waker.clone());
            std::thread::Builder::new()
                .name(format!("coap group {group}"))
                .spawn(move || receive_group(&s, membership, &tx, &waker))?;
            self.groups.push(Group {
                group,
                interface,
                membership,
                socket,
            });
        }
        Ok(())
    }

    fn apply(&mut self, cmd: Command) {
        let now = clock::now();
        match cmd {
            Command::Request {
                peer,
                request,
                reply,
                id_tx,
            } => {
                let id = self.ep.request(now, peer, request);
                self.replies.insert(id, (peer, reply));
                if let Some(tx) = id_tx {
                    let _ = tx.send(id);
                }
            }
            Command::Cancel(id) => {
                self.ep.cancel(now, id);
                // The Cancelled failure event is dropped with the reply.
                self.replies.remove(&id);
            }
            Command::Respond { id, response } => self.ep.respond(now, id, response),
            Command::Notify { id, response, done } => {
                let _ = done.send(self.ep.notify(now, id, response));
            }
            Command::Ping { peer, reply } => {
                let id = self.ep.ping(now, peer);
                self.pings.insert(id, reply);
            }
            Command::PathStats { peer, reply } => {
                let _ = reply.send(self.ep.path_stats(peer));
            }
            Command::RememberRtt { peer, rtt } => self.ep.remember_rtt(now, peer, rtt),
            Command::Membership {
                group,
                interface,
                join,
                done,
            } => {
                let _ = done.send(self.membership(group, interface, join));
            }
            Command::GroupDatagram {
                membership,
                peer,
                data,
                loopback,
            } => {
                // A datagram that arrived before its group was left is dropped.
                if self.groups.iter().any(|g| g.membership == membership) {
                    self.ep.handle(now, peer, &data, true);
                    self.events(loopback);
                }
            }
            // Ends the thread's loop before it gets here.
            Command::Shutdown => {}
        }
    }

    /// Fails every request to `peer` with `error` and stops its exchanges.
    fn fail_peer(&mut self, peer: SocketAddr, error: RequestError) {
        let now = clock::now();
        let ids: Vec<RequestId> = self
            .replies
            .iter()
            .filter(|(_, (p, _))| *p == peer)
            .map(|(id, _)| *id)
            .collect();
        for id in ids {
            // Removed first: the Cancelled failure the endpoint reports is dropped.
            if let Some((_, reply)) = self.replies.remove(&id) {
                self.ep.cancel(now, id);
                match reply {
                    Reply::Once(tx) | Reply::Tracked(tx, _) => {
                        let _ = tx.send(Err(error.clone()));
                    }
                    Reply::Stream(tx) => {
                        let _ = tx.send(StreamItem::Failed(error.clone()));
                    }
                    Reply::Body(tx) => {
                        let _ = tx.send(BodyItem::Failed(error.clone()));
                    }
                }
            }
        }
    }

    /// Hands on the endpoint's events; a request among them came over loopback when
    /// `loopback` says so (the datagram just handled did).
    fn events(&mut self, loopback: bool) {
        while let Some(ev) = self.ep.poll_event() {
            self.dispatch(ev, loopback);
        }
    }

    fn dispatch(&mut self, ev: Event, loopback: bool) {
        match ev {
            Event::Request(mut req) => match &self.server {
                Some(s) => {
                    let id = req.id;
                    req.identity = self.dtls.as_ref().and_then(|d| d.identity(req.peer));
                    req.loopback = loopback;
                    if s.send(ServerEvent::Request(Box::new(req))).is_err() {
                        self.ep.respond(
                            clock::now(),
                            id,
                            Response::diagnostic(coap::Code::SERVICE_UNAVAILABLE, "shutting down"),
                        );
                    }
                }
                None => self
                    .ep
                    .respond(clock::now(), req.id, Response::new(coap::Code::NOT_FOUND)),
            },
            Event::ObservationEnded { id } => {
                if let Some(s) = &self.server {
                    let _ = s.send(ServerEvent::ObservationEnded(id));
                }
            }
            Event::Response { id, response } => {
                if let Some((peer, Reply::Stream(tx))) = self.replies.get(&id) {
                    // An Observe request stays open for its notifications; anything else ends.
                    let observing = response.options.contains(coap::OptionNumber::OBSERVE);
                    let _ = tx.send(StreamItem::Response(*peer, Box::new(response)));
                    if !observing {
                        self.replies.remove(&id);
                    }
                    return;
                }
                match self.replies.remove(&id) {
                    Some((_, Reply::Once(tx) | Reply::Tracked(tx, _))) => {
                        let _ = tx.send(Ok(response));
                    }
                    Some((_, Reply::Body(tx))) => {
                        let _ = tx.send(BodyItem::Done(Box::new(response)));
                    }
                    Some((_, Reply::Stream(_))) | None => {}
                }
            }
            Event::BodyChunk {
                id, data, total, ..
            } => {
                let gone = match self.replies.get(&id) {
                    Some((_, Reply::Body(tx))) => tx.send(BodyItem::Chunk(data, total)).is_err(),
                    _ => false,
                };
                if gone {
                    // Nobody reads the body any more: stop the transfer.
                    self.replies.remove(&id);
                    self.ep.cancel(clock::now(), id);
                }
            }
            Event::Progress { id, done, total } => {
                if let Some((_, Reply::Tracked(_, p))) = self.replies.get(&id) {
                    let _ = p.send(Progress { done, total });
                }
            }
            Event::Notification { id, response } => {
                // A notification without Observe is the last one (RFC 7641 §3.2).
                let last = !response.options.contains(coap::OptionNumber::OBSERVE);
                if let Some((peer, Reply::Stream(tx))) = self.replies.get(&id) {
                    let _ = tx.send(StreamItem::Response(*peer, Box::new(response)));
                }
                if last {
                    self.replies.remove(&id);
                }
            }
            Event::MulticastResponse { id, peer, response } => {
                if let Some((_, Reply::Stream(tx))) = self.replies.get(&id) {
                    let _ = tx.send(StreamItem::Response(peer, Box::new(response)));
                }
            }
            Event::MulticastDone { id } => {
                self.replies.remove(&id);
            }
            Event::RequestFailed { id, error } => match self.replies.remove(&id) {
                Some((_, Reply::Once(tx) | Reply::Tracked(tx, _))) => {
                    let _ = tx.send(Err(error));
                }
                Some((_, Reply::Stream(tx))) => {
                    let _ = tx.send(StreamItem::Failed(error));
                }
                Some((_, Reply::Body(tx))) => {
                    let _ = tx.send(BodyItem::Failed(error));
                }
                None => {
                    if let Some(tx) = self.pings.remove(&id) {
                        let _ = tx.send(Err(error));
                    }
                }
            },
            Event::Pong { id } => {
                if let Some(tx) = self.pings.remove(&id) {
                    let _ = tx.send(Ok(()));
                }
            }
        }
    }
}

/// Whether a receive error only says the read timeout passed with nothing received.
fn timed_out(e: &std::io::Error) -> bool {
    matches!(
        e.kind(),
        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
    )
}

/// A group socket's thread: hands every datagram to the endpoint thread until the group
/// is left or the endpoint is gone.
fn receive_group(
    socket: &Arc<Socket>,
    membership: u64,
    tx: &mpsc::WeakUnboundedSender<Command>,
    waker: &Weak<Waker>,
) {
    let mut buf = vec![0u8; RECV_BUFFER];
    if let Err(e) = socket.set_read_timeout(Some(MAX_WAIT)) {
        tracing::debug!(error = %e, "group socket read timeout not set");
    }
    loop {
        let got = socket.recv(&mut buf);
        // The endpoint thread holds the other reference while the group is joined.
        if Arc::strong_count(socket) == 1 {
            return;
        }
        match got {
            Ok(d) if d.forged_loopback() => {
                tracing::debug!(peer = %d.peer, "dropped: a loopback source from outside");
            }
            Ok(d) => {
                let (Some(tx), Some(waker)) = (tx.upgrade(), waker.upgrade()) else {
                    return;
                };
                let cmd = Command::GroupDatagram {
                    membership,
                    peer: d.peer,
                    data: buf[..d.len].to_vec(),
                    loopback: d.loopback == Some(true),
                };
                if tx.send(cmd).is_err() {
                    return;
                }
                waker.wake();
            }
            Err(e) if timed_out(&e) => {
                if tx.upgrade().is_none() {
                    return;
                }
            }
            Err(e) => tracing::debug!(error = %e, "group recv failed"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Resource, Router, Server, ServerConfig, handler};

    #[tokio::test]
    async fn without_a_waker_the_thread_polls_for_commands() {
        // A host whose loopback cannot reach the socket's address gives no waker.
        let router = Router::new();
        router.add(
            "/x",
            Resource::new().get(handler(|_| async {
                Response::new(coap::Code::CONTENT).with_payload("x")
            })),
        );
        let any: SocketAddr = ([127, 0, 0, 1], 0).into();
        let server =
            Server::bind(&[any], ServerConfig::default(), router).unwrap_or_else(|e| panic!("{e}"));
        let socket = Socket::bind(any).unwrap_or_else(|e| panic!("{e}"));
        let waker = Waker {
            socket: None,
            pending: Arc::new(AtomicBool::new(false)),
        };
        let handle = start(socket, EndpointConfig::default(), None, waker, None)
            .unwrap_or_else(|e| panic!("{e}"));
        let (tx, rx) = oneshot::channel();
        let request = Request::new(coap::Code::GET, "/x");
        handle
            .send(Command::Request {
                peer: server.local_addrs()[0],
                request,
                reply: Reply::Once(tx),
                id_tx: None,
            })
            .unwrap_or_else(|e| panic!("{e}"));
        let response = tokio::time::timeout(Duration::from_secs(10), rx)
            .await
            .unwrap_or_else(|_| panic!("no response"))
            .unwrap_or_else(|_| panic!("endpoint gone"))
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(&response.payload[..], b"x");
    }
}
