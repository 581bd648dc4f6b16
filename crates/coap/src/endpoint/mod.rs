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
//! Layers, one module each, each with its own state in [`Endpoint`]; the client and
//! server layers are types with their own behaviour, acting on a `Context` that lends
//! them the message layer, the configuration and the event queue:
//! - `message`: message IDs, timers, CON retransmission with exponential back-off,
//!   deduplication, the outbox, and the path to each peer (round-trip estimate,
//!   congestion controller, counters). It knows nothing of requests.
//! - `client`: requests this endpoint sends (tokens, transparent Block1 upload and Block2
//!   reassembly that resumes from the block it lacks, Observe, multicast), admitted per
//!   peer by NSTART (`congestion`).
//! - `window` and `download`: a Block2 download with many block requests in flight,
//!   paced by the path's congestion controller (`congestion`: BBR unless
//!   `EndpointConfig::congestion` says NSTART), lost ones asked for again.
//! - `server`: requests it receives, in stages (a duplicate, `verify`'s check of the
//!   peer's address (RFC 9175 Echo, amplification limits), bad options, Q-Block, Block2
//!   slicing from a stored representation, Block1 assembly, then the application),
//!   piggybacked or separate responses, observations it serves, Leisure.
//! - `types`: what the owner sees (requests, responses, events, errors).
//!
//! This file owns the entry points and routes between the layers: a datagram's ACK or
//! Reset to the purpose of its CON, a timer to its layer. `client` and `server` use
//! `message` (through `context`); `message` uses neither, and neither uses the other.
//!
//! A client request is a sequence of *steps*, one message exchange each, one at a time;
//! a windowed download is the exception, its block requests in flight together (the
//! message layer is the same for both).

mod client;
mod client_state;
mod congestion;
mod context;
mod download;
mod message;
mod qblock;
mod qclient;
mod qserver;
mod reply;
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
pub use congestion::RoundTrace;
pub use types::{
    Event, IncomingId, IncomingRequest, ObservationId, PathStats, Request, RequestError, RequestId,
    Response, ServerStats, Transmit,
};

use crate::config::EndpointConfig;
use crate::dedup::{Fingerprint, Seen};
use crate::msg::{Message, Reaction, Type};
use crate::peer_key::{MidKey, PeerKey};
use client_state::ClientLayer;
use context::Context;
use message::{MessageLayer, Purpose, TimerKind};
use server_state::{Incoming, ServerLayer};

/// A CoAP endpoint. See the module documentation for the driving protocol.
pub struct Endpoint {
    config: EndpointConfig,
    msg: MessageLayer,
    client: ClientLayer,
    server: ServerLayer,
    next_id: u64,
    events: VecDeque<Event>,
}

impl Endpoint {
    /// A new endpoint. All randomness comes from `config.rng_seed`, but for the key of its
    /// Echo values, which must be unpredictable (`verify`).
    pub fn new(config: EndpointConfig) -> Self {
        Self {
            msg: MessageLayer::new(config.rng_seed, config.exchange_lifetime),
            client: ClientLayer::default(),
            server: ServerLayer::new(),
            config,
            next_id: 1,
            events: VecDeque::new(),
        }
    }

    /// The layers, with the context they act on.
    fn parts(&mut self) -> (Context<'_>, &mut ClientLayer, &mut ServerLayer) {
        let cx = Context::new(
            &self.config,
            &mut self.msg,
            &mut self.events,
            &mut self.next_id,
        );
        (cx, &mut self.client, &mut self.server)
    }

    /// The configuration.
    pub fn config(&self) -> &EndpointConfig {
        &self.config
    }

    /// Starts a request to `peer`. The outcome arrives as [`Event::Response`] or
    /// [`Event::RequestFailed`] with the returned id.
    pub fn request(&mut self, now: Instant, peer: SocketAddr, req: Request) -> RequestId {
        let (mut cx, client, _) = self.parts();
        client.request(&mut cx, now, peer, req)
    }

