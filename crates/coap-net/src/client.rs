//! The client: requests with transparent block-wise transfer, Observe as a stream,
//! multicast requests that collect every server's response, ping; over UDP (or DTLS), or
//! over TCP ([`Client::tcp`], `coap+tcp://`) or WebSockets ([`Client::ws`], `coap+ws://`),
//! either with TLS ([`Client::tls`], [`Client::wss`]), chosen when it is made, so that what sends
//! requests does not care which.

use std::net::SocketAddr;

use coap::{EndpointConfig, Request, RequestId, Response};
use tokio::sync::{mpsc, oneshot};

use crate::Error;
use crate::driver::{self, BodyItem, Command, EndpointHandle, Progress, Reply, StreamItem};
use crate::dtls::Psk;
use crate::socket::Socket;
use crate::tcp::{TcpClient, TcpObservation};

/// How often [`Client::multicast_until`] asks again whether it is done.
const RECHECK: std::time::Duration = std::time::Duration::from_millis(50);

/// The wildcard address of `peer`'s family, any port.
fn any_for(peer: SocketAddr) -> SocketAddr {
    if peer.is_ipv4() {
        ([0, 0, 0, 0], 0).into()
    } else {
        ([0u16; 8], 0).into()
    }
}

/// A CoAP client on one socket, or over TCP connections. Cheap to clone; requests from
/// clones share the socket, the message IDs and NSTART (or the connections).
///
/// Over TCP ([`Client::tcp`]) or WebSockets ([`Client::ws`]) a request goes whole, as one message, and its response
/// comes so: [`Client::send_with_progress`] reports once, when it has come, and
/// [`Client::send_streamed`] gives the body as one piece; multicast is refused with
/// [`Error::Unsupported`] (RFC 8323 has none), and there are no path statistics.
/// [`Client::observe`] works over either (RFC 8323 §7 over streams).
#[derive(Clone, Debug)]
pub struct Client {
    transport: Transport,
}

/// How a [`Client`] reaches its servers.
#[derive(Clone, Debug)]
enum Transport {
    /// Datagrams from one endpoint's socket (UDP, or DTLS over it).
    Udp(EndpointHandle),
    /// One TCP connection per server, or one WebSocket (RFC 8323).
    Tcp(TcpClient),
}

/// A seed for a new client endpoint's message IDs and tokens
/// ([`EndpointConfig::rng_seed`]) that no other client shares, in this process or another.
/// A fixed seed makes every new socket send the same message IDs with the same tokens;
/// when the kernel gives one the port of an earlier one (it reuses free ephemeral ports)
/// within EXCHANGE_LIFETIME, the server takes its requests for that socket's duplicates
/// (RFC 7252 §4.5) and answers them from its deduplication store: the old answers, say
/// an earlier scene's frame, with nothing to tell them apart. The keys of std's
/// `RandomState` come from the OS (different in every process and thread, and moved on
/// by every `new`); the process id and a counter are hashed under them.
pub fn fresh_seed() -> u64 {
    use std::hash::{BuildHasher as _, RandomState};
    use std::sync::atomic::{AtomicU64, Ordering};
    static CLIENTS: AtomicU64 = AtomicU64::new(0);
    RandomState::new().hash_one((std::process::id(), CLIENTS.fetch_add(1, Ordering::Relaxed)))
}

impl Client {
    /// A client on a socket bound to `addr` (port 0 picks a free one).
    pub fn bind(addr: SocketAddr, config: EndpointConfig) -> std::io::Result<Self> {
        Self::bind_secured(addr, config, None)
    }

    /// [`Client::bind`] speaking DTLS (`coaps://`) with `psk` (a [`Psk::Client`]), when
    /// given: every peer is reached through a DTLS session, opened at its first request.
    pub fn bind_secured(
        addr: SocketAddr,
        config: EndpointConfig,
        psk: Option<&Psk>,
    ) -> std::io::Result<Self> {
        let socket = Socket::bind(addr)?;
        let handle = driver::spawn(socket, config, None, psk)?;
        Ok(Self::from_handle(handle))
    }

