//! One task per socket owns a `coap::Endpoint`: it moves datagrams between the socket and
//! the endpoint, sleeps until the endpoint's next timeout, and exchanges commands and
//! events with the rest of the program over channels. Nothing here decides protocol
//! behaviour.

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;

use coap::{
    Endpoint, EndpointConfig, Event, IncomingRequest, ObservationId, Request, RequestError,
    RequestId, Response,
};
use tokio::sync::{mpsc, oneshot};

use crate::clock;
use crate::socket::{RECV_BUFFER, Received, Socket};

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
    Done(Response),
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
    Response(SocketAddr, Response),
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
    Membership {
        group: IpAddr,
        interface: u32,
        join: bool,
        done: oneshot::Sender<std::io::Result<()>>,
    },
    Shutdown,
}

/// A handle to a running endpoint task. Cloning it is cheap; the task ends when every
/// handle and the server side are gone.
#[derive(Clone, Debug)]
pub struct EndpointHandle {
    pub(crate) tx: mpsc::UnboundedSender<Command>,
    local: SocketAddr,
}

/// Requests received by an endpoint that serves, and the end of observations.
pub(crate) enum ServerEvent {
    Request(IncomingRequest),
    ObservationEnded(ObservationId),
}

impl EndpointHandle {
    /// The socket's local address.
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }

    pub(crate) fn send(&self, cmd: Command) -> Result<(), crate::Error> {
        self.tx.send(cmd).map_err(|_| crate::Error::Closed)
    }
}

/// Starts the task for `socket`. Requests go to `server` when given; a client-only
/// endpoint answers them 4.04.
pub(crate) fn spawn(
    socket: Socket,
    config: EndpointConfig,
    server: Option<mpsc::UnboundedSender<ServerEvent>>,
) -> EndpointHandle {
    let (tx, rx) = mpsc::unbounded_channel();
    let local = socket.local_addr();
    tokio::spawn(run(Arc::new(socket), Endpoint::new(config), rx, server));
    EndpointHandle { tx, local }
}

async fn run(
    socket: Arc<Socket>,
    mut ep: Endpoint,
    mut rx: mpsc::UnboundedReceiver<Command>,
    server: Option<mpsc::UnboundedSender<ServerEvent>>,
) {
    let mut buf = vec![0u8; RECV_BUFFER];
    let mut received: Vec<Received> = Vec::new();
    // Group sockets of a server bound to a unicast address: they only receive; every
    // answer leaves from the unicast socket (RFC 7390 §2.5: from the unicast address).
    let mut groups: Vec<(IpAddr, u32, Socket)> = Vec::new();
    // Allocated with the first group socket: most endpoints never join a group.
    let mut group_buf: Vec<u8> = Vec::new();
    let mut group_received: Vec<Received> = Vec::new();
    let mut replies: HashMap<RequestId, (SocketAddr, Reply)> = HashMap::new();
    let mut pings: HashMap<RequestId, oneshot::Sender<Result<(), RequestError>>> = HashMap::new();
    let mut open = true;
    // One timer, moved only when the endpoint's next deadline moves.
    let far = tokio::time::Instant::now() + std::time::Duration::from_secs(86_400 * 365);
    let sleep = tokio::time::sleep_until(far);
    tokio::pin!(sleep);
    let mut armed: Option<std::time::Instant> = None;
    loop {
        while let Some(t) = ep.poll_transmit() {
            if let Err(e) = socket.send_to(&t.data, t.peer).await {
                tracing::debug!(peer = %t.peer, error = %e, "send failed");
            }
        }
        while let Some(ev) = ep.poll_event() {
            dispatch(ev, &mut replies, &mut pings, server.as_ref(), &mut ep);
        }
        if !open
            && replies.is_empty()
            && pings.is_empty()
            && server.as_ref().is_none_or(|s| s.is_closed())
        {
            return;
        }
        let timeout = ep.poll_timeout();
        if timeout != armed {
            armed = timeout;
            sleep
                .as_mut()
                .reset(timeout.map_or(far, tokio::time::Instant::from_std));
        }
        tokio::select! {
            r = socket.recv(&mut buf, &mut received) => match r {
                Ok(()) => {
                    let now = clock::now();
                    for d in &received {
                        let (start, len) = d.range;
                        ep.handle(now, d.peer, &buf[start..start + len], d.multicast);
                    }
                }
                // ICMP errors (port unreachable) surface here on Linux; they say nothing
                // the retransmission timers do not already handle.
                Err(e) => tracing::debug!(error = %e, "recv failed"),
            },
            r = recv_any(&groups, &mut group_buf, &mut group_received), if !groups.is_empty() => match r {
                Ok(()) => {
                    let now = clock::now();
                    for d in &group_received {
                        let (start, len) = d.range;
                        ep.handle(now, d.peer, &group_buf[start..start + len], true);
                    }
                }
                Err(e) => tracing::debug!(error = %e, "group recv failed"),
            },
            cmd = rx.recv(), if open => match cmd {
                Some(Command::Shutdown) => return,
                Some(Command::Membership { group, interface, join, done }) => {
                    let joined = membership(&socket, &mut groups, group, interface, join);
                    if !groups.is_empty() && group_buf.is_empty() {
                        group_buf = vec![0u8; RECV_BUFFER];
                    }
                    let _ = done.send(joined);
                }
                Some(cmd) => apply(cmd, &mut ep, &mut replies, &mut pings),
                None => open = false,
            },
            () = &mut sleep, if armed.is_some() => {
                // Fired: re-arm on the next turn even if the deadline stays the same.
                armed = None;
                ep.handle_timeout(clock::now());
            }
        }
    }
}

