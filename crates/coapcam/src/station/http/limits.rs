//! What one HTTP client, and all of them together, may hold of the station: a [`Counter`]
//! of things under way (connections, event streams, proxied requests) per client and in
//! all, and [`WriteTimeout`], the connection that gives up on a client that takes no
//! bytes.

use std::collections::HashMap;
use std::future::Future as _;
use std::io;
use std::net::IpAddr;
use std::pin::Pin;
use std::sync::{Arc, Mutex, PoisonError};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::time::Sleep;

/// How often a [`Counter`] says that it refuses, at most: its first refusal is logged,
/// later ones are counted into the next message, which comes after this long.
const WARN_EVERY: Duration = Duration::from_secs(60);

/// The client an address counts as: an IPv4 address (also written IPv4-mapped), or the
/// /64 of an IPv6 address (one host picks addresses from its /64 at will).
pub fn client_of(ip: IpAddr) -> IpAddr {
    match ip.to_canonical() {
        IpAddr::V4(v4) => IpAddr::V4(v4),
        IpAddr::V6(v6) => IpAddr::V6((u128::from(v6) & !u128::from(u64::MAX)).into()),
    }
}

/// The most files this process may have open (its soft `RLIMIT_NOFILE`), when known.
pub fn open_files() -> Option<u64> {
    use nix::sys::resource::{Resource, getrlimit};
    getrlimit(Resource::RLIMIT_NOFILE)
        .ok()
        .map(|(soft, _)| soft)
}

/// How many connections the HTTP side serves and answers with a refusal at once, each an
/// open file: its own bounds, or less where the process may open fewer files than they
/// take, so that its connections hold at most half of them (the other half for the
/// cameras, the log, the sockets and the other outputs) and running out of files never
/// stops it from answering.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Bounds {
    /// Connections served at once, in all.
    pub connections: usize,
    /// Connections served at once to one client: at most half of `connections`, so that
    /// one client never takes every place.
    pub per_client: usize,
    /// Refused connections whose answer is under way at once.
    pub refusing: usize,
}

impl Bounds {
    /// The bounds `connections`, `per_client` and `refusing`, within `open_files`.
    pub fn within(
        open_files: Option<u64>,
        connections: usize,
        per_client: usize,
        refusing: usize,
    ) -> Self {
        let half = open_files.map_or(usize::MAX, |n| usize::try_from(n / 2).unwrap_or(usize::MAX));
        let connections = connections.min(half.saturating_mul(4) / 5).max(2);
        Self {
            connections,
            per_client: per_client.min(connections / 2).max(1),
            refusing: refusing.min(half / 5).max(1),
        }
    }
}

/// Which bound a refused start met.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Full {
    /// The client's own ([`Counter::per_client`]): 429.
    Client,
    /// The station's, all clients together ([`Counter::in_all`]): 503.
    All,
}

/// Things of one kind under way, per client ([`client_of`]) and in all, each within its
/// bound.
#[derive(Debug)]
pub struct Counter {
    /// What it counts, in the log's messages ("connections").
    what: &'static str,
    /// The most one client may have.
    pub per_client: usize,
    /// The most all clients together may have.
    pub in_all: usize,
    by_client: HashMap<IpAddr, usize>,
    total: usize,
    /// When the last refusal was logged, and the refusals since.
    warned: Option<Instant>,
    refused: u64,
}

/// One thing counted in a [`Counter`] until dropped.
#[derive(Debug)]
pub struct Counted {
    counter: Arc<Mutex<Counter>>,
    client: IpAddr,
}

impl Counter {
    /// A counter of `what`, with its bounds.
    pub fn new(what: &'static str, per_client: usize, in_all: usize) -> Arc<Mutex<Self>> {
        Arc::new(Mutex::new(Self {
            what,
            per_client,
            in_all,
            by_client: HashMap::new(),
            total: 0,
            warned: None,
            refused: 0,
        }))
    }