    /// Tells the endpoint a round trip to `peer` remembered from before (another
    /// process's estimate, as TCP's metrics cache keeps one per destination), so that its
    /// first CON times out after about `SRTT + max(4 RTTVAR, 100 ms)` instead of
    /// ACK_TIMEOUT. Taken only while the path has no estimate of its own, and as a weak
    /// sample: the first measured round trip replaces it entirely.
    pub fn remember_rtt(&mut self, now: Instant, peer: SocketAddr, rtt: std::time::Duration) {
        let path = self.msg.path(now, peer);
        if path.rtt.srtt().is_none() && !rtt.is_zero() {
            path.rtt.on_sample(now, rtt, false);
        }
    }

    /// Sends a CoAP ping (an empty CON, RFC 7252 §4.3): [`Event::Pong`] when the peer
    /// answers with a Reset, [`Event::RequestFailed`] after MAX_RETRANSMIT.
    pub fn ping(&mut self, now: Instant, peer: SocketAddr) -> RequestId {
        let (mut cx, client, _) = self.parts();
        client.ping(&mut cx, now, peer)
    }

    /// Abandons a request; [`Event::RequestFailed`] with [`RequestError::Cancelled`]
    /// follows if it was still running.
    pub fn cancel(&mut self, now: Instant, id: RequestId) {
        let (mut cx, client, _) = self.parts();
        client.cancel(&mut cx, now, id);
    }

    /// Answers a request from [`Event::Request`]. A body larger than one block is stored
    /// and sent with Block2 (ETag and Size2 added); later blocks are served from the store.
    /// Answering an unknown or already answered id does nothing.
    /// The answer to a multicast request waits for the end of its leisure (RFC 7252
    /// §8.2), held by the endpoint.
    pub fn respond(&mut self, now: Instant, id: IncomingId, response: Response) {
        let (mut cx, _, server) = self.parts();
        server.respond(&mut cx, now, id, response);
    }

    /// Sends a notification to an established observation (RFC 7641 §4.2): the Observe
    /// sequence number goes up by one, every `notify_con_interval`-th notification is a CON
    /// (§4.5), and a body larger than one block goes out as Block2 block 0 with the rest
    /// kept for the client's continuations (RFC 7959 §2.6). While a CON notification is
    /// unacknowledged the next waits, only the newest kept, and goes on the ACK (§4.5.2:
    /// one in flight; an observer that stopped answering costs one retransmitted
    /// notification, not one per change); the CON's timeout ends the observation. A
    /// non-success response ends the observation. Returns false when the observation no
    /// longer exists, so the application can forget it.
    pub fn notify(&mut self, now: Instant, id: ObservationId, response: Response) -> bool {
        let (mut cx, _, server) = self.parts();
        server.notify(&mut cx, now, id, response)
    }

    /// The network says nothing listens at `peer` (an ICMP port unreachable for a datagram
    /// sent to it): the observations it had end, each with [`Event::ObservationEnded`], as
    /// when it rejects a notification (RFC 7641 §3.6), rather than when a confirmable
    /// notification goes unacknowledged after every retransmission.
    pub fn peer_unreachable(&mut self, peer: SocketAddr) {
        let (mut cx, _, server) = self.parts();
        server.end_observations_of(&mut cx, peer);
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
            TimerKind::QClient { id, at } => self.client.qclient_timer_is(id, at),
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

    /// The next round trip a path's congestion controller recorded, with the peer, when
    /// [`EndpointConfig::trace_congestion`] is on (each path's rounds oldest first; a
    /// path keeps its last 4,096 untaken rounds).
    pub fn poll_round_trace(&mut self) -> Option<(SocketAddr, RoundTrace)> {
        if !self.config.trace_congestion {
            return None;
        }
        self.msg.paths.iter_mut().find_map(|(peer, path)| {
            let round = path.existing_controller()?.poll_round()?;
            Some((peer.0, round))
        })
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
            let (mut cx, client, server) = self.parts();
            let cx = &mut cx;
            match kind {
                TimerKind::Retransmit { peer, mid, tx } => {
                    let max = cx.config.max_retransmit;
                    if let Some(purpose) = cx.msg.on_retransmit_timer(now, peer, mid, tx, max) {
                        exchange_failed(cx, client, server, now, purpose);
                    }
                }
                TimerKind::RequestAck { id, at } => client.on_request_ack_timer(cx, now, id, at),
                TimerKind::Step { id, generation } => client.on_step_timer(cx, now, id, generation),
                TimerKind::Window { id, at } => client.on_window_timer(cx, now, id, at),
                TimerKind::Deadline { id } => client.on_deadline(cx, now, id),
                TimerKind::SeparateAck { id } => server.ack_pending(cx, id),
                TimerKind::Leisure { id } => server.on_leisure_timer(cx, now, id),
                TimerKind::QClient { id, at } => client.on_qclient_timer(cx, now, id, at),
                TimerKind::QSet { id, at } => server.on_qset_timer(cx, now, id, at),
                TimerKind::QReceive { id, at } => server.on_qreceive_timer(cx, now, id, at),
                TimerKind::Sweep { at } => server.on_sweep_timer(cx, now, at),
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
                let (mut cx, _, server) = self.parts();
                let mut req = Incoming::read(cx.config, now, peer, msg, payload, multicast);
                server.on_request(&mut cx, now, &mut req, data.len());
            }
            Type::Con | Type::Non if msg.code.is_response() => {
                self.on_separate_response(now, peer, &mut msg, payload)
            }
            // An empty NON is a format error (§4.3); unknown code classes are ignored.
            Type::Con | Type::Non => {}
        }
    }

