//! The endpoint's datagram handling. The input is a script of operations on one
//! `coap::Endpoint` with small limits and a virtual clock (the first byte's low bit turns
//! RFC 9175 address verification on):
//!
//! | op % 6 | operation                                                                 |
//! |--------|---------------------------------------------------------------------------|
//! | 0      | a raw datagram from one of three peers (optionally "multicast")           |
//! | 1      | a reply to a request the endpoint sent: its token (and MID for an ACK),    |
//! |        | a fuzzed type and code, then fuzzed option and payload bytes               |
//! | 2      | advance the clock and call `handle_timeout`                                |
//! | 3      | start a client request (method, CON/NON, block size, body length,         |
//! |        | Observe, multicast, timeout)                                               |
//! | 4      | `respond` to a request the endpoint delivered (code, body, ETag, Observe)  |
//! | 5      | `ping` a peer, `cancel` a request or `notify` an observation               |
//!
//! After every operation all transmits and events are drained and checked: the endpoint
//! never panics, only emits datagrams that decode and fit a UDP path MTU, ends each request
//! at most once, never has more unanswered requests than its limit, and at the end
//! (every request cancelled, the clock run forward until no timer is left) has no request
//! in flight and has ended every request.

#![no_main]

use std::collections::HashSet;
use std::net::SocketAddr;
use std::time::{Duration, Instant};

use coap::endpoint::ObservationId;
use coap::msg::Message;
use coap::{
    BlockOpt, Code, Endpoint, EndpointConfig, Event, IncomingId, Limits, OptionNumber, Request,
    RequestId, Response, Type,
};
use libfuzzer_sys::fuzz_target;

/// Requests the script may start (and pings it may send).
const MAX_REQUESTS: usize = 8;
/// Largest datagram the endpoint may emit: a 1024-byte block plus header and options.
const MAX_DATAGRAM: usize = 1152;
/// Timer firings allowed for the final run-down before it counts as a livelock.
const MAX_FINAL_TIMERS: usize = 20_000;

const PEERS: [[u8; 4]; 3] = [[192, 0, 2, 1], [192, 0, 2, 2], [198, 51, 100, 7]];

fn peer(i: u8) -> SocketAddr {
    SocketAddr::from((PEERS[usize::from(i) % PEERS.len()], 5683))
}

/// `verify`: RFC 9175 address verification on (the peers are not on loopback, so their
/// requests are then challenged); off, every server path is reachable.
fn config(verify: bool) -> EndpointConfig {
    EndpointConfig {
        verify_addresses: verify,
        limits: Limits {
            dedup_entries: 32,
            dedup_bytes: 16 << 10,
            block1_peer_bytes: 4 << 10,
            block1_total_bytes: 8 << 10,
            block2_store_bytes: 16 << 10,
            blockwise_lifetime: Duration::from_secs(60),
            client_body_bytes: 16 << 10,
            pending_requests: 8,
            ..Limits::default()
        },
        ..EndpointConfig::default()
    }
}

/// A fixed epoch for the virtual clock; only offsets from it matter.
fn epoch() -> Instant {
    Instant::now()
}

fn body(len: u16, salt: u8) -> Vec<u8> {
    (0..len).map(|i| (i as u8).wrapping_mul(salt)).collect()
}

struct Cursor<'a>(&'a [u8]);

impl<'a> Cursor<'a> {
    fn byte(&mut self) -> Option<u8> {
        let (&b, rest) = self.0.split_first()?;
        self.0 = rest;
        Some(b)
    }

    fn u16(&mut self) -> Option<u16> {
        Some(u16::from_be_bytes([self.byte()?, self.byte()?]))
    }

    /// Up to `n` bytes (fewer at the end of the input).
    fn take(&mut self, n: usize) -> &'a [u8] {
        let (head, rest) = self.0.split_at(n.min(self.0.len()));
        self.0 = rest;
        head
    }
}

/// A request the endpoint sent, remembered so the script can answer it.
#[derive(Clone, Copy)]
struct Sent {
    peer: SocketAddr,
    ty: Type,
    message_id: u16,
    token: coap::Token,
}

struct Harness {
    ep: Endpoint,
    now: Instant,
    /// Most recent requests the endpoint sent (newest last), at most 8.
    sent: Vec<Sent>,
    /// Requests delivered to the application and not answered yet, with their
    /// observation if they registered one.
    incoming: Vec<(IncomingId, Option<ObservationId>)>,
    /// Observations the application accepted.
    observations: Vec<ObservationId>,
    started: Vec<RequestId>,
    /// Requests that may receive a response and keep going (Observe, multicast).
    open_ended: HashSet<RequestId>,
    /// Requests that got a response (possibly not their last event).
    answered: HashSet<RequestId>,
    /// Requests that ended: failed, ponged, multicast done, or answered once and for all.
    ended: HashSet<RequestId>,
}

