//! `coapcam bench transfer`: the researcher's instrument. Whole-body GETs of seeded random
//! bodies through emulated links (the `netem` crate, in this process), with our client's
//! three transfer modes, libcoap 4.3.1 (RFC 7959), libcoap 4.3.5 (RFC 9177 Q-Block2 NON)
//! and QUIC (`quic-bench`: quinn with BBR) as the modern-transport reference. Every
//! client and server is a child process, so every mode is timed the same way: the client
//! process's wall time, start to exit. Every body is compared bit-exact with the original.
//! The result is a markdown table on standard output, and optionally JSON and a PNG plot.
//! Pair runs (`--pairs`) start two clients of one mode at once through one 50 Mbit/s relay
//! and report how the link's bytes were shared between them, in a second table.

use std::cmp::Reverse;
use std::fmt::Write as _;
use std::fs::File;
use std::io::{BufRead as _, BufReader};
use std::net::{Ipv4Addr, SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::mpsc;
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use clap::{Args, ValueEnum};
use image::{Rgb, RgbImage};
use netem::{Counters, DeliveredBytes, DirConfig, LinkConfig, Netem};
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore as _, SeedableRng as _};

use crate::cli::{Exit, error_text, outln};
use coapcam::stats::Spread;
use coapcam::vision::picture;

/// The largest body `--sizes` accepts (what `quic-bench get` takes at most).
const MAX_BODY: u64 = 256 << 20;
/// Block size of every CoAP mode, bytes (SZX 6).
const BLOCK_BYTES: u32 = 1024;
/// How often a running client is checked for its exit: the resolution of the times.
const POLL: Duration = Duration::from_millis(1);
/// How long a server may take to answer its first ping.
const STARTUP: Duration = Duration::from_secs(20);
/// How long the untimed loopback PUT (and the GET that checks it) to a libcoap server
/// may take.
const SETUP_TRANSFER: Duration = Duration::from_secs(120);
/// Datagrams the relay holds at most per direction (`coapcam netem`'s default).
const RELAY_QUEUE_LIMIT: usize = 1000;
/// 50 Mbit/s in bytes per second.
const RATE_50_MBIT: u64 = 6_250_000;
/// The bottleneck's drop-tail buffer of `20ms-2%-50mbit` (as in the simulator's test).
const QUEUE_64_KB: usize = 64_000;
/// The link of the pair runs: two transfers at once through its rate limit.
const PAIR_LINK: Link = Link::Rtt20Loss2Rate50;
/// A pair run holds when the smaller of the two clients' shares is at least this.
const FAIR_SHARE: f64 = 0.35;
/// Mixed into the seeds of the pair runs' relays, so that they differ from the single runs'.
const PAIR_SEED: u64 = 0x7061_6972;

/// Flags of `bench transfer`.
#[derive(Debug, Args)]
#[command(after_long_help = "\
Each cell of the table is one (link, size, mode): the client fetches a body of that size \
through that link RUNS times (SLOW_RUNS for the slow modes). Runs are interleaved: run 1 \
of every mode, then run 2, ..., so a change of the machine's load hits every mode alike. \
Run i of every mode goes through a fresh relay seeded alike (from --seed, the link, the \
size and i).

Timing: the client's whole process, from its start to its exit, as a user of each \
command waits for it (checked every millisecond). QUIC's time includes its handshake; \
CoAP needs none. Servers start before and are not timed.

Links (the emulator runs in this process, between the client and the server; every \
figure is for each direction):
  loopback          no relay: the client talks to the server directly
  20ms              10 ms each way (a 20 ms round trip)
  20ms-2%           20 ms round trip, 2 % loss each way
  20ms-2%-50mbit    20 ms, 2 %, 50 Mbit/s each way with a 64,000-byte drop-tail queue
  100ms-5%          50 ms each way, 5 % loss each way

Modes (1024-byte blocks for every CoAP mode):
  stop-and-wait     coapcam get --transfer stop-and-wait (RFC 7959), against coapcam serve
  window            coapcam get --transfer window (many blocks in flight), against coapcam serve
  q-block           coapcam get --transfer q-block (RFC 9177), against coapcam serve
  libcoap-4.3.1     coap-client-notls (Debian libcoap3-bin, RFC 7959 CON) against \
coap-server-notls -d, the body PUT first
  libcoap-4.3.5-qblock
                    libcoap 4.3.5's coap-client -L 5 -N (Q-Block2, NON) against its \
coap-server -L 5 -d, the body PUT first; found in $COAPCAM_LIBCOAP435 or \
~/.cache/coapcam-peers/libcoap-4.3.5/build (../shared/peers/build-libcoap.sh builds it)
  quic              quic-bench get (quinn with BBR, one stream) against quic-bench serve; \
found in $COAPCAM_QUIC_BENCH or next to this executable (cargo build --release -p quic-bench)
The slow modes are stop-and-wait and both libcoap modes. A mode whose programs are \
missing is reported as unavailable, loudly, and shown so in the table.

Bodies are random bytes from --seed, one file per size. libcoap's servers get theirs by \
a PUT on loopback before anything is timed, checked by a GET. A run succeeds when the \
client exits with status 0 within --cap and its output equals the body byte for byte; a \
client that exits 0 with a short file fails the run.

Two transfers at once (--pairs N, when 20ms-2%-50mbit is among --links): for each size \
and each fast mode, N runs of two clients of that mode started together through one relay \
of that link to one server, to see whether they share the 50 Mbit/s fairly. Both clients \
are timed and checked like any run. When the first of them ends, the relay's count of the \
payload bytes it has delivered to each client so far gives the shares: each client's bytes \
over the sum of both (the relay knows the clients by address, not by process, so a run \
reports its smaller and its larger share). A pair run holds when its smaller share is at \
least 35 %. Its link utilisation is both bodies (2 x size) over the later client's time, \
as a fraction of 50 Mbit/s. The slow modes are not paired; --pairs 0 runs none.

Output: the table on standard output, one row per (link, size), one column per mode: \
the median of the successful runs in seconds, [min-max] of them and successful/runs, \
then ratios of medians, and every failed run with its reason under the table. After it, \
when pairs ran, the table of the pair runs, one row per (size, mode): the median smaller \
share [min-max], the runs that held, the median link utilisation [min-max] and \
successful/runs (successful: both clients), medians of the successful runs. Progress goes \
to standard error. --json writes every \
run (time, exit, bit-exactness, the relay's counters) and every pair run (both clients, \
the bytes delivered to each client address when the first ended, the shares, the \
utilisation); --plot draws the medians against the loss rate, one panel per size.

Exit status: 0 when the benchmark ran, failed runs included (they are results); 1 when \
it could not run (a body or output file could not be written, a relay could not bind).")]
pub(super) struct TransferArgs {
    /// Runs per cell of the fast modes (window, q-block, quic).
    #[arg(long, value_name = "N", default_value_t = 5,
          value_parser = clap::value_parser!(u32).range(1..))]
    runs: u32,
    /// Runs per cell of the slow modes (stop-and-wait, libcoap-4.3.1, libcoap-4.3.5-qblock).
    #[arg(long, value_name = "N", default_value_t = 1,
          value_parser = clap::value_parser!(u32).range(1..))]
    slow_runs: u32,
    /// Body sizes in bytes, comma-separated (921610 and 2764810 are a 640x480 and a
    /// 1280x720 RGB frame; 10032012 the thesis's largest body).
    #[arg(long, value_name = "BYTES,...", value_delimiter = ',',
          default_values = ["921610", "2764810"],
          value_parser = clap::value_parser!(u64).range(1..=MAX_BODY))]
    sizes: Vec<u64>,
    /// Links, comma-separated: loopback, 20ms, 20ms-2%, 20ms-2%-50mbit, 100ms-5% (see
    /// below).
    #[arg(long, value_name = "LINK,...", value_delimiter = ',', hide_possible_values = true,
          default_values = ["loopback", "20ms", "20ms-2%", "20ms-2%-50mbit", "100ms-5%"])]
    links: Vec<Link>,
    /// Modes, comma-separated: stop-and-wait, window, q-block, libcoap-4.3.1,
    /// libcoap-4.3.5-qblock, quic (see below); the table's columns in this order.
    #[arg(long, value_name = "MODE,...", value_delimiter = ',', hide_possible_values = true,
          default_values = ["stop-and-wait", "window", "q-block", "libcoap-4.3.1",
                            "libcoap-4.3.5-qblock", "quic"])]
    modes: Vec<Mode>,
    /// Pair runs per size and fast mode: two clients at once through one 20ms-2%-50mbit
    /// relay (see below); 0 runs none, and none run when that link is not among --links.
    #[arg(long, value_name = "N", default_value_t = 3)]
    pairs: u32,
    /// Seconds a run may take; a client still running then is killed and the run failed.
    #[arg(long, value_name = "SECONDS", default_value = "120", value_parser = parse_cap)]
    cap: Duration,
    /// Seed of the bodies and of the relays' loss decisions.
    #[arg(long, value_name = "N", default_value_t = 1)]
    seed: u64,
    /// Also write every run, the links, the modes and the machine as JSON into FILE.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    /// Also draw the medians against the loss rate into FILE (PNG), one panel per size.
    #[arg(long, value_name = "FILE.png")]
    plot: Option<PathBuf>,
}

fn parse_cap(text: &str) -> Result<Duration, String> {
    let cap = crate::cli::netem::parse_seconds(text)?;
    if cap.is_zero() {
        return Err(format!("{text} s: the cap must be more than 0"));
    }
    Ok(cap)
}

/// An emulated link between client and server.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Link {
    /// No relay.
    #[value(name = "loopback")]
    Loopback,
    /// 10 ms each way.
    #[value(name = "20ms")]
    Rtt20,
    /// 10 ms and 2 % loss each way.
    #[value(name = "20ms-2%")]
    Rtt20Loss2,
    /// 10 ms, 2 % loss, 50 Mbit/s with a 64 KB queue, each way.
    #[value(name = "20ms-2%-50mbit")]
    Rtt20Loss2Rate50,
    /// 50 ms and 5 % loss each way.
    #[value(name = "100ms-5%")]
    Rtt100Loss5,
}

