//! The message layer (RFC 7252 §4): message IDs, the timers, confirmable messages waiting
//! for their ACK and their retransmission with exponential back-off, the deduplication
//! store, and the datagrams waiting to be sent. It knows nothing of requests: a CON's
//! [`Purpose`] says whom its ACK, Reset or failure concerns, and the endpoint routes it.

use std::cmp::Reverse;
use std::collections::{BinaryHeap, VecDeque};
use std::net::SocketAddr;
use std::time::{Duration, Instant};

use bytes::{Bytes, BytesMut};
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore, SeedableRng};

use super::congestion::{self, Backoff, Controller, RttEstimator};
use super::types::{PathStats, Transmit};
use crate::config::EndpointConfig;
use crate::dedup::{Dedup, Seen};
use crate::msg::{Message, Outgoing};
use crate::peer_key::{FastMap, MidKey, PeerKey};

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub(super) enum TimerKind {
    Retransmit {
        peer: SocketAddr,
        mid: u16,
        tx: u8,
    },
    /// The retransmission check of a request's CON, armed at `at` (see
    /// [`ClientRequest::ack_timer`]).
    RequestAck {
        id: u64,
        at: Instant,
    },
    Step {
        id: u64,
        generation: u32,
    },
    /// The loss, probe or pacing timer of a windowed download, armed at `at`.
    Window {
        id: u64,
        at: Instant,
    },
    Deadline {
        id: u64,
    },
    SeparateAck {
        id: u64,
    },
    /// The end of the leisure of an answered multicast request (RFC 7252 §8.2).
    Leisure {
        id: u64,
    },
    /// The next set of a body the server sends with Q-Block2, due at `at`.
    QSet {
        id: u64,
        at: Instant,
    },
    /// The timer of a body a client fetches or sends with Q-Block, due at `at`.
    QClient {
        id: u64,
        at: Instant,
    },
    /// The receive timer of a body the server receives with Q-Block1, due at `at`.
    QReceive {
        id: u64,
        at: Instant,
    },
    /// The expiry of the server's idle uploads and stored representations, due at `at`.
    Sweep {
        at: Instant,
    },
}

#[derive(Debug, Clone, Copy)]
pub(super) enum Purpose {
    Request(u64),
    Ping(u64),
    SeparateResponse,
    Notification(u64),
}

/// A CON message waiting for its ACK (RFC 7252 §4.2).
pub(super) struct OutCon {
    /// The datagram to send again. A request's step keeps none: its message is built
    /// again from the request (same message ID, token, options and payload), so the
    /// block-by-block path sends each CON from the shared chunk, without an allocation.
    data: Option<Bytes>,
    /// Retransmissions so far.
    pub(super) tx: u8,
    /// When it was first sent (its round trip is measured from there).
    pub(super) first_sent: Instant,
    timeout: Duration,
    /// How `timeout` grows at each retransmission.
    backoff: Backoff,
    /// When it is sent again (or given up) unless acknowledged.
    at: Instant,
    pub(super) purpose: Purpose,
}

/// Bytes of the chunk that messages sent once are encoded into ([`Outbox::send`]).
const ENCODE_CHUNK: usize = 16 << 10;

/// The datagrams waiting for [`Endpoint::poll_transmit`].
#[derive(Default)]
pub(super) struct Outbox {
    pub(super) queue: VecDeque<Transmit>,
    /// Where [`Outbox::send`] encodes.
    chunk: BytesMut,
}

impl Outbox {
    /// Queues a message that goes out once and is not kept (not a CON that keeps its
    /// encoding until its ACK). It is encoded into a chunk shared with the messages before
    /// it, so a block costs no allocation of its own; once they are all sent and dropped,
    /// the chunk is used again from its start (so a caller that keeps a [`Transmit`]
    /// keeps its whole chunk).
    pub(super) fn send(&mut self, peer: SocketAddr, msg: &Outgoing<'_>) {
        self.send_with(peer, msg.payload.len(), |out| msg.encode_into(out));
    }

