//! `coapcam netem`: a userspace UDP link emulator.
//!
//! Clients send to `--listen`; each datagram goes on to `--forward` from a socket of its
//! own per client address (created on the client's first datagram), so that whatever the
//! server answers on that socket goes back to that client from the listen socket.
//!
//! Each direction ("up" = client -> server, "down" = server -> client) has its own loss
//! probability, delay, jitter, rate limit and random generator. The decisions live in
//! [`Link`], which takes the arrival time as an argument and reads no clock, so it is
//! tested without sockets; [`Netem::run`] is the driver: one task, one timer heap of
//! pending datagrams, one `sleep_until` on the earliest.
//!
//! Per datagram, in this order:
//! 1. two draws from the direction's ChaCha8 generator (seeded by `--seed`, one stream per
//!    direction): the loss draw, then the jitter draw. Both are taken whatever the outcome,
//!    so a replay with the same seed and the same arrival order per direction makes the same
//!    decisions, and changing the loss leaves the jitter of every datagram as it was;
//! 2. lost with the direction's probability;
//! 3. dropped as an overflow when the direction already holds `--queue-limit` datagrams;
//! 4. rate limit: it leaves the serializer at `max(arrival, previous departure) +
//!    len / rate` (payload bytes only, no header overhead);
//! 5. then it is delivered `delay ± jitter` later (uniform, clamped at zero, like the
//!    kernel's netem). Jitter reorders datagrams whose delays differ by more than
//!    their spacing; with no jitter the order of a direction is kept.
//!
//! Datagrams that the OS drops before netem reads them (a burst beyond the 4 MiB receive
//! buffer it asks for) are not counted; nor are bytes of UDP/IP headers.

use std::cmp::{Ordering, Reverse};
use std::collections::{BinaryHeap, HashMap};
use std::fmt;
use std::future::{Future, pending, poll_fn};
use std::io;
use std::net::{Ipv4Addr, Ipv6Addr, SocketAddr};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use anyhow::Context as _;
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore, SeedableRng};
use serde::Serialize;
use tokio::io::ReadBuf;
use tokio::net::UdpSocket;

/// The largest UDP payload (IPv4: 65,535 − 8 − 20 bytes).
const MAX_DATAGRAM_BYTES: usize = 65_507;

/// Receive buffer asked of the OS for every socket, so that a burst is queued rather than
/// dropped uncounted before netem reads it (Linux caps it at `net.core.rmem_max`).
const RECV_BUFFER_BYTES: usize = 4 << 20;

/// The largest delay or jitter a flag accepts, in milliseconds (one hour).
const MAX_DELAY_MS: u64 = 3_600_000;

/// Client addresses served at once; datagrams from further clients are refused, so a
/// flood of source addresses cannot exhaust file descriptors.
const MAX_CLIENTS: usize = 256;

/// Arguments of `coapcam netem`.
#[derive(Debug, Clone, clap::Args)]
#[command(after_long_help = "\
Per-direction flags (--loss-up, --delay-down-ms, ...) override the flag for both \
directions. \"up\" is client -> server, \"down\" is server -> client.

Each datagram's delay is uniform in [delay - jitter, delay + jitter] (clamped at 0), so \
jitter reorders datagrams. With --rate, a direction is a serializer: a datagram leaves it \
at max(arrival, previous departure) + bytes / rate, then the delay starts.

Randomness comes from ChaCha8 seeded by --seed, one stream per direction, two draws per \
datagram (loss, then jitter): the same seed and the same arrival order give the same \
decisions.

