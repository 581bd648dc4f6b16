//! The link model, sans-IO: each datagram's fate from the arrival time it is given, and
//! the counters. No clock, no socket: tested on literal instants.

use std::fmt;
use std::time::{Duration, Instant};

use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore, SeedableRng};
use serde::Serialize;

/// A direction of the link.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dir {
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
pub struct DirConfig {
    /// Probability that a datagram is lost, in [0, 1].
    pub loss: f64,
    /// Mean one-way delay (the flags allow up to an hour).
    pub delay: Duration,
    /// Each delay is uniform in `delay ± jitter`, clamped at zero.
    pub jitter: Duration,
    /// Serialization rate in payload bytes per second; `None` is unlimited.
    pub rate_bytes_per_s: Option<u64>,
    /// Probability that a datagram skips the delay (and the serializer's queue), so it
    /// overtakes those before it, in [0, 1] (Linux netem's `reorder`).
    pub reorder: f64,
}

impl DirConfig {
    /// A direction that loses datagrams with probability `loss`, delays them by `delay`
    /// ± `jitter`, and serializes them at `rate_bytes_per_s` (`None`: no limit).
    pub fn new(
        loss: f64,
        delay: Duration,
        jitter: Duration,
        rate_bytes_per_s: Option<u64>,
    ) -> Self {
        Self {
            loss,
            delay,
            jitter,
            rate_bytes_per_s,
            reorder: 0.0,
        }
    }

    /// The same, with probability `reorder` that a datagram skips the delay.
    pub fn with_reorder(self, reorder: f64) -> Self {
        Self { reorder, ..self }
    }
}

/// Both directions, the seed and the queue bound.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinkConfig {
    /// Client -> server.
    pub up: DirConfig,
    /// Server -> client.
    pub down: DirConfig,
    /// Seed of both directions' generators (one ChaCha8 stream each).
    pub seed: u64,
    /// Datagrams held at most per direction.
    pub queue_limit: usize,
    /// Bytes waiting for a rate-limited direction's serializer at most (a bottleneck's
    /// drop-tail buffer); `None` bounds them only by `queue_limit`.
    pub queue_bytes: Option<usize>,
}

/// What happens to one datagram.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fate {
    /// Lost on the link (the loss probability).
    Drop,
    /// Dropped because the direction already holds `queue_limit` datagrams, or its
    /// serializer `queue_bytes` bytes.
    Overflow,
    /// Delivered at this instant.
    DeliverAt(Instant),
}

/// The counters of one direction.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct DirCounters {
    /// Datagrams that arrived.
    pub received: u64,
    /// Datagrams lost on purpose (the loss probability).
    pub dropped: u64,
    /// Datagrams dropped because the queue was full.
    pub overflowed: u64,
    /// Datagrams sent on.
    pub forwarded: u64,
    /// Datagrams whose send failed (the OS refused it); not forwarded.
    pub send_errors: u64,
    /// Datagrams still held when netem stopped; never sent.
    pub unsent: u64,
    /// Payload bytes that arrived.
    pub bytes_received: u64,
    /// Payload bytes sent on.
    pub bytes_forwarded: u64,
    /// Most datagrams held at once.
    pub max_queue: u64,
}

/// Everything netem counted, printed when it ends.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Counters {
    /// The seed the run used.
    pub seed: u64,
    /// How long netem ran, in milliseconds.
    pub elapsed_ms: u64,
    /// Client addresses served.
    pub clients: u64,
    /// Datagrams ignored because `MAX_CLIENTS` clients were already served.
    pub clients_refused: u64,
    /// Client -> server.
    pub up: DirCounters,
    /// Server -> client.
    pub down: DirCounters,
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
pub struct Link {
    dirs: [DirState; 2],
    queue_limit: usize,
    queue_bytes: Option<usize>,
    seed: u64,
}

impl Link {
    /// A link with fresh generators seeded from `config.seed` (stream 0 up, 1 down).
    pub fn new(config: LinkConfig) -> Self {
        Self {
            dirs: [
                DirState::new(config.up, config.seed, 0),
                DirState::new(config.down, config.seed, 1),
            ],
            queue_limit: config.queue_limit,
            queue_bytes: config.queue_bytes,
            seed: config.seed,
        }
    }

