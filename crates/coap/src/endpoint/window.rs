//! A windowed Block2 download: which blocks to ask for, which requests are in flight,
//! which are lost, and the blocks that arrived ahead of the next one to deliver.
//!
//! Every block of a representation can be asked for on its own (RFC 7959 §2.4), so after
//! block 0 the client asks for many blocks at once, as NON requests that the peer's
//! congestion controller (`congestion`) admits and paces; up to the last block Size2 implies,
//! or, without Size2, until a block comes without `more`. Each request is one
//! *transmission* with a sequence number; a block asked for again gets a new one. Loss is
//! found by time, as RACK finds it (RFC 8985): a request is lost when one sent after it
//! has been answered and it is older than the *loss delay*, `SRTT + 4 RTTVAR` plus an
//! eighth, growing by another eighth (to at most twice) each time a block declared lost
//! arrives after all (the path reorders); a probe timeout covers the tail. Blocks are
//! delivered in order; those that arrive early wait in a buffer of at most [`MAX_AHEAD`]
//! blocks, which also bounds how far ahead of the next block to deliver a request may
//! reach.

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, Instant};

use super::congestion::SendState;
use crate::peer_key::FastMap;

/// Blocks a download may ask for beyond the next one it delivers (4 MiB of 1 KiB
/// blocks). Behind a lost block the others wait for it a loss delay and a round trip or
/// more (its request may be lost again), so the buffer must hold several
/// bandwidth-delay products: with 1 MiB, 10 MB through 100 ms and 5 % loss took 12 s
/// (QUIC 2 s), with 4 MiB 2.5 s.
pub(super) const MAX_AHEAD: u32 = 4096;

/// One block request on the wire.
#[derive(Debug, Clone, Copy)]
struct Tx {
    num: u32,
    /// The block was asked for before (its round trip is ambiguous).
    again: bool,
    state: SendState,
}

/// What a download reports, and the endpoint sums per peer.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) struct TransferStats {
    /// Block requests sent, including those sent again.
    pub(super) requests: u64,
    /// Requests declared lost (a block asked for again).
    pub(super) lost: u64,
    /// Blocks that arrived after their request was declared lost (spurious losses).
    pub(super) late: u64,
    /// Blocks that arrived twice.
    pub(super) duplicates: u64,
    /// The most requests in flight at once.
    pub(super) max_window: u64,
}

/// What happened to an arriving block.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Arrival {
    /// Delivered already or waiting ahead: drop it.
    Duplicate,
    /// The next block to deliver.
    Next,
    /// A later block: keep it for later.
    Ahead,
}

/// The largest block number (20 bits, RFC 7959 §2.2).
const MAX_BLOCK: u32 = (1 << 20) - 1;

/// The state of one windowed download.
#[derive(Debug)]
pub(super) struct Window {
    /// The number of the last block (the largest possible one until it is known).
    last: u32,
    /// Whether `last` is known (from Size2, or a block without `more`).
    last_known: bool,
    /// The next block never asked for.
    next_new: u32,
    /// The next block to deliver.
    next_deliver: u32,
    /// Blocks that arrived ahead of `next_deliver`.
    ahead: BTreeMap<u32, Vec<u8>>,
    /// Requests in flight, by sequence number.
    in_flight: BTreeMap<u64, Tx>,
    /// The sequence number of each block's request in flight.
    outstanding: FastMap<u32, u64>,
    /// Blocks whose request was lost, to ask for again (lowest first).
    lost: BTreeSet<u32>,
    /// The latest-sent request answered so far.
    largest_answered: u64,
    seq: u64,
    /// When the earliest in-flight request becomes lost by the time threshold.
    loss_at: Option<Instant>,
    /// The probe timer's origin: the last arrival or probe.
    pub(super) last_arrival: Instant,
    /// The last time a block arrived (or the window started).
    pub(super) heard: Instant,
    /// Probe timeouts in a row without an arrival.
    pub(super) probes: u32,
    pub(super) stats: TransferStats,
}

