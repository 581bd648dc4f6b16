//! A deterministic simulator: endpoints on a virtual clock joined by a seeded link that
//! drops, duplicates, delays, reorders and enforces an MTU.
//!
//! `Sim::run_until` moves time straight to the next thing that happens (a datagram
//! arriving, an endpoint timer, a delayed application response), so minutes of protocol
//! time take milliseconds.

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::net::SocketAddr;
use std::time::{Duration, Instant};

use bytes::Bytes;
use coap::{
    BlockOpt, Code, Endpoint, EndpointConfig, Event, IncomingId, IncomingRequest, Message,
    OptionNumber, Response, Type,
};
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore, SeedableRng};

/// The one real instant the tests use, as the epoch of virtual time.
#[expect(
    clippy::disallowed_methods,
    reason = "the simulator's epoch; everything after is virtual"
)]
pub(crate) fn epoch() -> Instant {
    Instant::now()
}

/// The multicast group of the simulation: a datagram sent here reaches every other node,
/// flagged as multicast.
pub(crate) const GROUP: SocketAddr = SocketAddr::new(
    std::net::IpAddr::V4(std::net::Ipv4Addr::new(224, 0, 1, 187)),
    5683,
);

/// What the link does to datagrams (the same in both directions).
#[derive(Debug, Clone)]
pub(crate) struct LinkConfig {
    /// Probability that a datagram is lost.
    pub(crate) loss: f64,
    /// Probability that a delivered datagram is delivered twice.
    pub(crate) duplicate: f64,
    /// One-way delay.
    pub(crate) delay: Duration,
    /// Extra random delay in [0, jitter): datagrams overtake each other.
    pub(crate) jitter: Duration,
    /// Datagrams longer than this are dropped.
    pub(crate) mtu: usize,
    /// Seed of the link's randomness.
    pub(crate) seed: u64,
    /// Each node's uplink rate in bytes per second (`None`: unlimited); what a node sends
    /// is serialized at this rate behind what it sent before.
    pub(crate) rate: Option<u64>,
    /// Bytes a node's uplink holds waiting to be serialized; beyond it, drop-tail.
    pub(crate) queue_bytes: usize,
}

impl Default for LinkConfig {
    fn default() -> Self {
        Self {
            loss: 0.0,
            duplicate: 0.0,
            delay: Duration::from_millis(5),
            jitter: Duration::ZERO,
            mtu: 1280,
            seed: 1,
            rate: None,
            queue_bytes: usize::MAX,
        }
    }
}

impl LinkConfig {
    /// A lossy link that also duplicates and reorders.
    pub(crate) fn lossy(loss: f64, seed: u64) -> Self {
        Self {
            loss,
            duplicate: loss / 4.0,
            jitter: Duration::from_millis(8),
            seed,
            ..Self::default()
        }
    }
}

/// What a simulated server does with a request.
pub(crate) enum Reply {
    /// Answer at once.
    Now(Response),
    /// Answer after this long (a slow handler).
    After(Duration, Response),
    /// Never answer.
    Never,
}

/// A request handler of a simulated node.
pub(crate) type Handler = Box<dyn FnMut(&IncomingRequest) -> Reply>;

/// One datagram as the link saw it.
#[derive(Debug, Clone)]
pub(crate) struct Record {
    /// Time since the start of the simulation.
    pub(crate) at: Duration,
    /// Sender.
    pub(crate) from: SocketAddr,
    /// Destination (a node, the group, or an address no node has).
    pub(crate) to: SocketAddr,
    /// Size of the datagram in bytes.
    pub(crate) len: usize,
    /// The decoded message (`None` if it did not decode).
    pub(crate) msg: Option<Message>,
    /// Whether the link dropped it.
    pub(crate) lost: bool,
}