The counters are printed on standard output when --duration has elapsed or on Ctrl-C.")]
pub(crate) struct NetemArgs {
    /// Address that clients send to (e.g. 127.0.0.1:5683; port 0 picks a free port, printed
    /// on standard error).
    #[arg(long, value_name = "ADDR")]
    listen: SocketAddr,
    /// Address of the server that datagrams are forwarded to (e.g. 127.0.0.1:5684).
    #[arg(long, value_name = "ADDR")]
    forward: SocketAddr,
    /// One-way delay added to every datagram, in milliseconds (at most 3600000), both
    /// directions.
    #[arg(long, value_name = "MS", default_value_t = 0, value_parser = ms_range())]
    delay_ms: u64,
    /// One-way delay client -> server, in milliseconds (overrides --delay-ms).
    #[arg(long, value_name = "MS", value_parser = ms_range())]
    delay_up_ms: Option<u64>,
    /// One-way delay server -> client, in milliseconds (overrides --delay-ms).
    #[arg(long, value_name = "MS", value_parser = ms_range())]
    delay_down_ms: Option<u64>,
    /// Jitter in milliseconds (at most 3600000), both directions: each delay is uniform in
    /// delay ± jitter.
    #[arg(long, value_name = "MS", default_value_t = 0, value_parser = ms_range())]
    jitter_ms: u64,
    /// Jitter client -> server, in milliseconds (overrides --jitter-ms).
    #[arg(long, value_name = "MS", value_parser = ms_range())]
    jitter_up_ms: Option<u64>,
    /// Jitter server -> client, in milliseconds (overrides --jitter-ms).
    #[arg(long, value_name = "MS", value_parser = ms_range())]
    jitter_down_ms: Option<u64>,
    /// Probability that a datagram is lost, 0 to 1 (0.1 = 10 %), both directions.
    #[arg(long, value_name = "P", default_value_t = 0.0, value_parser = parse_probability)]
    loss: f64,
    /// Loss probability client -> server, 0 to 1 (overrides --loss).
    #[arg(long, value_name = "P", value_parser = parse_probability)]
    loss_up: Option<f64>,
    /// Loss probability server -> client, 0 to 1 (overrides --loss).
    #[arg(long, value_name = "P", value_parser = parse_probability)]
    loss_down: Option<f64>,
    /// Rate limit in bytes (UDP payload) per second, both directions; unlimited if absent.
    #[arg(long, value_name = "BYTES_PER_S", value_parser = clap::value_parser!(u64).range(1..))]
    rate: Option<u64>,
    /// Rate limit client -> server, in bytes per second (overrides --rate).
    #[arg(long, value_name = "BYTES_PER_S", value_parser = clap::value_parser!(u64).range(1..))]
    rate_up: Option<u64>,
    /// Rate limit server -> client, in bytes per second (overrides --rate).
    #[arg(long, value_name = "BYTES_PER_S", value_parser = clap::value_parser!(u64).range(1..))]
    rate_down: Option<u64>,
    /// Datagrams held at most per direction (delayed or waiting for the rate limit); more
    /// are dropped and counted as overflowed.
    #[arg(long, value_name = "DATAGRAMS", default_value_t = 1000,
          value_parser = clap::value_parser!(u64).range(1..))]
    queue_limit: u64,
    /// Seed of the random generator (loss and jitter decisions).
    #[arg(long, value_name = "N", default_value_t = 0)]
    seed: u64,
    /// Stop after this many seconds (fractions allowed, e.g. 2.5); runs until Ctrl-C if
    /// absent.
    #[arg(long, value_name = "S", value_parser = parse_seconds)]
    duration: Option<Duration>,
    /// Print the counters as one JSON object instead of a table.
    #[arg(long)]
    pub(crate) json: bool,
}

/// Milliseconds from 0 to [`MAX_DELAY_MS`].
fn ms_range() -> clap::builder::RangedU64ValueParser<u64> {
    clap::value_parser!(u64).range(0..=MAX_DELAY_MS)
}

fn parse_probability(text: &str) -> Result<f64, String> {
    let p: f64 = text.parse().map_err(|e| format!("not a number ({e})"))?;
    if (0.0..=1.0).contains(&p) {
        Ok(p)
    } else {
        Err(format!("{p} is not a probability between 0 and 1"))
    }
}

fn parse_seconds(text: &str) -> Result<Duration, String> {
    let seconds: f64 = text
        .parse()
        .map_err(|e| format!("not a number of seconds ({e})"))?;
    Duration::try_from_secs_f64(seconds).map_err(|e| format!("{seconds} s: {e}"))
}