    /// A client on an endpoint that already runs (a server's, [`crate::Server::client_for`]).
    pub(crate) fn from_handle(handle: EndpointHandle) -> Self {
        Self {
            transport: Transport::Udp(handle),
        }
    }

    /// A `coap+tcp` client (RFC 8323): a connection to each server it sends to, opened by
    /// the first request. Of `config` only the body limit
    /// ([`coap::Limits::client_body_bytes`]) applies.
    pub fn tcp(config: &EndpointConfig) -> Self {
        Self {
            transport: Transport::Tcp(TcpClient::new(config.limits.client_body_bytes)),
        }
    }

    /// A `coap+ws` client (RFC 8323 §4): as [`Client::tcp`], each connection a WebSocket
    /// to the server's `/.well-known/coap`.
    pub fn ws(config: &EndpointConfig) -> Self {
        let ws = TcpClient::websocket(config.limits.client_body_bytes);
        Self {
            transport: Transport::Tcp(ws),
        }
    }

    /// A `coaps+tcp` client (RFC 8323, TLS): as [`Client::tcp`], each connection TLS with
    /// `key` (a [`Psk::Client`]; see [`TcpClient::tls`]).
    pub fn tls(config: &EndpointConfig, key: &Psk) -> std::io::Result<Self> {
        let tls = TcpClient::tls(config.limits.client_body_bytes, key)?;
        Ok(Self {
            transport: Transport::Tcp(tls),
        })
    }

    /// A `coaps+ws` client (RFC 8323 §4, a `wss` WebSocket): as [`Client::ws`] over TLS
    /// with `key` (see [`TcpClient::wss`]).
    pub fn wss(config: &EndpointConfig, key: &Psk) -> std::io::Result<Self> {
        let wss = TcpClient::wss(config.limits.client_body_bytes, key)?;
        Ok(Self {
            transport: Transport::Tcp(wss),
        })
    }

    /// The endpoint of a UDP client; over TCP, [`Error::Unsupported`] naming `what`.
    fn udp(&self, what: &'static str) -> Result<&EndpointHandle, Error> {
        match &self.transport {
            Transport::Udp(handle) => Ok(handle),
            Transport::Tcp(_) => Err(Error::Unsupported(what)),
        }
    }

    /// A client on an ephemeral port of the right address family for `peer`.
    pub fn for_peer(peer: SocketAddr, config: EndpointConfig) -> std::io::Result<Self> {
        Self::bind(any_for(peer), config)
    }

    /// [`Client::for_peer`] speaking DTLS with `psk`, when given.
    pub fn for_peer_secured(
        peer: SocketAddr,
        config: EndpointConfig,
        psk: Option<&Psk>,
    ) -> std::io::Result<Self> {
        Self::bind_secured(any_for(peer), config, psk)
    }

    /// The local socket address. A TCP client, which has an address per connection,
    /// answers the unspecified IPv4 address and port 0.
    pub fn local_addr(&self) -> SocketAddr {
        match &self.transport {
            Transport::Udp(handle) => handle.local_addr(),
            Transport::Tcp(_) => ([0, 0, 0, 0], 0).into(),
        }
    }

    /// Sends a request and waits for its whole response (every block).
    pub async fn send(&self, peer: SocketAddr, request: Request) -> Result<Response, Error> {
        let handle = match &self.transport {
            Transport::Udp(handle) => handle,
            Transport::Tcp(tcp) => return tcp.send(peer, request).await,
        };
        let (tx, rx) = oneshot::channel();
        handle.send(Command::Request {
            peer,
            request,
            reply: Reply::Once(tx),
            id_tx: None,
        })?;
        rx.await.map_err(|_| Error::Closed)?.map_err(Error::Request)
    }

    /// Like [`Client::send`], and reports the progress of a block-wise transfer on
    /// `progress` after every block.
    pub async fn send_with_progress(
        &self,
        peer: SocketAddr,
        mut request: Request,
        progress: mpsc::UnboundedSender<Progress>,
    ) -> Result<Response, Error> {
        if let Transport::Tcp(tcp) = &self.transport {
            let response = tcp.send(peer, request).await?;
            let done = response.payload.len();
            let _ = progress.send(Progress {
                done,
                total: Some(done),
            });
            return Ok(response);
        }
        request.progress = true;
        let (tx, rx) = oneshot::channel();
        let reply = Reply::Tracked(tx, progress);
        self.udp("progress")?.send(Command::Request {
            peer,
            request,
            reply,
            id_tx: None,
        })?;
        rx.await.map_err(|_| Error::Closed)?.map_err(Error::Request)
    }