impl Record {
    /// A short line: time, type, code, message ID, and the block option if any.
    pub(crate) fn line(&self) -> String {
        let Some(m) = &self.msg else {
            return format!("{} ms garbage", self.at.as_millis());
        };
        let ty = match m.ty {
            Type::Con => "CON",
            Type::Non => "NON",
            Type::Ack => "ACK",
            Type::Rst => "RST",
        };
        let mut s = format!(
            "{} ms {ty} {:?} mid={}",
            self.at.as_millis(),
            m.code,
            m.message_id
        );
        if let Some(b) = m.options.block1() {
            s.push_str(&format!(" b1={b}"));
        }
        if let Some(b) = m.options.block2() {
            s.push_str(&format!(" b2={b}"));
        }
        if let Some(b) = m.options.block(OptionNumber::Q_BLOCK1) {
            s.push_str(&format!(" q1={b}"));
        }
        for v in m.options.values(OptionNumber::Q_BLOCK2) {
            if let Some(b) = BlockOpt::decode(v) {
                s.push_str(&format!(" q2={b}"));
            }
        }
        if m.code == Code::REQUEST_ENTITY_INCOMPLETE
            && m.options.uint(OptionNumber::CONTENT_FORMAT) == Some(272)
        {
            s.push_str(&format!(" missing={:?}", cbor_uints(&m.payload)));
        }
        if self.lost {
            s.push_str(" LOST");
        }
        s
    }
}

/// The unsigned integers of a CBOR sequence (a 4.08's missing blocks), as far as they
/// decode.
fn cbor_uints(mut bytes: &[u8]) -> Vec<u64> {
    let mut out = Vec::new();
    while let Some((&head, rest)) = bytes.split_first() {
        let len = match head {
            0x00..=0x17 => 0,
            0x18 => 1,
            0x19 => 2,
            0x1a => 4,
            _ => break,
        };
        let Some(arg) = rest.get(..len) else { break };
        let value = if len == 0 {
            u64::from(head)
        } else {
            arg.iter().fold(0, |v, &b| v << 8 | u64::from(b))
        };
        out.push(value);
        bytes = &rest[len..];
    }
    out
}

/// How a node's thread meets real time, which virtual time otherwise spares it: timers
/// that fire late and on coarse ticks, and spans in which it does not run at all.
#[derive(Debug, Clone, Default)]
pub(crate) struct Wakeups {
    /// Timers fire only on ticks of this length (counted from the start), at the second
    /// tick after their due time: 1-2 ticks late, as a receive timeout counted in the
    /// kernel's jiffies is (4 ms each at HZ=250). A datagram wakes the node at once, and
    /// it then handles the timers due by then too. Zero: timers fire on time.
    pub(crate) tick: Duration,
    /// Spans `(start, length)` since the start in which the node's thread does not run (a
    /// busy CPU, a page fault, a garbage collection elsewhere): what arrives meanwhile,
    /// and its timers, wait until the span ends.
    pub(crate) stalls: Vec<(Duration, Duration)>,
}

/// A simulated node: an endpoint, an optional request handler, and what it reported.
pub(crate) struct Node {
    /// Its address.
    pub(crate) addr: SocketAddr,
    /// Its endpoint.
    pub(crate) ep: Endpoint,
    handler: Option<Handler>,
    /// Client events (responses, failures, pongs), with the time they came.
    pub(crate) events: Vec<(Duration, Event)>,
    /// Requests the handler saw.
    pub(crate) requests_seen: usize,
    /// How its thread wakes up (`None`: on time, every timer checked at every step).
    pub(crate) wakeups: Option<Wakeups>,
}

/// A datagram on the link: arrival, sequence, destination node, sender, multicast, bytes.
type InFlight = (Instant, u64, usize, SocketAddr, bool, Bytes);
/// A slow handler's response: due, sequence, node, request, slot in `delayed_responses`.
type Delayed = (Instant, u64, usize, IncomingId, usize);

/// The simulation.
pub(crate) struct Sim {
    start: Instant,
    /// Current virtual time.
    pub(crate) now: Instant,
    /// The nodes.
    pub(crate) nodes: Vec<Node>,
    pub(crate) link: LinkConfig,
    rng: ChaCha8Rng,
    seq: u64,
    in_flight: BinaryHeap<Reverse<InFlight>>,
    delayed: BinaryHeap<Reverse<Delayed>>,
    delayed_responses: Vec<Option<Response>>,
    /// Every datagram sent, in order.
    pub(crate) log: Vec<Record>,
    /// Whether to keep `log` (large transfers turn it off).
    pub(crate) record: bool,
    /// Per node: when its uplink is free, and the departures it holds (instant, bytes).
    uplinks: Vec<(Instant, std::collections::VecDeque<(Instant, usize)>)>,
    /// Datagrams dropped because an uplink queue was full.
    pub(crate) overflows: u64,
}

impl Sim {
    /// An empty simulation on `link`.
    pub(crate) fn new(link: LinkConfig) -> Self {
        let start = epoch();
        Self {
            start,
            now: start,
            nodes: Vec::new(),
            rng: ChaCha8Rng::seed_from_u64(link.seed),
            link,
            seq: 0,
            in_flight: BinaryHeap::new(),
            delayed: BinaryHeap::new(),
            delayed_responses: Vec::new(),
            log: Vec::new(),
            record: true,
            uplinks: Vec::new(),
            overflows: 0,
        }
    }