impl Link {
    fn name(self) -> &'static str {
        match self {
            Self::Loopback => "loopback",
            Self::Rtt20 => "20ms",
            Self::Rtt20Loss2 => "20ms-2%",
            Self::Rtt20Loss2Rate50 => "20ms-2%-50mbit",
            Self::Rtt100Loss5 => "100ms-5%",
        }
    }

    fn description(self) -> &'static str {
        match self {
            Self::Loopback => "no relay: the client talks to the server on 127.0.0.1",
            Self::Rtt20 => "10 ms each way (20 ms round trip), no loss",
            Self::Rtt20Loss2 => "10 ms each way, 2 % loss each way",
            Self::Rtt20Loss2Rate50 => {
                "10 ms each way, 2 % loss each way, 50 Mbit/s each way with a 64,000-byte \
                 drop-tail queue"
            }
            Self::Rtt100Loss5 => "50 ms each way (100 ms round trip), 5 % loss each way",
        }
    }

    /// Loss probability, one-way delay and rate of each direction; `None` for loopback.
    fn shape(self) -> Option<(f64, Duration, Option<u64>, Option<usize>)> {
        let ms = Duration::from_millis;
        match self {
            Self::Loopback => None,
            Self::Rtt20 => Some((0.0, ms(10), None, None)),
            Self::Rtt20Loss2 => Some((0.02, ms(10), None, None)),
            Self::Rtt20Loss2Rate50 => Some((0.02, ms(10), Some(RATE_50_MBIT), Some(QUEUE_64_KB))),
            Self::Rtt100Loss5 => Some((0.05, ms(50), None, None)),
        }
    }

    /// The relay's configuration with `seed`; `None` for loopback.
    fn config(self, seed: u64) -> Option<LinkConfig> {
        let (loss, delay, rate, queue_bytes) = self.shape()?;
        let direction = DirConfig::new(loss, delay, Duration::ZERO, rate);
        Some(LinkConfig {
            up: direction,
            down: direction,
            seed,
            queue_limit: RELAY_QUEUE_LIMIT,
            queue_bytes,
        })
    }

    /// Loss each way, percent (the plot's x).
    fn loss_percent(self) -> f64 {
        self.shape().map_or(0.0, |s| s.0 * 100.0)
    }

    /// Whether the plot joins this link's points with a line (the 20 ms links that
    /// differ only in loss).
    fn on_line(self) -> bool {
        matches!(self, Self::Rtt20 | Self::Rtt20Loss2)
    }

    fn marker(self) -> Marker {
        match self {
            Self::Loopback => Marker::Square,
            Self::Rtt20 | Self::Rtt20Loss2 => Marker::Circle,
            Self::Rtt20Loss2Rate50 => Marker::Triangle,
            Self::Rtt100Loss5 => Marker::Diamond,
        }
    }

    fn json(self) -> serde_json::Value {
        let direction = self.shape().map(|(loss, delay, rate, _)| {
            serde_json::json!({
                "loss": loss, "delay_ms": delay.as_secs_f64() * 1e3, "jitter_ms": 0,
                "rate_bytes_per_s": rate,
            })
        });
        serde_json::json!({
            "name": self.name(),
            "description": self.description(),
            "relay": self.shape().is_some(),
            "up": direction,
            "down": direction,
            "queue_limit_datagrams": self.shape().map(|_| RELAY_QUEUE_LIMIT),
            "queue_bytes": self.shape().and_then(|s| s.3),
        })
    }
}

/// A client and the server it fetches from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Mode {
    /// Ours, RFC 7959 one block per round trip.
    #[value(name = "stop-and-wait")]
    StopAndWait,
    /// Ours, many blocks in flight.
    #[value(name = "window")]
    Window,
    /// Ours, RFC 9177 Q-Block2.
    #[value(name = "q-block")]
    QBlock,
    /// libcoap 4.3.1 (Debian), RFC 7959.
    #[value(name = "libcoap-4.3.1")]
    Libcoap431,
    /// libcoap 4.3.5 built from source, Q-Block2 NON.
    #[value(name = "libcoap-4.3.5-qblock")]
    Libcoap435,
    /// quinn with BBR.
    #[value(name = "quic")]
    Quic,
}

impl Mode {
    fn name(self) -> &'static str {
        match self {
            Self::StopAndWait => "stop-and-wait",
            Self::Window => "window",
            Self::QBlock => "q-block",
            Self::Libcoap431 => "libcoap-4.3.1",
            Self::Libcoap435 => "libcoap-4.3.5-qblock",
            Self::Quic => "quic",
        }
    }

    /// The name in ratio headers.
    fn short(self) -> &'static str {
        match self {
            Self::Libcoap435 => "libcoap-4.3.5",
            Self::Quic => "QUIC",
            other => other.name(),
        }
    }

    fn description(self) -> &'static str {
        match self {
            Self::StopAndWait => {
                "coapcam get --transfer stop-and-wait (RFC 7959, one block per round trip) \
                 against coapcam serve --no-cameras --static"
            }
            Self::Window => {
                "coapcam get --transfer window (many block requests in flight, paced by a \
                 congestion controller) against coapcam serve --no-cameras --static"
            }
            Self::QBlock => {
                "coapcam get --transfer q-block (RFC 9177 Q-Block2) against coapcam serve \
                 --no-cameras --static"
            }
            Self::Libcoap431 => {
                "libcoap 4.3.1 coap-client-notls -b 1024 (RFC 7959, CON) against \
                 coap-server-notls -d, the body PUT first on loopback"
            }
            Self::Libcoap435 => {
                "libcoap 4.3.5 coap-client -L 5 -N -b 1024 (RFC 9177 Q-Block2, NON) against \
                 coap-server -L 5 -d, the body PUT first on loopback"
            }
            Self::Quic => {
                "quic-bench get (quinn 0.11 with BBR, one bidirectional stream, handshake \
                 included) against quic-bench serve"
            }
        }
    }

    /// Stop-and-wait and both libcoap modes take minutes on lossy links.
    fn slow(self) -> bool {
        matches!(
            self,
            Self::StopAndWait | Self::Libcoap431 | Self::Libcoap435
        )
    }

    /// The plot's colour.
    fn color(self) -> Rgb<u8> {
        Rgb(match self {
            Self::StopAndWait => [255, 127, 14],
            Self::Window => [31, 119, 180],
            Self::QBlock => [44, 160, 44],
            Self::Libcoap431 => [214, 39, 40],
            Self::Libcoap435 => [148, 103, 189],
            Self::Quic => [40, 40, 40],
        })
    }
}

/// The order given, each once.
fn unique<T: PartialEq + Copy>(items: &[T]) -> Vec<T> {
    let mut out = Vec::new();
    for &item in items {
        if !out.contains(&item) {
            out.push(item);
        }
    }
    out
}

// ---------------------------------------------------------------------------------------
// Child processes and relays

/// A child process, killed and reaped on drop.
struct Proc {
    child: Child,
    name: String,
    /// When it started (when the spawn returned): where its time counts from.
    started: Instant,
}

impl Proc {
    fn spawn(mut command: Command, name: &str) -> anyhow::Result<Self> {
        let child = command
            .stdin(Stdio::null())
            .spawn()
            .with_context(|| format!("starting {name}"))?;
        Ok(Self {
            child,
            name: name.to_owned(),
            started: Instant::now(),
        })
    }

