//! The relay: sockets, a timer heap of held datagrams, and the link model deciding.

use std::cmp::{Ordering, Reverse};
use std::collections::{BinaryHeap, HashMap};
use std::future::{Future, pending, poll_fn};
use std::io;
use std::net::{Ipv4Addr, Ipv6Addr, SocketAddr};
use std::sync::{Arc, Mutex, PoisonError};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use tokio::io::ReadBuf;
use tokio::net::UdpSocket;

use crate::link::{Counters, Dir, Fate, Link, LinkConfig};

/// The largest UDP payload (IPv4: 65,535 − 8 − 20 bytes).
const MAX_DATAGRAM_BYTES: usize = 65_507;

/// Receive buffer asked of the OS for every socket, so that a burst is queued rather than
/// dropped uncounted before netem reads it (Linux caps it at `net.core.rmem_max`).
const RECV_BUFFER_BYTES: usize = 4 << 20;

/// Client addresses served at once; datagrams from further clients are refused, so a
/// flood of source addresses cannot exhaust file descriptors.
pub const MAX_CLIENTS: usize = 256;

/// Why the relay stopped short.
#[derive(Debug, thiserror::Error)]
pub enum NetemError {
    /// A socket could not be bound.
    #[error("binding {what} {addr}")]
    Bind {
        /// Which socket.
        what: &'static str,
        /// Its address.
        addr: SocketAddr,
        /// Why.
        #[source]
        source: io::Error,
    },
    /// The listen socket's address could not be read.
    #[error("reading the listen socket's address")]
    LocalAddr(#[source] io::Error),
    /// A receive failed for a reason other than an earlier datagram's ICMP error.
    #[error("receiving from {from}")]
    Receive {
        /// `clients` or `the server`.
        from: &'static str,
        /// Why.
        #[source]
        source: io::Error,
    },
    /// The stop future failed (e.g. the Ctrl-C handler could not be installed).
    #[error("waiting for the stop signal")]
    Stop(#[source] io::Error),
}

/// A datagram waiting in the timer heap.
#[derive(Debug)]
struct Pending {
    due: Instant,
    /// Arrival order: equal due times leave in the order they came.
    seq: u64,
    dir: Dir,
    /// The client it came from (up) or goes to (down).
    client: SocketAddr,
    payload: Vec<u8>,
}

impl PartialEq for Pending {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}

impl Eq for Pending {}

impl PartialOrd for Pending {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for Pending {
    fn cmp(&self, other: &Self) -> Ordering {
        (self.due, self.seq).cmp(&(other.due, other.seq))
    }
}

/// Reads the clock of the tokio runtime, so a paused test clock would drive it too.
fn now() -> Instant {
    tokio::time::Instant::now().into_std()
}

async fn sleep_until(deadline: Option<Instant>) {
    match deadline {
        Some(at) => tokio::time::sleep_until(at.into()).await,
        None => pending().await,
    }
}

/// What woke the driver.
enum Wake {
    Stop,
    Timer,
    FromClient(usize, SocketAddr),
    FromServer(usize, SocketAddr),
}

/// The payload bytes a relay has delivered downstream (server -> client) to each client
/// address, counted when a datagram is sent to the client; readable while the relay runs
/// (a handle from [`Netem::delivered`], cloned freely).
#[derive(Debug, Clone, Default)]
pub struct DeliveredBytes(Arc<Mutex<HashMap<SocketAddr, u64>>>);

impl DeliveredBytes {
    /// The bytes delivered to each client so far.
    pub fn snapshot(&self) -> HashMap<SocketAddr, u64> {
        self.0
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    fn add(&self, client: SocketAddr, bytes: usize) {
        let mut counts = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        *counts.entry(client).or_default() += bytes as u64;
    }
}

/// A bound link emulator, ready to run.
#[derive(Debug)]
pub struct Netem {
    listen: UdpSocket,
    forward: SocketAddr,
    duration: Option<Duration>,
    link: Link,
    delivered: DeliveredBytes,
}

impl Netem {
    /// Binds `listen`, where clients send to; datagrams go on to `forward` through
    /// `link`; [`Netem::run`] stops by itself after `duration` if one is given.
    pub fn bind(
        listen: SocketAddr,
        forward: SocketAddr,
        link: LinkConfig,
        duration: Option<Duration>,
    ) -> Result<Self, NetemError> {
        let listen = bind(listen).map_err(|source| NetemError::Bind {
            what: "the listen address",
            addr: listen,
            source,
        })?;
        Ok(Self {
            listen,
            forward,
            duration,
            link: Link::new(link),
            delivered: DeliveredBytes::default(),
        })
    }

    /// A handle on the bytes this relay delivers to each client, to read while it runs.
    pub fn delivered(&self) -> DeliveredBytes {
        self.delivered.clone()
    }

    /// The address clients send to (the actual port when the listen address asked for
    /// port 0).
    pub fn local_addr(&self) -> Result<SocketAddr, NetemError> {
        self.listen.local_addr().map_err(NetemError::LocalAddr)
    }

    /// The address that each client's upstream socket binds: loopback for a loopback
    /// server, so traffic to a local server stays on loopback; otherwise any address.
    fn upstream_bind_addr(&self) -> SocketAddr {
        let ip = match (self.forward, self.forward.ip().is_loopback()) {
            (SocketAddr::V4(_), true) => Ipv4Addr::LOCALHOST.into(),
            (SocketAddr::V4(_), false) => Ipv4Addr::UNSPECIFIED.into(),
            (SocketAddr::V6(_), true) => Ipv6Addr::LOCALHOST.into(),
            (SocketAddr::V6(_), false) => Ipv6Addr::UNSPECIFIED.into(),
        };
        SocketAddr::new(ip, 0)
    }

    /// Relays datagrams until the duration has elapsed or `stop` completes (an error from
    /// `stop` ends the run with that error), then returns the counters. Datagrams still
    /// held then are not sent.
    pub async fn run(
        mut self,
        stop: impl Future<Output = io::Result<()>>,
    ) -> Result<Counters, NetemError> {
        let started = now();
        let end = self.duration.and_then(|d| started.checked_add(d));
        let mut heap: BinaryHeap<Reverse<Pending>> = BinaryHeap::new();
        let mut upstreams = Upstreams::default();
        let mut clients_refused = 0u64;
        let mut seq = 0u64;
        let mut from_client = vec![0u8; MAX_DATAGRAM_BYTES];
        let mut from_server = vec![0u8; MAX_DATAGRAM_BYTES];
        let end_sleep = sleep_until(end);
        tokio::pin!(stop, end_sleep);

        loop {
            let next_due = heap.peek().map(|Reverse(p)| p.due);
            let wake = tokio::select! {
                biased;
                stopped = &mut stop => {
                    stopped.map_err(NetemError::Stop)?;
                    Wake::Stop
                }
                () = &mut end_sleep => Wake::Stop,
                () = sleep_until(next_due) => Wake::Timer,
                received = self.listen.recv_from(&mut from_client) => match received {
                    Ok((len, client)) => Wake::FromClient(len, client),
                    Err(e) if is_transient(&e) => continue,
                    Err(e) => return Err(NetemError::Receive { from: "clients", source: e }),
                },
                received = poll_fn(|cx| upstreams.poll_recv(cx, &mut from_server)) => {
                    match received {
                        Ok((len, client)) => Wake::FromServer(len, client),
                        Err(e) if is_transient(&e) => continue,
                        Err(e) => {
                            return Err(NetemError::Receive { from: "the server", source: e });
                        }
                    }
                }
            };
            let now = now();
            match wake {
                Wake::Stop => break,
                Wake::Timer => {
                    while let Some(Reverse(p)) = heap.peek()
                        && p.due <= now
                    {
                        let Some(Reverse(p)) = heap.pop() else { break };
                        let sent = match p.dir {
                            Dir::Up => upstreams
                                .socket(p.client)
                                .is_some_and(|s| s.try_send_to(&p.payload, self.forward).is_ok()),
                            Dir::Down => self.listen.try_send_to(&p.payload, p.client).is_ok(),
                        };
                        if sent && p.dir == Dir::Down {
                            self.delivered.add(p.client, p.payload.len());
                        }
                        self.link.on_departed(p.dir, p.payload.len(), sent);
                    }
                }
                Wake::FromClient(len, client) => {
                    if upstreams.socket(client).is_none() {
                        if upstreams.len() >= MAX_CLIENTS {
                            clients_refused += 1;
                            continue;
                        }
                        let addr = self.upstream_bind_addr();
                        let socket = bind(addr).map_err(|source| NetemError::Bind {
                            what: "an upstream socket",
                            addr,
                            source,
                        })?;
                        upstreams.insert(client, socket);
                    }
                    if let Fate::DeliverAt(due) = self.link.on_datagram(now, Dir::Up, len) {
                        let payload = from_client[..len].to_vec();
                        heap.push(Reverse(Pending {
                            due,
                            seq,
                            dir: Dir::Up,
                            client,
                            payload,
                        }));
                        seq += 1;
                    }
                }
                Wake::FromServer(len, client) => {
                    if let Fate::DeliverAt(due) = self.link.on_datagram(now, Dir::Down, len) {
                        let payload = from_server[..len].to_vec();
                        heap.push(Reverse(Pending {
                            due,
                            seq,
                            dir: Dir::Down,
                            client,
                            payload,
                        }));
                        seq += 1;
                    }
                }
            }
        }

        let elapsed = now().saturating_duration_since(started);
        Ok(Counters {
            seed: self.link.seed(),
            elapsed_ms: u64::try_from(elapsed.as_millis()).unwrap_or(u64::MAX),
            clients: upstreams.len() as u64,
            clients_refused,
            up: self.link.counters(Dir::Up),
            down: self.link.counters(Dir::Down),
        })
    }
}

/// A UDP socket bound to `addr` with a receive buffer of [`RECV_BUFFER_BYTES`].
fn bind(addr: SocketAddr) -> io::Result<UdpSocket> {
    let socket = socket2::Socket::new(
        socket2::Domain::for_address(addr),
        socket2::Type::DGRAM,
        Some(socket2::Protocol::UDP),
    )?;
    socket.set_recv_buffer_size(RECV_BUFFER_BYTES)?;
    socket.set_nonblocking(true)?;
    socket.bind(&addr.into())?;
    UdpSocket::from_std(socket.into())
}

/// The socket each client's datagrams go to the server from, in the order the clients
/// came.
#[derive(Default)]
struct Upstreams {
    sockets: Vec<(SocketAddr, UdpSocket)>,
    index: HashMap<SocketAddr, usize>,
    /// Where the next receive starts looking, so that one busy client cannot starve the
    /// others (two transfers through one link must be able to share it).
    next: usize,
}

impl Upstreams {
    fn len(&self) -> usize {
        self.sockets.len()
    }

    fn socket(&self, client: SocketAddr) -> Option<&UdpSocket> {
        self.index.get(&client).map(|&i| &self.sockets[i].1)
    }

    fn insert(&mut self, client: SocketAddr, socket: UdpSocket) {
        self.index.insert(client, self.sockets.len());
        self.sockets.push((client, socket));
    }

    /// Receives from the first client's socket with a datagram, round-robin; returns its
    /// length and the client it belongs to.
    fn poll_recv(
        &mut self,
        cx: &mut Context<'_>,
        buf: &mut [u8],
    ) -> Poll<io::Result<(usize, SocketAddr)>> {
        let n = self.sockets.len();
        for k in 0..n {
            let i = (self.next + k) % n;
            let (client, socket) = &self.sockets[i];
            let mut read = ReadBuf::new(buf);
            match socket.poll_recv_from(cx, &mut read) {
                Poll::Ready(result) => {
                    self.next = (i + 1) % n;
                    return Poll::Ready(result.map(|_| (read.filled().len(), *client)));
                }
                Poll::Pending => {}
            }
        }
        Poll::Pending
    }
}

/// Errors that a UDP receive reports about an earlier datagram (an ICMP unreachable) or a
/// spurious wake-up; the socket goes on working.
fn is_transient(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionRefused
            | io::ErrorKind::ConnectionReset
            | io::ErrorKind::Interrupted
            | io::ErrorKind::WouldBlock
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::link::DirConfig;

    fn localhost() -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], 0))
    }