    /// Sends a request and streams the body of a success response while its blocks
    /// arrive (RFC 7959 Block2), in pieces of 64 KiB, so a large body is never reassembled
    /// in memory and the reader wakes once per piece, not per block. The
    /// pieces are provisional: only [`BodyPart::End`] says the body arrived whole; an
    /// error after some pieces (an ETag that changed mid-transfer, a missing block, a
    /// total that differs from Size2, a timeout) means they must be discarded. Dropping
    /// the stream cancels the transfer. Pieces the reader has not taken yet wait in a
    /// queue, which the endpoint's `client_body_bytes` limit bounds like any body.
    pub fn send_streamed(
        &self,
        peer: SocketAddr,
        mut request: Request,
    ) -> Result<BodyStream, Error> {
        let (tx, rx) = mpsc::unbounded_channel();
        if let Transport::Tcp(tcp) = &self.transport {
            let tcp = tcp.clone();
            tokio::spawn(async move {
                let item = match tcp.send(peer, request).await {
                    Err(Error::Request(e)) => BodyItem::Failed(e),
                    Err(_) => return,
                    Ok(mut response) => {
                        if response.code.is_success() && !response.payload.is_empty() {
                            let body = std::mem::take(&mut response.payload);
                            let total = Some(body.len());
                            let _ = tx.send(BodyItem::Chunk(body, total));
                        }
                        BodyItem::Done(Box::new(response))
                    }
                };
                let _ = tx.send(item);
            });
            return Ok(BodyStream { rx });
        }
        request.stream = true;
        self.udp("streaming")?.send(Command::Request {
            peer,
            request,
            reply: Reply::Body(tx),
            id_tx: None,
        })?;
        Ok(BodyStream { rx })
    }

    /// [`Client::send_streamed`] into `sink`: writes each piece as it arrives and returns
    /// the response (with an empty payload) and the number of body bytes written. On an
    /// error the sink holds a partial body: write to a temporary place and keep it only
    /// on `Ok`.
    pub async fn send_to_writer<W: std::io::Write>(
        &self,
        peer: SocketAddr,
        request: Request,
        sink: &mut W,
    ) -> Result<(Response, usize), Error> {
        let mut stream = self.send_streamed(peer, request)?;
        let mut written = 0;
        loop {
            match stream.next().await? {
                BodyPart::Chunk { data, .. } => {
                    sink.write_all(&data)?;
                    written += data.len();
                }
                BodyPart::End(response) => {
                    sink.flush()?;
                    return Ok((*response, written));
                }
            }
        }
    }

    /// Registers an Observe on `peer` (the request gets Observe 0). The stream yields the
    /// first response, then each notification; dropping it cancels the observation (over
    /// UDP the next notification is answered with a Reset; over a stream a GET with
    /// Observe 1 deregisters, RFC 8323 §7.4).
    pub async fn observe(
        &self,
        peer: SocketAddr,
        mut request: Request,
    ) -> Result<Observation, Error> {
        let mut follow_up = request.clone();
        follow_up.options.remove(coap::OptionNumber::OBSERVE);
        request.options.set_uint(coap::OptionNumber::OBSERVE, 0);
        if let Transport::Tcp(tcp) = &self.transport {
            let (registration, rx) = tcp.observe(peer, request).await?;
            return Ok(Observation {
                rx,
                registration: Registration::Stream(registration),
                client: self.clone(),
                follow_up,
                skipped: 0,
            });
        }
        let (tx, rx) = mpsc::unbounded_channel();
        let (id_tx, id_rx) = oneshot::channel();
        self.udp("Observe")?.send(Command::Request {
            peer,
            request,
            reply: Reply::Stream(tx),
            id_tx: Some(id_tx),
        })?;
        let id = id_rx.await.map_err(|_| Error::Closed)?;
        Ok(Observation {
            rx,
            registration: Registration::Udp(id),
            client: self.clone(),
            follow_up,
            skipped: 0,
        })
    }

