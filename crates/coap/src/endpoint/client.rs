//! The client side's behaviour: requests this endpoint sends, step by step (the state is
//! in `client_state`).

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use bytes::Bytes;
use rand_core::RngCore;

use super::client_state::ClientLayer;
use super::client_state::{
    ClientRequest, Peer, STREAM_PIECE, Step, Waiting, is_newer, take_response,
};
use super::congestion::{Controller, Nstart};
use super::context::Context;
use super::message::{Due, Purpose, TimerKind};
use super::types::{Event, Request, RequestError, RequestId, Response};
use crate::config::Transfer;
use crate::msg::{BlockOpt, Code, Message, OptionNumber, Token, Type};
use crate::peer_key::{MidKey, PeerKey};

/// The longest Echo value a client sends back (RFC 9175 §2.2.1: the option holds 1 to 40
/// bytes).
const MAX_ECHO: usize = 40;

impl ClientLayer {
    /// Starts a request ([`Endpoint::request`]).
    pub(super) fn request(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        peer: SocketAddr,
        req: Request,
    ) -> RequestId {
        let id = cx.new_id();
        let token = self.new_token(cx);
        let szx1 = req
            .block_szx
            .unwrap_or(cx.config.max_block_szx)
            .min(cx.config.max_block_szx);
        let user_block2 = req.options.contains(OptionNumber::BLOCK2);
        let observe = req.options.uint(OptionNumber::OBSERVE) == Some(0);
        let mut req = req;
        req.transfer = req.transfer.or(Some(cx.config.transfer));
        if req.multicast {
            req.confirmable = false;
            req.timeout = Some(req.timeout.unwrap_or(Duration::from_secs(5)));
        }
        if let Some(t) = req.timeout {
            cx.msg.schedule(now + t, TimerKind::Deadline { id });
        }
        let step = if req.payload.len() > BlockOpt::size_of(szx1) {
            Step::Upload { offset: 0 }
        } else {
            Step::Whole
        };
        // A request body in blocks goes with Q-Block1 if asked (block 0 is the CON that
        // finds out whether the server knows it).
        let qup = (matches!(step, Step::Upload { .. })
            && req.transfer == Some(Transfer::QBlock)
            && req.confirmable)
            .then(|| self.new_qup(cx, szx1, &req.options, req.payload.len(), peer));
        self.requests.insert(
            id,
            ClientRequest {
                peer,
                req,
                token,
                szx1,
                step,
                waiting: Waiting::Queued,
                generation: 0,
                failures: 0,
                restarts: 0,
                echoes: 0,
                body: Vec::new(),
                received: 0,
                etag: None,
                first_options: None,
                user_block2,
                observe,
                ack_timer: None,
                block_head: None,
                window: None,
                window_timer: None,
                qdown: None,
                qup,
            },
        );
        self.by_token.insert(token, id);
        let nstart = cx.config.nstart;
        self.peers
            .entry(PeerKey(peer))
            .or_insert_with(|| Peer::new(Nstart::new(nstart)))
            .queue
            .push_back(id);
        self.pump(cx, now, peer);
        RequestId(id)
    }

    /// Sends a ping ([`Endpoint::ping`]).
    pub(super) fn ping(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        peer: SocketAddr,
    ) -> RequestId {
        let id = cx.new_id();
        let mid = cx.msg.next_mid(now, peer);
        cx.msg.send_con(
            now,
            peer,
            &Message::empty(Type::Con, mid),
            Purpose::Ping(id),
            cx.config,
        );
        RequestId(id)
    }

    /// Abandons a request ([`Endpoint::cancel`]).
    pub(super) fn cancel(&mut self, cx: &mut Context<'_>, now: Instant, id: RequestId) {
        if self.requests.contains_key(&id.0) {
            self.fail(cx, now, id.0, RequestError::Cancelled);
        }
    }

    pub(super) fn new_token(&mut self, cx: &mut Context<'_>) -> Token {
        let len = cx.config.token_len.min(8);
        loop {
            let bytes = cx.msg.rng.next_u64().to_be_bytes();
            // NOTE(unwrap): len <= 8.
            let token = Token::new(&bytes[..len]).unwrap_or_default();
            if len == 0 || !self.by_token.contains_key(&token) {
                return token;
            }
        }
    }