impl Window {
    /// A download of blocks `1..=last` (block 0 arrived already; `None`: the size is not
    /// known, blocks are asked for until one comes without `more`), at `now`.
    pub(super) fn new(now: Instant, last: Option<u32>) -> Self {
        Self {
            last: last.unwrap_or(MAX_BLOCK),
            last_known: last.is_some(),
            next_new: 1,
            next_deliver: 1,
            ahead: BTreeMap::new(),
            in_flight: BTreeMap::new(),
            outstanding: FastMap::default(),
            lost: BTreeSet::new(),
            largest_answered: 0,
            seq: 0,
            loss_at: None,
            last_arrival: now,
            heard: now,
            probes: 0,
            stats: TransferStats::default(),
        }
    }

    /// The block to ask for next, if any: a lost one first, then the next new one
    /// within [`MAX_AHEAD`] of the next to deliver.
    pub(super) fn next_block(&self) -> Option<u32> {
        if let Some(&num) = self.lost.first() {
            return Some(num);
        }
        let reach = self.next_deliver.saturating_add(MAX_AHEAD);
        (self.next_new <= self.last && self.next_new < reach).then_some(self.next_new)
    }

    /// Records the request for `num` just sent.
    pub(super) fn on_sent(&mut self, num: u32, state: SendState) {
        if self.in_flight.is_empty() {
            // Nothing was awaited until now (the window waited for pacing or message
            // IDs): the probe timer and the give-up start from here.
            self.last_arrival = state.sent();
            self.heard = state.sent();
        }
        self.seq += 1;
        self.lost.remove(&num);
        let again = num < self.next_new;
        self.next_new = self.next_new.max(num + 1);
        self.in_flight.insert(self.seq, Tx { num, again, state });
        self.outstanding.insert(num, self.seq);
        self.stats.requests += 1;
        self.stats.max_window = self.stats.max_window.max(self.in_flight.len() as u64);
    }

    /// Whether requests are in flight (answers are awaited).
    pub(super) fn awaiting(&self) -> bool {
        !self.in_flight.is_empty()
    }

    /// Whether every block has been delivered.
    pub(super) fn complete(&self) -> bool {
        self.next_deliver > self.last
    }

    /// Block `num` arrived at `now`; `rtt` is the path's `SRTT + 4 RTTVAR`.
    /// Returns what to do with it and, if its request was in flight (not declared lost),
    /// the request's send state and its round trip if unambiguous (Karn); `lost` is
    /// called for each request this arrival shows lost.
    pub(super) fn on_block(
        &mut self,
        now: Instant,
        num: u32,
        rtt: Duration,
        mut lost: impl FnMut(),
    ) -> (Arrival, Option<(SendState, Option<Duration>)>) {
        // The request this answers, if it is still in flight (a duplicate answers one
        // too: the block's request sent again after a false alarm).
        let tx = self.outstanding.remove(&num).and_then(|seq| {
            let tx = self.in_flight.remove(&seq);
            self.detect_lost(now, seq, rtt, &mut lost);
            tx
        });
        if num < self.next_deliver || num > self.last || self.ahead.contains_key(&num) {
            self.stats.duplicates += 1;
            return (Arrival::Duplicate, tx.map(|tx| (tx.state, None)));
        }
        self.last_arrival = now;
        self.heard = now;
        self.probes = 0;
        let sample = tx.map(|tx| {
            let rtt = (!tx.again).then(|| now.saturating_duration_since(tx.state.sent()));
            (tx.state, rtt)
        });
        if sample.is_none() && self.lost.remove(&num) {
            // Declared lost before and not asked for again yet.
            self.stats.late += 1;
        }
        let arrival = if num == self.next_deliver {
            Arrival::Next
        } else {
            Arrival::Ahead
        };
        (arrival, sample)
    }

    /// The loss delay for a path whose `SRTT + 4 RTTVAR` is `rtt`.
    fn loss_delay(&self, rtt: Duration) -> Duration {
        rtt * (9 + self.stats.late.min(7) as u32) / 8
    }