    /// Counts one more for the client at `ip`, unless that client or all of them have as
    /// many as they may. Refusals are logged at most once a minute, with the number
    /// refused since the last message.
    pub fn start(counter: &Arc<Mutex<Self>>, ip: IpAddr) -> Result<Counted, Full> {
        let client = client_of(ip);
        let mut c = counter.lock().unwrap_or_else(PoisonError::into_inner);
        let mine = c.by_client.get(&client).copied().unwrap_or(0);
        let full = if mine >= c.per_client {
            Some(Full::Client)
        } else if c.total >= c.in_all {
            Some(Full::All)
        } else {
            None
        };
        if let Some(full) = full {
            c.refuse(client, full);
            return Err(full);
        }
        c.by_client.insert(client, mine + 1);
        c.total += 1;
        Ok(Counted {
            counter: counter.clone(),
            client,
        })
    }

    /// How many there are under way in all.
    pub fn total(counter: &Arc<Mutex<Self>>) -> usize {
        counter.lock().unwrap_or_else(PoisonError::into_inner).total
    }

    fn refuse(&mut self, client: IpAddr, full: Full) {
        self.refused += 1;
        if self.warned.is_some_and(|at| at.elapsed() < WARN_EVERY) {
            return;
        }
        let others = match self.refused - 1 {
            0 => String::new(),
            n => format!(" ({n} more refused since the last message)"),
        };
        match full {
            Full::Client => tracing::warn!(
                "http: refusing {} of client {client}: it has {}, the most one client may have (an IPv4 address or an IPv6 /64); said at most once a minute{others}",
                self.what,
                self.per_client
            ),
            Full::All => tracing::warn!(
                "http: refusing {}: {} are open, the most the station serves; said at most once a minute{others}",
                self.what,
                self.in_all
            ),
        }
        self.warned = Some(Instant::now());
        self.refused = 0;
    }
}

impl Drop for Counted {
    fn drop(&mut self) {
        let mut c = self.counter.lock().unwrap_or_else(PoisonError::into_inner);
        c.total -= 1;
        if let Some(n) = c.by_client.get_mut(&self.client) {
            *n -= 1;
            if *n == 0 {
                c.by_client.remove(&self.client);
            }
        }
    }
}

/// A connection whose writes fail (`TimedOut`) once the peer has taken no byte for
/// `timeout`: a client that never reads is dropped then, and what was held for it freed.
pub struct WriteTimeout<T> {
    io: T,
    timeout: Duration,
    /// Since a write could not go on: the deadline.
    stalled: Option<Pin<Box<Sleep>>>,
}

impl<T> WriteTimeout<T> {
    /// `io`, whose writes fail after `timeout` without progress.
    pub fn new(io: T, timeout: Duration) -> Self {
        Self {
            io,
            timeout,
            stalled: None,
        }
    }