    /// Starts queued requests while the peer has fewer outstanding than its congestion
    /// controller allows.
    pub(super) fn pump(&mut self, cx: &mut Context<'_>, now: Instant, peer: SocketAddr) {
        loop {
            let Some(p) = self.peers.get_mut(&PeerKey(peer)) else {
                return;
            };
            if p.active >= p.controller.window() {
                return;
            }
            let Some(id) = p.queue.pop_front() else {
                if p.active == 0 {
                    self.peers.remove(&PeerKey(peer));
                }
                return;
            };
            p.active += 1;
            self.send_step(cx, now, id);
        }
    }

    pub(super) fn send_step(&mut self, cx: &mut Context<'_>, now: Instant, id: u64) {
        let Some(peer) = self.requests.get(&id).map(|r| r.peer) else {
            return;
        };
        let mid = cx.msg.next_mid(now, peer);
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        r.send_step(mid, &mut cx.msg.outbox);
        r.generation += 1;
        let (peer, generation) = (r.peer, r.generation);
        if r.req.multicast {
            // RFC 7390 §2.5: sent once, responses collected until the deadline.
            r.waiting = Waiting::Collecting;
        } else if r.req.confirmable {
            r.waiting = Waiting::Ack(mid);
            let at = cx
                .msg
                .await_ack(now, peer, mid, Purpose::Request(id), None, cx.config);
            self.arm_request_ack(cx, id, at);
        } else {
            r.waiting = Waiting::Response {
                non_tx: Some(0),
                mid,
            };
            let (t, _) = cx.msg.initial_timeout(now, peer, cx.config);
            cx.msg.schedule(now + t, TimerKind::Step { id, generation });
        }
    }

    /// Makes sure the request's ACK timer fires no later than `at`.
    pub(super) fn arm_request_ack(&mut self, cx: &mut Context<'_>, id: u64, at: Instant) {
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if r.ack_timer.is_some_and(|armed| armed <= at) {
            return;
        }
        r.ack_timer = Some(at);
        cx.msg.schedule(at, TimerKind::RequestAck { id, at });
    }

    /// The ACK timer of a request: the CON it waits for is sent again if due (RFC 7252
    /// §4.2, the timeout growing by its backoff factor), its step fails after MAX_RETRANSMIT; a CON
    /// due later re-arms the timer for then.
    pub(super) fn on_request_ack_timer(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        at: Instant,
    ) {
        let max = cx.config.max_retransmit;
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if r.ack_timer != Some(at) {
            return;
        }
        r.ack_timer = None;
        let Waiting::Ack(mid) = r.waiting else {
            return;
        };
        match cx.msg.request_con_due(now, r.peer, mid, max) {
            Due::Gone => {}
            Due::Later(due) => self.arm_request_ack(cx, id, due),
            Due::Resend(due) => {
                r.send_step(mid, &mut cx.msg.outbox);
                self.arm_request_ack(cx, id, due);
            }
            Due::GaveUp => self.step_failed(cx, now, id, RequestError::Timeout),
        }
    }

    /// The ACK or Reset of a request's CON: a Reset fails it, a piggybacked response is
    /// its answer, an empty ACK means the answer comes separately.
    pub(super) fn on_request_ack(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        msg: &mut Message,
        payload: &[u8],
    ) {
        if msg.ty == Type::Rst {
            self.fail(cx, now, id, RequestError::Reset);
        } else if msg.code.is_response()
            && let Some(r) = self.requests.get_mut(&id).filter(|r| r.token == msg.token)
        {
            // Piggybacked: the exchange ended with this ACK.
            r.waiting = Waiting::Response {
                non_tx: None,
                mid: msg.message_id,
            };
            self.on_response(cx, now, id, msg, payload);
        } else {
            self.on_empty_ack(cx, now, id);
        }
    }