    /// Kills it (if it still runs) and reaps it.
    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// An error if it has exited.
    fn check_running(&mut self) -> anyhow::Result<()> {
        match self.child.try_wait() {
            Ok(None) => Ok(()),
            Ok(Some(status)) => bail!("{} exited ({status})", self.name),
            Err(e) => Err(e).with_context(|| format!("waiting for {}", self.name)),
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A `netem` relay on a thread of its own (its own tokio runtime), until dropped.
struct Relay {
    addr: SocketAddr,
    /// The bytes it has delivered to each client so far.
    delivered: DeliveredBytes,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<JoinHandle<anyhow::Result<Counters>>>,
}

impl Relay {
    /// Binds a relay on 127.0.0.1 to `forward` through `config`.
    fn start(forward: SocketAddr, config: LinkConfig) -> anyhow::Result<Self> {
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let (addr_tx, addr_rx) = mpsc::channel();
        let thread = thread::Builder::new()
            .name("netem".into())
            .spawn(move || -> anyhow::Result<Counters> {
                let runtime = tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                    .context("starting the relay's tokio runtime")?;
                runtime.block_on(async move {
                    let listen = SocketAddr::from((Ipv4Addr::LOCALHOST, 0));
                    let bound = Netem::bind(listen, forward, config, None)
                        .and_then(|n| Ok((n.local_addr()?, n)));
                    let netem = match bound {
                        Ok((addr, netem)) => {
                            let _ = addr_tx.send(Ok((addr, netem.delivered())));
                            netem
                        }
                        Err(e) => {
                            let _ = addr_tx.send(Err(e.to_string()));
                            bail!("binding the relay: {e}");
                        }
                    };
                    // A dropped sender stops the relay too.
                    let stop = async move {
                        let _ = stop_rx.await;
                        Ok(())
                    };
                    Ok(netem.run(stop).await?)
                })
            })
            .context("starting the relay's thread")?;
        let mut relay = Self {
            addr: SocketAddr::from((Ipv4Addr::LOCALHOST, 0)),
            delivered: DeliveredBytes::default(),
            stop: Some(stop_tx),
            thread: Some(thread),
        };
        (relay.addr, relay.delivered) = match addr_rx.recv() {
            Ok(Ok(bound)) => bound,
            Ok(Err(e)) => bail!("binding a relay on 127.0.0.1: {e}"),
            Err(_) => bail!("the relay's thread ended before it bound"),
        };
        Ok(relay)
    }

    /// Stops it and returns its counters.
    fn finish(mut self) -> anyhow::Result<Counters> {
        self.stop.take();
        let thread = self.thread.take().context("the relay already stopped")?;
        match thread.join() {
            Ok(counters) => counters,
            Err(_) => bail!("the relay's thread panicked"),
        }
    }
}

impl Drop for Relay {
    fn drop(&mut self) {
        self.stop.take();
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// A free UDP port on 127.0.0.1 (free when asked: a server started on it may still lose
/// it to another program, which [`start_coap_server`] retries).
fn free_port() -> anyhow::Result<u16> {
    let socket = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0)).context("finding a free UDP port")?;
    Ok(socket
        .local_addr()
        .context("finding a free UDP port")?
        .port())
}

/// Whether a CoAP server answers at `addr`: an empty CON (a CoAP ping, RFC 7252 §4.3)
/// that every server answers with a RST.
fn coap_answers(addr: SocketAddr) -> bool {
    let Ok(socket) = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0)) else {
        return false;
    };
    let ping = [0x40, 0x00, 0x7a, 0x5e];
    let mut buf = [0u8; 64];
    socket
        .set_read_timeout(Some(Duration::from_millis(100)))
        .is_ok()
        && socket.send_to(&ping, addr).is_ok()
        && matches!(socket.recv_from(&mut buf), Ok((n, from)) if n >= 4 && from == addr)
}

/// Starts a CoAP server with `command(port)` on a free port and waits until it answers a
/// ping; its standard error goes to `log`. Tries three ports.
fn start_coap_server(
    name: &str,
    log: &Path,
    command: impl Fn(u16) -> Command,
) -> anyhow::Result<(Proc, SocketAddr)> {
    let mut last = None;
    for _ in 0..3 {
        let port = free_port()?;
        let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
        let mut cmd = command(port);
        let stderr = File::create(log).with_context(|| format!("creating {}", log.display()))?;
        cmd.stdout(Stdio::null()).stderr(stderr);
        let mut server = Proc::spawn(cmd, name)?;
        let started = Instant::now();
        let up = loop {
            if let Err(e) = server.check_running() {
                break Err(e);
            }
            if coap_answers(addr) {
                break Ok(());
            }
            if started.elapsed() > STARTUP {
                break Err(anyhow::anyhow!(
                    "{name} did not answer on {addr} within {} s",
                    STARTUP.as_secs()
                ));
            }
        };
        match up {
            Ok(()) => return Ok((server, addr)),
            Err(e) => last = Some(e.context(tail(log))),
        }
    }
    Err(last.unwrap_or_else(|| anyhow::anyhow!("{name} did not start")))
}

/// The last lines of a log file, for an error message.
fn tail(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let lines: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
    let start = lines.len().saturating_sub(4);
    let mut out = lines[start..].join(" | ");
    if out.len() > 600 {
        let cut = (0..=out.len() - 600)
            .rev()
            .find(|&i| out.is_char_boundary(i))
            .unwrap_or(0);
        out = format!("...{}", &out[cut..]);
    }
    if out.is_empty() {
        "(nothing on standard error)".into()
    } else {
        out
    }
}

/// Runs `command` to its end within `limit`; an error says why it failed.
fn run_to_end(mut command: Command, name: &str, log: &Path, limit: Duration) -> anyhow::Result<()> {
    let stderr = File::create(log).with_context(|| format!("creating {}", log.display()))?;
    command.stdout(Stdio::null()).stderr(stderr);
    let mut proc = Proc::spawn(command, name)?;
    let (status, _) = wait_capped(&mut proc, limit)?;
    match status {
        Some(s) if s.success() => Ok(()),
        Some(s) => bail!("{name} failed ({s}): {}", tail(log)),
        None => bail!("{name} did not end within {} s", limit.as_secs()),
    }
}

/// Waits for `proc` to exit, killing it `cap` after its start; its exit status (`None`:
/// killed) and the time from its start to when its exit was seen.
fn wait_capped(proc: &mut Proc, cap: Duration) -> anyhow::Result<(Option<ExitStatus>, Duration)> {
    let ended = wait_all_capped(std::slice::from_mut(proc), cap, || {})?;
    Ok(ended[0])
}

/// Waits for every one of `procs` to exit, checking each every [`POLL`] and killing one
/// still running `cap` after its start. Per process, in order: its exit status (`None`:
/// killed) and the time from its start to when its end was seen. `on_first_end` is called
/// once, right after the check that first sees one of them end.
fn wait_all_capped(
    procs: &mut [Proc],
    cap: Duration,
    on_first_end: impl FnOnce(),
) -> anyhow::Result<Vec<(Option<ExitStatus>, Duration)>> {
    let mut ended: Vec<Option<(Option<ExitStatus>, Duration)>> = vec![None; procs.len()];
    let mut on_first_end = Some(on_first_end);
    loop {
        for (proc, end) in procs.iter_mut().zip(&mut ended) {
            if end.is_some() {
                continue;
            }
            let polled = proc
                .child
                .try_wait()
                .with_context(|| format!("waiting for {}", proc.name));
            let elapsed = proc.started.elapsed();
            if let Some(status) = polled? {
                *end = Some((Some(status), elapsed));
            } else if elapsed >= cap {
                proc.kill();
                *end = Some((None, elapsed));
            }
        }
        if ended.iter().any(Option::is_some)
            && let Some(first) = on_first_end.take()
        {
            first();
        }
        if ended.iter().all(Option::is_some) {
            return Ok(ended.into_iter().flatten().collect());
        }
        thread::sleep(POLL);
    }
}

// ---------------------------------------------------------------------------------------
// Peers and servers

/// Where the programs of the modes are.
struct Programs {
    coapcam: PathBuf,
    libcoap431: Result<(PathBuf, PathBuf), String>,
    libcoap435: Result<(PathBuf, PathBuf), String>,
    quic: Result<PathBuf, String>,
}

fn on_path(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|dir| dir.join(name))
        .find(|p| p.is_file())
}

impl Programs {
    fn locate() -> anyhow::Result<Self> {
        let coapcam = std::env::current_exe().context("finding this executable")?;
        let libcoap431 = match (on_path("coap-client-notls"), on_path("coap-server-notls")) {
            (Some(client), Some(server)) => Ok((client, server)),
            _ => Err(
                "coap-client-notls or coap-server-notls is not on PATH (Debian package \
                      libcoap3-bin: apt-get install libcoap3-bin)"
                    .to_owned(),
            ),
        };
        let dir = std::env::var_os("COAPCAM_LIBCOAP435").map_or_else(
            || {
                let home = std::env::var_os("HOME").unwrap_or_default();
                PathBuf::from(home).join(".cache/coapcam-peers/libcoap-4.3.5/build")
            },
            PathBuf::from,
        );
        let (client, server) = (dir.join("coap-client"), dir.join("coap-server"));
        let missing = [&client, &server]
            .into_iter()
            .find(|p| !p.is_file())
            .cloned();
        let libcoap435 = match missing {
            None => Ok((client, server)),
            Some(missing) => Err(format!(
                "{} is missing (../shared/peers/build-libcoap.sh builds libcoap 4.3.5 there; \
                 COAPCAM_LIBCOAP435 names another folder)",
                missing.display()
            )),
        };
        let quic = std::env::var_os("COAPCAM_QUIC_BENCH").map_or_else(
            || {
                coapcam
                    .parent()
                    .map_or_else(|| PathBuf::from("quic-bench"), |d| d.join("quic-bench"))
            },
            PathBuf::from,
        );
        let quic = if quic.is_file() {
            Ok(quic)
        } else {
            Err(format!(
                "{} is missing (cargo build --release -p quic-bench builds it next to coapcam; \
                 COAPCAM_QUIC_BENCH names another path)",
                quic.display()
            ))
        };
        Ok(Self {
            coapcam,
            libcoap431,
            libcoap435,
            quic,
        })
    }

    /// Why `mode` cannot run here, if it cannot.
    fn missing(&self, mode: Mode) -> Option<&str> {
        match mode {
            Mode::StopAndWait | Mode::Window | Mode::QBlock => None,
            Mode::Libcoap431 => self.libcoap431.as_ref().err().map(String::as_str),
            Mode::Libcoap435 => self.libcoap435.as_ref().err().map(String::as_str),
            Mode::Quic => self.quic.as_ref().err().map(String::as_str),
        }
    }
}

/// What a client of one mode fetches a body of one size from.
#[derive(Debug, Clone)]
struct Target {
    addr: SocketAddr,
    /// The URI path (CoAP modes) or the certificate (QUIC).
    path: String,
}

/// Servers started for a mode, and where each size's body is.
type Started = (Vec<Proc>, Vec<(u64, Target)>);

/// The servers of the benchmark and, per (mode, size), where to fetch from or why it
/// cannot be.
struct Servers {
    _procs: Vec<Proc>,
    targets: Vec<(Mode, u64, Result<Target, String>)>,
}

impl Servers {
    fn target(&self, mode: Mode, size: u64) -> Result<&Target, &str> {
        self.targets
            .iter()
            .find(|(m, s, _)| *m == mode && *s == size)
            .map_or(Err("no server"), |(_, _, t)| {
                t.as_ref().map_err(String::as_str)
            })
    }

    /// Starts the servers that `modes` need, holding `bodies`. A server that does not
    /// start, or a body it does not give back, makes those cells' runs fail (reported);
    /// it does not stop the benchmark.
    fn start(
        programs: &Programs,
        modes: &[Mode],
        bodies: &[Body],
        work: &Path,
    ) -> anyhow::Result<Self> {
        let mut procs = Vec::new();
        let mut targets = Vec::new();
        let mut record = |mode: Mode, result: anyhow::Result<Vec<(u64, Target)>>| match result {
            Ok(list) => {
                for (size, target) in list {
                    targets.push((mode, size, Ok(target)));
                }
            }
            Err(e) => {
                let why = error_text(&e);
                eprintln!("coapcam: bench transfer: {}: {why}", mode.name());
                for body in bodies {
                    targets.push((mode, body.size, Err(why.clone())));
                }
            }
        };
        let ours: Vec<Mode> = modes
            .iter()
            .copied()
            .filter(|m| matches!(m, Mode::StopAndWait | Mode::Window | Mode::QBlock))
            .collect();
        if !ours.is_empty() {
            let started = start_coap_server("coapcam serve", &work.join("serve.log"), |port| {
                let mut cmd = Command::new(&programs.coapcam);
                cmd.arg("serve")
                    .arg("--no-cameras")
                    .arg("--static")
                    .arg(work.join("files"))
                    .arg("--bind")
                    .arg(format!("127.0.0.1:{port}"));
                cmd
            });
            let started = started.map(|(proc, addr)| {
                procs.push(proc);
                bodies
                    .iter()
                    .map(|b| {
                        let path = format!("/files/{}", b.file_name());
                        (b.size, Target { addr, path })
                    })
                    .collect::<Vec<_>>()
            });
            match started {
                Ok(list) => {
                    for mode in ours {
                        record(mode, Ok(list.clone()));
                    }
                }
                Err(e) => {
                    let why = format!("{e:#}");
                    for mode in ours {
                        record(mode, Err(anyhow::anyhow!("{why}")));
                    }
                }
            }
        }
        for mode in modes {
            let started = match mode {
                Mode::Libcoap431 => {
                    let Ok((client, server)) = &programs.libcoap431 else {
                        continue;
                    };
                    libcoap_server(*mode, client, server, false, bodies, work)
                }
                Mode::Libcoap435 => {
                    let Ok((client, server)) = &programs.libcoap435 else {
                        continue;
                    };
                    libcoap_server(*mode, client, server, true, bodies, work)
                }
                Mode::Quic => {
                    let Ok(quic) = &programs.quic else { continue };
                    quic_servers(quic, bodies, work)
                }
                _ => continue,
            };
            let list = started.map(|(mut started, list)| {
                procs.append(&mut started);
                list
            });
            record(*mode, list);
        }
        Ok(Self {
            _procs: procs,
            targets,
        })
    }
}