    fn on_ack_or_reset(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        msg: &mut Message,
        payload: &[u8],
    ) {
        let (mut cx, client, server) = self.parts();
        let cx = &mut cx;
        // ACK and RST are matched by message ID only (RFC 7252 §4.2, §4.3); an unknown one
        // is ignored.
        let Some(x) = cx.msg.exchanges.remove(&MidKey(peer, msg.message_id)) else {
            if msg.ty == Type::Rst {
                // A Reset to a NON notification ends the observation (RFC 7641 §3.6).
                if let Some(id) = server.notified_with(peer, msg.message_id) {
                    server.end_observation(cx, id);
                }
            }
            return;
        };
        cx.msg.on_acknowledged(now, peer, x.first_sent, x.tx);
        match x.purpose {
            Purpose::Ping(id) => cx.events.push_back(Event::Pong { id: RequestId(id) }),
            Purpose::SeparateResponse => {}
            Purpose::Notification(obs) if msg.ty == Type::Rst => server.end_observation(cx, obs),
            Purpose::Notification(obs) => server.on_notification_acked(cx, now, obs),
            Purpose::Request(id) => client.on_request_ack(cx, now, id, msg, payload),
        }
    }

    /// A CON or NON response (not piggybacked): acknowledged, or rejected when it matches
    /// no request, remembered for its duplicates, then the client's.
    fn on_separate_response(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        msg: &mut Message,
        payload: &[u8],
    ) {
        let (mut cx, client, server) = self.parts();
        let cx = &mut cx;
        let known = client.by_token.get(&msg.token).copied();
        if server.replay_duplicate(cx, now, peer, msg) {
            return;
        }
        let lifetime = if msg.ty == Type::Con {
            cx.config.exchange_lifetime
        } else {
            cx.config.non_lifetime
        };
        let seen = match (known, msg.ty) {
            // RFC 7252 §5.3.2: a response we cannot match is rejected with a Reset.
            (None, _) => cx
                .msg
                .reply_with(peer, Message::empty(Type::Rst, msg.message_id)),
            (Some(_), Type::Con) => cx
                .msg
                .reply_with(peer, Message::empty(Type::Ack, msg.message_id)),
            (Some(_), _) => Seen::Silent,
        };
        let key = (peer, msg.message_id);
        let limits = cx.limits();
        (cx.msg.dedup).insert(now, key, Fingerprint::of(msg), now + lifetime, seen, limits);
        let Some(id) = known else { return };
        client.on_separate_response_to(cx, now, id, peer, msg, payload);
    }
}

/// A CON given up after MAX_RETRANSMIT, routed by its purpose.
fn exchange_failed(
    cx: &mut Context<'_>,
    client: &mut ClientLayer,
    server: &mut ServerLayer,
    now: Instant,
    purpose: Purpose,
) {
    match purpose {
        Purpose::Request(id) => client.step_failed(cx, now, id, RequestError::Timeout),
        Purpose::Ping(id) => {
            cx.events.push_back(Event::RequestFailed {
                id: RequestId(id),
                error: RequestError::Timeout,
            });
        }
        Purpose::SeparateResponse => {}
        Purpose::Notification(obs) => server.end_observation(cx, obs),
    }
}