    /// A separate response (CON or NON) to request `id`, already acknowledged and
    /// deduplicated: a multicast answer, a notification, or the request's answer.
    pub(super) fn on_separate_response_to(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        peer: SocketAddr,
        msg: &mut Message,
        payload: &[u8],
    ) {
        match self.requests.get_mut(&id) {
            Some(r) if r.waiting == Waiting::Collecting => {
                let response = take_response(msg, payload);
                cx.events.push_back(Event::MulticastResponse {
                    id: RequestId(id),
                    peer,
                    response,
                });
            }
            Some(r) if r.peer != peer => {}
            Some(r) => {
                if let Waiting::Observing(last) = r.waiting {
                    let seq = msg.options.uint(OptionNumber::OBSERVE);
                    // RFC 7641 §3.4: deliver only notifications newer than the last one.
                    if let Some(seq) = seq.filter(|v| is_newer(last, *v)) {
                        r.waiting = Waiting::Observing(seq);
                        let response = take_response(msg, payload);
                        cx.events.push_back(Event::Notification {
                            id: RequestId(id),
                            response,
                        });
                    } else if seq.is_none() {
                        // A final response without Observe ends the observation (§3.2).
                        let response = take_response(msg, payload);
                        self.finish(cx, now, id);
                        cx.events.push_back(Event::Notification {
                            id: RequestId(id),
                            response,
                        });
                    }
                    return;
                }
                self.on_response(cx, now, id, msg, payload);
            }
            None => {}
        }
    }

    /// The deadline of request `id` (its `timeout`): a multicast request's collection
    /// ends; a request still waiting for its answer fails. An established observation
    /// outlives it: it bounds the wait for the registration's answer.
    pub(super) fn on_deadline(&mut self, cx: &mut Context<'_>, now: Instant, id: u64) {
        match self.waiting(id) {
            Some(Waiting::Collecting) => {
                self.finish(cx, now, id);
                cx.events
                    .push_back(Event::MulticastDone { id: RequestId(id) });
            }
            Some(Waiting::Observing(_)) | None => {}
            Some(_) => self.fail(cx, now, id, RequestError::Timeout),
        }
    }

    pub(super) fn on_empty_ack(&mut self, cx: &mut Context<'_>, now: Instant, id: u64) {
        let timeout = cx.config.response_timeout;
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if r.qup.is_some() {
            return self.qup_probe_acked(cx, now, id);
        }
        if let Waiting::Ack(mid) = r.waiting {
            r.waiting = Waiting::Response { non_tx: None, mid };
            r.generation += 1;
            let generation = r.generation;
            cx.msg
                .schedule(now + timeout, TimerKind::Step { id, generation });
        }
    }

    pub(super) fn on_step_timer(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        generation: u32,
    ) {
        let max = cx.config.max_retransmit;
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if r.generation != generation {
            return;
        }
        match r.waiting {
            Waiting::Response {
                non_tx: Some(tx), ..
            } if tx < max => {
                // A NON request gets no ACK; resend it (new message ID, same token) after
                // the timeout a CON would start with, doubling each time.
                let peer = r.peer;
                let mid = cx.msg.next_mid(now, peer);
                let Some(r) = self.requests.get_mut(&id) else {
                    return;
                };
                r.send_step(mid, &mut cx.msg.outbox);
                r.waiting = Waiting::Response {
                    non_tx: Some(tx + 1),
                    mid,
                };
                let t = cx.msg.initial_timeout(now, peer, cx.config).0 * (1u32 << (tx + 1));
                cx.msg.schedule(now + t, TimerKind::Step { id, generation });
            }
            _ => self.step_failed(cx, now, id, RequestError::Timeout),
        }
    }

    /// One exchange failed. A block-wise step is resumed (the same block again) up to
    /// `block_retries` consecutive times; anything else fails the request.
    pub(super) fn step_failed(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        error: RequestError,
    ) {
        let retries = cx.config.block_retries;
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if r.step_has_block_option() && r.failures < retries {
            r.failures += 1;
            self.send_step(cx, now, id);
        } else {
            self.fail(cx, now, id, error);
        }
    }

    pub(super) fn fail(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        error: RequestError,
    ) {
        self.finish(cx, now, id);
        cx.events.push_back(Event::RequestFailed {
            id: RequestId(id),
            error,
        });
    }

