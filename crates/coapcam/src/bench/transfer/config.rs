//! What `bench transfer` runs: its configuration, the emulated links and the modes (a
//! client program and the server it fetches from).

use std::str::FromStr;
use std::time::Duration;

use netem::{DirConfig, LinkConfig};

/// The largest body the benchmark takes (what `quic-bench get` takes at most).
pub const MAX_BODY: u64 = 256 << 20;
/// Block size of every CoAP mode, bytes (SZX 6).
pub(super) const BLOCK_BYTES: u32 = 1024;
/// How long a server may take to answer its first ping.
pub(super) const STARTUP: Duration = Duration::from_secs(20);
/// How long the untimed loopback PUT (and the GET that checks it) to a libcoap server
/// may take.
pub(super) const SETUP_TRANSFER: Duration = Duration::from_secs(120);
/// Datagrams the relay holds at most per direction (`coapcam netem`'s default).
pub(super) const RELAY_QUEUE_LIMIT: usize = 1000;
/// 50 Mbit/s in bytes per second.
pub(super) const RATE_50_MBIT: u64 = 6_250_000;
/// The bottleneck's drop-tail buffer of `20ms-2%-50mbit` (as in the simulator's test).
pub(super) const QUEUE_64_KB: usize = 64_000;
/// The link of the pair runs: two transfers at once through its rate limit.
pub(super) const PAIR_LINK: Link = Link::Rtt20Loss2Rate50;
/// A pair run holds when the smaller of the two clients' shares is at least this.
pub(super) const FAIR_SHARE: f64 = 0.35;
/// Successful runs both cells need before the table prints the ratio of their medians:
/// with fewer, one slow run in a bimodal mode moves a median too far.
pub(super) const MIN_RATIO_RUNS: usize = 15;
/// Mixed into the seeds of the pair runs' relays, so that they differ from the single runs'.
pub(super) const PAIR_SEED: u64 = 0x7061_6972;

/// What to run.
#[derive(Debug, Clone)]
pub struct Config {
    /// Runs per cell of the fast modes (window, q-block, quic).
    pub runs: u32,
    /// Runs per cell of the slow modes (stop-and-wait, both libcoap modes).
    pub slow_runs: u32,
    /// Body sizes, bytes.
    pub sizes: Vec<u64>,
    /// The links, in the table's order.
    pub links: Vec<Link>,
    /// The modes: the table's columns in this order.
    pub modes: Vec<Mode>,
    /// Pair runs per size and fast mode (none when `PAIR_LINK` is not among the links).
    pub pairs: u32,
    /// How long a run may take; a client still running then is killed and the run failed.
    pub cap: Duration,
    /// Seed of the bodies and of the relays' loss decisions.
    pub seed: u64,
}

/// An emulated link between client and server.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Link {
    /// No relay.
    Loopback,
    /// 10 ms each way.
    Rtt20,
    /// 10 ms and 2 % loss each way.
    Rtt20Loss2,
    /// 10 ms, 2 % loss, 50 Mbit/s with a 64 KB queue, each way.
    Rtt20Loss2Rate50,
    /// 50 ms and 5 % loss each way.
    Rtt100Loss5,
}

impl Link {
    /// Its name on the command line and in the report.
    pub fn name(self) -> &'static str {
        match self {
            Self::Loopback => "loopback",
            Self::Rtt20 => "20ms",
            Self::Rtt20Loss2 => "20ms-2%",
            Self::Rtt20Loss2Rate50 => "20ms-2%-50mbit",
            Self::Rtt100Loss5 => "100ms-5%",
        }
    }

    /// What it does to each direction, in words.
    pub fn description(self) -> &'static str {
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
    pub fn shape(self) -> Option<(f64, Duration, Option<u64>, Option<usize>)> {
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
    pub fn config(self, seed: u64) -> Option<LinkConfig> {
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
    pub fn loss_percent(self) -> f64 {
        self.shape().map_or(0.0, |s| s.0 * 100.0)
    }

    /// Whether the plot joins this link's points with a line (the 20 ms links that
    /// differ only in loss).
    pub fn on_line(self) -> bool {
        matches!(self, Self::Rtt20 | Self::Rtt20Loss2)
    }
}

/// A client and the server it fetches from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// Ours, RFC 7959 one block per round trip.
    StopAndWait,
    /// Ours, many blocks in flight.
    Window,
    /// Ours, RFC 9177 Q-Block2.
    QBlock,
    /// libcoap 4.3.1 (Debian), RFC 7959.
    Libcoap431,
    /// libcoap 4.3.5 built from source, Q-Block2 NON.
    Libcoap435,
    /// quinn with BBR.
    Quic,
}

impl Mode {
    /// Its name on the command line and in the report.
    pub fn name(self) -> &'static str {
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
    pub fn short(self) -> &'static str {
        match self {
            Self::Libcoap435 => "libcoap-4.3.5",
            Self::Quic => "QUIC",
            other => other.name(),
        }
    }

    /// Which programs it runs, in words.
    pub fn description(self) -> &'static str {
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
    pub fn slow(self) -> bool {
        matches!(
            self,
            Self::StopAndWait | Self::Libcoap431 | Self::Libcoap435
        )
    }
}

/// The order given, each once.
pub(super) fn unique<T: PartialEq + Copy>(items: &[T]) -> Vec<T> {
    let mut out = Vec::new();
    for &item in items {
        if !out.contains(&item) {
            out.push(item);
        }
    }
    out
}

impl Link {
    /// Every link, in the order of the default table.
    pub const ALL: [Self; 5] = [
        Self::Loopback,
        Self::Rtt20,
        Self::Rtt20Loss2,
        Self::Rtt20Loss2Rate50,
        Self::Rtt100Loss5,
    ];
}

impl Mode {
    /// Every mode, in the order of the default table.
    pub const ALL: [Self; 6] = [
        Self::StopAndWait,
        Self::Window,
        Self::QBlock,
        Self::Libcoap431,
        Self::Libcoap435,
        Self::Quic,
    ];
}

/// A name that is no link or mode, with the names there are.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{given:?} is none of {}", known.join(", "))]
pub struct UnknownName {
    given: String,
    known: Vec<&'static str>,
}

impl FromStr for Link {
    type Err = UnknownName;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        by_name(&Self::ALL, Self::name, s)
    }
}

impl FromStr for Mode {
    type Err = UnknownName;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        by_name(&Self::ALL, Self::name, s)
    }
}

/// The one of `all` whose `name` is `given`.
fn by_name<T: Copy>(all: &[T], name: fn(T) -> &'static str, given: &str) -> Result<T, UnknownName> {
    all.iter()
        .copied()
        .find(|&t| name(t) == given)
        .ok_or_else(|| UnknownName {
            given: given.to_owned(),
            known: all.iter().map(|&t| name(t)).collect(),
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn links_and_modes_are_parsed_by_their_names() {
        for link in Link::ALL {
            assert_eq!(link.name().parse::<Link>(), Ok(link));
        }
        for mode in Mode::ALL {
            assert_eq!(mode.name().parse::<Mode>(), Ok(mode));
        }
        let e = "20 ms".parse::<Link>().unwrap_err().to_string();
        assert!(e.contains("\"20 ms\"") && e.contains("100ms-5%"), "{e}");
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
}