    fn direction(loss: f64, delay_ms: u64, jitter_ms: u64) -> DirConfig {
        let ms = Duration::from_millis;
        DirConfig::new(loss, ms(delay_ms), ms(jitter_ms), None)
    }

    fn config(up: DirConfig, down: DirConfig, seed: u64) -> LinkConfig {
        LinkConfig {
            up,
            down,
            seed,
            queue_limit: 1000,
            queue_bytes: None,
        }
    }

    /// An echo server on 127.0.0.1 that prefixes nothing and answers every datagram.
    async fn echo_server() -> anyhow::Result<(SocketAddr, tokio::task::JoinHandle<()>)> {
        let socket = UdpSocket::bind("127.0.0.1:0").await?;
        let addr = socket.local_addr()?;
        let task = tokio::spawn(async move {
            let mut buf = vec![0u8; MAX_DATAGRAM_BYTES];
            while let Ok((len, peer)) = socket.recv_from(&mut buf).await {
                if socket.send_to(&buf[..len], peer).await.is_err() {
                    break;
                }
            }
        });
        Ok((addr, task))
    }

    /// A running netem in front of `forward`, stopped through the returned sender.
    async fn start(
        forward: SocketAddr,
        link: LinkConfig,
    ) -> anyhow::Result<(
        SocketAddr,
        tokio::sync::oneshot::Sender<()>,
        tokio::task::JoinHandle<Result<Counters, NetemError>>,
    )> {
        let netem = Netem::bind(localhost(), forward, link, None)?;
        let addr = netem.local_addr()?;
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(netem.run(async move {
            let _ = stopped.await;
            Ok(())
        }));
        Ok((addr, stop, task))
    }