    /// Sends a request to a multicast group and collects every server's response until the
    /// request's timeout (5 s when unset). An answer sent block-wise is completed by
    /// unicast requests to its server.
    pub async fn multicast(
        &self,
        group: SocketAddr,
        request: Request,
    ) -> Result<Vec<(SocketAddr, Response)>, Error> {
        self.multicast_expecting(group, request, None).await
    }

    /// [`Client::multicast`] that stops collecting as soon as `expected` servers have
    /// answered (or at the timeout, whichever comes first).
    pub async fn multicast_expecting(
        &self,
        group: SocketAddr,
        request: Request,
        expected: Option<usize>,
    ) -> Result<Vec<(SocketAddr, Response)>, Error> {
        self.multicast_until(group, request, |answers| {
            expected.is_some_and(|n| answers.len() >= n)
        })
        .await
    }

    /// [`Client::multicast`] that stops collecting as soon as `done` says the answers so
    /// far are enough (e.g. every member a directory lists has answered), or at the
    /// timeout, whichever comes first. `done` is asked after each answer and every
    /// 50 ms.
    pub async fn multicast_until(
        &self,
        group: SocketAddr,
        mut request: Request,
        mut done: impl FnMut(&[(SocketAddr, Response)]) -> bool,
    ) -> Result<Vec<(SocketAddr, Response)>, Error> {
        request.multicast = true;
        let follow_up = request.clone();
        let (tx, mut rx) = mpsc::unbounded_channel();
        self.udp("multicast")?.send(Command::Request {
            peer: group,
            request,
            reply: Reply::Stream(tx),
            id_tx: None,
        })?;
        let mut out = Vec::new();
        loop {
            // `done` is asked after each answer and every RECHECK: it may depend on what
            // the caller learns meanwhile (a member found gone).
            match tokio::time::timeout(RECHECK, rx.recv()).await {
                Ok(Some(StreamItem::Response(peer, r))) => out.push((peer, *r)),
                Ok(Some(StreamItem::Failed(e))) => return Err(Error::Request(e)),
                Ok(None) => break,
                Err(_) => {}
            }
            if done(&out) {
                break;
            }
        }
        for (peer, response) in &mut out {
            if let Some(echo) = response
                .options
                .first(coap::OptionNumber::ECHO)
                .filter(|_| response.code == coap::Code::UNAUTHORIZED)
            {
                // RFC 9175 §2.4: this server has not verified our address and answered
                // the group request with an Echo challenge only; the request goes to it
                // again by unicast, with the Echo value.
                let mut again = follow_up.clone();
                again.multicast = false;
                again.options.set(coap::OptionNumber::ECHO, echo);
                *response = self.send(*peer, again).await?;
            }
            self.rest_of_blocks(*peer, &follow_up, response, false)
                .await?;
        }
        Ok(out)
    }