    /// Removes a finished request and frees its NSTART slot.
    pub(super) fn finish(&mut self, cx: &mut Context<'_>, now: Instant, id: u64) {
        self.end_window(cx, now, id);
        let Some(r) = self.requests.remove(&id) else {
            return;
        };
        self.by_token.remove(&r.token);
        let q_tokens = r.qdown.iter().flat_map(|d| &d.tokens);
        for t in q_tokens.chain(r.qup.iter().flat_map(|u| &u.tokens)) {
            self.by_token.remove(t);
        }
        match r.waiting {
            Waiting::Ack(mid) => {
                cx.msg.exchanges.remove(&MidKey(r.peer, mid));
            }
            Waiting::Queued => {
                if let Some(p) = self.peers.get_mut(&PeerKey(r.peer)) {
                    p.queue.retain(|q| *q != id);
                }
                return;
            }
            // An observation gave its NSTART slot back when it was established.
            Waiting::Observing(_) => return,
            Waiting::Response { .. } | Waiting::Collecting | Waiting::Window => {}
        }
        self.release_slot(cx, now, r.peer);
    }

    pub(super) fn release_slot(&mut self, cx: &mut Context<'_>, now: Instant, peer: SocketAddr) {
        if let Some(p) = self.peers.get_mut(&PeerKey(peer)) {
            p.active = p.active.saturating_sub(1);
        }
        self.pump(cx, now, peer);
    }

    /// Delivers the final response of a request. An Observe registration that the server
    /// accepted (a success carrying Observe) stays alive for its notifications and frees
    /// its NSTART slot; anything else is finished.
    pub(super) fn complete(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        response: Response,
    ) {
        let seq = response.options.uint(OptionNumber::OBSERVE);
        let observing = self.requests.get_mut(&id).and_then(|r| {
            let seq = seq.filter(|_| r.observe && response.code.is_success())?;
            r.waiting = Waiting::Observing(seq);
            Some(r.peer)
        });
        match observing {
            Some(peer) => self.release_slot(cx, now, peer),
            None => self.finish(cx, now, id),
        }
        cx.events.push_back(Event::Response {
            id: RequestId(id),
            response,
        });
    }

    /// A response (piggybacked or separate) matched to request `id` by token.
    pub(super) fn on_response(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        msg: &mut Message,
        payload: &[u8],
    ) {
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if msg.code == Code::UNAUTHORIZED
            && r.echoes < 2
            && r.window.is_none()
            && r.qdown.is_none()
            && let Some(echo) = msg
                .options
                .first(OptionNumber::ECHO)
                .filter(|e| (1..=MAX_ECHO).contains(&e.len()))
        {
            // RFC 9175 §2.3: the server wants proof of this endpoint's address (or a fresh
            // request); the step goes again with its Echo value, and later steps carry it
            // too (a server that has verified the address ignores it). A value longer
            // than the option allows is not sent back (the 4.01 is the answer): a server
            // must not make its clients carry a kilobyte in every request.
            r.end_exchange(cx.msg);
            r.echoes += 1;
            r.req.options.set(OptionNumber::ECHO, echo);
            r.block_head = None;
            // A body sent in blocks goes again from its first block: a server that asks
            // for the value once the whole body arrived (an application's own freshness
            // check) has handed the body over and no longer holds its blocks.
            if let Step::Upload { .. } = r.step {
                r.step = Step::Upload { offset: 0 };
            }
            r.generation += 1;
            return self.send_step(cx, now, id);
        }
        if r.window.is_some() {
            return self.on_window_response(cx, now, id, msg, payload);
        }
        if r.qdown.is_some() {
            return self.on_qdown_response(cx, now, id, msg, payload);
        }
        if r.qup.is_some() {
            r.end_exchange(cx.msg);
            return self.on_qup_response(cx, now, id, msg, payload);
        }
        if r.step == Step::Whole && r.may_qblock() {
            if msg.code == Code::BAD_OPTION {
                // RFC 9177 §4.1: the server does not know Q-Block2; RFC 7959 then, with a
                // window.
                r.req.transfer = Some(Transfer::Window);
                return self.send_step(cx, now, id);
            }
            if let Some(q) = msg
                .options
                .block(OptionNumber::Q_BLOCK2)
                .filter(|q| q.more && msg.code.is_success())
            {
                r.end_exchange(cx.msg);
                return self.start_qdown(cx, now, id, msg, payload, q);
            }
        }
        self.on_step_response(cx, now, id, msg, payload);
    }