    /// Queues the message that `encode` appends to the chunk (as [`Outbox::send`]).
    pub(super) fn send_with(
        &mut self,
        peer: SocketAddr,
        payload: usize,
        encode: impl FnOnce(&mut BytesMut),
    ) {
        // Room for the payload and usual header and options, without counting them
        // first; a message with more options grows the chunk as it is written.
        let room = payload + 128;
        // Back to the front of the chunk when every datagram cut from it is gone (the
        // usual case: each is sent before the next is encoded), so that block after block
        // is written to the same cache lines.
        let _ = self.chunk.try_reclaim(ENCODE_CHUNK);
        if self.chunk.capacity() < room {
            self.chunk.reserve(room.max(ENCODE_CHUNK));
        }
        encode(&mut self.chunk);
        let data = self.chunk.split().freeze();
        self.queue.push_back(Transmit { peer, data });
    }
}

/// What a request's ACK timer does about its CON ([`MessageLayer::request_con_due`]).
pub(super) enum Due {
    /// Acknowledged already, or the request moved on.
    Gone,
    /// Not due yet: check again then.
    Later(Instant),
    /// Send it again now; due again then.
    Resend(Instant),
    /// MAX_RETRANSMIT reached: the exchange is over.
    GaveUp,
}

/// How many message IDs apart [`MessageLayer::mid_free_at`] records the time.
const MID_SAMPLE: u64 = 256;

/// Paths remembered at most; past it, those without requests in flight are forgotten,
/// those given a message ID within EXCHANGE_LIFETIME last ([`MessageLayer::path`]).
const MAX_PATHS: usize = 4096;

/// The message IDs this endpoint issues to one peer. RFC 7252 §4.4 asks an ID be unique
/// per pair of source and destination endpoints within EXCHANGE_LIFETIME, so each peer
/// (a multicast group too: a request to a group is one such pair) has an ID space of its
/// own, starting at a random ID: a client that fetches from several servers uses up 65,536
/// IDs per EXCHANGE_LIFETIME with each, not with all of them together.
struct MessageIds {
    next: u16,
    /// IDs issued so far, and a sample of when: (time, count) every [`MID_SAMPLE`] IDs,
    /// kept for EXCHANGE_LIFETIME ([`MessageLayer::mid_free_at`]).
    issued: u64,
    recorded: u64,
    expired: u64,
    samples: VecDeque<(Instant, u64)>,
    /// When the last was issued: the path is not forgotten within EXCHANGE_LIFETIME of it
    /// unless it must be ([`MessageLayer::path`]).
    last: Option<Instant>,
}

/// What the endpoint knows of the path to one peer: its round-trip estimate, the
/// congestion controller of its windowed transfers (made by the first), their counters,
/// and the message IDs issued to the peer.
pub(super) struct Path {
    pub(super) rtt: RttEstimator,
    controller: Option<Box<dyn Controller>>,
    pub(super) stats: PathStats,
    mids: MessageIds,
}

impl Path {
    /// The controller of the windowed transfers, made as `config` chooses if none is yet.
    pub(super) fn controller(
        &mut self,
        now: Instant,
        config: &EndpointConfig,
    ) -> &mut dyn Controller {
        &mut **self
            .controller
            .get_or_insert_with(|| congestion::for_path(config, now))
    }

    /// The controller of the windowed transfers, if one ever ran on this path.
    pub(super) fn existing_controller(&mut self) -> Option<&mut (dyn Controller + 'static)> {
        self.controller.as_deref_mut()
    }

    /// The statistics with the current estimate.
    pub(super) fn stats(&self) -> PathStats {
        PathStats {
            srtt: self.rtt.srtt(),
            rttvar: self.rtt.rttvar(),
            min_rtt: self.rtt.min(),
            ..self.stats
        }
    }
}

/// The message layer's state.
pub(super) struct MessageLayer {
    pub(super) paths: FastMap<PeerKey, Path>,
    pub(super) rng: ChaCha8Rng,
    /// EXCHANGE_LIFETIME: how long a path keeps the record of its message IDs.
    exchange_lifetime: Duration,
    timer_seq: u64,
    pub(super) timers: BinaryHeap<Reverse<(Instant, u64, TimerKind)>>,
    pub(super) outbox: Outbox,
    pub(super) exchanges: FastMap<MidKey, OutCon>,
    pub(super) dedup: Dedup,
}

impl MessageLayer {
    pub(super) fn new(seed: u64, exchange_lifetime: Duration) -> Self {
        Self {
            paths: FastMap::default(),
            rng: ChaCha8Rng::seed_from_u64(seed),
            exchange_lifetime,
            timer_seq: 0,
            timers: BinaryHeap::new(),
            outbox: Outbox::default(),
            exchanges: FastMap::default(),
            dedup: Dedup::new(),
        }
    }