impl Harness {
    fn end(&mut self, id: RequestId) {
        assert!(self.started.contains(&id), "event for unknown {id:?}");
        assert!(self.ended.insert(id), "{id:?} ended twice");
    }

    fn ongoing(&self, id: RequestId) {
        assert!(self.started.contains(&id), "event for unknown {id:?}");
        assert!(!self.ended.contains(&id), "event for {id:?} after it ended");
    }

    /// Drains and checks everything the endpoint produced.
    fn drain(&mut self) {
        while let Some(t) = self.ep.poll_transmit() {
            assert!(
                t.data.len() <= MAX_DATAGRAM,
                "{}-byte datagram to {}: {:?}",
                t.data.len(),
                t.peer,
                Message::decode(&t.data).map(|m| (m.ty, m.code, m.options))
            );
            let msg = match Message::decode(&t.data) {
                Ok(m) => m,
                Err(e) => panic!(
                    "endpoint sent an undecodable datagram ({e}): {:02x?}",
                    t.data
                ),
            };
            if msg.code.is_request() {
                if self.sent.len() == 8 {
                    self.sent.remove(0);
                }
                self.sent.push(Sent {
                    peer: t.peer,
                    ty: msg.ty,
                    message_id: msg.message_id,
                    token: msg.token,
                });
            }
        }
        while let Some(event) = self.ep.poll_event() {
            match event {
                Event::Request(req) => {
                    self.incoming.push((req.id, req.observe));
                    assert!(
                        self.incoming.len() <= self.ep.config().limits.pending_requests,
                        "more unanswered requests than the limit"
                    );
                }
                Event::Response { id, .. } => {
                    self.ongoing(id);
                    self.answered.insert(id);
                    if !self.open_ended.contains(&id) {
                        self.end(id);
                    }
                }
                Event::Notification { id, .. }
                | Event::MulticastResponse { id, .. }
                | Event::Progress { id, .. }
                | Event::BodyChunk { id, .. } => {
                    self.ongoing(id);
                }
                Event::RequestFailed { id, .. }
                | Event::Pong { id }
                | Event::MulticastDone { id } => self.end(id),
                Event::ObservationEnded { id } => self.observations.retain(|o| *o != id),
            }
        }
    }