impl NetemArgs {
    /// The link that these flags describe, per-direction flags overriding the shared ones.
    fn link_config(&self) -> LinkConfig {
        let direction =
            |loss: Option<f64>, delay_ms: Option<u64>, jitter_ms, rate: Option<u64>| DirConfig {
                loss: loss.unwrap_or(self.loss),
                delay: Duration::from_millis(delay_ms.unwrap_or(self.delay_ms)),
                jitter: Duration::from_millis(jitter_ms),
                rate_bytes_per_s: rate.or(self.rate),
            };
        LinkConfig {
            up: direction(
                self.loss_up,
                self.delay_up_ms,
                self.jitter_up_ms.unwrap_or(self.jitter_ms),
                self.rate_up,
            ),
            down: direction(
                self.loss_down,
                self.delay_down_ms,
                self.jitter_down_ms.unwrap_or(self.jitter_ms),
                self.rate_down,
            ),
            seed: self.seed,
            queue_limit: usize::try_from(self.queue_limit).unwrap_or(usize::MAX),
        }
    }
}

/// A direction of the link.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Dir {
    /// Client -> server.
    Up,
    /// Server -> client.
    Down,
}

impl Dir {
    const fn index(self) -> usize {
        match self {
            Self::Up => 0,
            Self::Down => 1,
        }
    }
}

/// What one direction does to datagrams.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct DirConfig {
    /// Probability that a datagram is lost, in [0, 1].
    pub(crate) loss: f64,
    /// Mean one-way delay (the flags allow up to an hour).
    pub(crate) delay: Duration,
    /// Each delay is uniform in `delay ± jitter`, clamped at zero.
    pub(crate) jitter: Duration,
    /// Serialization rate in payload bytes per second; `None` is unlimited.
    pub(crate) rate_bytes_per_s: Option<u64>,
}

/// Both directions, the seed and the queue bound.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct LinkConfig {
    /// Client -> server.
    pub(crate) up: DirConfig,
    /// Server -> client.
    pub(crate) down: DirConfig,
    /// Seed of both directions' generators (one ChaCha8 stream each).
    pub(crate) seed: u64,
    /// Datagrams held at most per direction.
    pub(crate) queue_limit: usize,
}

/// What happens to one datagram.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Fate {
    /// Lost on the link (the loss probability).
    Drop,
    /// Dropped because the direction already holds `queue_limit` datagrams.
    Overflow,
    /// Delivered at this instant.
    DeliverAt(Instant),
}

/// The counters of one direction.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, Serialize)]
pub(crate) struct DirCounters {
    /// Datagrams that arrived.
    pub(crate) received: u64,
    /// Datagrams lost on purpose (the loss probability).
    pub(crate) dropped: u64,
    /// Datagrams dropped because the queue was full.
    pub(crate) overflowed: u64,
    /// Datagrams sent on.
    pub(crate) forwarded: u64,
    /// Datagrams whose send failed (the OS refused it); not forwarded.
    pub(crate) send_errors: u64,
    /// Datagrams still held when netem stopped; never sent.
    pub(crate) unsent: u64,
    /// Payload bytes that arrived.
    pub(crate) bytes_received: u64,
    /// Payload bytes sent on.
    pub(crate) bytes_forwarded: u64,
    /// Most datagrams held at once.
    pub(crate) max_queue: u64,
}

/// Everything netem counted, printed when it ends.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub(crate) struct Counters {
    /// The seed the run used.
    pub(crate) seed: u64,
    /// How long netem ran, in milliseconds.
    pub(crate) elapsed_ms: u64,
    /// Client addresses served.
    pub(crate) clients: u64,
    /// Datagrams ignored because `MAX_CLIENTS` clients were already served.
    pub(crate) clients_refused: u64,
    /// Client -> server.
    pub(crate) up: DirCounters,
    /// Server -> client.
    pub(crate) down: DirCounters,
}

impl fmt::Display for Counters {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "netem: ran {}.{:03} s, seed {}, {} client(s), {} datagram(s) from refused clients",
            self.elapsed_ms / 1000,
            self.elapsed_ms % 1000,
            self.seed,
            self.clients,
            self.clients_refused
        )?;
        writeln!(
            f,
            "{:<5} {:>9} {:>9} {:>10} {:>9} {:>11} {:>7} {:>14} {:>15} {:>9}",
            "dir",
            "received",
            "dropped",
            "overflowed",
            "forwarded",
            "send_errors",
            "unsent",
            "bytes_received",
            "bytes_forwarded",
            "max_queue"
        )?;
        for (name, c) in [("up", &self.up), ("down", &self.down)] {
            writeln!(
                f,
                "{name:<5} {:>9} {:>9} {:>10} {:>9} {:>11} {:>7} {:>14} {:>15} {:>9}",
                c.received,
                c.dropped,
                c.overflowed,
                c.forwarded,
                c.send_errors,
                c.unsent,
                c.bytes_received,
                c.bytes_forwarded,
                c.max_queue
            )?;
        }
        Ok(())
    }
}

