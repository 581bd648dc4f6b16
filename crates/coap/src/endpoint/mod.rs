//! The endpoint: one CoAP endpoint (one socket's worth of peers), driven as quinn-proto is.
//!
//! Inputs: [`Endpoint::handle`] (a datagram), [`Endpoint::handle_timeout`],
//! [`Endpoint::request`], [`Endpoint::respond`], [`Endpoint::ping`], [`Endpoint::cancel`].
//! Outputs: [`Endpoint::poll_transmit`], [`Endpoint::poll_timeout`], [`Endpoint::poll_event`].
//!
//! Call order: after any input, drain `poll_transmit` and `poll_event`, then sleep until
//! `poll_timeout` and call `handle_timeout`. A `handle_timeout` before anything is due is a
//! no-op, so spurious wake-ups are harmless.
//!
//! Layers, one module each, each with its own state in [`Endpoint`]:
//! - `message`: message IDs, timers, CON retransmission with exponential back-off,
//!   deduplication, the outbox, and the path to each peer (round-trip estimate,
//!   congestion controller, counters). It knows nothing of requests.
//! - `client`: requests this endpoint sends (tokens, transparent Block1 upload and Block2
//!   reassembly that resumes from the block it lacks, Observe, multicast), admitted per
//!   peer by NSTART (`congestion`).
//! - `window` and `download`: a Block2 download with many block requests in flight,
//!   paced by the path's congestion controller (`congestion`: BBR unless
//!   `EndpointConfig::congestion` says NSTART), lost ones asked for again.
//! - `server`: requests it receives (Block1 assembly, Block2 slicing from a stored
//!   representation, piggybacked or separate responses, observations it serves), after
//!   `verify` has checked the peer's address (RFC 9175 Echo, amplification limits).
//! - `types`: what the owner sees (requests, responses, events, errors).
//!
//! This file owns the entry points and routes between the layers: a datagram's ACK or
//! Reset to the purpose of its CON, a timer to its layer. `client` and `server` use
//! `message`; `message` uses neither.
//!
//! A client request is a sequence of *steps*, one message exchange each, one at a time;
//! a windowed download is the exception, its block requests in flight together (the
//! message layer is the same for both).

mod client;
mod client_state;
mod congestion;
mod download;
mod message;
mod qblock;
mod qclient;
mod qserver;
mod server;
mod server_state;
mod types;
mod verify;
mod window;

use std::cmp::Reverse;
use std::collections::VecDeque;
use std::net::SocketAddr;
use std::time::Instant;

pub use crate::config::Transfer;
pub use types::{
    Event, IncomingId, IncomingRequest, ObservationId, PathStats, Request, RequestError, RequestId,
    Response, ServerStats, Transmit,
};

use crate::config::EndpointConfig;
use crate::dedup::{Fingerprint, Seen};
use crate::msg::{Message, Reaction, Type};
use crate::peer_key::{MidKey, PeerKey};
use client_state::{ClientLayer, Waiting};
use message::{MessageLayer, Purpose, TimerKind};
use server_state::ServerLayer;
use verify::AddressCheck;

/// A CoAP endpoint. See the module documentation for the driving protocol.
pub struct Endpoint {
    config: EndpointConfig,
    msg: MessageLayer,
    client: ClientLayer,
    server: ServerLayer,
    verify: AddressCheck,
    next_id: u64,
    events: VecDeque<Event>,
}

impl Endpoint {
    /// A new endpoint. All randomness comes from `config.rng_seed`, but for the key of its
    /// Echo values, which must be unpredictable (`verify`).
    pub fn new(config: EndpointConfig) -> Self {
        Self {
            msg: MessageLayer::new(config.rng_seed),
            client: ClientLayer::default(),
            server: ServerLayer::new(),
            verify: AddressCheck::new(),
            config,
            next_id: 1,
            events: VecDeque::new(),
        }
    }

    /// The configuration.
    pub fn config(&self) -> &EndpointConfig {
        &self.config
    }

    /// The next datagram to send.
    pub fn poll_transmit(&mut self) -> Option<Transmit> {
        self.msg.outbox.queue.pop_front()
    }

    /// When [`Endpoint::handle_timeout`] should be called next. Timers that would do
    /// nothing when they fire (the retransmission of a message already acknowledged, the
    /// step of a request that moved on) are dropped first, so a long transfer does not
    /// wake its owner once more per block, ACK_TIMEOUT after each acknowledgement.
    pub fn poll_timeout(&mut self) -> Option<Instant> {
        while let Some(Reverse((at, _, kind))) = self.msg.timers.peek().copied() {
            if self.timer_is_live(kind) {
                return Some(at);
            }
            self.msg.timers.pop();
        }
        None
    }