    /// Requests sent before the latest answered one (`seq` or before) that are older
    /// than the loss delay are lost.
    fn detect_lost(&mut self, now: Instant, seq: u64, rtt: Duration, lost: &mut impl FnMut()) {
        self.largest_answered = self.largest_answered.max(seq);
        let delay = self.loss_delay(rtt);
        let gone: Vec<u64> = self
            .in_flight
            .range(..self.largest_answered)
            .filter(|(_, tx)| tx.state.sent() + delay <= now)
            .map(|(&s, _)| s)
            .collect();
        for s in gone {
            self.declare_lost(s);
            lost();
        }
        self.set_loss_time(rtt);
    }

    /// The time the earliest request sent before the latest answered one becomes lost.
    fn set_loss_time(&mut self, rtt: Duration) {
        self.loss_at = self
            .in_flight
            .range(..self.largest_answered)
            .next()
            .map(|(_, tx)| tx.state.sent() + self.loss_delay(rtt));
    }

    fn declare_lost(&mut self, seq: u64) {
        if let Some(tx) = self.in_flight.remove(&seq) {
            self.outstanding.remove(&tx.num);
            self.lost.insert(tx.num);
            self.stats.lost += 1;
        }
    }

    /// The last block's number, if known.
    pub(super) fn last(&self) -> Option<u32> {
        self.last_known.then_some(self.last)
    }

    /// Block `last` came without `more`: requests for blocks after it (answered with
    /// 4.02, RFC 7959 §2.2) are forgotten. Returns how many were in flight.
    pub(super) fn set_last(&mut self, last: u32) -> usize {
        self.last = last;
        self.last_known = true;
        self.lost.retain(|&num| num <= last);
        self.outstanding.retain(|&num, _| num <= last);
        let before = self.in_flight.len();
        self.in_flight.retain(|_, tx| tx.num <= last);
        before - self.in_flight.len()
    }

    /// Keeps a block that arrived ahead of the next to deliver.
    pub(super) fn keep(&mut self, num: u32, payload: &[u8]) {
        self.ahead.insert(num, payload.to_vec());
    }

    /// The next block was delivered; returns the block after it if it is waiting.
    pub(super) fn delivered(&mut self) -> Option<Vec<u8>> {
        self.next_deliver += 1;
        self.ahead.remove(&self.next_deliver)
    }

    /// When the window's timer should fire: the loss time, else the probe timeout.
    pub(super) fn timer(&self, pto: Duration) -> Option<Instant> {
        if self.in_flight.is_empty() {
            return None;
        }
        let probe = self.last_arrival + pto * (1 << self.probes.min(6));
        Some(self.loss_at.map_or(probe, |at| at.min(probe)))
    }

    /// The timer fired at `now`: requests past the time threshold are lost; when the
    /// probe timeout passed, so is every request older than it (at least the oldest).
    /// Returns how many were declared lost.
    pub(super) fn on_timer(&mut self, now: Instant, rtt: Duration, pto: Duration) -> usize {
        let delay = self.loss_delay(rtt);
        let mut gone: BTreeSet<u64> = self
            .in_flight
            .range(..self.largest_answered)
            .filter(|(_, tx)| tx.state.sent() + delay <= now)
            .map(|(&s, _)| s)
            .collect();
        let probe_due = self
            .timer(pto)
            .is_some_and(|_| self.last_arrival + pto * (1 << self.probes.min(6)) <= now);
        if probe_due {
            self.probes += 1;
            self.last_arrival = now;
            let old = self
                .in_flight
                .iter()
                .filter(|(_, tx)| tx.state.sent() + pto <= now);
            gone.extend(old.map(|(&s, _)| s));
            if gone.is_empty() {
                gone.extend(self.in_flight.keys().next());
            }
        }
        for &s in &gone {
            self.declare_lost(s);
        }
        self.set_loss_time(rtt);
        gone.len()
    }

    /// Requests in flight (forgotten when the transfer ends).
    pub(super) fn abandon(&mut self) -> usize {
        let n = self.in_flight.len();
        self.in_flight.clear();
        n
    }
}