/// The counters as printed: a table, or one line of JSON with `json`.
pub(crate) fn report(counters: &Counters, json: bool) -> anyhow::Result<String> {
    if json {
        serde_json::to_string(counters).context("encoding the counters as JSON")
    } else {
        Ok(counters.to_string().trim_end().to_owned())
    }
}

/// One direction's state: its generator, its serializer and its counters.
#[derive(Debug, Clone)]
struct DirState {
    config: DirConfig,
    rng: ChaCha8Rng,
    /// When the serializer is free again (rate limit only).
    free_at: Option<Instant>,
    held: usize,
    counters: DirCounters,
}

impl DirState {
    fn new(config: DirConfig, seed: u64, stream: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        rng.set_stream(stream);
        Self {
            config,
            rng,
            free_at: None,
            held: 0,
            counters: DirCounters::default(),
        }
    }

    /// The delay drawn from `draw`: uniform in `delay ± jitter`, clamped at zero.
    fn delay(&self, draw: u64) -> Duration {
        let jitter_ns = self.config.jitter.as_nanos();
        let delay_ns = self.config.delay.as_nanos();
        // Multiply-high maps the draw onto 0..=2 * jitter_ns without a modulo bias worth
        // the name; no overflow for jitters below 2^63 ns (the flags allow one hour).
        let offset_ns = (u128::from(draw) * (2 * jitter_ns + 1)) >> 64;
        let ns = (delay_ns + offset_ns).saturating_sub(jitter_ns);
        Duration::from_nanos(u64::try_from(ns).unwrap_or(u64::MAX))
    }
}

/// A uniform number in [0, 1) from 53 bits of `draw`.
fn unit(draw: u64) -> f64 {
    (draw >> 11) as f64 / (1u64 << 53) as f64
}

/// The link's decisions and counters; sans-IO: time is an argument, nothing is sent.
#[derive(Debug, Clone)]
pub(crate) struct Link {
    dirs: [DirState; 2],
    queue_limit: usize,
    seed: u64,
}

impl Link {
    /// A link with fresh generators seeded from `config.seed` (stream 0 up, 1 down).
    pub(crate) fn new(config: LinkConfig) -> Self {
        Self {
            dirs: [
                DirState::new(config.up, config.seed, 0),
                DirState::new(config.down, config.seed, 1),
            ],
            queue_limit: config.queue_limit,
            seed: config.seed,
        }
    }

    /// Decides the fate of a datagram of `len` bytes that arrived at `now` going `dir`.
    /// A datagram given `DeliverAt` is held until [`Link::on_departed`] is called for it.
    pub(crate) fn on_datagram(&mut self, now: Instant, dir: Dir, len: usize) -> Fate {
        let queue_limit = self.queue_limit;
        let state = &mut self.dirs[dir.index()];
        let loss_draw = state.rng.next_u64();
        let jitter_draw = state.rng.next_u64();
        state.counters.received += 1;
        state.counters.bytes_received += len as u64;
        if unit(loss_draw) < state.config.loss {
            state.counters.dropped += 1;
            return Fate::Drop;
        }
        if state.held >= queue_limit {
            state.counters.overflowed += 1;
            return Fate::Overflow;
        }
        let departs = match state.config.rate_bytes_per_s {
            Some(rate) => {
                let start = state.free_at.map_or(now, |free| free.max(now));
                let ns = (len as u128 * 1_000_000_000).div_ceil(u128::from(rate));
                let departs = start + Duration::from_nanos(u64::try_from(ns).unwrap_or(u64::MAX));
                state.free_at = Some(departs);
                departs
            }
            None => now,
        };
        state.held += 1;
        state.counters.max_queue = state.counters.max_queue.max(state.held as u64);
        Fate::DeliverAt(departs + state.delay(jitter_draw))
    }