/// Joins or leaves a group: on the socket itself when it is bound to a wildcard address
/// (it then receives the group's datagrams too), else through a group socket of its own.
fn membership(
    socket: &Socket,
    groups: &mut Vec<(IpAddr, u32, Socket)>,
    group: IpAddr,
    interface: u32,
    join: bool,
) -> std::io::Result<()> {
    if socket.local_addr().ip().is_unspecified() {
        return if join {
            socket.join(group, interface)
        } else {
            socket.leave(group, interface)
        };
    }
    groups.retain(|(g, i, _)| !(*g == group && *i == interface));
    if join {
        let s = Socket::bind_group(group, socket.local_addr().port(), interface)?;
        groups.push((group, interface, s));
    }
    Ok(())
}

/// Waits for a datagram on any of the group sockets.
async fn recv_any(
    groups: &[(IpAddr, u32, Socket)],
    buf: &mut [u8],
    out: &mut Vec<Received>,
) -> std::io::Result<()> {
    std::future::poll_fn(|cx| {
        for (_, _, s) in groups {
            if let std::task::Poll::Ready(r) = s.poll_recv(cx, buf, out) {
                return std::task::Poll::Ready(r);
            }
        }
        std::task::Poll::Pending
    })
    .await
}

fn apply(
    cmd: Command,
    ep: &mut Endpoint,
    replies: &mut HashMap<RequestId, (SocketAddr, Reply)>,
    pings: &mut HashMap<RequestId, oneshot::Sender<Result<(), RequestError>>>,
) {
    let now = clock::now();
    match cmd {
        Command::Request {
            peer,
            request,
            reply,
            id_tx,
        } => {
            let id = ep.request(now, peer, request);
            replies.insert(id, (peer, reply));
            if let Some(tx) = id_tx {
                let _ = tx.send(id);
            }
        }
        Command::Cancel(id) => {
            ep.cancel(now, id);
            // The Cancelled failure event is dropped with the reply.
            replies.remove(&id);
        }
        Command::Respond { id, response } => ep.respond(now, id, response),
        Command::Notify { id, response, done } => {
            let _ = done.send(ep.notify(now, id, response));
        }
        Command::Ping { peer, reply } => {
            let id = ep.ping(now, peer);
            pings.insert(id, reply);
        }
        // Handled by the task loop, which owns the sockets.
        Command::Membership { .. } | Command::Shutdown => {}
    }
}

fn dispatch(
    ev: Event,
    replies: &mut HashMap<RequestId, (SocketAddr, Reply)>,
    pings: &mut HashMap<RequestId, oneshot::Sender<Result<(), RequestError>>>,
    server: Option<&mpsc::UnboundedSender<ServerEvent>>,
    ep: &mut Endpoint,
) {
    match ev {
        Event::Request(req) => match server {
            Some(s) => {
                let id = req.id;
                if s.send(ServerEvent::Request(req)).is_err() {
                    ep.respond(
                        clock::now(),
                        id,
                        Response::diagnostic(coap::Code::SERVICE_UNAVAILABLE, "shutting down"),
                    );
                }
            }
            None => ep.respond(clock::now(), req.id, Response::new(coap::Code::NOT_FOUND)),
        },
        Event::ObservationEnded { id } => {
            if let Some(s) = server {
                let _ = s.send(ServerEvent::ObservationEnded(id));
            }
        }
        Event::Response { id, response } => match replies.get(&id) {
            Some((peer, Reply::Stream(tx))) => {
                // An Observe request stays open for its notifications; anything else ends.
                let observing = response.options.contains(coap::OptionNumber::OBSERVE);
                let _ = tx.send(StreamItem::Response(*peer, response));
                if !observing {
                    replies.remove(&id);
                }
            }
            Some((_, Reply::Once(_) | Reply::Tracked(..) | Reply::Body(_))) => {
                match replies.remove(&id) {
                    Some((_, Reply::Once(tx) | Reply::Tracked(tx, _))) => {
                        let _ = tx.send(Ok(response));
                    }
                    Some((_, Reply::Body(tx))) => {
                        let _ = tx.send(BodyItem::Done(response));
                    }
                    _ => {}
                }
            }
            None => {}
        },
        Event::BodyChunk {
            id, data, total, ..
        } => {
            let gone = match replies.get(&id) {
                Some((_, Reply::Body(tx))) => tx.send(BodyItem::Chunk(data, total)).is_err(),
                _ => false,
            };
            if gone {
                // Nobody reads the body any more: stop the transfer.
                replies.remove(&id);
                ep.cancel(clock::now(), id);
            }
        }
        Event::Progress { id, done, total } => {
            if let Some((_, Reply::Tracked(_, p))) = replies.get(&id) {
                let _ = p.send(Progress { done, total });
            }
        }
        Event::Notification { id, response } => {
            // A notification without Observe is the last one (RFC 7641 §3.2).
            let last = !response.options.contains(coap::OptionNumber::OBSERVE);
            if let Some((peer, Reply::Stream(tx))) = replies.get(&id) {
                let _ = tx.send(StreamItem::Response(*peer, response));
            }
            if last {
                replies.remove(&id);
            }
        }
        Event::MulticastResponse { id, peer, response } => {
            if let Some((_, Reply::Stream(tx))) = replies.get(&id) {
                let _ = tx.send(StreamItem::Response(peer, response));
            }
        }
        Event::MulticastDone { id } => {
            replies.remove(&id);
        }
        Event::RequestFailed { id, error } => match replies.remove(&id) {
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
                if let Some(tx) = pings.remove(&id) {
                    let _ = tx.send(Err(error));
                }
            }
        },
        Event::Pong { id } => {
            if let Some(tx) = pings.remove(&id) {
                let _ = tx.send(Ok(()));
            }
        }
    }
}