    /// How long a drain waits for one more datagram: far longer than a loaded machine
    /// may hold up the test's runtime between two of them.
    const QUIET: Duration = Duration::from_secs(1);

    /// Receives datagrams until none has come for `quiet`; bounded by 5 s in all.
    async fn drain(socket: &UdpSocket, quiet: Duration) -> Vec<Vec<u8>> {
        let mut got = Vec::new();
        let mut buf = vec![0u8; MAX_DATAGRAM_BYTES];
        let give_up = tokio::time::Instant::now() + Duration::from_secs(5);
        while tokio::time::Instant::now() < give_up {
            match tokio::time::timeout(quiet, socket.recv(&mut buf)).await {
                Ok(Ok(len)) => got.push(buf[..len].to_vec()),
                Ok(Err(_)) | Err(_) => break,
            }
        }
        got
    }

    #[tokio::test]
    async fn relays_both_ways_after_the_configured_delay() -> anyhow::Result<()> {
        let (server, echo) = echo_server().await?;
        let (netem, stop, task) = start(
            server,
            config(direction(0.0, 15, 0), direction(0.0, 25, 0), 0),
        )
        .await?;
        let client = UdpSocket::bind("127.0.0.1:0").await?;
        let mut buf = [0u8; 64];
        for i in 0..5u8 {
            let sent = tokio::time::Instant::now();
            client.send_to(&[i; 10], netem).await?;
            let len = tokio::time::timeout(Duration::from_secs(2), client.recv(&mut buf)).await??;
            assert_eq!(&buf[..len], &[i; 10]);
            assert!(
                sent.elapsed() >= Duration::from_millis(40),
                "{:?}",
                sent.elapsed()
            );
        }
        let _ = stop.send(());
        let counters = task.await??;
        echo.abort();
        assert_eq!(counters.clients, 1);
        for c in [counters.up, counters.down] {
            assert_eq!((c.received, c.forwarded, c.dropped, c.unsent), (5, 5, 0, 0));
            assert_eq!(
                (c.bytes_received, c.bytes_forwarded, c.max_queue),
                (50, 50, 1)
            );
        }
        Ok(())
    }