    /// Records that a held datagram of `len` bytes left going `dir`: `sent` if the OS took
    /// it, otherwise it counts as a send error.
    pub(crate) fn on_departed(&mut self, dir: Dir, len: usize, sent: bool) {
        let state = &mut self.dirs[dir.index()];
        state.held = state.held.saturating_sub(1);
        if sent {
            state.counters.forwarded += 1;
            state.counters.bytes_forwarded += len as u64;
        } else {
            state.counters.send_errors += 1;
        }
    }

    /// The counters of `dir`; datagrams still held count as unsent.
    pub(crate) fn counters(&self, dir: Dir) -> DirCounters {
        let state = &self.dirs[dir.index()];
        DirCounters {
            unsent: state.held as u64,
            ..state.counters
        }
    }
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

/// A bound link emulator, ready to run.
#[derive(Debug)]
pub(crate) struct Netem {
    listen: UdpSocket,
    forward: SocketAddr,
    duration: Option<Duration>,
    link: Link,
}

impl Netem {
    /// Binds the listen socket of `args`.
    pub(crate) async fn bind(args: &NetemArgs) -> anyhow::Result<Self> {
        let listen = bind(args.listen)
            .with_context(|| format!("binding the listen address {}", args.listen))?;
        Ok(Self {
            listen,
            forward: args.forward,
            duration: args.duration,
            link: Link::new(args.link_config()),
        })
    }