    /// A new message ID for a message to `peer` (the next of the peer's own ID space).
    pub(super) fn next_mid(&mut self, now: Instant, peer: SocketAddr) -> u16 {
        let ids = &mut self.path(now, peer).mids;
        ids.next = ids.next.wrapping_add(1);
        ids.issued += 1;
        ids.last = Some(now);
        ids.next
    }

    /// When the next message ID to `peer` is free to use again (RFC 7252 §4.4: not within
    /// EXCHANGE_LIFETIME of its last use; the IDs come round every 65,536), or `None` if it
    /// is now. Called by the senders that can wait (a window's block requests), which also
    /// keep the record: every [`MID_SAMPLE`] IDs, the time they see. An ID issued between
    /// two records counts as used at the later one, so the answer errs on the safe side.
    pub(super) fn mid_free_at(&mut self, now: Instant, peer: SocketAddr) -> Option<Instant> {
        let lifetime = self.exchange_lifetime;
        let ids = &mut self.path(now, peer).mids;
        if ids.issued >= ids.recorded + MID_SAMPLE {
            ids.samples.push_back((now, ids.issued));
            ids.recorded = ids.issued;
        }
        while let Some(&(at, n)) = ids.samples.front() {
            if at + lifetime > now {
                break;
            }
            ids.samples.pop_front();
            ids.expired = n;
        }
        // The next ID was last issued as number `issued + 1 - 65,536`; the first record at
        // or after that count is no earlier than its use. If that record has expired, so
        // has the use.
        let last_use = (ids.issued + 1).checked_sub(1 << 16)?;
        if last_use <= ids.expired {
            return None;
        }
        let i = ids.samples.partition_point(|&(_, n)| n < last_use);
        let &(at, _) = ids.samples.get(i)?;
        Some(at + lifetime).filter(|&free| free > now)
    }

    pub(super) fn schedule(&mut self, at: Instant, kind: TimerKind) {
        self.timer_seq += 1;
        self.timers.push(Reverse((at, self.timer_seq, kind)));
    }

    /// The path to `peer`, created if new.
    pub(super) fn path(&mut self, now: Instant, peer: SocketAddr) -> &mut Path {
        if self.paths.len() >= MAX_PATHS && !self.paths.contains_key(&PeerKey(peer)) {
            let busy = |p: &Path| p.controller.as_ref().is_some_and(|c| c.in_flight() > 0);
            // Forgotten first: the paths with nothing in flight and no message ID issued
            // within EXCHANGE_LIFETIME.
            let lifetime = self.exchange_lifetime;
            self.paths
                .retain(|_, p| busy(p) || p.mids.last.is_some_and(|at| at + lifetime > now));
            if self.paths.len() >= MAX_PATHS {
                // Still full (more than MAX_PATHS peers got an ID within EXCHANGE_LIFETIME):
                // those with nothing in flight are forgotten all the same. Such a peer, met
                // again, starts at a new random ID, which may be one it got within
                // EXCHANGE_LIFETIME (about n in 65,536 for each message, after n IDs to it):
                // the peer would take that message for a duplicate of the earlier one, and
                // a CON of it still awaiting its ACK would be replaced by the new one.
                self.paths.retain(|_, p| busy(p));
            }
        }
        if !self.paths.contains_key(&PeerKey(peer)) {
            // A new peer on a host this endpoint knows (another port: a new process of
            // a client, each with a socket of its own) starts from that host's round
            // trip, as a weak sample its first measured one replaces: its first CON
            // then times out after about that, not ACK_TIMEOUT (TCP keeps its metrics
            // per destination address too).
            let host = self
                .paths
                .iter()
                .filter(|(k, _)| k.0.ip() == peer.ip())
                .filter_map(|(_, p)| p.rtt.srtt())
                .min();
            let mut rtt = RttEstimator::new(now);
            if let Some(srtt) = host {
                rtt.on_sample(now, srtt, false);
            }
            let mids = MessageIds {
                next: self.rng.next_u32() as u16,
                issued: 0,
                recorded: 0,
                expired: 0,
                samples: VecDeque::new(),
                last: None,
            };
            self.paths.insert(
                PeerKey(peer),
                Path {
                    rtt,
                    controller: None,
                    stats: PathStats::default(),
                    mids,
                },
            );
        }
        self.paths
            .get_mut(&PeerKey(peer))
            .unwrap_or_else(|| unreachable!("inserted above"))
    }