    fn step(&mut self, op: u8, cur: &mut Cursor<'_>) -> Option<()> {
        match op % 6 {
            0 => {
                let len = usize::from(cur.u16()? % 1500);
                let data = cur.take(len);
                self.ep
                    .handle(self.now, peer(op >> 3), data, op & 0x80 != 0);
            }
            1 => {
                let sent = *self
                    .sent
                    .get(usize::from(cur.byte()?) % self.sent.len().max(1))?;
                let kind = cur.byte()?;
                let code = cur.byte()?;
                let len = usize::from(cur.u16()? % 1500);
                let rest = cur.take(len);
                // Piggybacked on the ACK of a CON, or a separate CON/NON response.
                let (ty, mid) = match (kind % 3, sent.ty) {
                    (0, Type::Con) => (2, sent.message_id),
                    (1, _) => (0, u16::from(kind) << 8 | u16::from(code)),
                    _ => (1, u16::from(kind) << 8 | u16::from(code)),
                };
                let token = sent.token.as_bytes();
                let mut data = Vec::with_capacity(4 + token.len() + rest.len());
                data.push(0x40 | (ty << 4) | token.len() as u8);
                data.push(code);
                data.extend_from_slice(&mid.to_be_bytes());
                data.extend_from_slice(token);
                data.extend_from_slice(rest);
                // A multicast request's responses come from any member of the group.
                let from = if kind & 0x80 != 0 {
                    peer(kind)
                } else {
                    sent.peer
                };
                self.ep.handle(self.now, from, &data, false);
            }
            2 => {
                let ms = u64::from(cur.u16()?) * 16;
                self.now += Duration::from_millis(ms);
                self.ep.handle_timeout(self.now);
            }
            3 => {
                let flags = cur.byte()?;
                let extra = cur.byte()?;
                let body_len = cur.u16()? % 6000;
                if self.started.len() >= MAX_REQUESTS {
                    return Some(());
                }
                let method = [Code::GET, Code::POST, Code::PUT, Code::FETCH][usize::from(op >> 6)];
                let mut req = Request::new(method, "cams/pointclouds");
                req.payload = body(body_len, 1).into();
                req.confirmable = flags & 1 == 0;
                if flags & 2 != 0 {
                    req.block_szx = Some((flags >> 2) % 7);
                }
                if flags & 0x20 != 0 {
                    req.timeout = Some(Duration::from_secs(u64::from(flags >> 6) * 30 + 5));
                }
                let observe = extra & 1 != 0;
                if observe {
                    req.options.set_uint(OptionNumber::OBSERVE, 0);
                }
                req.multicast = extra & 2 != 0;
                req.progress = extra & 8 != 0;
                req.stream = extra & 16 != 0;
                let id = self.ep.request(self.now, peer(op >> 3), req);
                self.started.push(id);
                if observe || extra & 2 != 0 {
                    self.open_ended.insert(id);
                }
            }
            4 => {
                let pick = usize::from(cur.byte()?);
                let code = cur.byte()?;
                let body_len = cur.u16()? % 6000;
                if self.incoming.is_empty() {
                    return Some(());
                }
                let (id, observation) = self.incoming.remove(pick % self.incoming.len());
                // Only response codes: the application never answers with a method.
                let code = Code::new(2 + (code >> 5) % 4, code & 0x1f);
                let mut response = Response::new(code).with_payload(body(body_len, 7));
                if op & 0x40 != 0 {
                    response.options.set(OptionNumber::ETAG, vec![op, code.0]);
                }
                if op & 0x80 != 0 {
                    response.options.set_block(
                        OptionNumber::BLOCK2,
                        BlockOpt {
                            num: u32::from(code.0 & 3),
                            more: false,
                            szx: code.0 % 7,
                        },
                    );
                }
                if op & 0x08 != 0 {
                    response.options.set_uint(OptionNumber::OBSERVE, 0);
                    if let Some(obs) = observation.filter(|_| code.is_success()) {
                        self.observations.push(obs);
                    }
                }
                self.ep.respond(self.now, id, response);
            }
            _ => match op >> 6 {
                0 | 1 => {
                    if self.started.len() < MAX_REQUESTS {
                        let id = self.ep.ping(self.now, peer(op >> 3));
                        self.started.push(id);
                    }
                }
                2 => {
                    let i = usize::from(cur.byte()?);
                    if let Some(&id) = self.started.get(i % self.started.len().max(1)) {
                        self.ep.cancel(self.now, id);
                    }
                }
                _ => {
                    let i = usize::from(cur.byte()?);
                    let code = cur.byte()?;
                    let body_len = cur.u16()? % 4000;
                    if self.observations.is_empty() {
                        return Some(());
                    }
                    let at = i % self.observations.len();
                    let code = Code::new(2 + (code >> 7) * 2, code & 0x1f);
                    let response = Response::new(code).with_payload(body(body_len, 3));
                    if !self.ep.notify(self.now, self.observations[at], response) {
                        self.observations.remove(at);
                    }
                }
            },
        }
        Some(())
    }
}

fuzz_target!(|data: &[u8]| {
    // The first byte's low bit turns address verification on.
    let verify = data.first().is_some_and(|b| b & 1 == 1);
    let mut h = Harness {
        ep: Endpoint::new(config(verify)),
        now: epoch(),
        sent: Vec::new(),
        incoming: Vec::new(),
        observations: Vec::new(),
        started: Vec::new(),
        open_ended: HashSet::new(),
        answered: HashSet::new(),
        ended: HashSet::new(),
    };
    let mut cur = Cursor(data);
    while let Some(op) = cur.byte() {
        let more = h.step(op, &mut cur);
        h.drain();
        if more.is_none() {
            break;
        }
    }
    // Cancel what is left (observations never end by themselves), then run the clock
    // forward: every timer must eventually fire and leave nothing behind.
    for id in h.started.clone() {
        h.ep.cancel(h.now, id);
        h.drain();
    }
    let mut fired = 0;
    while let Some(at) = h.ep.poll_timeout() {
        fired += 1;
        assert!(fired <= MAX_FINAL_TIMERS, "timers never run out");
        h.now = h.now.max(at);
        h.ep.handle_timeout(h.now);
        h.drain();
    }
    assert_eq!(
        h.ep.requests_in_flight(),
        0,
        "requests left after every timer fired"
    );
    for id in &h.started {
        assert!(
            h.ended.contains(id) || h.answered.contains(id),
            "{id:?} never ended"
        );
    }
});