/// A libcoap server (`-d`: a PUT creates a resource; `-L 5` for Q-Block) holding every
/// body, PUT on loopback with the same version's client and checked with a GET.
fn libcoap_server(
    mode: Mode,
    client: &Path,
    server: &Path,
    qblock: bool,
    bodies: &[Body],
    work: &Path,
) -> anyhow::Result<Started> {
    let tag = mode.name();
    let resources = (bodies.len() + 2).max(10).to_string();
    let (proc, addr) = start_coap_server(
        &server.display().to_string(),
        &work.join(format!("{tag}-server.log")),
        |port| {
            let mut cmd = Command::new(server);
            cmd.args(["-A", "127.0.0.1", "-p", &port.to_string(), "-d", &resources]);
            if qblock {
                cmd.args(["-L", "5"]);
            }
            cmd
        },
    )?;
    let wait = SETUP_TRANSFER.as_secs().to_string();
    let mut list = Vec::new();
    for body in bodies {
        let path = format!("/body-{}", body.size);
        let uri = format!("coap://{addr}{path}");
        let log = work.join(format!("{tag}-setup.log"));
        let mut put = Command::new(client);
        put.args(["-m", "put", "-b", "1024", "-B", &wait, "-f"])
            .arg(&body.path)
            .arg(&uri);
        run_to_end(
            put,
            &format!("{} -m put {uri}", client.display()),
            &log,
            SETUP_TRANSFER,
        )?;
        let check = work.join(format!("{tag}-check"));
        let mut get = Command::new(client);
        get.args(["-b", "1024", "-B", &wait, "-o"])
            .arg(&check)
            .arg(&uri);
        run_to_end(
            get,
            &format!("{} {uri}", client.display()),
            &log,
            SETUP_TRANSFER,
        )?;
        if let Some(diff) = difference(&check, &body.bytes) {
            bail!("the server gave back another body than was PUT to {uri}: {diff}");
        }
        let _ = std::fs::remove_file(&check);
        list.push((body.size, Target { addr, path }));
    }
    Ok((vec![proc], list))
}

/// One `quic-bench serve` per body (it serves one file), each on a port of its choice.
fn quic_servers(quic: &Path, bodies: &[Body], work: &Path) -> anyhow::Result<Started> {
    let mut procs = Vec::new();
    let mut list = Vec::new();
    for body in bodies {
        let cert = work.join(format!("quic-{}.der", body.size));
        let log = work.join(format!("quic-{}.log", body.size));
        let mut cmd = Command::new(quic);
        cmd.arg("serve")
            .arg("127.0.0.1:0")
            .arg(&body.path)
            .arg(&cert)
            .stdout(Stdio::piped())
            .stderr(File::create(&log).with_context(|| format!("creating {}", log.display()))?);
        let mut proc = Proc::spawn(cmd, "quic-bench serve")?;
        let stdout = proc
            .child
            .stdout
            .take()
            .context("quic-bench serve's output")?;
        // It prints "ready ADDR" once bound; the thread reads on to the end so a later
        // line never blocks it.
        let (tx, rx) = mpsc::channel();
        thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if let Some(addr) = line.strip_prefix("ready ") {
                    let _ = tx.send(addr.trim().parse::<SocketAddr>());
                }
            }
        });
        let addr = match rx.recv_timeout(STARTUP) {
            Ok(Ok(addr)) => addr,
            Ok(Err(e)) => bail!("quic-bench serve printed a bad address: {e}"),
            Err(_) => {
                let _ = proc.check_running();
                bail!("quic-bench serve did not start: {}", tail(&log));
            }
        };
        procs.push(proc);
        let path = cert
            .to_str()
            .context("the certificate's path is not UTF-8")?;
        list.push((
            body.size,
            Target {
                addr,
                path: path.to_owned(),
            },
        ));
    }
    Ok((procs, list))
}

/// The client command of one run of `mode` fetching from `addr` into `out`.
fn client_command(
    programs: &Programs,
    mode: Mode,
    addr: SocketAddr,
    target: &Target,
    out: &Path,
    cap: Duration,
) -> anyhow::Result<Command> {
    let uri = format!("coap://{addr}{}", target.path);
    // libcoap gives up by itself after -B seconds, exit status 0; past the cap, so that
    // the cap is what stops it.
    let wait = (cap.as_secs() + 10).to_string();
    let mut cmd;
    match mode {
        Mode::StopAndWait | Mode::Window | Mode::QBlock => {
            let transfer = match mode {
                Mode::StopAndWait => "stop-and-wait",
                Mode::Window => "window",
                _ => "q-block",
            };
            cmd = Command::new(&programs.coapcam);
            cmd.arg("get")
                .arg(&uri)
                .arg("-o")
                .arg(out)
                .args(["--transfer", transfer]);
        }
        Mode::Libcoap431 => {
            let (client, _) = programs
                .libcoap431
                .as_ref()
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            cmd = Command::new(client);
            cmd.args(["-b", "1024", "-B", &wait, "-o"])
                .arg(out)
                .arg(&uri);
        }
        Mode::Libcoap435 => {
            let (client, _) = programs
                .libcoap435
                .as_ref()
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            cmd = Command::new(client);
            cmd.args(["-L", "5", "-N", "-b", "1024", "-B", &wait, "-o"])
                .arg(out)
                .arg(&uri);
        }
        Mode::Quic => {
            let quic = programs.quic.as_ref().map_err(|e| anyhow::anyhow!("{e}"))?;
            cmd = Command::new(quic);
            cmd.arg("get")
                .arg(addr.to_string())
                .arg(&target.path)
                .arg(out);
        }
    }
    Ok(cmd)
}

// ---------------------------------------------------------------------------------------
// Bodies and runs

/// A body of random bytes and its file.
struct Body {
    size: u64,
    path: PathBuf,
    bytes: Vec<u8>,
}

impl Body {
    fn file_name(&self) -> String {
        format!("body-{}.bin", self.size)
    }

    /// `size` random bytes from `seed` (ChaCha8), written into `dir`.
    fn write(dir: &Path, size: u64, seed: u64) -> anyhow::Result<Self> {
        let len = usize::try_from(size).context("body size")?;
        let mut bytes = vec![0u8; len];
        ChaCha8Rng::seed_from_u64(mix(seed, size)).fill_bytes(&mut bytes);
        let mut body = Self {
            size,
            path: PathBuf::new(),
            bytes,
        };
        body.path = dir.join(body.file_name());
        std::fs::write(&body.path, &body.bytes)
            .with_context(|| format!("writing {}", body.path.display()))?;
        Ok(body)
    }
}

/// SplitMix64's finaliser of `a` and `b`: seeds that differ in any input differ.
fn mix(a: u64, b: u64) -> u64 {
    let mut z = a
        .wrapping_add(b.wrapping_mul(0x9e37_79b9_7f4a_7c15))
        .wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// How `got` (a file) differs from `want`; `None` if it is the same, byte for byte.
fn difference(got: &Path, want: &[u8]) -> Option<String> {
    let bytes = match std::fs::read(got) {
        Ok(b) => b,
        Err(e) => return Some(format!("no output ({}: {e})", got.display())),
    };
    if bytes == want {
        return None;
    }
    let first = bytes.iter().zip(want).position(|(a, b)| a != b);
    Some(
        match first {
            Some(i) => format!(
                "body differs: {} of {} bytes, first difference at byte {i}",
                bytes.len(),
                want.len()
            ),
            None => format!(
                "body differs: {} of {} bytes, the same up to there",
                bytes.len(),
                want.len()
            ),
        } + &which_block(&bytes, want),
    )
}

/// For a short output that starts with one of the body's other blocks (a client that
/// wrote the wrong block), which one: `"; it starts with block N"`; else nothing.
fn which_block(got: &[u8], want: &[u8]) -> String {
    let block = BLOCK_BYTES as usize;
    let Some(head) = got.get(..block) else {
        return String::new();
    };
    want.chunks(block)
        .position(|c| c == head)
        .filter(|&n| n > 0)
        .map_or_else(String::new, |n| {
            format!("; it starts with block {n} of the body")
        })
}

/// One run's result.
#[derive(Debug, Clone)]
struct RunResult {
    /// Client process wall time, seconds (until it was killed, for a run past the cap).
    time_s: f64,
    ok: bool,
    /// The exit code; `None` when killed at the cap or by a signal, or not started.
    exit: Option<i32>,
    killed_at_cap: bool,
    /// Whether the output equals the body; `None` if the client failed before that
    /// mattered (or it wrote nothing).
    bit_exact: Option<bool>,
    error: Option<String>,
    relay: Option<Counters>,
}

impl RunResult {
    fn failed(error: String) -> Self {
        Self {
            time_s: f64::NAN,
            ok: false,
            exit: None,
            killed_at_cap: false,
            bit_exact: None,
            error: Some(error),
            relay: None,
        }
    }

    fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "time_s": self.time_s.is_finite().then_some(self.time_s),
            "ok": self.ok,
            "exit": self.exit,
            "killed_at_cap": self.killed_at_cap,
            "bit_exact": self.bit_exact,
            "error": self.error,
            "relay": self.relay,
        })
    }
}

/// A client to run: its command, the file it writes the body into and the log of its
/// standard error.
struct Client<'a> {
    cmd: Command,
    out: &'a Path,
    log: &'a Path,
}

/// Runs one client and checks its output.
fn time_client(
    client: Client<'_>,
    name: &str,
    cap: Duration,
    body: &[u8],
) -> anyhow::Result<RunResult> {
    time_clients(vec![client], name, cap, body, || {})?
        .pop()
        .context("a client without a result")
}

/// Starts `clients` one right after the other, waits for all of them (each timed from its
/// own start) and checks each one's output against `body`; one result per client, in
/// order. `on_first_end` is called once, as soon as the first of them is seen to end (its
/// exit, or its kill at the cap). A client that cannot start fails the run of every one
/// (those started are killed).
fn time_clients(
    clients: Vec<Client<'_>>,
    name: &str,
    cap: Duration,
    body: &[u8],
    on_first_end: impl FnOnce(),
) -> anyhow::Result<Vec<RunResult>> {
    let count = clients.len();
    let mut procs = Vec::with_capacity(count);
    let mut files = Vec::with_capacity(count);
    for (i, Client { mut cmd, out, log }) in clients.into_iter().enumerate() {
        let _ = std::fs::remove_file(out);
        let stderr = File::create(log).with_context(|| format!("creating {}", log.display()))?;
        cmd.stdout(Stdio::null()).stderr(stderr);
        match Proc::spawn(cmd, name) {
            Ok(proc) => procs.push(proc),
            Err(e) => {
                let why = error_text(&e);
                let result = |j| {
                    if j == i {
                        RunResult::failed(why.clone())
                    } else {
                        RunResult::failed(format!("another client of the run failed: {why}"))
                    }
                };
                return Ok((0..count).map(result).collect());
            }
        }
        files.push((out, log));
    }
    let ended = wait_all_capped(&mut procs, cap, on_first_end)?;
    drop(procs);
    Ok(ended
        .into_iter()
        .zip(files)
        .map(|((status, elapsed), (out, log))| client_result(status, elapsed, cap, out, log, body))
        .collect())
}