    /// The path's probe timeout (`SRTT + 4 RTTVAR`) if it has a round-trip estimate:
    /// what the Q-Block timers use in place of the RFC's fixed values.
    pub(super) fn estimate(&self, peer: SocketAddr) -> Option<Duration> {
        let rtt = &self.paths.get(&PeerKey(peer))?.rtt;
        rtt.srtt().map(|_| rtt.pto(Duration::ZERO))
    }

    /// A uniform sample in [0, 1).
    pub(super) fn unit(&mut self) -> f64 {
        (self.rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// The timeout of a CON (or a NON request) to `peer`: the path's estimate (ACK_TIMEOUT
    /// before one exists) scaled by a uniform random factor in [1, ACK_RANDOM_FACTOR]; and
    /// what it grows by at each retransmission: CoCoA's variable backoff factor for an
    /// estimate, RFC 7252's doubling for ACK_TIMEOUT.
    pub(super) fn initial_timeout(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        config: &EndpointConfig,
    ) -> (Duration, Backoff) {
        // The path is made if new: a peer on a host known already starts from its
        // round trip ([`MessageLayer::path`]).
        let estimate = (self.path(now, peer).rtt).con_timeout(now, config.ack_timeout);
        let base = estimate.unwrap_or(config.ack_timeout);
        let unit = self.unit();
        let spread = (config.ack_random_factor - 1.0).max(0.0);
        let jitter = base.as_secs_f64() * 1e9 * spread * unit;
        // Whole nanoseconds added, rather than Duration::mul_f64's checked conversion of
        // the product: this runs for every CON of a transfer.
        let timeout = base + Duration::from_nanos(jitter as u64);
        (timeout, estimate.map_or(Backoff::DOUBLING, Backoff::cocoa))
    }

    /// An exchange with `peer` first sent at `first_sent` was acknowledged at `now` after
    /// `tx` retransmissions: a round-trip sample, strong if it was sent once, weak
    /// (CoCoA) if sent at most three times, none otherwise.
    pub(super) fn on_acknowledged(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        first_sent: Instant,
        tx: u8,
    ) {
        if tx <= 2 {
            let rtt = now.saturating_duration_since(first_sent);
            self.path(now, peer).rtt.on_sample(now, rtt, tx == 0);
        }
    }

    /// Counts a retransmission to `peer`.
    fn count_retransmission(&mut self, now: Instant, peer: SocketAddr) {
        self.path(now, peer).stats.retransmissions += 1;
    }

    /// Sends a message that goes out once ([`Outbox::send`]).
    pub(super) fn send(&mut self, peer: SocketAddr, msg: &Message) {
        self.outbox.send(peer, &msg.outgoing());
    }

    /// Sends a reply and keeps the message (not its encoding, which shares a chunk with
    /// other messages) to send again for duplicates.
    pub(super) fn reply_with(&mut self, peer: SocketAddr, msg: Message) -> Seen {
        self.send(peer, &msg);
        Seen::Replied(Box::new(msg))
    }

    /// Sends a CON that keeps its own encoding for retransmission (a ping, a
    /// notification, a separate response).
    pub(super) fn send_con(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        msg: &Message,
        purpose: Purpose,
        config: &EndpointConfig,
    ) {
        let data = Bytes::from(msg.encode());
        self.outbox.queue.push_back(Transmit {
            peer,
            data: data.clone(),
        });
        self.await_ack(now, peer, msg.message_id, purpose, Some(data), config);
    }

    /// Records a CON just sent (RFC 7252 §4.2) and returns when it is due again. `data`
    /// is what to send again, with a retransmission timer of its own; `None` for a
    /// request's step, which is built again when its request's ACK timer fires.
    pub(super) fn await_ack(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        mid: u16,
        purpose: Purpose,
        data: Option<Bytes>,
        config: &EndpointConfig,
    ) -> Instant {
        let (timeout, backoff) = self.initial_timeout(now, peer, config);
        let at = now + timeout;
        let retransmits = data.is_some();
        self.exchanges.insert(
            MidKey(peer, mid),
            OutCon {
                data,
                tx: 0,
                first_sent: now,
                timeout,
                backoff,
                at,
                purpose,
            },
        );
        if retransmits {
            self.schedule(at, TimerKind::Retransmit { peer, mid, tx: 0 });
        }
        at
    }

    /// What a request's ACK timer does about its CON (`peer`, `mid`): wait longer, send it
    /// again now (its timeout multiplied by the backoff factor) or give it up after MAX_RETRANSMIT.
    pub(super) fn request_con_due(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        mid: u16,
        max_retransmit: u8,
    ) -> Due {
        let key = MidKey(peer, mid);
        let Some(x) = self.exchanges.get_mut(&key) else {
            return Due::Gone;
        };
        if x.at > now {
            Due::Later(x.at)
        } else if x.tx < max_retransmit {
            x.tx += 1;
            x.timeout = x.backoff.next(x.timeout);
            x.at = now + x.timeout;
            let at = x.at;
            self.count_retransmission(now, peer);
            Due::Resend(at)
        } else {
            self.exchanges.remove(&key);
            Due::GaveUp
        }
    }

    /// The retransmission timer of a CON that keeps its datagram: sent again, the timeout
    /// growing by the backoff factor; after MAX_RETRANSMIT it is given up and its purpose
    /// returned.
    pub(super) fn on_retransmit_timer(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        mid: u16,
        tx: u8,
        max_retransmit: u8,
    ) -> Option<Purpose> {
        let x = self.exchanges.get_mut(&MidKey(peer, mid))?;
        if x.tx != tx {
            return None;
        }
        if x.tx < max_retransmit {
            // Only a request's CON keeps no datagram, and it has no timer of this kind.
            debug_assert!(x.data.is_some(), "a request's CON has its own ACK timer");
            let data = x.data.clone()?;
            x.tx += 1;
            x.timeout = x.backoff.next(x.timeout);
            x.at = now + x.timeout;
            let (at, tx) = (x.at, x.tx);
            self.outbox.queue.push_back(Transmit { peer, data });
            self.schedule(at, TimerKind::Retransmit { peer, mid, tx });
            self.count_retransmission(now, peer);
            return None;
        }
        self.exchanges.remove(&MidKey(peer, mid)).map(|x| x.purpose)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn peer(n: usize) -> SocketAddr {
        SocketAddr::from(([10, 0, (n >> 8) as u8, n as u8], 5683))
    }

    #[test]
    fn each_peer_counts_its_own_message_ids() {
        let lifetime = Duration::from_secs(60);
        let mut ml = MessageLayer::new(1, lifetime);
        let now = crate::test_epoch();
        let (a, b) = (peer(1), peer(2));
        let first = ml.next_mid(now, a);
        for _ in 0..1000 {
            ml.next_mid(now, b);
        }
        assert_eq!(ml.next_mid(now, a), first.wrapping_add(1));
        // 65,535 more to `a` within the lifetime: its next ID waits, `b`'s does not.
        for _ in 0..65_535 {
            ml.next_mid(now, a);
            ml.mid_free_at(now, a);
        }
        assert_eq!(ml.mid_free_at(now, a), Some(now + lifetime));
        assert_eq!(ml.mid_free_at(now, b), None);
    }

    #[test]
    fn a_peer_given_an_id_within_the_lifetime_is_forgotten_last() {
        let lifetime = Duration::from_secs(60);
        let mut ml = MessageLayer::new(2, lifetime);
        let now = crate::test_epoch();
        let a = peer(0);
        let mid = ml.next_mid(now, a);
        // The table fills with paths that got no ID: they go, `a` stays and goes on.
        for n in 1..=MAX_PATHS {
            ml.path(now, peer(n));
        }
        assert!(ml.paths.len() < MAX_PATHS);
        assert_eq!(ml.next_mid(now, a), mid.wrapping_add(1));
        // A lifetime later `a` may go too.
        let later = now + lifetime;
        for n in 1..=MAX_PATHS {
            ml.path(later, peer(MAX_PATHS + n));
        }
        assert!(!ml.paths.contains_key(&PeerKey(a)));
        // More peers with IDs within the lifetime than the table holds: they are
        // forgotten all the same (nothing is in flight).
        for n in 0..=MAX_PATHS {
            ml.next_mid(later, peer(3 * MAX_PATHS + n));
        }
        assert!(ml.paths.len() < MAX_PATHS);
    }
}