    /// A response to request `id` past the Echo and Q-Block checks: if it answers the step
    /// in flight (late answers to earlier steps are dropped), the exchange is over; an
    /// upload goes on with its next block, or again with smaller ones.
    fn on_step_response(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        msg: &mut Message,
        payload: &[u8],
    ) {
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        let current = match r.step {
            Step::Upload { offset } => msg
                .options
                .block1()
                .is_none_or(|b| b.num as usize == offset / BlockOpt::size_of(r.szx1)),
            Step::Download { num, .. } => msg.options.block2().is_none_or(|b| b.num == num),
            Step::Whole => true,
        };
        if !current || r.waiting == Waiting::Queued {
            if !current && msg.ty == Type::Ack {
                // The ACK of the step's own CON answers another block: that exchange is
                // over, so the block is asked for again rather than waited for.
                return self.step_failed(
                    cx,
                    now,
                    id,
                    RequestError::Protocol("the response is for another block"),
                );
            }
            return;
        }
        // A separate response also acknowledges the request (RFC 7252 §5.2.2).
        r.end_exchange(cx.msg);
        r.generation += 1;
        r.failures = 0;

        if let Step::Upload { offset } = r.step {
            let size = BlockOpt::size_of(r.szx1);
            let sent_end = (offset + size).min(r.req.payload.len());
            if msg.code == Code::CONTINUE {
                let Some(b1) = msg.options.block1() else {
                    return self.fail(
                        cx,
                        now,
                        id,
                        RequestError::Protocol("2.31 Continue without Block1"),
                    );
                };
                if sent_end >= r.req.payload.len() {
                    return self.fail(
                        cx,
                        now,
                        id,
                        RequestError::Protocol("2.31 Continue after the last block"),
                    );
                }
                // RFC 7959 §2.3: continue with the server's block size if it is smaller;
                // the offset stays, so the block number scales.
                r.szx1 = r.szx1.min(b1.szx);
                r.step = Step::Upload { offset: sent_end };
                if r.req.progress && offset >> 16 != sent_end >> 16 {
                    let total = Some(r.req.payload.len());
                    cx.events.push_back(Event::Progress {
                        id: RequestId(id),
                        done: sent_end,
                        total,
                    });
                }
                return self.send_step(cx, now, id);
            }
            if msg.code == Code::REQUEST_ENTITY_TOO_LARGE
                && let Some(b1) = msg
                    .options
                    .block1()
                    .filter(|b| b.szx < r.szx1 && r.restarts < 4)
            {
                // RFC 7959 §2.9.3: the server wants smaller blocks; start over with them.
                r.restarts += 1;
                r.szx1 = b1.szx;
                r.step = Step::Upload { offset: 0 };
                return self.send_step(cx, now, id);
            }
        } else if r.step == Step::Whole
            && msg.code == Code::REQUEST_ENTITY_TOO_LARGE
            && !r.req.payload.is_empty()
            && let Some(b1) = msg.options.block1().filter(|_| r.restarts < 4)
        {
            // The body fit one message but not the server: go block-wise at its size.
            r.restarts += 1;
            r.szx1 = b1.szx.min(r.szx1);
            r.step = Step::Upload { offset: 0 };
            return self.send_step(cx, now, id);
        }

        self.on_final_response(cx, now, id, msg, payload);
    }