    /// Adds a node at `127.0.0.<n>:5683`; returns its index.
    pub(crate) fn add(&mut self, config: EndpointConfig, handler: Option<Handler>) -> usize {
        let n = self.nodes.len();
        let addr = SocketAddr::from(([127, 0, 0, n as u8 + 1], 5683));
        self.add_at(addr, config, handler)
    }

    /// Adds a node at `addr` (not on loopback: its address must be verified, RFC 9175).
    pub(crate) fn add_at(
        &mut self,
        addr: SocketAddr,
        config: EndpointConfig,
        handler: Option<Handler>,
    ) -> usize {
        let n = self.nodes.len();
        self.nodes.push(Node {
            addr,
            ep: Endpoint::new(config),
            handler,
            events: Vec::new(),
            requests_seen: 0,
            wakeups: None,
        });
        self.uplinks.push((self.now, Default::default()));
        n
    }

    /// Time since the start.
    pub(crate) fn elapsed(&self) -> Duration {
        self.now - self.start
    }

    fn unit(&mut self) -> f64 {
        (self.rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Injects a raw datagram from `from` to node `to`, delivered after the link delay
    /// without loss.
    pub(crate) fn inject(&mut self, from: SocketAddr, to: usize, data: &[u8]) {
        self.inject_to(from, to, data, false);
    }

    /// [`Sim::inject`], as sent to the group: node `to` receives it as a multicast
    /// request.
    pub(crate) fn inject_to_group(&mut self, from: SocketAddr, to: usize, data: &[u8]) {
        self.inject_to(from, to, data, true);
    }

    fn inject_to(&mut self, from: SocketAddr, to: usize, data: &[u8], multicast: bool) {
        self.seq += 1;
        let at = self.now + self.link.delay;
        self.in_flight.push(Reverse((
            at,
            self.seq,
            to,
            from,
            multicast,
            Bytes::copy_from_slice(data),
        )));
    }

    fn node_index(&self, addr: SocketAddr) -> Option<usize> {
        self.nodes.iter().position(|n| n.addr == addr)
    }

    /// Hands requests to handlers and moves every node's output onto the link.
    fn drain(&mut self) {
        for i in 0..self.nodes.len() {
            while let Some(ev) = self.nodes[i].ep.poll_event() {
                match ev {
                    Event::Request(req) => self.on_request(i, req),
                    other => {
                        let at = self.elapsed();
                        self.nodes[i].events.push((at, other));
                    }
                }
            }
            while let Some(t) = self.nodes[i].ep.poll_transmit() {
                let from = self.nodes[i].addr;
                let lost = t.data.len() > self.link.mtu || self.unit() < self.link.loss;
                if self.record {
                    let at = self.elapsed();
                    let msg = Message::decode(&t.data).ok();
                    self.log.push(Record {
                        at,
                        from,
                        to: t.peer,
                        len: t.data.len(),
                        msg,
                        lost,
                    });
                }
                let multicast = t.peer == GROUP;
                let targets: Vec<usize> = if multicast {
                    (0..self.nodes.len()).filter(|&n| n != i).collect()
                } else {
                    self.node_index(t.peer).into_iter().collect()
                };
                if lost {
                    continue;
                }
                let Some(departs) = self.serialize(i, t.data.len()) else {
                    self.overflows += 1;
                    continue;
                };
                for to in targets {
                    let copies = if self.unit() < self.link.duplicate {
                        2
                    } else {
                        1
                    };
                    for _ in 0..copies {
                        let jitter = self.link.jitter.mul_f64(self.unit());
                        self.seq += 1;
                        let at = self.awake_at(to, departs + self.link.delay + jitter);
                        let data = t.data.clone();
                        self.in_flight
                            .push(Reverse((at, self.seq, to, from, multicast, data)));
                    }
                }
            }
        }
    }

    /// The first instant at or after `at` at which node `i`'s thread runs (the end of a
    /// stall it falls in).
    fn awake_at(&self, i: usize, at: Instant) -> Instant {
        let Some(w) = &self.nodes[i].wakeups else {
            return at;
        };
        let mut at = at;
        for &(from, len) in &w.stalls {
            let (a, b) = (self.start + from, self.start + from + len);
            if at >= a && at < b {
                at = b;
            }
        }
        at
    }

    /// When node `i` wakes up for a timer due at `due`.
    fn timer_wakeup(&self, i: usize, due: Instant) -> Instant {
        let Some(w) = &self.nodes[i].wakeups else {
            return due;
        };
        let mut at = due;
        if !w.tick.is_zero() {
            let since = due.saturating_duration_since(self.start).as_nanos();
            let tick = w.tick.as_nanos();
            let ticks = (since / tick + 2) as u32;
            at = self.start + w.tick * ticks;
        }
        self.awake_at(i, at)
    }

    /// When a datagram of `len` bytes sent now by node `i` leaves its uplink, or `None`
    /// if the uplink's queue is full.
    fn serialize(&mut self, i: usize, len: usize) -> Option<Instant> {
        let Some(rate) = self.link.rate else {
            return Some(self.now);
        };
        let now = self.now;
        let (free, held) = &mut self.uplinks[i];
        while held.front().is_some_and(|(at, _)| *at <= now) {
            held.pop_front();
        }
        let queued: usize = held.iter().map(|(_, n)| n).sum();
        if queued + len > self.link.queue_bytes {
            return None;
        }
        let start = (*free).max(now);
        let departs = start + Duration::from_nanos((len as u64 * 1_000_000_000).div_ceil(rate));
        *free = departs;
        held.push_back((departs, len));
        Some(departs)
    }

    fn on_request(&mut self, i: usize, req: IncomingRequest) {
        self.nodes[i].requests_seen += 1;
        let reply = match self.nodes[i].handler.as_mut() {
            Some(h) => h(&req),
            None => Reply::Never,
        };
        match reply {
            Reply::Now(resp) => {
                let now = self.now;
                self.nodes[i].ep.respond(now, req.id, resp);
            }
            Reply::After(d, resp) => {
                self.seq += 1;
                let slot = self.delayed_responses.len();
                self.delayed
                    .push(Reverse((self.now + d, self.seq, i, req.id, slot)));
                self.delayed_responses.push(Some(resp));
            }
            Reply::Never => {}
        }
    }

    /// Runs until `done` holds or nothing is left to happen or `limit` of virtual time
    /// passed. Returns whether `done` held.
    pub(crate) fn run_until(
        &mut self,
        limit: Duration,
        mut done: impl FnMut(&Self) -> bool,
    ) -> bool {
        let deadline = self.now + limit;
        loop {
            self.drain();
            if done(self) {
                return true;
            }
            let next_packet = self.in_flight.peek().map(|Reverse((at, ..))| *at);
            let mut timers = Vec::with_capacity(self.nodes.len());
            for i in 0..self.nodes.len() {
                let due = self.nodes[i].ep.poll_timeout();
                timers.push(due.map(|d| self.timer_wakeup(i, d)));
            }
            let next_timer = timers.iter().flatten().min().copied();
            let next_delayed = self.delayed.peek().map(|Reverse((at, ..))| *at);
            let Some(next) = [next_packet, next_timer, next_delayed]
                .into_iter()
                .flatten()
                .min()
            else {
                return false;
            };
            if next > deadline {
                self.now = deadline;
                return false;
            }
            self.now = self.now.max(next);
            let now = self.now;
            // Nodes whose thread runs now: a datagram arrived, or a timer woke it.
            let mut woken: Vec<bool> = timers.iter().map(|t| t.is_some_and(|t| t <= now)).collect();
            while let Some(Reverse((at, _, to, from, multicast, data))) =
                self.in_flight.peek().cloned()
            {
                if at > now {
                    break;
                }
                self.in_flight.pop();
                woken[to] = true;
                self.nodes[to].ep.handle(now, from, &data, multicast);
            }
            while let Some(Reverse((at, _, i, id, slot))) = self.delayed.peek().copied() {
                if at > now {
                    break;
                }
                self.delayed.pop();
                if let Some(resp) = self.delayed_responses[slot].take() {
                    self.nodes[i].ep.respond(now, id, resp);
                }
            }
            for (n, woken) in self.nodes.iter_mut().zip(woken) {
                if woken || n.wakeups.is_none() {
                    n.ep.handle_timeout(now);
                }
            }
        }
    }

    /// Runs until node `i` has at least one client event.
    pub(crate) fn run_to_event(&mut self, i: usize, limit: Duration) -> bool {
        self.run_until(limit, |s| !s.nodes[i].events.is_empty())
    }
}