/// The result of a client that ended with `status` (`None`: killed at the cap) `elapsed`
/// after its start: its output in `out` compared with `body` (and removed), the reason of a
/// failure from its `log`.
fn client_result(
    status: Option<ExitStatus>,
    elapsed: Duration,
    cap: Duration,
    out: &Path,
    log: &Path,
    body: &[u8],
) -> RunResult {
    let wrote = out.exists();
    let diff = wrote.then(|| difference(out, body)).flatten();
    let bit_exact = wrote.then_some(diff.is_none());
    let _ = std::fs::remove_file(out);
    let mut result = RunResult {
        time_s: elapsed.as_secs_f64(),
        ok: false,
        exit: status.and_then(|s| s.code()),
        killed_at_cap: status.is_none(),
        bit_exact,
        error: None,
        relay: None,
    };
    result.error = match status {
        None => Some(format!(
            "still running after the cap of {} s, killed",
            cap.as_secs_f64()
        )),
        Some(s) if !s.success() => Some(format!("exited with {s}: {}", tail(log))),
        Some(_) if !wrote => Some("exited with 0 but wrote no output".into()),
        Some(_) => diff.map(|d| format!("exited with 0 but the {d}")),
    };
    result.ok = result.error.is_none();
    result
}

/// One (link, size, mode) and its runs.
struct Cell {
    link: Link,
    size: u64,
    mode: Mode,
    /// Why it was not run (the mode is unavailable or its server did not start).
    skipped: Option<String>,
    runs: Vec<RunResult>,
}

impl Cell {
    fn ok_times(&self) -> Vec<f64> {
        self.runs
            .iter()
            .filter(|r| r.ok)
            .map(|r| r.time_s)
            .collect()
    }

    /// Median, min and max of the successful runs.
    fn stats(&self) -> Option<Spread> {
        Spread::of(&self.ok_times())
    }

    fn ok_count(&self) -> usize {
        self.runs.iter().filter(|r| r.ok).count()
    }

    /// The table's text: `median [min-max] ok/runs`.
    fn text(&self) -> String {
        if self.skipped.is_some() {
            return "unavailable".into();
        }
        let count = format!("{}/{}", self.ok_count(), self.runs.len());
        match self.stats() {
            Some(Spread { median, min, max }) => {
                format!("{median:.3} [{min:.3}-{max:.3}] {count}")
            }
            None => format!("failed {count}"),
        }
    }

    fn json(&self) -> serde_json::Value {
        let stats = self.stats();
        let pick = |f: fn(Spread) -> f64| stats.map(f);
        let all_bit_exact =
            !self.runs.is_empty() && self.runs.iter().all(|r| r.bit_exact == Some(true));
        let times: Vec<Option<f64>> = self
            .runs
            .iter()
            .map(|r| r.time_s.is_finite().then_some(r.time_s))
            .collect();
        serde_json::json!({
            "link": self.link.name(),
            "bytes": self.size,
            "mode": self.mode.name(),
            "unavailable": self.skipped,
            "runs": self.runs.len(),
            "ok": self.ok_count(),
            "all_bit_exact": all_bit_exact,
            "median_s": pick(|s| s.median),
            "min_s": pick(|s| s.min),
            "max_s": pick(|s| s.max),
            "times_s": times,
            "ok_flags": self.runs.iter().map(|r| r.ok).collect::<Vec<_>>(),
            "results": self.runs.iter().map(RunResult::json).collect::<Vec<_>>(),
        })
    }
}

/// A ratio column: the median of `num`'s cell over `den`'s.
fn ratio_columns(modes: &[Mode]) -> Vec<(Mode, Mode)> {
    let has = |m: Mode| modes.contains(&m);
    let mut out = Vec::new();
    if has(Mode::Window) && has(Mode::Quic) {
        out.push((Mode::Window, Mode::Quic));
    }
    let reference = if has(Mode::Window) {
        Some(Mode::Window)
    } else if has(Mode::Quic) {
        Some(Mode::Quic)
    } else {
        None
    };
    if let Some(den) = reference {
        for &m in modes {
            if m != Mode::Window && m != Mode::Quic {
                out.push((m, den));
            }
        }
    }
    out
}

/// One pair run: two clients of one mode at once through one relay of [`PAIR_LINK`].
struct PairRun {
    /// Both clients, in the order they were started.
    clients: Vec<RunResult>,
    /// The payload bytes the relay had delivered to each client address when the first
    /// client ended, the most first.
    delivered: Vec<(SocketAddr, u64)>,
    relay: Counters,
}

impl PairRun {
    /// Both clients succeeded.
    fn ok(&self) -> bool {
        self.clients.iter().all(|c| c.ok)
    }

    /// The smaller and the larger client's share of the bytes delivered to both when the
    /// first ended; `None` if none was delivered.
    fn shares(&self) -> Option<(f64, f64)> {
        let total: u64 = self.delivered.iter().map(|&(_, n)| n).sum();
        let most = self.delivered.first()?.1;
        // A client that had been delivered nothing yet is not in the count.
        let least = if self.delivered.len() < self.clients.len() {
            0
        } else {
            self.delivered.last()?.1
        };
        (total > 0).then(|| (least as f64 / total as f64, most as f64 / total as f64))
    }

    fn holds(&self) -> bool {
        self.shares()
            .is_some_and(|(smaller, _)| smaller >= FAIR_SHARE)
    }

    /// The later client's time, seconds (NaN when the clients did not start).
    fn later_s(&self) -> f64 {
        self.clients
            .iter()
            .map(|c| c.time_s)
            .fold(f64::NAN, f64::max)
    }

    /// Both bodies of `size` bytes over the later client's time, as a fraction of the
    /// link's rate.
    fn utilisation(&self, size: u64) -> f64 {
        let bytes = (self.clients.len() as u64 * size) as f64;
        bytes / self.later_s() / RATE_50_MBIT as f64
    }

    /// The progress line's summary: both times, the shares, the utilisation and the
    /// failures.
    fn summary(&self, size: u64) -> String {
        let times: Vec<String> = self
            .clients
            .iter()
            .map(|c| format!("{:.3} s", c.time_s))
            .collect();
        let shares = self.shares().map_or_else(
            || "no bytes delivered".to_owned(),
            |(smaller, larger)| {
                format!(
                    "shares {:.1} % and {:.1} %",
                    smaller * 100.0,
                    larger * 100.0
                )
            },
        );
        let errors: Vec<String> = self
            .clients
            .iter()
            .enumerate()
            .filter_map(|(i, c)| Some(format!("client {}: {}", i + 1, c.error.as_ref()?)))
            .collect();
        let outcome = if errors.is_empty() {
            "ok".to_owned()
        } else {
            format!("FAILED: {}", errors.join("; "))
        };
        format!(
            "{}, {shares}, link {:.0} %: {outcome}",
            times.join(" and "),
            self.utilisation(size) * 100.0
        )
    }

    fn json(&self, size: u64) -> serde_json::Value {
        let finite = |x: f64| x.is_finite().then_some(x);
        let shares = self.shares();
        serde_json::json!({
            "ok": self.ok(),
            "clients": self.clients.iter().map(RunResult::json).collect::<Vec<_>>(),
            "delivered_at_first_end": self.delivered.iter().map(|(client, bytes)| {
                serde_json::json!({ "client": client.to_string(), "bytes": bytes })
            }).collect::<Vec<_>>(),
            "smaller_share": shares.map(|s| s.0),
            "larger_share": shares.map(|s| s.1),
            "holds": self.holds(),
            "later_s": finite(self.later_s()),
            "aggregate_bytes_per_s": finite(self.utilisation(size) * RATE_50_MBIT as f64),
            "utilisation": finite(self.utilisation(size)),
            "relay": self.relay,
        })
    }
}

/// The pair runs of one (size, mode).
struct PairCell {
    size: u64,
    mode: Mode,
    /// Why it was not run (the mode is unavailable or its server did not start).
    skipped: Option<String>,
    runs: Vec<PairRun>,
}

impl PairCell {
    fn ok_runs(&self) -> impl Iterator<Item = &PairRun> {
        self.runs.iter().filter(|r| r.ok())
    }

    /// Median, min and max of the smaller shares of the successful runs.
    fn smaller_shares(&self) -> Option<Spread> {
        let shares: Vec<f64> = self
            .ok_runs()
            .map(|r| r.shares().map_or(0.0, |s| s.0))
            .collect();
        Spread::of(&shares)
    }

    /// Median, min and max of the link utilisation of the successful runs.
    fn utilisation(&self) -> Option<Spread> {
        let used: Vec<f64> = self.ok_runs().map(|r| r.utilisation(self.size)).collect();
        Spread::of(&used)
    }

    /// The successful runs that held.
    fn holding(&self) -> usize {
        self.ok_runs().filter(|r| r.holds()).count()
    }

    /// The table's row.
    fn row(&self) -> Vec<String> {
        let mut row = vec![self.size.to_string(), self.mode.name().to_owned()];
        if self.skipped.is_some() {
            row.extend(["unavailable", "", "", ""].map(str::to_owned));
            return row;
        }
        let percent = |s: Option<Spread>| {
            s.map_or_else(
                || "-".to_owned(),
                |Spread { median, min, max }| {
                    format!(
                        "{:.1} % [{:.1}-{:.1}]",
                        median * 100.0,
                        min * 100.0,
                        max * 100.0
                    )
                },
            )
        };
        let ok = self.ok_runs().count();
        let runs = self.runs.len();
        row.extend([
            percent(self.smaller_shares()),
            format!("{}/{runs}", self.holding()),
            percent(self.utilisation()),
            format!("{ok}/{runs}"),
        ]);
        row
    }

    fn json(&self) -> serde_json::Value {
        let shares = self.smaller_shares();
        let used = self.utilisation();
        serde_json::json!({
            "bytes": self.size,
            "mode": self.mode.name(),
            "unavailable": self.skipped,
            "runs": self.runs.len(),
            "ok": self.ok_runs().count(),
            "holding": self.holding(),
            "median_smaller_share": shares.map(|s| s.median),
            "min_smaller_share": shares.map(|s| s.min),
            "max_smaller_share": shares.map(|s| s.max),
            "median_utilisation": used.map(|s| s.median),
            "min_utilisation": used.map(|s| s.min),
            "max_utilisation": used.map(|s| s.max),
            "results": self.runs.iter().map(|r| r.json(self.size)).collect::<Vec<_>>(),
        })
    }
}