    /// The response to request `id` once its body is sent: whole, an error, or a block
    /// of a body in blocks (block 0 checked and its options kept).
    fn on_final_response(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        msg: &mut Message,
        payload: &[u8],
    ) {
        let limit = cx.config.limits.client_body_bytes;
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        let b2 = msg
            .options
            .block2()
            .filter(|_| !r.user_block2 && msg.code.is_success());
        let Some(b2) = b2 else {
            // An error response ends the transfer with what the server said (a 5.03 in
            // the middle of a block-wise transfer is the server's answer, not a broken
            // protocol); the blocks so far are dropped.
            if r.first_options.take().is_some() && msg.code.is_success() {
                // Reassembly ended with a block lacking Block2: a broken server.
                return self.fail(
                    cx,
                    now,
                    id,
                    RequestError::Protocol("block-wise response lost its Block2"),
                );
            }
            let mut response = take_response(msg, payload);
            if r.req.stream && response.code.is_success() && !response.payload.is_empty() {
                let data = std::mem::take(&mut response.payload);
                cx.events.push_back(Event::BodyChunk {
                    id: RequestId(id),
                    offset: 0,
                    total: Some(data.len()),
                    data,
                });
            }
            return self.complete(cx, now, id, response);
        };
        if r.first_options.is_some() && msg.options.etag() != r.etag.as_deref() {
            // RFC 7959 §2.4: the representation changed. Streamed pieces cannot be taken
            // back, so a streamed request fails; a reassembled one starts over, a few
            // times at most.
            if r.restarts >= 4 || r.req.stream {
                return self.fail(cx, now, id, RequestError::RepresentationChanged);
            }
            r.restarts += 1;
            r.body.clear();
            r.received = 0;
            r.first_options = None;
            r.step = Step::Download {
                num: 0,
                szx: b2.szx,
            };
            return self.send_step(cx, now, id);
        }
        if r.first_options.is_none() {
            if b2.num != 0 {
                return self.fail(
                    cx,
                    now,
                    id,
                    RequestError::Protocol("first Block2 response is not block 0"),
                );
            }
            let size2 = msg.options.uint(OptionNumber::SIZE2).map(|t| t as usize);
            if size2.is_some_and(|t| t > limit) {
                // A body announced larger than the limit is refused at its first block,
                // not after `limit` bytes of it have been fetched.
                return self.fail(cx, now, id, RequestError::TooLarge { limit });
            }
            let mut first = msg.options.clone();
            first.remove(OptionNumber::BLOCK2);
            r.etag = msg.options.etag().map(<[u8]>::to_vec);
            // Room for the first piece of a streamed body, or for the whole body Size2
            // announced (within the limit), not regrown block by block.
            let room = if r.req.stream {
                if b2.more { STREAM_PIECE + b2.size() } else { 0 }
            } else {
                size2.unwrap_or(0)
            };
            r.body.reserve(room);
            r.first_options = Some(first);
        }
        self.on_next_block(cx, now, id, msg, payload, b2);
    }

    /// Block `b2` of the body of request `id`, after block 0's checks: appended if it is
    /// the next, then the next asked for, a window started, or the body complete.
    fn on_next_block(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        msg: &mut Message,
        payload: &[u8],
        b2: BlockOpt,
    ) {
        let limit = cx.config.limits.client_body_bytes;
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if b2.offset() != r.received {
            // A block we did not ask for at this offset: ask again for the one we lack.
            let size = b2.size();
            r.step = Step::Download {
                num: (r.received / size) as u32,
                szx: b2.szx,
            };
            return self.send_step(cx, now, id);
        }
        if let Err(e) = r.append(id, payload, b2.more, b2.size(), limit, cx.events) {
            return self.fail(cx, now, id, e);
        }
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if b2.more && b2.num == 0 && r.may_window() {
            let size2 = r
                .first_options
                .as_ref()
                .and_then(|o| o.uint(OptionNumber::SIZE2));
            if size2.is_some_and(|t| t as usize <= b2.size()) {
                // More blocks, and a size that ends within this one: a window would have
                // nothing to ask for and wait for the timeout.
                return self.fail(
                    cx,
                    now,
                    id,
                    RequestError::Protocol("the body does not have the size Size2 announced"),
                );
            }
            let last = size2
                .and_then(|t| (t as usize).checked_sub(1))
                .map(|end| (end / b2.size()) as u32);
            return self.start_window(cx, now, id, b2.szx, last);
        }
        if b2.more {
            let num = (r.received / b2.size()) as u32;
            r.step = Step::Download { num, szx: b2.szx };
            return self.send_step(cx, now, id);
        }
        let body = Bytes::from(std::mem::take(&mut r.body));
        let options = r.first_options.take().unwrap_or_default();
        let response = Response::with_parts(msg.code, options, body);
        self.complete(cx, now, id, response);
    }
}