    /// While a write cannot go on (`Pending`): the deadline's, an error once it is past.
    /// `wrote`: the call writes bytes, so that its `Ready` is progress (a flush's is not).
    fn watch<R>(
        &mut self,
        cx: &mut Context<'_>,
        poll: Poll<io::Result<R>>,
        wrote: bool,
    ) -> Poll<io::Result<R>> {
        if poll.is_ready() {
            if wrote {
                self.stalled = None;
            }
            return poll;
        }
        let timeout = self.timeout;
        let deadline = self
            .stalled
            .get_or_insert_with(|| Box::pin(tokio::time::sleep(timeout)));
        match deadline.as_mut().poll(cx) {
            Poll::Ready(()) => Poll::Ready(Err(io::Error::new(
                io::ErrorKind::TimedOut,
                format!(
                    "the client took no bytes for {} s (the write timeout)",
                    timeout.as_secs()
                ),
            ))),
            Poll::Pending => Poll::Pending,
        }
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for WriteTimeout<T> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        Pin::new(&mut self.io).poll_read(cx, buf)
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for WriteTimeout<T> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let poll = Pin::new(&mut self.io).poll_write(cx, buf);
        self.watch(cx, poll, true)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let poll = Pin::new(&mut self.io).poll_write_vectored(cx, bufs);
        self.watch(cx, poll, true)
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let poll = Pin::new(&mut self.io).poll_flush(cx);
        self.watch(cx, poll, false)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let poll = Pin::new(&mut self.io).poll_shutdown(cx);
        self.watch(cx, poll, false)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_connections_hold_at_most_half_the_files_the_process_may_open() {
        assert_eq!(
            Bounds::within(Some(4096), 1024, 64, 1024),
            Bounds {
                connections: 1024,
                per_client: 64,
                refusing: 409
            }
        );
        assert_eq!(
            Bounds::within(None, 1024, 64, 1024),
            Bounds {
                connections: 1024,
                per_client: 64,
                refusing: 1024
            }
        );
        // systemd's default soft limit, and `ulimit -n 128`.
        assert_eq!(
            Bounds::within(Some(1024), 1024, 64, 1024),
            Bounds {
                connections: 409,
                per_client: 64,
                refusing: 102
            }
        );
        let small = Bounds::within(Some(128), 1024, 64, 1024);
        assert_eq!(
            small,
            Bounds {
                connections: 51,
                per_client: 25,
                refusing: 12
            }
        );
        assert!(small.connections + small.refusing <= 64);
    }

    #[tokio::test(start_paused = true)]
    async fn a_peer_that_takes_no_bytes_fails_the_write_after_the_timeout() {
        use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
        let (near, mut far) = tokio::io::duplex(1024);
        let mut io = WriteTimeout::new(near, Duration::from_secs(10));
        // The peer takes bytes now and then: each write goes on.
        for _ in 0..3 {
            io.write_all(&[7; 1024]).await.expect("room");
            tokio::time::sleep(Duration::from_secs(9)).await;
            let mut got = [0; 1024];
            far.read_exact(&mut got).await.expect("the bytes");
        }
        // Then it takes none: the write fails once 10 s passed without progress.
        io.write_all(&[7; 1024]).await.expect("room");
        let started = tokio::time::Instant::now();
        let e = io.write_all(&[7; 1]).await.expect_err("no room, ever");
        assert_eq!(e.kind(), io::ErrorKind::TimedOut);
        // The runtime's paused clock, which jumps to each timer: no wall-clock time.
        assert_eq!(started.elapsed(), Duration::from_secs(10));
    }

    #[test]
    fn a_client_is_an_ipv4_address_or_an_ipv6_slash_64_and_each_bound_holds() {
        let counter = Counter::new("things", 2, 8);
        let ip = |s: &str| s.parse::<IpAddr>().unwrap();
        let a = Counter::start(&counter, ip("192.0.2.1")).unwrap();
        let b = Counter::start(&counter, ip("::ffff:192.0.2.1")).unwrap();
        assert_eq!(
            Counter::start(&counter, ip("192.0.2.1")).unwrap_err(),
            Full::Client
        );
        let c = Counter::start(&counter, ip("fd00::1")).unwrap();
        let _d = Counter::start(&counter, ip("fd00::2:1")).unwrap();
        assert_eq!(
            Counter::start(&counter, ip("fd00::ffff")).unwrap_err(),
            Full::Client,
            "one /64"
        );
        drop(a);
        let _a = Counter::start(&counter, ip("192.0.2.1")).unwrap();
        let more: Vec<Counted> = (3..7)
            .filter_map(|n| Counter::start(&counter, ip(&format!("192.0.2.{n}"))).ok())
            .collect();
        assert_eq!(more.len(), 4, "8 in all");
        assert_eq!(Counter::total(&counter), 8);
        assert_eq!(
            Counter::start(&counter, ip("192.0.2.9")).unwrap_err(),
            Full::All
        );
        drop((b, c));
        assert!(Counter::start(&counter, ip("192.0.2.9")).is_ok());
        assert_eq!(Counter::total(&counter), 6, "a refusal counts nothing");
    }
}