/// Two clients of `mode` fetching `body` from `target` at once through one relay of
/// `config`; the relay's delivered bytes are read when the first client ends.
fn run_pair(
    programs: &Programs,
    mode: Mode,
    target: &Target,
    config: LinkConfig,
    body: &Body,
    cap: Duration,
    work: &Path,
) -> anyhow::Result<PairRun> {
    let relay = Relay::start(target.addr, config)?;
    let outs = [work.join("out-1"), work.join("out-2")];
    let logs = [work.join("client-1.log"), work.join("client-2.log")];
    let mut clients = Vec::new();
    for (out, log) in outs.iter().zip(&logs) {
        let cmd = client_command(programs, mode, relay.addr, target, out, cap)?;
        clients.push(Client { cmd, out, log });
    }
    let mut delivered = Vec::new();
    let clients = time_clients(clients, mode.name(), cap, &body.bytes, || {
        delivered = relay.delivered.snapshot().into_iter().collect();
    })?;
    delivered.sort_unstable_by_key(|&(client, bytes)| (Reverse(bytes), client));
    Ok(PairRun {
        clients,
        delivered,
        relay: relay.finish()?,
    })
}

// ---------------------------------------------------------------------------------------
// The benchmark

/// A scratch directory, removed on drop.
struct WorkDir(PathBuf);

impl Drop for WorkDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Runs `bench transfer`.
pub(super) async fn run(args: TransferArgs) -> anyhow::Result<Exit> {
    tokio::task::spawn_blocking(move || run_blocking(&args))
        .await
        .context("the benchmark's thread")?
}

fn run_blocking(args: &TransferArgs) -> anyhow::Result<Exit> {
    let sizes = unique(&args.sizes);
    let links = unique(&args.links);
    let modes = unique(&args.modes);
    if sizes.is_empty() || links.is_empty() || modes.is_empty() {
        bail!("--sizes, --links and --modes each need at least one value");
    }
    // Fail before any work on an output file whose folder is missing.
    for path in [&args.json, &args.plot].into_iter().flatten() {
        let dir = path.parent().filter(|d| !d.as_os_str().is_empty());
        if dir.is_some_and(|d| !d.is_dir()) {
            bail!("cannot write {}: its folder does not exist", path.display());
        }
    }
    let work = WorkDir(
        std::env::temp_dir().join(format!("coapcam-bench-transfer-{}", std::process::id())),
    );
    let files = work.0.join("files");
    std::fs::create_dir_all(&files).with_context(|| format!("creating {}", files.display()))?;
    let bodies = sizes
        .iter()
        .map(|&size| Body::write(&files, size, args.seed))
        .collect::<anyhow::Result<Vec<_>>>()?;

    let programs = Programs::locate()?;
    for &mode in &modes {
        if let Some(why) = programs.missing(mode) {
            eprintln!(
                "\n!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!\n\
                 !!! bench transfer: mode {} is UNAVAILABLE: {why}\n\
                 !!! It is shown as unavailable in the table and the JSON.\n\
                 !!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!\n",
                mode.name()
            );
        }
    }
    let available: Vec<Mode> = modes
        .iter()
        .copied()
        .filter(|&m| programs.missing(m).is_none())
        .collect();
    let servers = Servers::start(&programs, &available, &bodies, &work.0)?;

    let runs_of = |m: Mode| {
        if m.slow() { args.slow_runs } else { args.runs }
    };
    let skipped = |mode: Mode, size: u64| {
        programs.missing(mode).map(str::to_owned).or_else(|| {
            servers
                .target(mode, size)
                .err()
                .map(|e| format!("setup failed: {e}"))
        })
    };
    let mut cells: Vec<Cell> = Vec::new();
    for &link in &links {
        for body in &bodies {
            for &mode in &modes {
                cells.push(Cell {
                    link,
                    size: body.size,
                    mode,
                    skipped: skipped(mode, body.size),
                    runs: Vec::new(),
                });
            }
        }
    }
    let mut pair_cells: Vec<PairCell> = Vec::new();
    if args.pairs > 0 && links.contains(&PAIR_LINK) {
        for body in &bodies {
            for &mode in modes.iter().filter(|m| !m.slow()) {
                pair_cells.push(PairCell {
                    size: body.size,
                    mode,
                    skipped: skipped(mode, body.size),
                    runs: Vec::new(),
                });
            }
        }
    }
    let runnable = pair_cells.iter().filter(|c| c.skipped.is_none()).count() as u32;
    let total: u32 = cells
        .iter()
        .filter(|c| c.skipped.is_none())
        .map(|c| runs_of(c.mode))
        .sum::<u32>()
        + runnable * args.pairs;
    let out = work.0.join("out");
    let log = work.0.join("client.log");
    let mut done = 0u32;
    for (link_index, &link) in links.iter().enumerate() {
        for body in &bodies {
            let row: Vec<usize> = (0..cells.len())
                .filter(|&i| cells[i].link == link && cells[i].size == body.size)
                .collect();
            let most = modes.iter().map(|&m| runs_of(m)).max().unwrap_or(0);
            for run in 0..most {
                let seed = mix(
                    mix(args.seed, link_index as u64),
                    mix(body.size, u64::from(run)),
                );
                for &i in &row {
                    let cell = &cells[i];
                    if cell.skipped.is_some() || run >= runs_of(cell.mode) {
                        continue;
                    }
                    let mode = cell.mode;
                    let target = servers
                        .target(mode, body.size)
                        .map_err(|e| anyhow::anyhow!("{e}"))?
                        .clone();
                    let relay = match link.config(seed) {
                        Some(config) => Some(Relay::start(target.addr, config)?),
                        None => None,
                    };
                    let addr = relay.as_ref().map_or(target.addr, |r| r.addr);
                    let cmd = client_command(&programs, mode, addr, &target, &out, args.cap)?;
                    let client = Client {
                        cmd,
                        out: &out,
                        log: &log,
                    };
                    let mut result = time_client(client, mode.name(), args.cap, &body.bytes)?;
                    if let Some(relay) = relay {
                        result.relay = Some(relay.finish()?);
                    }
                    done += 1;
                    eprintln!(
                        "[{done}/{total}] {} {} B {} run {}/{}: {:.3} s {}",
                        link.name(),
                        body.size,
                        mode.name(),
                        run + 1,
                        runs_of(mode),
                        result.time_s,
                        result
                            .error
                            .as_deref()
                            .map_or_else(|| "ok".to_owned(), |e| format!("FAILED: {e}"))
                    );
                    cells[i].runs.push(result);
                }
            }
        }
    }
    for body in &bodies {
        for run in 0..args.pairs {
            let seed = mix(mix(args.seed, PAIR_SEED), mix(body.size, u64::from(run)));
            let config = PAIR_LINK
                .config(seed)
                .context("the pair runs' link has a relay")?;
            for cell in &mut pair_cells {
                if cell.size != body.size || cell.skipped.is_some() {
                    continue;
                }
                let target = servers
                    .target(cell.mode, body.size)
                    .map_err(|e| anyhow::anyhow!("{e}"))?;
                let pair = run_pair(
                    &programs, cell.mode, target, config, body, args.cap, &work.0,
                )?;
                done += 1;
                eprintln!(
                    "[{done}/{total}] {} {} B {} pair run {}/{}: {}",
                    PAIR_LINK.name(),
                    body.size,
                    cell.mode.name(),
                    run + 1,
                    args.pairs,
                    pair.summary(body.size)
                );
                cell.runs.push(pair);
            }
        }
    }
    drop(servers);

    outln!("{}", table(args, &links, &bodies, &modes, &cells));
    if !pair_cells.is_empty() {
        outln!("\n{}", pair_table(args, &pair_cells));
    }
    if let Some(path) = &args.json {
        let json = report_json(args, &links, &modes, &cells, &pair_cells, &programs);
        let text = serde_json::to_string_pretty(&json).context("encoding the JSON")?;
        std::fs::write(path, text + "\n").with_context(|| format!("writing {}", path.display()))?;
    }
    if let Some(path) = &args.plot {
        picture::save(&plot(&sizes, &links, &modes, &cells), path)?;
    }
    Ok(Exit::Success)
}

/// The markdown table, its heading and the failures under it.
fn table(
    args: &TransferArgs,
    links: &[Link],
    bodies: &[Body],
    modes: &[Mode],
    cells: &[Cell],
) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "Whole-body GETs, {BLOCK_BYTES}-byte blocks for CoAP, through netem (in process): \
         seconds of the client's whole process, median of the successful runs [min-max] \
         successful/runs (runs per cell: {}, stop-and-wait and libcoap: {}; cap {} s; seed {}). \
         Every body compared bit-exact with the original.",
        args.runs,
        args.slow_runs,
        args.cap.as_secs_f64(),
        args.seed
    );
    let _ = writeln!(s);
    let ratios = ratio_columns(modes);
    let mut header = vec!["link".to_owned(), "bytes".to_owned()];
    header.extend(modes.iter().map(|m| m.name().to_owned()));
    header.extend(
        ratios
            .iter()
            .map(|(a, b)| format!("{} / {}", a.short(), b.short())),
    );
    let mut rows = Vec::new();
    for &link in links {
        for body in bodies {
            let cell = |m: Mode| {
                cells
                    .iter()
                    .find(|c| c.link == link && c.size == body.size && c.mode == m)
            };
            let mut row = vec![link.name().to_owned(), body.size.to_string()];
            row.extend(
                modes
                    .iter()
                    .map(|&m| cell(m).map_or_else(String::new, Cell::text)),
            );
            for &(a, b) in &ratios {
                let median = |m| cell(m).and_then(Cell::stats).map(|s| s.median);
                row.push(match (median(a), median(b)) {
                    (Some(a), Some(b)) if b > 0.0 => format!("{:.2}x", a / b),
                    _ => "-".into(),
                });
            }
            rows.push(row);
        }
    }
    s += &markdown(&header, &rows, 1);
    let mut notes = Vec::new();
    for c in cells {
        if let Some(why) = &c.skipped {
            notes.push(format!(
                "{} {} B {}: unavailable: {why}",
                c.link.name(),
                c.size,
                c.mode.name()
            ));
            continue;
        }
        for (i, r) in c.runs.iter().enumerate() {
            if let Some(e) = &r.error {
                notes.push(format!(
                    "{} {} B {} run {}: {e}",
                    c.link.name(),
                    c.size,
                    c.mode.name(),
                    i + 1
                ));
            }
        }
    }
    failures(&mut s, &notes);
    s.trim_end().to_owned()
}