    /// A multicast answer or a notification that came as Block2 block 0 with more to
    /// follow: the other blocks are asked of that server by unicast (RFC 7959 §2.8 with
    /// RFC 7390; §2.6 for Observe), one after the other, and must carry the first block's
    /// ETag. When one does not, the representation changed meanwhile: with `refetch` (an
    /// observed resource, where that is the normal case) the new representation is
    /// fetched whole by a GET without Block2, which the endpoint reassembles and starts
    /// over a few times itself; the notification keeps its Observe number. Without it, or
    /// when even that fetch keeps changing, it fails with
    /// [`coap::RequestError::RepresentationChanged`].
    async fn rest_of_blocks(
        &self,
        peer: SocketAddr,
        original: &Request,
        response: &mut Response,
        refetch: bool,
    ) -> Result<(), Error> {
        let Some(first) = response.options.block2().filter(|b| b.more && b.num == 0) else {
            return Ok(());
        };
        let etag = response.options.etag().map(<[u8]>::to_vec);
        let mut body = response.payload.to_vec();
        let mut block = first;
        while block.more {
            let mut next = original.clone();
            next.multicast = false;
            next.payload = bytes::Bytes::new();
            let num = u32::try_from(body.len() / block.size()).map_err(|_| {
                Error::Request(coap::RequestError::Protocol("block number out of range"))
            })?;
            let opt = coap::BlockOpt {
                num,
                more: false,
                szx: block.szx,
            };
            next.options.set_block(coap::OptionNumber::BLOCK2, opt);
            let r = self.send(peer, next).await?;
            let got = r
                .options
                .block2()
                .filter(|b| b.num == num && r.code.is_success());
            let Some(got) = got else {
                return Err(Error::Request(coap::RequestError::Protocol(
                    "a multicast follow-up lost its Block2",
                )));
            };
            if r.options.etag().map(<[u8]>::to_vec) != etag {
                if !refetch {
                    return Err(Error::Request(coap::RequestError::RepresentationChanged));
                }
                let mut whole = original.clone();
                whole.multicast = false;
                whole.payload = bytes::Bytes::new();
                whole.options.remove(coap::OptionNumber::BLOCK2);
                let observe = response.options.uint(coap::OptionNumber::OBSERVE);
                *response = self.send(peer, whole).await?;
                if let Some(seq) = observe {
                    response.options.set_uint(coap::OptionNumber::OBSERVE, seq);
                }
                return Ok(());
            }
            body.extend_from_slice(&r.payload);
            block = got;
        }
        response.options.remove(coap::OptionNumber::BLOCK2);
        response.payload = body.into();
        Ok(())
    }

    /// What the endpoint knows of the path to `peer`: its round-trip estimate and what its
    /// windowed transfers counted (`None` before any exchange with it).
    pub async fn path_stats(&self, peer: SocketAddr) -> Result<Option<coap::PathStats>, Error> {
        let Transport::Udp(handle) = &self.transport else {
            return Ok(None);
        };
        let (tx, rx) = oneshot::channel();
        handle.send(Command::PathStats { peer, reply: tx })?;
        rx.await.map_err(|_| Error::Closed)
    }

    /// A round trip to `peer` remembered from before (another process's estimate): the
    /// endpoint's first CON to it times out after about that instead of ACK_TIMEOUT, until
    /// it measures one of its own ([`coap::Endpoint::remember_rtt`]). A TCP client, which
    /// has no retransmission timer, ignores it.
    pub fn remember_rtt(&self, peer: SocketAddr, rtt: std::time::Duration) -> Result<(), Error> {
        match &self.transport {
            Transport::Udp(handle) => handle.send(Command::RememberRtt { peer, rtt }),
            Transport::Tcp(_) => Ok(()),
        }
    }

    /// A CoAP ping: `Ok` when the peer answers the empty CON (over TCP: when it answers
    /// a Ping with a Pong within [`coap::connection::DEFAULT_RESPONSE_TIMEOUT`]).
    pub async fn ping(&self, peer: SocketAddr) -> Result<(), Error> {
        let handle = match &self.transport {
            Transport::Udp(handle) => handle,
            Transport::Tcp(tcp) => {
                return tcp
                    .ping(peer, coap::connection::DEFAULT_RESPONSE_TIMEOUT)
                    .await;
            }
        };
        let (tx, rx) = oneshot::channel();
        handle.send(Command::Ping { peer, reply: tx })?;
        rx.await.map_err(|_| Error::Closed)?.map_err(Error::Request)
    }
}

/// A body arriving piece by piece ([`Client::send_streamed`]).
#[derive(Debug)]
pub struct BodyStream {
    rx: mpsc::UnboundedReceiver<BodyItem>,
}

/// One item of a [`BodyStream`].
#[derive(Debug)]
pub enum BodyPart {
    /// The next piece of the body, in order.
    Chunk {
        /// The bytes.
        data: bytes::Bytes,
        /// The whole size, when the server announced it (Size2).
        total: Option<usize>,
    },
    /// The body is complete; the response carries the code and options of the first
    /// block and an empty payload (or the diagnostic of an error response). Boxed: a
    /// response keeps its options inline, and a stream yields far more chunks than ends.
    End(Box<Response>),
}