    /// Decides the fate of a datagram of `len` bytes that arrived at `now` going `dir`.
    /// A datagram given `DeliverAt` is held until [`Link::on_departed`] is called for it.
    pub fn on_datagram(&mut self, now: Instant, dir: Dir, len: usize) -> Fate {
        let queue_limit = self.queue_limit;
        let queue_bytes = self.queue_bytes;
        let state = &mut self.dirs[dir.index()];
        let loss_draw = state.rng.next_u64();
        let jitter_draw = state.rng.next_u64();
        state.counters.received += 1;
        state.counters.bytes_received += len as u64;
        if unit(loss_draw) < state.config.loss {
            state.counters.dropped += 1;
            return Fate::Drop;
        }
        // A third draw only when reordering is on: links without it keep the two draws
        // per datagram (and the decisions) they always had.
        let skips = state.config.reorder > 0.0 && unit(state.rng.next_u64()) < state.config.reorder;
        if state.held >= queue_limit {
            state.counters.overflowed += 1;
            return Fate::Overflow;
        }
        if skips {
            state.held += 1;
            state.counters.max_queue = state.counters.max_queue.max(state.held as u64);
            return Fate::DeliverAt(now);
        }
        let departs = match state.config.rate_bytes_per_s {
            Some(rate) => {
                let start = state.free_at.map_or(now, |free| free.max(now));
                // The bytes still waiting for the serializer: its backlog at this rate.
                let backlog =
                    start.duration_since(now).as_nanos() * u128::from(rate) / 1_000_000_000;
                if queue_bytes.is_some_and(|limit| backlog + len as u128 > limit as u128) {
                    state.counters.overflowed += 1;
                    return Fate::Overflow;
                }
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
    pub fn on_departed(&mut self, dir: Dir, len: usize, sent: bool) {
        let state = &mut self.dirs[dir.index()];
        state.held = state.held.saturating_sub(1);
        if sent {
            state.counters.forwarded += 1;
            state.counters.bytes_forwarded += len as u64;
        } else {
            state.counters.send_errors += 1;
        }
    }

    /// The seed its generators started from.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// The counters of `dir`; datagrams still held count as unsent.
    pub fn counters(&self, dir: Dir) -> DirCounters {
        let state = &self.dirs[dir.index()];
        DirCounters {
            unsent: state.held as u64,
            ..state.counters
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn direction(loss: f64, delay_ms: u64, jitter_ms: u64, rate: Option<u64>) -> DirConfig {
        let ms = Duration::from_millis;
        DirConfig::new(loss, ms(delay_ms), ms(jitter_ms), rate)
    }

    fn link(up: DirConfig, down: DirConfig, seed: u64) -> Link {
        Link::new(LinkConfig {
            up,
            down,
            seed,
            queue_limit: usize::MAX,
            queue_bytes: None,
        })
    }

    fn delivery(fate: Fate) -> Instant {
        match fate {
            Fate::DeliverAt(at) => at,
            other => panic!("expected a delivery, got {other:?}"),
        }
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
            queue_bytes: None,
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
    fn counters_print_as_a_table_and_as_json() -> Result<(), serde_json::Error> {
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
        let text = counters.to_string();
        assert!(
            text.starts_with("netem: ran 1.234 s, seed 7, 1 client(s)"),
            "{text}"
        );
        assert_eq!(text.trim_end().lines().count(), 4);
        let json = serde_json::to_value(counters)?;
        assert_eq!(json["up"]["dropped"], 1);
        assert_eq!(json["down"]["max_queue"], 0);
        assert_eq!(json["elapsed_ms"], 1234);
        Ok(())
    }

    #[test]
    fn a_bottleneck_drops_what_its_byte_buffer_cannot_hold() {
        // 1,000 bytes per second: a 500-byte datagram takes 0.5 s to serialize.
        let t0 = Instant::now();
        let mut l = Link::new(LinkConfig {
            up: direction(0.0, 0, 0, Some(1000)),
            down: direction(0.0, 0, 0, None),
            seed: 1,
            queue_limit: usize::MAX,
            queue_bytes: Some(1200),
        });
        let fates: Vec<Fate> = (0..4).map(|_| l.on_datagram(t0, Dir::Up, 500)).collect();
        let s = Duration::from_millis;
        // Backlogs seen: 0, 500 and 1,000 bytes fit with the next 500 up to 1,200 only for
        // the first two; the third would make 1,500.
        assert_eq!(
            fates,
            [
                Fate::DeliverAt(t0 + s(500)),
                Fate::DeliverAt(t0 + s(1000)),
                Fate::Overflow,
                Fate::Overflow
            ]
        );
        // Half a second later the first has left: room again.
        assert_eq!(
            l.on_datagram(t0 + s(500), Dir::Up, 500),
            Fate::DeliverAt(t0 + s(1500))
        );
        assert_eq!(l.counters(Dir::Up).overflowed, 2);
    }

    #[test]
    fn reordering_lets_a_share_of_datagrams_overtake_the_delayed_ones() {
        let t0 = Instant::now();
        let mut l = link(
            direction(0.0, 50, 0, None).with_reorder(0.25),
            direction(0.0, 50, 0, None),
            7,
        );
        let n = 4000;
        let early = (0..n)
            .filter(|_| delivery(l.on_datagram(t0, Dir::Up, 100)) == t0)
            .count();
        let share = early as f64 / n as f64;
        assert!((share - 0.25).abs() < 0.03, "{share}");
        // Without reordering nothing skips the delay.
        assert!((0..100).all(|_| delivery(l.on_datagram(t0, Dir::Down, 100)) > t0));
    }
}