/// The list of failed runs under a table, if any.
fn failures(s: &mut String, notes: &[String]) {
    if !notes.is_empty() {
        let _ = writeln!(s, "\nFailed or not run:");
        for n in notes {
            let _ = writeln!(s, "- {n}");
        }
    }
}

/// A markdown table of `header` and `rows`, its columns padded to their widest cell: the
/// first `text` columns to the left, the others (numbers) to the right.
fn markdown(header: &[String], rows: &[Vec<String>], text: usize) -> String {
    let widths: Vec<usize> = (0..header.len())
        .map(|i| {
            rows.iter()
                .map(|r| r[i].chars().count())
                .chain([header[i].chars().count()])
                .max()
                .unwrap_or(0)
        })
        .collect();
    let line = |cells: &[String]| {
        let mut l = String::from("|");
        for (i, c) in cells.iter().enumerate() {
            if i < text {
                let _ = write!(l, " {c:<w$} |", w = widths[i]);
            } else {
                let _ = write!(l, " {c:>w$} |", w = widths[i]);
            }
        }
        l
    };
    let mut s = String::new();
    let _ = writeln!(s, "{}", line(header));
    let mut rule = String::from("|");
    for (i, w) in widths.iter().enumerate() {
        let dashes = "-".repeat(*w);
        if i < text {
            let _ = write!(rule, "-{dashes}-|");
        } else {
            let _ = write!(rule, "-{dashes}:|");
        }
    }
    let _ = writeln!(s, "{rule}");
    for row in rows {
        let _ = writeln!(s, "{}", line(row));
    }
    s
}

/// The markdown table of the pair runs, its heading and the failures under it.
fn pair_table(args: &TransferArgs, cells: &[PairCell]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "Two transfers at once through {}: two clients of one mode started together through \
         one relay to one server ({} runs per row; cap {} s; seed {}). Smaller share: the \
         smaller client's part of the payload bytes the relay had delivered to the two when \
         the first one ended; a run holds when it is at least {:.0} %. Link utilisation: both \
         bodies over the later client's time, as a fraction of 50 Mbit/s. Medians of the \
         successful runs (both clients bit-exact within the cap) [min-max].",
        PAIR_LINK.name(),
        args.pairs,
        args.cap.as_secs_f64(),
        args.seed,
        FAIR_SHARE * 100.0
    );
    let _ = writeln!(s);
    let header = [
        "bytes",
        "mode",
        "smaller share",
        "holds",
        "link utilisation",
        "ok",
    ]
    .map(str::to_owned);
    let rows: Vec<Vec<String>> = cells.iter().map(PairCell::row).collect();
    s += &markdown(&header, &rows, 2);
    let mut notes = Vec::new();
    for c in cells {
        if let Some(why) = &c.skipped {
            notes.push(format!(
                "{} B {}: unavailable: {why}",
                c.size,
                c.mode.name()
            ));
            continue;
        }
        for (i, run) in c.runs.iter().enumerate() {
            for (k, client) in run.clients.iter().enumerate() {
                if let Some(e) = &client.error {
                    notes.push(format!(
                        "{} B {} pair run {} client {}: {e}",
                        c.size,
                        c.mode.name(),
                        i + 1,
                        k + 1
                    ));
                }
            }
        }
    }
    failures(&mut s, &notes);
    s.trim_end().to_owned()
}

/// `uname -a`, or what /proc says.
fn machine() -> serde_json::Value {
    let uname = Command::new("uname")
        .arg("-a")
        .stderr(Stdio::null())
        .output()
        .ok()
        .filter(|o| o.status.success())
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_owned());
    let cpu = std::fs::read_to_string("/proc/cpuinfo").ok().and_then(|t| {
        t.lines()
            .find(|l| l.starts_with("model name"))
            .and_then(|l| l.split_once(':'))
            .map(|(_, v)| v.trim().to_owned())
    });
    let load = std::fs::read_to_string("/proc/loadavg")
        .ok()
        .map(|t| t.trim().to_owned());
    serde_json::json!({
        "uname": uname,
        "arch": std::env::consts::ARCH,
        "cpu": cpu,
        "cpus": thread::available_parallelism().map(usize::from).ok(),
        "loadavg_at_end": load,
    })
}

fn report_json(
    args: &TransferArgs,
    links: &[Link],
    modes: &[Mode],
    cells: &[Cell],
    pair_cells: &[PairCell],
    programs: &Programs,
) -> serde_json::Value {
    let unix_s = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let program = |p: &Result<PathBuf, String>| match p {
        Ok(p) => serde_json::json!(p.display().to_string()),
        Err(_) => serde_json::Value::Null,
    };
    let pair = |p: &Result<(PathBuf, PathBuf), String>| program(&p.clone().map(|(c, _)| c));
    serde_json::json!({
        "benchmark": "coapcam bench transfer",
        "coapcam_version": env!("CARGO_PKG_VERSION"),
        "argv": std::env::args().collect::<Vec<_>>(),
        "finished_unix_s": unix_s,
        "timing": "wall time of the client's whole process, from its start to its exit as \
                   seen by polling every 1 ms; servers started before and are not timed; \
                   QUIC's time includes its handshake",
        "check": "every output compared byte for byte with the body; a run is ok when the \
                  client exited 0 within the cap and its output is bit-exact",
        "statistics": "median, min and max over the successful runs; the median of an even \
                       count is the mean of the middle two",
        "block_bytes": BLOCK_BYTES,
        "runs": args.runs,
        "slow_runs": args.slow_runs,
        "cap_s": args.cap.as_secs_f64(),
        "seed": args.seed,
        "machine": machine(),
        "programs": {
            "coapcam": programs.coapcam.display().to_string(),
            "libcoap_4_3_1_client": pair(&programs.libcoap431),
            "libcoap_4_3_5_client": pair(&programs.libcoap435),
            "quic_bench": program(&programs.quic),
        },
        "links": links.iter().map(|l| l.json()).collect::<Vec<_>>(),
        "modes": modes.iter().map(|&m| serde_json::json!({
            "name": m.name(),
            "description": m.description(),
            "slow": m.slow(),
            "unavailable": programs.missing(m),
        })).collect::<Vec<_>>(),
        "cells": cells.iter().map(Cell::json).collect::<Vec<_>>(),
        "pairs": {
            "runs": args.pairs,
            "link": PAIR_LINK.name(),
            "rate_bytes_per_s": RATE_50_MBIT,
            "what": "two clients of one mode started together through one relay of the \
                     link to one server, per size and fast mode; none when --pairs is 0 \
                     or the link is not among --links",
            "shares": "each client address's payload bytes delivered by the relay \
                       (server to client) when the first client ended, over the sum of \
                       both; the relay knows clients by address, not by process, so a run \
                       gives its smaller and larger share",
            "holds_at_smaller_share": FAIR_SHARE,
            "utilisation": "2 x bytes over the later client's time, over the link's rate",
            "statistics": "median, min and max over the successful runs (both clients ok)",
            "cells": pair_cells.iter().map(PairCell::json).collect::<Vec<_>>(),
        },
    })
}

// ---------------------------------------------------------------------------------------
// The plot

/// Width and height of one size's panel, pixels.
const PANEL: (u32, u32) = (600, 450);
/// Width of the legend on the right, pixels.
const LEGEND_WIDTH: u32 = 300;
/// The plot area inside a panel: left, top, right, bottom margins.
const MARGIN: (u32, u32, u32, u32) = (72, 44, 20, 56);
const WHITE: Rgb<u8> = Rgb([255, 255, 255]);
const INK: Rgb<u8> = Rgb([30, 30, 30]);
const GRID: Rgb<u8> = Rgb([215, 215, 215]);
const MINOR_GRID: Rgb<u8> = Rgb([238, 238, 238]);

/// A point's shape: which link it was measured on.
#[derive(Debug, Clone, Copy)]
enum Marker {
    Circle,
    Square,
    Triangle,
    Diamond,
}

/// A canvas with the few primitives the plot needs, clipped to the image.
struct Canvas(RgbImage);

impl Canvas {
    fn dot(&mut self, x: i64, y: i64, color: Rgb<u8>) {
        if let (Ok(x), Ok(y)) = (u32::try_from(x), u32::try_from(y))
            && x < self.0.width()
            && y < self.0.height()
        {
            self.0.put_pixel(x, y, color);
        }
    }

    /// A line `width` pixels thick.
    fn line(&mut self, from: (i64, i64), to: (i64, i64), width: u32, color: Rgb<u8>) {
        let point = |(x, y): (i64, i64)| [x as f32, y as f32];
        picture::draw_line(&mut self.0, point(from), point(to), color, width);
    }

    fn marker(&mut self, (x, y): (i64, i64), marker: Marker, color: Rgb<u8>) {
        const R: i64 = 5;
        for dy in -R..=R {
            for dx in -R..=R {
                let inside = match marker {
                    Marker::Circle => dx * dx + dy * dy <= R * R,
                    Marker::Square => dx.abs() < R && dy.abs() < R,
                    Marker::Diamond => dx.abs() + dy.abs() <= R + 1,
                    // Apex up, base at the bottom.
                    Marker::Triangle => dy >= -R && 2 * dx.abs() <= dy + R,
                };
                if inside {
                    self.dot(x + dx, y + dy, color);
                }
            }
        }
    }

    fn cross(&mut self, (x, y): (i64, i64), color: Rgb<u8>) {
        self.line((x - 5, y - 5), (x + 5, y + 5), 2, color);
        self.line((x - 5, y + 5), (x + 5, y - 5), 2, color);
    }

    /// Text in the 8x8 font, its top left at `at` (kept inside the image).
    fn text(&mut self, at: (i64, i64), text: &str, color: Rgb<u8>) {
        let at = (at.0.max(0) as u32, at.1.max(0) as u32);
        picture::draw_text(&mut self.0, at, text, 1, color);
    }

    fn text_centered(&mut self, center_x: i64, y: i64, text: &str, color: Rgb<u8>) {
        let width = i64::from(picture::text_width(text, 1));
        self.text((center_x - width / 2, y), text, color);
    }
}

/// `n` with thousands separators.
fn grouped(n: u64) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// A decade's label: 0.01, 0.1, 1, 10, ...
fn decade_label(exponent: i32) -> String {
    if exponent >= 0 {
        format!("{}", 10f64.powi(exponent))
    } else {
        format!(
            "{:.*}",
            exponent.unsigned_abs() as usize,
            10f64.powi(exponent)
        )
    }
}