    #[tokio::test]
    async fn loss_is_counted_and_replays_with_the_seed() -> anyhow::Result<()> {
        let (server, echo) = echo_server().await?;
        let mut runs = Vec::new();
        for _ in 0..2 {
            let (netem, stop, task) = start(
                server,
                config(direction(0.3, 0, 0), direction(0.0, 0, 0), 77),
            )
            .await?;
            let client = UdpSocket::bind("127.0.0.1:0").await?;
            for i in 0..200u16 {
                client.send_to(&i.to_be_bytes(), netem).await?;
            }
            let echoes = drain(&client, QUIET).await;
            let _ = stop.send(());
            let counters = task.await??;
            assert_eq!(counters.up.received, 200);
            assert_eq!(counters.up.dropped + counters.up.forwarded, 200);
            assert!((30..=90).contains(&counters.up.dropped), "{counters:?}");
            assert_eq!(counters.down.received, counters.up.forwarded);
            assert_eq!(counters.down.dropped, 0);
            assert_eq!(echoes.len() as u64, counters.down.forwarded);
            runs.push((counters.up.dropped, echoes));
        }
        echo.abort();
        assert_eq!(runs[0], runs[1]);
        Ok(())
    }

    #[tokio::test]
    async fn replies_go_back_to_the_client_that_asked() -> anyhow::Result<()> {
        let (server, echo) = echo_server().await?;
        let (netem, stop, task) = start(
            server,
            config(direction(0.0, 3, 3), direction(0.0, 3, 3), 0),
        )
        .await?;
        let a = UdpSocket::bind("127.0.0.1:0").await?;
        let b = UdpSocket::bind("127.0.0.1:0").await?;
        for _ in 0..10 {
            a.send_to(b"from a", netem).await?;
            b.send_to(b"from b", netem).await?;
        }
        let (got_a, got_b) = tokio::join!(drain(&a, QUIET), drain(&b, QUIET));
        let _ = stop.send(());
        let counters = task.await??;
        echo.abort();
        assert_eq!(counters.clients, 2);
        assert_eq!(got_a, vec![b"from a".to_vec(); 10]);
        assert_eq!(got_b, vec![b"from b".to_vec(); 10]);
        assert_eq!((counters.up.forwarded, counters.down.forwarded), (20, 20));
        Ok(())
    }

