//! `coapcam netem`: the `netem` crate's link emulator between clients and a server (its
//! crate documentation says what the link does to each datagram, in which order).

use std::net::SocketAddr;
use std::time::Duration;

use anyhow::Context as _;
use netem::{Counters, DirConfig, LinkConfig, Netem};

/// The largest delay or jitter a flag accepts, in milliseconds (one hour).
const MAX_DELAY_MS: u64 = 3_600_000;

/// Arguments of `coapcam netem`.
#[derive(Debug, Clone, clap::Args)]
#[command(after_long_help = "\
Per-direction flags (--loss-up, --delay-down-ms, ...) override the flag for both \
directions. \"up\" is client -> server, \"down\" is server -> client.

Each datagram's delay is uniform in [delay - jitter, delay + jitter] (clamped at 0), so \
jitter reorders datagrams. With --rate, a direction is a serializer: a datagram leaves it \
at max(arrival, previous departure) + bytes / rate, then the delay starts.

With --queue-bytes, a datagram that would find more than that many bytes waiting for \
the serializer is dropped (a bottleneck's drop-tail buffer). With --reorder P, a datagram \
skips delay and serializer with probability P and overtakes those before it.

Randomness comes from ChaCha8 seeded by --seed, one stream per direction, two draws per \
datagram (loss, then jitter; a third for --reorder): the same seed and the same arrival \
order give the same decisions.

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
    /// With --rate: bytes at most waiting for a direction's serializer, the buffer of a
    /// bottleneck (e.g. 65536); more are dropped (drop-tail) and counted as overflowed.
    #[arg(long, value_name = "BYTES", value_parser = clap::value_parser!(u64).range(1..))]
    queue_bytes: Option<u64>,
    /// Probability that a datagram skips the delay and overtakes those before it, both
    /// directions (Linux netem's reorder).
    #[arg(long, value_name = "P", default_value_t = 0.0, value_parser = parse_probability)]
    reorder: f64,
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

pub(crate) fn parse_seconds(text: &str) -> Result<Duration, String> {
    super::values::positive_seconds(text)
}

impl NetemArgs {
    /// The link that these flags describe, per-direction flags overriding the shared ones.
    fn link_config(&self) -> LinkConfig {
        let direction = |loss: Option<f64>, delay_ms: Option<u64>, jitter_ms, rate: Option<u64>| {
            DirConfig::new(
                loss.unwrap_or(self.loss),
                Duration::from_millis(delay_ms.unwrap_or(self.delay_ms)),
                Duration::from_millis(jitter_ms),
                rate.or(self.rate),
            )
            .with_reorder(self.reorder)
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
            queue_bytes: self
                .queue_bytes
                .map(|b| usize::try_from(b).unwrap_or(usize::MAX)),
        }
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

/// `coapcam netem`: binds, reports the listen address on standard error, relays until
/// `--duration` or Ctrl-C, and returns the counters.
pub(crate) async fn run(args: NetemArgs) -> anyhow::Result<Counters> {
    let netem = Netem::bind(args.listen, args.forward, args.link_config(), args.duration)?;
    eprintln!(
        "netem: listening on {}, forwarding to {}",
        netem.local_addr()?,
        args.forward
    );
    Ok(netem.run(tokio::signal::ctrl_c()).await?)
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
        let ms = Duration::from_millis;
        DirConfig::new(loss, ms(delay_ms), ms(jitter_ms), rate)
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
}