/// The plot: one panel per size, the median time of each (link, mode) against the link's
/// loss rate on a log scale of seconds, with a bar from the fastest to the slowest
/// successful run; the two 20 ms links joined by a line per mode; a cross at the top for
/// a cell whose every run failed. `PANEL.0 * sizes + LEGEND_WIDTH` by `PANEL.1` pixels.
fn plot(sizes: &[u64], links: &[Link], modes: &[Mode], cells: &[Cell]) -> RgbImage {
    let width = PANEL.0 * sizes.len() as u32 + LEGEND_WIDTH;
    let mut c = Canvas(RgbImage::from_pixel(width, PANEL.1, WHITE));
    let times: Vec<f64> = cells
        .iter()
        .flat_map(Cell::ok_times)
        .filter(|t| *t > 0.0)
        .collect();
    let (lo, hi) = match Spread::of(&times) {
        Some(Spread { min, max, .. }) => (min.log10().floor() as i32, max.log10().ceil() as i32),
        None => (-2, 1),
    };
    let hi = hi.max(lo + 1);
    let max_loss = links
        .iter()
        .map(|l| l.loss_percent())
        .fold(0.0, f64::max)
        .ceil()
        .max(1.0);
    let (ml, mt, mr, mb) = MARGIN;
    let (pw, ph) = (i64::from(PANEL.0 - ml - mr), i64::from(PANEL.1 - mt - mb));
    for (p, &size) in sizes.iter().enumerate() {
        let x0 = i64::from(PANEL.0) * p as i64 + i64::from(ml);
        let y0 = i64::from(mt);
        let to_x = |loss: f64| x0 + ((loss / max_loss) * (pw - 48) as f64).round() as i64 + 24;
        let to_y = |t: f64| {
            let f = (t.log10() - f64::from(lo)) / f64::from(hi - lo);
            y0 + ph - (f * ph as f64).round() as i64
        };
        c.text_centered(x0 + pw / 2, 12, &format!("{} bytes", grouped(size)), INK);
        c.text((x0 - 64, y0 - 18), "seconds (log)", INK);
        // Grid: decades, with 2 and 5 in between.
        for e in lo..=hi {
            let decade = 10f64.powi(e);
            if e < hi {
                for m in [2.0, 5.0] {
                    let y = to_y(decade * m);
                    c.line((x0, y), (x0 + pw, y), 1, MINOR_GRID);
                }
            }
            let y = to_y(decade);
            c.line((x0, y), (x0 + pw, y), 1, GRID);
            let label = decade_label(e);
            let w = i64::from(picture::text_width(&label, 1));
            c.text((x0 - 8 - w, y - 4), &label, INK);
        }
        let step = if max_loss > 10.0 { 5.0 } else { 1.0 };
        let mut loss = 0.0;
        while loss <= max_loss {
            let x = to_x(loss);
            c.line((x, y0), (x, y0 + ph), 1, MINOR_GRID);
            c.line((x, y0 + ph), (x, y0 + ph + 4), 1, INK);
            c.text_centered(x, y0 + ph + 10, &format!("{loss}"), INK);
            loss += step;
        }
        c.text_centered(x0 + pw / 2, y0 + ph + 30, "loss each way, %", INK);
        // The frame.
        c.line((x0, y0), (x0 + pw, y0), 1, INK);
        c.line((x0, y0 + ph), (x0 + pw, y0 + ph), 1, INK);
        c.line((x0, y0), (x0, y0 + ph), 1, INK);
        c.line((x0 + pw, y0), (x0 + pw, y0 + ph), 1, INK);
        for (mi, &mode) in modes.iter().enumerate() {
            let color = mode.color();
            // Modes side by side at one loss rate, so their bars do not hide each other.
            let shift = (mi as i64 * 2 - (modes.len() as i64 - 1)) * 3;
            let cell = |link: Link| {
                cells
                    .iter()
                    .find(|c| c.link == link && c.size == size && c.mode == mode)
            };
            let mut joined: Vec<(i64, i64)> = links
                .iter()
                .filter(|l| l.on_line())
                .filter_map(|&l| {
                    let median = cell(l)?.stats()?.median;
                    Some((to_x(l.loss_percent()) + shift, to_y(median)))
                })
                .collect();
            joined.sort_unstable();
            for pair in joined.windows(2) {
                c.line(pair[0], pair[1], 2, color);
            }
            for &link in links {
                let Some(cell) = cell(link) else { continue };
                let x = to_x(link.loss_percent()) + shift;
                match cell.stats() {
                    Some(Spread { median, min, max }) => {
                        let (top, bottom) = (to_y(max), to_y(min));
                        c.line((x, top), (x, bottom), 1, color);
                        c.line((x - 3, top), (x + 3, top), 1, color);
                        c.line((x - 3, bottom), (x + 3, bottom), 1, color);
                        c.marker((x, to_y(median)), link.marker(), color);
                    }
                    None if !cell.runs.is_empty() => c.cross((x, y0 + 8), color),
                    None => {}
                }
            }
        }
    }
    // The legend.
    let lx = i64::from(PANEL.0) * sizes.len() as i64 + 10;
    let mut y = i64::from(mt);
    c.text((lx, y), "modes (median,", INK);
    c.text((lx, y + 11), "bar: min-max of ok runs)", INK);
    y += 30;
    for &mode in modes {
        c.line((lx, y + 4), (lx + 22, y + 4), 2, mode.color());
        c.marker((lx + 11, y + 4), Marker::Circle, mode.color());
        c.text((lx + 30, y), mode.name(), INK);
        y += 16;
    }
    y += 12;
    c.text((lx, y), "links", INK);
    y += 16;
    for &link in links {
        c.marker((lx + 11, y + 4), link.marker(), INK);
        c.text((lx + 30, y), link.name(), INK);
        y += 16;
    }
    c.line((lx, y + 4), (lx + 22, y + 4), 2, INK);
    c.text((lx + 30, y), "joins the 20 ms links", INK);
    y += 16;
    c.cross((lx + 11, y + 4), INK);
    c.text((lx + 30, y), "every run failed", INK);
    c.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use netem::DirCounters;

    #[test]
    fn ratios_compare_with_window_and_window_with_quic() {
        let all = [
            Mode::StopAndWait,
            Mode::Window,
            Mode::QBlock,
            Mode::Libcoap431,
            Mode::Libcoap435,
            Mode::Quic,
        ];
        let names: Vec<String> = ratio_columns(&all)
            .iter()
            .map(|(a, b)| format!("{} / {}", a.short(), b.short()))
            .collect();
        assert_eq!(
            names,
            [
                "window / QUIC",
                "stop-and-wait / window",
                "q-block / window",
                "libcoap-4.3.1 / window",
                "libcoap-4.3.5 / window"
            ]
        );
        assert_eq!(ratio_columns(&[Mode::Libcoap431, Mode::Quic]).len(), 1);
        assert!(ratio_columns(&[Mode::Libcoap431]).is_empty());
    }

    #[test]
    fn links_are_the_issue_s_five() {
        let config = Link::Rtt20Loss2Rate50.config(7).unwrap();
        assert_eq!(config.up.delay, Duration::from_millis(10));
        assert_eq!(config.down.loss, 0.02);
        assert_eq!(config.down.rate_bytes_per_s, Some(6_250_000));
        assert_eq!(config.queue_bytes, Some(64_000));
        assert_eq!(config.seed, 7);
        assert!(Link::Loopback.config(7).is_none());
        assert_eq!(
            Link::Rtt100Loss5.config(1).unwrap().up.delay,
            Duration::from_millis(50)
        );
        assert_eq!(Link::Rtt100Loss5.loss_percent(), 5.0);
    }

    #[test]
    fn bodies_are_reproducible_from_the_seed() {
        let dir = std::env::temp_dir().join(format!("coapcam-bt-unit-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let other = dir.join("other");
        std::fs::create_dir_all(&other).unwrap();
        let a = Body::write(&dir, 1000, 3).unwrap();
        let b = Body::write(&other, 1000, 3).unwrap();
        let c = Body::write(&other, 1000, 4).unwrap();
        assert_eq!(a.bytes, b.bytes);
        assert_ne!(a.bytes, c.bytes);
        assert_eq!(std::fs::read(&a.path).unwrap(), a.bytes);
        assert_eq!(difference(&a.path, &a.bytes), None);
        assert!(
            difference(&a.path, &c.bytes)
                .unwrap()
                .contains("first difference")
        );
        let body: Vec<u8> = (0..4096u32).map(|i| (i / 1024) as u8).collect();
        assert_eq!(
            which_block(&body[2048..3072], &body),
            "; it starts with block 2 of the body"
        );
        assert_eq!(which_block(&body[..1024], &body), "");
        assert_eq!(which_block(&body[..10], &body), "");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn pair_shares_are_of_the_bytes_delivered_when_the_first_client_ended() {
        let ok = RunResult {
            time_s: 2.0,
            ok: true,
            exit: Some(0),
            killed_at_cap: false,
            bit_exact: Some(true),
            error: None,
            relay: None,
        };
        let addr = |port| SocketAddr::from((Ipv4Addr::LOCALHOST, port));
        let mut pair = PairRun {
            clients: vec![ok.clone(), RunResult { time_s: 2.5, ..ok }],
            delivered: vec![(addr(1), 600), (addr(2), 400)],
            relay: Counters {
                seed: 0,
                elapsed_ms: 2500,
                clients: 2,
                clients_refused: 0,
                up: DirCounters::default(),
                down: DirCounters::default(),
            },
        };
        assert_eq!(pair.shares(), Some((0.4, 0.6)));
        assert!(pair.holds() && pair.ok());
        assert_eq!(pair.later_s(), 2.5);
        // 2 x 6,250,000 bytes in 2.5 s: 80 % of 50 Mbit/s.
        assert!((pair.utilisation(6_250_000) - 0.8).abs() < 1e-12);
        pair.delivered = vec![(addr(1), 900), (addr(2), 100)];
        assert!(!pair.holds());
        // A client that had nothing yet.
        pair.delivered = vec![(addr(2), 500)];
        assert_eq!(pair.shares(), Some((0.0, 1.0)));
        pair.delivered.clear();
        assert_eq!(pair.shares(), None);
        assert!(!pair.holds());
    }

    #[test]
    fn labels() {
        assert_eq!(grouped(10_032_012), "10,032,012");
        assert_eq!(grouped(999), "999");
        assert_eq!(decade_label(-2), "0.01");
        assert_eq!(decade_label(0), "1");
        assert_eq!(decade_label(2), "100");
    }
}