    #[tokio::test]
    async fn counts_the_bytes_delivered_to_each_client_while_it_runs() -> anyhow::Result<()> {
        let (server, echo) = echo_server().await?;
        // Loss up only: what the server never answers is never delivered.
        let link = config(direction(0.3, 0, 0), direction(0.0, 2, 0), 5);
        let netem = Netem::bind(localhost(), server, link, None)?;
        let addr = netem.local_addr()?;
        let delivered = netem.delivered();
        assert!(delivered.snapshot().is_empty());
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(netem.run(async move {
            let _ = stopped.await;
            Ok(())
        }));
        let a = UdpSocket::bind("127.0.0.1:0").await?;
        let b = UdpSocket::bind("127.0.0.1:0").await?;
        for _ in 0..50 {
            a.send_to(&[1; 10], addr).await?;
            b.send_to(&[2; 300], addr).await?;
        }
        let (got_a, got_b) = tokio::join!(drain(&a, QUIET), drain(&b, QUIET));
        // Read while the relay still runs.
        let counts = delivered.snapshot();
        let _ = stop.send(());
        let counters = task.await??;
        echo.abort();
        let bytes = |got: &[Vec<u8>]| got.iter().map(Vec::len).sum::<usize>() as u64;
        assert_eq!(counts.len(), 2, "{counts:?}");
        assert_eq!(counts.get(&a.local_addr()?), Some(&bytes(&got_a)));
        assert_eq!(counts.get(&b.local_addr()?), Some(&bytes(&got_b)));
        assert!(got_a.len() < 50 && got_b.len() < 50, "{counters:?}");
        assert_eq!(counts.values().sum::<u64>(), counters.down.bytes_forwarded);
        Ok(())
    }

    #[tokio::test]
    async fn receives_from_busy_clients_in_turn() -> anyhow::Result<()> {
        let mut upstreams = Upstreams::default();
        let sender = UdpSocket::bind(localhost()).await?;
        let mut clients = Vec::new();
        for port in [1, 2, 3] {
            let client = SocketAddr::from(([127, 0, 0, 1], port));
            let socket = bind(localhost())?;
            for _ in 0..4 {
                sender.send_to(&[port as u8], socket.local_addr()?).await?;
            }
            upstreams.insert(client, socket);
            clients.push(client);
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
        let mut buf = [0u8; 16];
        let mut order = Vec::new();
        for _ in 0..6 {
            let (_, client) = poll_fn(|cx| upstreams.poll_recv(cx, &mut buf)).await?;
            order.push(client.port());
        }
        assert_eq!(order, [1, 2, 3, 1, 2, 3]);
        Ok(())
    }

    #[tokio::test]
    async fn stops_when_the_duration_has_elapsed() -> anyhow::Result<()> {
        let (server, echo) = echo_server().await?;
        let link = config(direction(0.0, 1000, 0), direction(0.0, 1000, 0), 0);
        let netem = Netem::bind(localhost(), server, link, Some(Duration::from_millis(100)))?;
        let addr = netem.local_addr()?;
        let client = UdpSocket::bind("127.0.0.1:0").await?;
        client.send_to(b"late", addr).await?;
        let counters = tokio::time::timeout(Duration::from_secs(5), netem.run(pending())).await??;
        echo.abort();
        assert!(counters.elapsed_ms >= 100, "{counters:?}");
        assert_eq!(
            (
                counters.up.received,
                counters.up.unsent,
                counters.up.forwarded
            ),
            (1, 1, 0)
        );
        Ok(())
    }
}