    /// Whether firing this timer now would do anything (the handlers' own checks).
    fn timer_is_live(&self, kind: TimerKind) -> bool {
        match kind {
            TimerKind::Retransmit { peer, mid, tx } => self
                .msg
                .exchanges
                .get(&MidKey(peer, mid))
                .is_some_and(|x| x.tx == tx),
            TimerKind::RequestAck { id, at } => self.client.ack_timer_is(id, at),
            TimerKind::Step { id, generation } => self.client.step_is(id, generation),
            TimerKind::Window { id, at } => self.client.window_timer_is(id, at),
            TimerKind::Deadline { id } => self.client.requests.contains_key(&id),
            TimerKind::SeparateAck { id } => self.server.awaits_separate_ack(id),
            TimerKind::Leisure { id } => self.server.held.contains_key(&id),
            TimerKind::QClient { id, at } => self.qclient_timer_is(id, at),
            TimerKind::QSet { id, at } => self.server.qsends.get(&id).is_some_and(|q| q.at == at),
            TimerKind::QReceive { id, at } => self
                .server
                .quploads
                .get(&id)
                .is_some_and(|u| u.at == at && !u.done),
            TimerKind::Sweep { at } => self.server.sweep_at == Some(at),
        }
    }

    /// The next event.
    pub fn poll_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    /// What this endpoint knows of the path to `peer` (its round trip, what its windowed
    /// transfers counted), if it has exchanged anything with it.
    pub fn path_stats(&self, peer: SocketAddr) -> Option<PathStats> {
        self.msg.paths.get(&PeerKey(peer)).map(message::Path::stats)
    }

    /// What the server side holds now.
    pub fn server_stats(&self) -> ServerStats {
        ServerStats {
            upload_bytes: self.server.block1.total_bytes(),
            stored_bytes: self.server.block2.bytes(),
            pending: self.server.unanswered(),
            observations: self.server.observations.len(),
        }
    }

    /// Requests in progress or queued (client side).
    pub fn requests_in_flight(&self) -> usize {
        self.client.requests.len()
    }

    /// Fires every timer due at `now`.
    pub fn handle_timeout(&mut self, now: Instant) {
        while let Some(Reverse((at, _, kind))) = self.msg.timers.peek().copied() {
            if at > now {
                break;
            }
            self.msg.timers.pop();
            match kind {
                TimerKind::Retransmit { peer, mid, tx } => {
                    let max = self.config.max_retransmit;
                    if let Some(purpose) = self.msg.on_retransmit_timer(now, peer, mid, tx, max) {
                        self.on_exchange_failed(now, purpose);
                    }
                }
                TimerKind::RequestAck { id, at } => self.on_request_ack_timer(now, id, at),
                TimerKind::Step { id, generation } => self.on_step_timer(now, id, generation),
                TimerKind::Window { id, at } => self.on_window_timer(now, id, at),
                TimerKind::Deadline { id } => match self.client.waiting(id) {
                    Some(Waiting::Collecting) => {
                        self.finish(now, id);
                        self.events
                            .push_back(Event::MulticastDone { id: RequestId(id) });
                    }
                    // An established observation outlives the timeout, which bounds
                    // the wait for the registration's answer.
                    Some(Waiting::Observing(_)) | None => {}
                    Some(_) => self.fail(now, id, RequestError::Timeout),
                },
                TimerKind::SeparateAck { id } => self.on_separate_ack_timer(now, id),
                TimerKind::Leisure { id } => self.on_leisure_timer(now, id),
                TimerKind::QClient { id, at } => self.on_qclient_timer(now, id, at),
                TimerKind::QSet { id, at } => self.on_qset_timer(now, id, at),
                TimerKind::QReceive { id, at } => self.on_qreceive_timer(now, id, at),
                TimerKind::Sweep { at } => self.on_sweep_timer(now, at),
            }
        }
    }