    /// The address clients send to (the actual port when `--listen` asked for port 0).
    pub(crate) fn local_addr(&self) -> anyhow::Result<SocketAddr> {
        self.listen
            .local_addr()
            .context("reading the listen socket's address")
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

    /// Relays datagrams until `--duration` has elapsed or `stop` completes (an error from
    /// `stop` ends the run with that error), then returns the counters. Datagrams still
    /// held then are not sent.
    pub(crate) async fn run(
        mut self,
        stop: impl Future<Output = io::Result<()>>,
    ) -> anyhow::Result<Counters> {
        let started = now();
        let end = self.duration.and_then(|d| started.checked_add(d));
        let mut heap: BinaryHeap<Reverse<Pending>> = BinaryHeap::new();
        let mut upstreams: HashMap<SocketAddr, UdpSocket> = HashMap::new();
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
                    stopped.context("waiting for Ctrl-C")?;
                    Wake::Stop
                }
                () = &mut end_sleep => Wake::Stop,
                () = sleep_until(next_due) => Wake::Timer,
                received = self.listen.recv_from(&mut from_client) => match received {
                    Ok((len, client)) => Wake::FromClient(len, client),
                    Err(e) if is_transient(&e) => continue,
                    Err(e) => return Err(e).context("receiving from clients"),
                },
                received = poll_fn(|cx| poll_upstreams(cx, &upstreams, &mut from_server)) => {
                    match received {
                        Ok((len, client)) => Wake::FromServer(len, client),
                        Err(e) if is_transient(&e) => continue,
                        Err(e) => return Err(e).context("receiving from the server"),
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
                                .get(&p.client)
                                .is_some_and(|s| s.try_send_to(&p.payload, self.forward).is_ok()),
                            Dir::Down => self.listen.try_send_to(&p.payload, p.client).is_ok(),
                        };
                        self.link.on_departed(p.dir, p.payload.len(), sent);
                    }
                }
                Wake::FromClient(len, client) => {
                    if !upstreams.contains_key(&client) {
                        if upstreams.len() >= MAX_CLIENTS {
                            clients_refused += 1;
                            continue;
                        }
                        let socket = bind(self.upstream_bind_addr())
                            .with_context(|| format!("binding an upstream socket for {client}"))?;
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
            seed: self.link.seed,
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

/// Receives from whichever client's upstream socket has a datagram; returns its length and
/// the client it belongs to.
fn poll_upstreams(
    cx: &mut Context<'_>,
    upstreams: &HashMap<SocketAddr, UdpSocket>,
    buf: &mut [u8],
) -> Poll<io::Result<(usize, SocketAddr)>> {
    for (client, socket) in upstreams {
        let mut read = ReadBuf::new(buf);
        match socket.poll_recv_from(cx, &mut read) {
            Poll::Ready(Ok(_)) => return Poll::Ready(Ok((read.filled().len(), *client))),
            Poll::Ready(Err(e)) => return Poll::Ready(Err(e)),
            Poll::Pending => {}
        }
    }
    Poll::Pending
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

/// `coapcam netem`: binds, reports the listen address on standard error, relays until
/// `--duration` or Ctrl-C, and returns the counters.
pub(crate) async fn run(args: NetemArgs) -> anyhow::Result<Counters> {
    let netem = Netem::bind(&args).await?;
    eprintln!(
        "netem: listening on {}, forwarding to {}",
        netem.local_addr()?,
        args.forward
    );
    netem.run(tokio::signal::ctrl_c()).await
}

#[cfg(test)]
mod tests {
    use super::*;

    use clap::Parser;

    #[derive(Debug, Parser)]
    struct TestCli {
        #[command(flatten)]
        args: NetemArgs,
    }

    fn args(flags: &[&str]) -> NetemArgs {
        let argv = ["netem"].iter().chain(flags);
        match TestCli::try_parse_from(argv) {
            Ok(cli) => cli.args,
            Err(e) => panic!("flags {flags:?}: {e}"),
        }
    }

    fn direction(loss: f64, delay_ms: u64, jitter_ms: u64, rate: Option<u64>) -> DirConfig {
        DirConfig {
            loss,
            delay: Duration::from_millis(delay_ms),
            jitter: Duration::from_millis(jitter_ms),
            rate_bytes_per_s: rate,
        }
    }

    fn link(up: DirConfig, down: DirConfig, seed: u64) -> Link {
        Link::new(LinkConfig {
            up,
            down,
            seed,
            queue_limit: usize::MAX,
        })
    }

    fn delivery(fate: Fate) -> Instant {
        match fate {
            Fate::DeliverAt(at) => at,
            other => panic!("expected a delivery, got {other:?}"),
        }
    }

    #[test]
    fn per_direction_flags_override_the_shared_ones() {
        let config = args(&[
            "--listen=127.0.0.1:0",
            "--forward=127.0.0.1:5683",
            "--loss=0.1",
            "--loss-down=0.3",
            "--delay-ms=20",
            "--delay-up-ms=5",
            "--jitter-ms=2",
            "--rate=1000",
            "--rate-up=500",
            "--seed=9",
        ])
        .link_config();
        assert_eq!(config.up, direction(0.1, 5, 2, Some(500)));
        assert_eq!(config.down, direction(0.3, 20, 2, Some(1000)));
        assert_eq!(config.seed, 9);
        assert_eq!(config.queue_limit, 1000);
    }

    #[test]
    fn bad_flag_values_are_refused() {
        for bad in [
            &["--loss=1.5"][..],
            &["--loss-up=-0.1"],
            &["--loss=lots"],
            &["--rate=0"],
            &["--duration=-1"],
            &["--duration=soon"],
            &["--queue-limit=0"],
            &["--delay-ms=3600001"],
            &["--jitter-down-ms=99999999999"],
        ] {
            let argv = ["netem", "--listen=127.0.0.1:0", "--forward=127.0.0.1:1"]
                .iter()
                .chain(bad);
            assert!(TestCli::try_parse_from(argv).is_err(), "{bad:?} accepted");
        }
        let fractional = args(&[
            "--listen=127.0.0.1:0",
            "--forward=127.0.0.1:1",
            "--duration=0.25",
        ]);
        assert_eq!(fractional.duration, Some(Duration::from_millis(250)));
    }

    #[test]
    fn loss_rate_is_close_to_the_configured_probability() {
        let t0 = Instant::now();
        for (loss, seed) in [(0.0, 1), (0.05, 2), (0.1, 3), (0.5, 4), (1.0, 5)] {
            let mut link = link(
                direction(loss, 0, 0, None),
                direction(0.0, 0, 0, None),
                seed,
            );
            let dropped = (0..10_000)
                .filter(|_| link.on_datagram(t0, Dir::Up, 100) == Fate::Drop)
                .count();
            let rate = dropped as f64 / 10_000.0;
            assert!((rate - loss).abs() <= 0.02, "loss {loss}: measured {rate}");
            assert_eq!(link.counters(Dir::Up).dropped, dropped as u64);
            assert_eq!(link.counters(Dir::Down).received, 0);
        }
    }

    #[test]
    fn the_same_seed_makes_the_same_decisions() {
        let t0 = Instant::now();
        let config = direction(0.2, 10, 8, Some(100_000));
        let fates = |seed| {
            let mut link = link(config, config, seed);
            (0..1000u64)
                .map(|i| {
                    let dir = if i % 3 == 0 { Dir::Down } else { Dir::Up };
                    link.on_datagram(t0 + Duration::from_micros(i * 300), dir, 200)
                })
                .collect::<Vec<_>>()
        };
        assert_eq!(fates(42), fates(42));
        assert_ne!(fates(42), fates(43));
    }

    #[test]
    fn directions_draw_from_their_own_streams() {
        let t0 = Instant::now();
        let config = direction(0.3, 10, 5, None);
        let mut alone = link(config, config, 7);
        let mut mixed = link(config, config, 7);
        for i in 0..500 {
            mixed.on_datagram(t0, Dir::Down, 50);
            let at = t0 + Duration::from_millis(i);
            assert_eq!(
                alone.on_datagram(at, Dir::Up, 80),
                mixed.on_datagram(at, Dir::Up, 80)
            );
        }
    }

    #[test]
    fn loss_does_not_shift_the_jitter_of_later_datagrams() {
        let t0 = Instant::now();
        let mut lossless = link(direction(0.0, 30, 10, None), direction(0.0, 0, 0, None), 5);
        let mut lossy = link(direction(0.4, 30, 10, None), direction(0.0, 0, 0, None), 5);
        let mut compared = 0;
        for _ in 0..500 {
            let kept = lossless.on_datagram(t0, Dir::Up, 10);
            if let fate @ Fate::DeliverAt(_) = lossy.on_datagram(t0, Dir::Up, 10) {
                assert_eq!(fate, kept);
                compared += 1;
            }
        }
        assert!(compared > 200, "{compared}");
    }

    #[test]
    fn delay_and_jitter_stay_within_bounds_and_spread() {
        let t0 = Instant::now();
        let mut link = link(direction(0.0, 50, 20, None), direction(0.0, 7, 0, None), 11);
        let delays: Vec<Duration> = (0..5000)
            .map(|_| delivery(link.on_datagram(t0, Dir::Up, 10)) - t0)
            .collect();
        let (low, high) = (Duration::from_millis(30), Duration::from_millis(70));
        assert!(delays.iter().all(|d| (low..=high).contains(d)));
        let min = delays.iter().min().copied().unwrap_or_default();
        let max = delays.iter().max().copied().unwrap_or_default();
        assert!(min < Duration::from_millis(31) && max > Duration::from_millis(69));
        let mean = delays.iter().sum::<Duration>() / 5000;
        assert!(mean.abs_diff(Duration::from_millis(50)) < Duration::from_millis(2));
        for _ in 0..10 {
            assert_eq!(
                delivery(link.on_datagram(t0, Dir::Down, 10)) - t0,
                Duration::from_millis(7)
            );
        }
    }

    #[test]
    fn jitter_larger_than_the_delay_is_clamped_at_zero() {
        let t0 = Instant::now();
        let mut link = link(direction(0.0, 2, 10, None), direction(0.0, 0, 0, None), 3);
        let delays: Vec<Duration> = (0..2000)
            .map(|_| delivery(link.on_datagram(t0, Dir::Up, 10)) - t0)
            .collect();
        assert!(delays.iter().all(|d| *d <= Duration::from_millis(12)));
        assert!(delays.contains(&Duration::ZERO));
    }

    #[test]
    fn rate_limit_spaces_departures_by_serialization_time() {
        let t0 = Instant::now();
        // 1000 B/s: a 100-byte datagram occupies the link for 100 ms.
        let mut link = link(
            direction(0.0, 10, 0, Some(1000)),
            direction(0.0, 0, 0, None),
            1,
        );
        let burst: Vec<Duration> = (0..5)
            .map(|_| delivery(link.on_datagram(t0, Dir::Up, 100)) - t0)
            .collect();
        let expected: Vec<Duration> = (1..=5)
            .map(|i| Duration::from_millis(100 * i + 10))
            .collect();
        assert_eq!(burst, expected);
        assert_eq!(link.counters(Dir::Up).max_queue, 5);
        // Once the serializer is idle, a datagram starts at its arrival.
        let later = t0 + Duration::from_secs(2);
        assert_eq!(
            delivery(link.on_datagram(later, Dir::Up, 50)) - later,
            Duration::from_millis(60)
        );
        // The other direction is unlimited.
        assert_eq!(delivery(link.on_datagram(t0, Dir::Down, 100_000)), t0);
    }

    #[test]
    fn queue_limit_overflows_and_departures_make_room() {
        let t0 = Instant::now();
        let mut link = Link::new(LinkConfig {
            up: direction(0.0, 100, 0, None),
            down: direction(0.0, 100, 0, None),
            seed: 0,
            queue_limit: 2,
        });
        assert!(matches!(
            link.on_datagram(t0, Dir::Up, 10),
            Fate::DeliverAt(_)
        ));
        assert!(matches!(
            link.on_datagram(t0, Dir::Up, 10),
            Fate::DeliverAt(_)
        ));
        assert_eq!(link.on_datagram(t0, Dir::Up, 10), Fate::Overflow);
        assert!(matches!(
            link.on_datagram(t0, Dir::Down, 10),
            Fate::DeliverAt(_)
        ));
        link.on_departed(Dir::Up, 10, true);
        link.on_departed(Dir::Up, 10, false);
        assert!(matches!(
            link.on_datagram(t0, Dir::Up, 10),
            Fate::DeliverAt(_)
        ));
        let up = link.counters(Dir::Up);
        assert_eq!(
            (
                up.received,
                up.overflowed,
                up.forwarded,
                up.send_errors,
                up.unsent,
                up.max_queue
            ),
            (4, 1, 1, 1, 1, 2)
        );
        assert_eq!((up.bytes_received, up.bytes_forwarded), (40, 10));
    }

    #[test]
    fn counters_print_as_a_table_and_as_json() -> anyhow::Result<()> {
        let counters = Counters {
            seed: 7,
            elapsed_ms: 1234,
            clients: 1,
            clients_refused: 0,
            up: DirCounters {
                received: 10,
                dropped: 1,
                forwarded: 9,
                ..DirCounters::default()
            },
            down: DirCounters::default(),
        };
        let text = report(&counters, false)?;
        assert!(
            text.starts_with("netem: ran 1.234 s, seed 7, 1 client(s)"),
            "{text}"
        );
        assert_eq!(text.lines().count(), 4);
        let json: serde_json::Value = serde_json::from_str(&report(&counters, true)?)?;
        assert_eq!(json["up"]["dropped"], 1);
        assert_eq!(json["down"]["max_queue"], 0);
        assert_eq!(json["elapsed_ms"], 1234);
        Ok(())
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
        flags: &[&str],
    ) -> anyhow::Result<(
        SocketAddr,
        tokio::sync::oneshot::Sender<()>,
        tokio::task::JoinHandle<anyhow::Result<Counters>>,
    )> {
        let mut all = vec![
            "--listen=127.0.0.1:0".to_owned(),
            format!("--forward={forward}"),
        ];
        all.extend(flags.iter().map(|f| (*f).to_owned()));
        let all: Vec<&str> = all.iter().map(String::as_str).collect();
        let netem = Netem::bind(&args(&all)).await?;
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
        let (netem, stop, task) =
            start(server, &["--delay-up-ms=15", "--delay-down-ms=25"]).await?;
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
            let (netem, stop, task) =
                start(server, &["--loss-up=0.3", "--loss-down=0", "--seed=77"]).await?;
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
        let (netem, stop, task) = start(server, &["--jitter-ms=3", "--delay-ms=3"]).await?;
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
    async fn stops_when_the_duration_has_elapsed() -> anyhow::Result<()> {
        let (server, echo) = echo_server().await?;
        let netem = Netem::bind(&args(&[
            "--listen=127.0.0.1:0",
            &format!("--forward={server}"),
            "--delay-ms=1000",
            "--duration=0.1",
        ]))
        .await?;
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