impl BodyStream {
    /// The next piece, or the end. After the end or an error it returns
    /// [`Error::Closed`].
    pub async fn next(&mut self) -> Result<BodyPart, Error> {
        // The endpoint drops its sender with the end or the error, so what follows them
        // is `None`.
        match self.rx.recv().await {
            Some(BodyItem::Chunk(data, total)) => Ok(BodyPart::Chunk { data, total }),
            Some(BodyItem::Done(response)) => Ok(BodyPart::End(response)),
            Some(BodyItem::Failed(e)) => Err(Error::Request(e)),
            None => Err(Error::Closed),
        }
    }
}

/// A running observation: the first response, then notifications.
#[derive(Debug)]
pub struct Observation {
    rx: mpsc::UnboundedReceiver<StreamItem>,
    registration: Registration,
    client: Client,
    /// The registration without Observe: what asks for the rest of a notification sent
    /// block-wise.
    follow_up: Request,
    /// Notifications [`Observation::newest`] skipped.
    skipped: u64,
}

impl Observation {
    /// The next response or notification, whole; `None` when the observation ended. A
    /// notification sent block-wise is completed by GETs of its other blocks (RFC 7959
    /// §2.6); when the resource changes in between, the new representation is fetched
    /// whole instead (it fails with [`coap::RequestError::RepresentationChanged`] only
    /// when that keeps changing too). An error completing a notification does not end
    /// the observation: the next call gives the next notification.
    pub async fn next(&mut self) -> Option<Result<Response, Error>> {
        match self.rx.recv().await? {
            StreamItem::Response(peer, r) => {
                let mut r = *r;
                Some(
                    self.client
                        .rest_of_blocks(peer, &self.follow_up, &mut r, true)
                        .await
                        .map(|()| r),
                )
            }
            StreamItem::Failed(e) => Some(Err(Error::Request(e))),
        }
    }

    /// The newest notification, whole, for an observer that wants the resource's latest
    /// state rather than every change (a live stream): notifications that arrived while
    /// the caller was busy are skipped ([`Observation::skipped`] counts them), and one sent
    /// block-wise is completed by a GET of the whole resource, whose blocks come through
    /// a window as any GET's. Its body is then the resource's representation when the GET
    /// was answered, which may be newer than the notification's block 0 (its code and
    /// options come with it). `None` when the observation ended.
    pub async fn newest(&mut self) -> Option<Result<Response, Error>> {
        let mut item = self.rx.recv().await?;
        while let StreamItem::Response(..) = item {
            match self.rx.try_recv() {
                Ok(newer) => {
                    self.skipped += 1;
                    item = newer;
                }
                Err(_) => break,
            }
        }
        match item {
            StreamItem::Response(peer, r) => {
                let more = r.options.block2().is_some_and(|b| b.more && b.num == 0);
                if !more {
                    return Some(Ok(*r));
                }
                let mut whole = self.follow_up.clone();
                whole.payload = bytes::Bytes::new();
                whole.options.remove(coap::OptionNumber::BLOCK2);
                let observe = r.options.uint(coap::OptionNumber::OBSERVE);
                Some(self.client.send(peer, whole).await.map(|mut got| {
                    if let Some(seq) = observe.filter(|_| got.code.is_success()) {
                        got.options.set_uint(coap::OptionNumber::OBSERVE, seq);
                    }
                    got
                }))
            }
            StreamItem::Failed(e) => Some(Err(Error::Request(e))),
        }
    }

    /// How many notifications [`Observation::newest`] skipped so far.
    pub fn skipped(&self) -> u64 {
        self.skipped
    }
}

/// What ends an [`Observation`] from the client's side.
#[derive(Debug)]
enum Registration {
    /// The endpoint's request: forgetting it makes the client answer the next
    /// notification with a Reset, which ends the observation on the server (RFC 7641
    /// §3.6).
    Udp(RequestId),
    /// Over a stream there is no Reset: the connection deregisters (RFC 8323 §7.4).
    Stream(TcpObservation),
}

impl Drop for Observation {
    fn drop(&mut self) {
        match (&self.registration, &self.client.transport) {
            (Registration::Udp(id), Transport::Udp(handle)) => {
                let _ = handle.send(Command::Cancel(*id));
            }
            (Registration::Stream(registration), _) => registration.cancel(),
            (Registration::Udp(_), Transport::Tcp(_)) => {}
        }
    }
}