    /// Takes one received datagram. `multicast` says it was addressed to a multicast group
    /// (then no error responses and no Resets are sent, RFC 7390 §2.7).
    pub fn handle(&mut self, now: Instant, peer: SocketAddr, data: &[u8], multicast: bool) {
        let mut msg = Message::empty(Type::Con, 0);
        let payload = match msg.decode_in_place(data) {
            Ok(payload) => payload,
            Err(e) => {
                if let (Reaction::Reset(mid), false) = (Reaction::from(&e), multicast) {
                    self.msg.send(peer, &Message::empty(Type::Rst, mid));
                }
                return;
            }
        };
        match msg.ty {
            // Passed on by reference: a message with its inline options is a few hundred
            // bytes, and each move would copy them. A response's payload stays in the
            // datagram until it is copied where it goes (into a body being reassembled).
            Type::Ack | Type::Rst => self.on_ack_or_reset(now, peer, &mut msg, payload),
            Type::Con if msg.code.is_empty() => {
                // CoAP ping (RFC 7252 §4.3): an empty CON is answered with a Reset.
                if !multicast {
                    self.msg
                        .send(peer, &Message::empty(Type::Rst, msg.message_id));
                }
            }
            Type::Con | Type::Non if msg.code.is_request() => {
                self.on_request(now, peer, msg, payload, data.len(), multicast);
            }
            Type::Con | Type::Non if msg.code.is_response() => {
                self.on_separate_response(now, peer, &mut msg, payload)
            }
            // An empty NON is a format error (§4.3); unknown code classes are ignored.
            Type::Con | Type::Non => {}
        }
    }

    /// A new id for a request, a ping, a received request or an observation.
    fn new_id(&mut self) -> u64 {
        self.next_id += 1;
        self.next_id
    }

    /// A CON given up after MAX_RETRANSMIT, routed by its purpose.
    fn on_exchange_failed(&mut self, now: Instant, purpose: Purpose) {
        match purpose {
            Purpose::Request(id) => self.step_failed(now, id, RequestError::Timeout),
            Purpose::Ping(id) => {
                self.events.push_back(Event::RequestFailed {
                    id: RequestId(id),
                    error: RequestError::Timeout,
                });
            }
            Purpose::SeparateResponse => {}
            Purpose::Notification(obs) => self.end_observation(obs),
        }
    }

    fn on_ack_or_reset(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        msg: &mut Message,
        payload: &[u8],
    ) {
        // ACK and RST are matched by message ID only (RFC 7252 §4.2, §4.3); an unknown one
        // is ignored.
        let Some(x) = self.msg.exchanges.remove(&MidKey(peer, msg.message_id)) else {
            if msg.ty == Type::Rst {
                // A Reset to a NON notification ends the observation (RFC 7641 §3.6).
                if let Some(id) = self.server.notified_with(peer, msg.message_id) {
                    self.end_observation(id);
                }
            }
            return;
        };
        self.msg.on_acknowledged(now, peer, x.first_sent, x.tx);
        match x.purpose {
            Purpose::Ping(id) => self.events.push_back(Event::Pong { id: RequestId(id) }),
            Purpose::SeparateResponse => {}
            Purpose::Notification(obs) => {
                if msg.ty == Type::Rst {
                    return self.end_observation(obs);
                }
                // Acknowledged: the notification that waited for it goes now.
                let Some(o) = self.server.observations.get_mut(&obs) else {
                    return;
                };
                o.in_flight = false;
                if let Some(next) = o.queued.take() {
                    self.notify(now, ObservationId(obs), next);
                }
            }
            Purpose::Request(id) => self.on_request_ack(now, id, msg, payload),
        }
    }

    /// A CON or NON response (not piggybacked).
    fn on_separate_response(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        msg: &mut Message,
        payload: &[u8],
    ) {
        let limits = self.config.limits.clone();
        let known = self.client.by_token.get(&msg.token).copied();
        if self.replay_duplicate(now, peer, msg, &limits) {
            return;
        }
        let lifetime = if msg.ty == Type::Con {
            self.config.exchange_lifetime
        } else {
            self.config.non_lifetime
        };
        let seen = match (known, msg.ty) {
            // RFC 7252 §5.3.2: a response we cannot match is rejected with a Reset.
            (None, _) => self.reply_with(peer, Message::empty(Type::Rst, msg.message_id)),
            (Some(_), Type::Con) => {
                self.reply_with(peer, Message::empty(Type::Ack, msg.message_id))
            }
            (Some(_), _) => Seen::Silent,
        };
        self.msg.dedup.insert(
            now,
            (peer, msg.message_id),
            Fingerprint::of(msg),
            now + lifetime,
            seen,
            &limits,
        );
        let Some(id) = known else { return };
        self.on_separate_response_to(now, id, peer, msg, payload);
    }
}
