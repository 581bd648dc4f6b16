//! The server side's behaviour: requests this endpoint receives, answered piggybacked or
//! separately, block-wise, observed (the state is in `server_state`).

use std::net::SocketAddr;
use std::time::Instant;

use bytes::Bytes;
use rand_core::RngCore;

use super::context::Context;
use super::message::{Purpose, TimerKind};
use super::qserver::QNext;
use super::reply::{answer, remember, reply, reply_header, reply_message};
use super::server_state::{
    Incoming, Observation, Pending, ServerLayer, block2_response, past_end, unreadable,
};
use super::types::{Event, IncomingId, IncomingRequest, ObservationId, Response};
use crate::block::{self, Block1Outcome, BlockKey, Slice, Source, Storing};
use crate::dedup::{Fingerprint, Seen};
use crate::msg::{BlockOpt, Code, Message, OptionNumber, Token, Type};

impl ServerLayer {
    /// A request of `size` bytes; its `payload` stays in the datagram until it is copied
    /// where it goes (an upload's block into the body being assembled). It goes through
    /// stages, each of which may answer it and end there.
    pub(super) fn on_request(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        req: &mut Incoming<'_>,
        size: usize,
    ) {
        // `Err(Answered)`: a stage answered (or dropped) the request.
        let _ = self.request_stages(cx, now, req, size);
    }

    fn request_stages(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        req: &mut Incoming<'_>,
        size: usize,
    ) -> Result<(), Answered> {
        // A Block2 continuation is looked up in the store before deduplication: the store
        // answers a duplicate just as well, and the message ID of a long transfer's
        // continuation may come round again to that of its first block, whose reply the
        // dedup store keeps (the token is the same). Q-Block blocks are served from the
        // store or assembled with duplicates found by block number, so they skip it too.
        if !req.continuation && !req.q_stateless() {
            self.replay_stage(cx, now, req)?;
        }
        req.budget = self.verify_stage(cx, now, req, size)?;
        self.critical_options_stage(cx, now, req)?;
        req.msg.options.drop_bad_elective();
        let key = req.block_key();
        let mut body = Assembled::default();
        if req.is_qblock() {
            match self.on_q_request(cx, now, req, &key) {
                QNext::Done => return Err(Answered),
                QNext::Dispatch(assembled) => body.bytes = assembled,
            }
        }
        if req.continuation {
            self.continuation_stage(cx, now, req, &key)?;
        }
        if let Some(b1) = req.block1 {
            body = self.block1_stage(cx, now, req, &key, b1)?;
        }
        self.hand_over(cx, now, req, key, body)
    }

    /// A duplicate is answered as the first one was.
    fn replay_stage(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        req: &Incoming<'_>,
    ) -> Result<(), Answered> {
        if self.replay_duplicate(cx, now, req.peer, &req.msg) {
            return Err(Answered);
        }
        Ok(())
    }

    /// RFC 9175 §2.4: an unverified peer gets at most three times `size` (the budget
    /// returned for a request the application may work on; `None` for a verified peer).
    ///
    /// A unicast request from an unverified peer is challenged here, before any work,
    /// whatever its method: the answer to a GET is known only once made and almost never
    /// fits three times a request in one block, so working on it first would let forged
    /// sources make the server grab for nothing (1,000 spoofed GETs a second took a
    /// core). Nothing is stored for the peer and the application does not run.
    ///
    /// A GET or FETCH sent to a group is worked on first, a few at a time, while such
    /// requests take the application no more than
    /// [`Limits::unverified_group_work`](crate::config::Limits::unverified_group_work)
    /// a second. A member must stay silent when its answer is an error (RFC 7390 §2.7: a
    /// member that lacks the resource), which it learns only from the answer; challenged
    /// first, the client's unicast retry with the Echo would draw the 4.04 that the group
    /// request must not. The answer goes if it fits the budget in one block, nothing goes
    /// for an error, else the challenge (`respond_unverified`). A group request comes only
    /// from inside the group's scope (the link or the site), where a sender could as well
    /// verify its own address and ask for the same work. The bound is in time, not in
    /// requests, because one GET may cost a thousand times another (a point cloud, a
    /// small document), and the application's build (a debug one) as much again; it keeps
    /// a flood of them to that share of a core. Past it they are challenged before any
    /// work.
    fn verify_stage(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        req: &Incoming<'_>,
        size: usize,
    ) -> Result<Option<usize>, Answered> {
        let limits = cx.limits();
        let msg = &req.msg;
        let verified = !cx.config.verify_addresses
            || self.verify.is_verified(
                now,
                req.peer,
                msg.options.first(OptionNumber::ECHO),
                limits.verified_lifetime,
                limits.verified_peers,
            );
        if verified {
            return Ok(None);
        }
        if req.multicast
            && matches!(msg.code, Code::GET | Code::FETCH)
            && msg.options.uint(OptionNumber::OBSERVE) != Some(0)
            && req.block1.is_none()
            && !req.continuation
            && !req.is_qblock()
            && self.unverified_group_work() < UNVERIFIED_GROUP_WORK_AT_ONCE
            && (self.verify).may_work_for_group(now, limits.unverified_group_work)
        {
            return Ok(Some(3 * size));
        }
        let header = reply_header(cx, now, req.peer, msg);
        let challenge = self.challenge(now, req.peer, msg.token, header, 3 * size);
        let seen = match challenge {
            Some(reply) => cx.msg.reply_with(req.peer, reply),
            // A CON gets a Reset rather than waiting for an answer that never comes.
            None if req.con => {
                (cx.msg).reply_with(req.peer, Message::empty(Type::Rst, msg.message_id))
            }
            None => Seen::Silent,
        };
        remember(cx, now, req, seen);
        Err(Answered)
    }

    /// RFC 7252 §5.4.1: a request with an unrecognized or malformed critical option gets
    /// 4.02 if it is a CON, a Reset if a NON.
    fn critical_options_stage(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        req: &Incoming<'_>,
    ) -> Result<(), Answered> {
        let Some(bad) = req.msg.options.first_bad_critical() else {
            return Ok(());
        };
        if req.continuation && self.replay_duplicate(cx, now, req.peer, &req.msg) {
            return Err(Answered);
        }
        let seen = if req.con {
            let text = format!("unrecognized or malformed critical option {}", bad.0);
            let mut response = Response::diagnostic(Code::BAD_OPTION, &text);
            if req.budget.is_some() {
                // The diagnostic could be many times a short request.
                response.payload = Bytes::new();
            }
            reply(cx, now, req, response)
        } else if req.multicast {
            Seen::Silent
        } else {
            let reset = Message::empty(Type::Rst, req.msg.message_id);
            cx.msg.reply_with(req.peer, reset)
        };
        remember(cx, now, req, seen);
        Err(Answered)
    }

    /// A Block2 continuation is served from the stored representation; the application
    /// never sees it (a POST grab must not grab again). A GET goes on when nothing is
    /// stored: it is safe, so the application renders it again and the block is cut from
    /// the new representation (its ETag tells the client whether the blocks still fit).
    fn continuation_stage(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        req: &Incoming<'_>,
        key: &BlockKey,
    ) -> Result<(), Answered> {
        let Some(b2) = req.block2 else { return Ok(()) };
        let (peer, msg) = (req.peer, &req.msg);
        let szx = b2.szx.min(cx.config.max_block_szx);
        let (ty, mid) = reply_header(cx, now, peer, msg);
        // Stored for this peer, or for a request this peer sent to a group.
        let group_key;
        let stored_key = if self.block2.contains(key) {
            key
        } else {
            group_key = key.for_group();
            &group_key
        };
        self.block2.settle(now, stored_key, block_pause(cx.config));
        let stored = self.block2.with_stored(now, stored_key, cx.limits(), |s| {
            if s.q_options.is_some() {
                // Stored for Q-Block2: not a body to cut Block2 blocks from.
                return Slice::Unreadable;
            }
            let slice = block::slice(&*s.body.0, b2.num, szx);
            if let Slice::Block(payload, opt) = &slice {
                // The block goes out as the stored options, encoded once, around this
                // Block2.
                let header = (ty, s.code, mid, msg.token);
                cx.msg.outbox.send_with(peer, payload.len(), |out| {
                    s.head.encode_into(out, header, opt.as_uint(), payload);
                });
            }
            slice
        });
        match stored {
            // Served from the store, which is idempotent (RFC 7252 §4.5 allows relaxing
            // deduplication then): a duplicate is cut again from the same bytes, and a
            // 10 MB transfer leaves no 10,000 dedup entries behind.
            Some(Slice::Block(_, opt)) => {
                self.block2.served(now, stored_key, opt.num, opt.more);
                return Err(Answered);
            }
            // RFC 7959 §2.2: a block past the end is a bad option.
            Some(Slice::PastEnd) => {
                if let Some(reply) = reply_message(cx, now, peer, msg, req.multicast, past_end()) {
                    cx.msg.send(peer, &reply);
                }
                return Err(Answered);
            }
            // The stored source can no longer be read as it was: as if nothing were stored.
            Some(Slice::Unreadable) => self.block2.remove(stored_key),
            None => {}
        }
        self.replay_stage(cx, now, req)?;
        if !matches!(msg.code, Code::GET | Code::FETCH) {
            let response = Response::diagnostic(
                Code::REQUEST_ENTITY_INCOMPLETE,
                "the representation is no longer stored; repeat the request from block 0",
            );
            answer(cx, now, req, response);
            return Err(Answered);
        }
        Ok(())
    }

    /// A Block1 block goes into its body: answered 2.31 Continue (or refused) until the
    /// body is whole, which goes on to the application.
    fn block1_stage(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        req: &Incoming<'_>,
        key: &BlockKey,
        b1: BlockOpt,
    ) -> Result<Assembled, Answered> {
        let size1 = req.msg.options.uint(OptionNumber::SIZE1);
        let outcome = (self.block1).handle(now, key.clone(), b1, size1, req.payload, cx.config);
        self.arm_sweep(cx, now + cx.limits().blockwise_lifetime);
        let response = match outcome {
            Block1Outcome::Continue(opt) => {
                let mut r = Response::new(Code::CONTINUE);
                r.options.set_block(OptionNumber::BLOCK1, opt);
                r
            }
            Block1Outcome::Refuse {
                code,
                diagnostic,
                size1,
            } => {
                let mut r = Response::diagnostic(code, diagnostic);
                if let Some(s) = size1 {
                    r.options.set_uint(OptionNumber::SIZE1, s);
                }
                if code == Code::SERVICE_UNAVAILABLE {
                    r.options.set_uint(OptionNumber::MAX_AGE, 5);
                }
                r
            }
            Block1Outcome::Complete(body, echo) => {
                return Ok(Assembled {
                    bytes: Some(body),
                    block1_echo: Some(echo),
                });
            }
        };
        answer(cx, now, req, response);
        Err(Answered)
    }

    /// The request goes to the application ([`Event::Request`]) and waits for its answer
    /// ([`ServerLayer::respond`]), unless too many wait already (5.03).
    fn hand_over(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        req: &mut Incoming<'_>,
        key: BlockKey,
        body: Assembled,
    ) -> Result<(), Answered> {
        if self.unanswered() >= cx.limits().pending_requests {
            let mut r = Response::new(Code::SERVICE_UNAVAILABLE);
            r.options.set_uint(OptionNumber::MAX_AGE, 1);
            answer(cx, now, req, r);
            return Err(Answered);
        }
        let id = cx.new_id();
        let (peer, multicast, con) = (req.peer, req.multicast, req.con);
        let observation = self.observe_option(cx, peer, &req.msg, &key);
        // RFC 7252 §8.2: a random instant within Leisure from now, drawn here so that the
        // draws follow the requests' order.
        let leisure = cx.config.leisure;
        let not_before =
            (multicast && !leisure.is_zero()).then(|| now + leisure.mul_f64(cx.msg.unit()));
        let pending = Pending {
            peer,
            mid: req.msg.message_id,
            token: req.msg.token,
            confirmable: con,
            acked: false,
            multicast,
            block2: req.block2,
            block1_echo: body.block1_echo,
            budget: req.budget,
            since: now,
            // A response to a group request is stored for the client's port, whatever
            // address its unicast follow-ups come from.
            key: if multicast { key.for_group() } else { key },
            observation,
            qblock2: if observation.is_none() {
                std::mem::take(&mut req.q2)
            } else {
                Vec::new()
            },
            not_before,
        };
        self.pending.insert(id, pending);
        let msg = &mut req.msg;
        let key = (peer, msg.message_id);
        let limits = cx.limits();
        let seen = Seen::Pending(id);
        (cx.msg.dedup).insert(now, key, Fingerprint::of(msg), req.expires, seen, limits);
        if con {
            let at = now + cx.config.separate_ack_delay;
            cx.msg.schedule(at, TimerKind::SeparateAck { id });
        }
        cx.events.push_back(Event::Request(IncomingRequest {
            id: IncomingId(id),
            peer,
            method: msg.code,
            options: std::mem::take(&mut msg.options),
            payload: body
                .bytes
                .unwrap_or_else(|| Bytes::copy_from_slice(req.payload)),
            multicast,
            confirmable: con,
            observe: observation.map(ObservationId),
            identity: None,
            loopback: false,
        }));
        Ok(())
    }

    /// The Echo challenge to a request from an unverified peer (RFC 9175 §2.4): 4.01 with
    /// an Echo value made for the peer, as a message of type `ty` and ID `message_id`. It
    /// goes to a multicast request too, as the one error a group member answers (the
    /// client repeats the request to this server by unicast). `None` when even the
    /// challenge is more than `budget` bytes (three times a request of 4 or 5 bytes).
    fn challenge(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        token: Token,
        (ty, message_id): (Type, u16),
        budget: usize,
    ) -> Option<Message> {
        let mut reply = Message {
            ty,
            code: Code::UNAUTHORIZED,
            message_id,
            token,
            options: Default::default(),
            payload: Bytes::new(),
        };
        reply
            .options
            .set(OptionNumber::ECHO, self.verify.echo(now, peer));
        (reply.encoded_len() <= budget).then_some(reply)
    }

    /// The message that answers `p`: piggybacked on the ACK of a CON request not yet
    /// acknowledged; otherwise with a new message ID, as `late` after the empty ACK of a
    /// CON request, as a NON to a NON one.
    fn pending_reply(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        p: &Pending,
        late: Type,
        response: Response,
    ) -> Message {
        let (ty, message_id) = match (p.confirmable, p.acked) {
            (true, false) => (Type::Ack, p.mid),
            (true, true) => (late, cx.msg.next_mid(now, p.peer)),
            (false, _) => (Type::Non, cx.msg.next_mid(now, p.peer)),
        };
        Message {
            ty,
            code: response.code,
            message_id,
            token: p.token,
            options: response.options,
            payload: response.payload,
        }
    }

    /// Answers request `p` that an unverified peer sent to a group (`verify_stage`): the
    /// response when it fits in `budget` bytes and one block, nothing for an error (RFC
    /// 7390 §2.7), the Echo challenge otherwise. Nothing is stored for the peer,
    /// and an answer after the empty ACK goes as a NON: a CON would be sent up to five
    /// times to an address nobody verified.
    fn respond_unverified(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        p: &Pending,
        response: Response,
        budget: usize,
    ) {
        let source = response.source.is_some();
        let answer = self.pending_reply(cx, now, p, Type::Non, response);
        let (ty, mid) = (answer.ty, answer.message_id);
        let fits = !source
            && answer.payload.len() <= BlockOpt::size_of(cx.config.max_block_szx)
            && answer.encoded_len() <= budget;
        // An error stays silent whatever its size: the challenge in its place would have
        // the client retry by unicast and receive the error after all.
        let reply = if p.multicast && answer.code.is_error() {
            None
        } else if !fits {
            self.challenge(now, p.peer, p.token, (ty, mid), budget)
                .or_else(|| (ty == Type::Ack).then(|| Message::empty(Type::Rst, mid)))
        } else {
            Some(answer)
        };
        let seen = match reply {
            Some(m) => cx.msg.reply_with(p.peer, m),
            None => Seen::Silent,
        };
        cx.msg.dedup.set_reply(p.peer, p.mid, seen);
    }

    /// Makes sure the sweep runs no later than `at`.
    pub(super) fn arm_sweep(&mut self, cx: &mut Context<'_>, at: Instant) {
        if self.sweep_at.is_some_and(|armed| armed <= at) {
            return;
        }
        self.sweep_at = Some(at);
        cx.msg.schedule(at, TimerKind::Sweep { at });
    }

    /// Drops the uploads and stored representations idle for their lifetime, so what an
    /// idle server holds shrinks without a request to trigger it, and arms the next sweep
    /// for the first of the rest to run out.
    pub(super) fn on_sweep_timer(&mut self, cx: &mut Context<'_>, now: Instant, at: Instant) {
        if self.sweep_at != Some(at) {
            return;
        }
        self.sweep_at = None;
        let limits = &cx.config.limits;
        self.block1.expire_all(now, limits);
        self.block2.expire(now, limits);
        let oldest = [self.block1.oldest(), self.block2.oldest()];
        if let Some(first) = oldest.into_iter().flatten().min() {
            self.arm_sweep(cx, first + limits.blockwise_lifetime);
        }
    }

    /// Answers a duplicate message as the first one was answered (RFC 7252 §4.5); whether
    /// `msg` was one.
    pub(super) fn replay_duplicate(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        peer: SocketAddr,
        msg: &Message,
    ) -> bool {
        let limits = cx.limits();
        let Some(seen) =
            cx.msg
                .dedup
                .check(now, peer, msg.message_id, Fingerprint::of(msg), limits)
        else {
            return false;
        };
        match seen.clone() {
            Seen::Replied(m) => cx.msg.send(peer, &m),
            Seen::Pending(id) if msg.ty == Type::Con => self.ack_pending(cx, id),
            Seen::Pending(_) | Seen::Silent => {}
        }
        true
    }

    /// RFC 7641 §2, §3.6: a GET or FETCH with Observe 0 registers (or re-registers, same
    /// peer and token) an observation; Observe 1 deregisters.
    pub(super) fn observe_option(
        &mut self,
        cx: &mut Context<'_>,
        peer: SocketAddr,
        msg: &Message,
        key: &BlockKey,
    ) -> Option<u64> {
        if !matches!(msg.code, Code::GET | Code::FETCH) {
            return None;
        }
        let value = msg.options.uint(OptionNumber::OBSERVE)?;
        let existing = self
            .observations
            .iter()
            .find(|(_, o)| o.peer == peer && o.token == msg.token)
            .map(|(id, _)| *id);
        match (value, existing) {
            (0, Some(id)) => Some(id),
            (0, None) if self.observations.len() < cx.config.limits.observations => {
                let id = cx.new_id();
                let o = Observation {
                    peer,
                    token: msg.token,
                    key: key.clone(),
                    established: false,
                    seq: 0,
                    sent: 0,
                    last_mid: None,
                    in_flight: false,
                    queued: None,
                };
                self.observations.insert(id, o);
                Some(id)
            }
            (1, Some(id)) => {
                self.end_observation(cx, id);
                None
            }
            _ => None,
        }
    }

    /// The CON notification of observation `obs` was acknowledged: the one that waited
    /// for it goes now.
    pub(super) fn on_notification_acked(&mut self, cx: &mut Context<'_>, now: Instant, obs: u64) {
        let Some(o) = self.observations.get_mut(&obs) else {
            return;
        };
        o.in_flight = false;
        if let Some(next) = o.queued.take() {
            self.notify(cx, now, ObservationId(obs), next);
        }
    }

    /// Ends every observation of `peer` ([`Endpoint::peer_unreachable`](super::Endpoint::peer_unreachable)).
    pub(super) fn end_observations_of(&mut self, cx: &mut Context<'_>, peer: SocketAddr) {
        let ids: Vec<u64> = (self.observations.iter())
            .filter(|(_, o)| o.peer == peer)
            .map(|(id, _)| *id)
            .collect();
        for id in ids {
            self.end_observation(cx, id);
        }
    }

    pub(super) fn end_observation(&mut self, cx: &mut Context<'_>, id: u64) {
        if self.observations.remove(&id).is_some() {
            cx.events.push_back(Event::ObservationEnded {
                id: ObservationId(id),
            });
        }
    }

    /// Sends a notification ([`Endpoint::notify`]).
    pub(super) fn notify(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: ObservationId,
        response: Response,
    ) -> bool {
        let interval = cx.config.notify_con_interval;
        let szx = cx.config.max_block_szx;
        let Some(o) = self.observations.get_mut(&id.0).filter(|o| o.established) else {
            return false;
        };
        if o.in_flight {
            o.queued = Some(response);
            return true;
        }
        o.seq = (o.seq + 1) & 0x00ff_ffff;
        o.sent += 1;
        let con = interval > 0 && o.sent % interval == 0;
        let (peer, token, key, seq) = (o.peer, o.token, o.key.clone(), o.seq);
        let mut response = self.blockwise_response(cx, now, key, None, response, szx, true);
        let success = response.code.is_success();
        if success {
            response.options.set_uint(OptionNumber::OBSERVE, seq);
        }
        let ty = if con { Type::Con } else { Type::Non };
        let msg = Message {
            ty,
            code: response.code,
            message_id: cx.msg.next_mid(now, peer),
            token,
            options: response.options,
            payload: response.payload,
        };
        if con {
            cx.msg
                .send_con(now, peer, &msg, Purpose::Notification(id.0), cx.config);
            if let Some(o) = self.observations.get_mut(&id.0) {
                o.in_flight = true;
            }
        } else {
            cx.msg.send(peer, &msg);
            if let Some(o) = self.observations.get_mut(&id.0) {
                o.last_mid = Some(msg.message_id);
            }
        }
        if !success {
            self.end_observation(cx, id.0);
        }
        true
    }

    /// Cuts a response into its first (or requested) block when it does not fit one, adding
    /// an ETag and storing the representation for the continuations; a `notification`'s
    /// waits while a client is partway through the one stored before
    /// ([`block::ServerCache::insert`]).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn blockwise_response(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        key: BlockKey,
        block2: Option<BlockOpt>,
        mut response: Response,
        max_szx: u8,
        notification: bool,
    ) -> Response {
        let limits = cx.limits();
        let szx = block2.map_or(max_szx, |b| b.szx.min(max_szx));
        let num = block2.map_or(0, |b| b.num);
        let body = match response.source.take() {
            Some(source) => source,
            // An error answers whatever block was asked for (RFC 7959's blocks are of the
            // representation a success carries).
            None if response.payload.len() <= BlockOpt::size_of(szx)
                && (num == 0 || !response.code.is_success()) =>
            {
                return response;
            }
            None => Source::new(std::mem::take(&mut response.payload)),
        };
        let len = body.0.len();
        if len <= BlockOpt::size_of(szx) && num == 0 {
            return match body.0.read(0..len) {
                Some(payload) => response.with_payload(payload),
                None => unreadable(),
            };
        }
        // Block numbers have 20 bits (RFC 7959 §2.2) and Size2 at most 4 bytes.
        if len > BlockOpt::size_of(szx) << 20 || u32::try_from(len).is_err() {
            return Response::diagnostic(
                Code::INTERNAL_SERVER_ERROR,
                "the representation is too large for block-wise transfer at this block size",
            );
        }
        if response.options.etag().is_none() {
            let etag = cx.msg.rng.next_u32().to_be_bytes();
            response.options.set(OptionNumber::ETAG, etag);
        }
        let Some(mut block) =
            block2_response(response.code, response.options.clone(), &body, num, szx)
        else {
            return unreadable();
        };
        if len > BlockOpt::size_of(szx) {
            self.arm_sweep(cx, now + limits.blockwise_lifetime);
            let (code, options) = (response.code, response.options);
            let how = if notification {
                Storing::Notification {
                    pause: block_pause(cx.config),
                }
            } else {
                Storing::Block2
            };
            (self.block2).insert(now, key, code, options, body, how, limits);
        }
        // The reply is remembered for duplicates for EXCHANGE_LIFETIME; a slice would keep
        // the whole representation (or a source's read-ahead window) alive that long.
        block.payload = Bytes::copy_from_slice(&block.payload);
        block
    }

    /// Sends the empty ACK of a CON request whose response is not ready (RFC 7252 §5.2.2).
    pub(super) fn ack_pending(&mut self, cx: &mut Context<'_>, id: u64) {
        let Some(p) = self.pending.get_mut(&id) else {
            return;
        };
        if p.acked || !p.confirmable {
            return;
        }
        p.acked = true;
        let (peer, mid) = (p.peer, p.mid);
        let seen = cx.msg.reply_with(peer, Message::empty(Type::Ack, mid));
        cx.msg.dedup.set_reply(peer, mid, seen);
    }

    /// Answers a received request ([`Endpoint::respond`]).
    pub(super) fn respond(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: IncomingId,
        response: Response,
    ) {
        let Some(p) = self.pending.remove(&id.0) else {
            return;
        };
        if p.budget.is_some() {
            self.verify
                .charge_group_work(now.saturating_duration_since(p.since));
        }
        if let Some(at) = p.not_before.filter(|&at| at > now) {
            self.held.insert(id.0, (p, response));
            cx.msg.schedule(at, TimerKind::Leisure { id: id.0 });
            return;
        }
        self.send_answer(cx, now, p, response);
    }

    /// The leisure of held answer `id` is over: it goes.
    pub(super) fn on_leisure_timer(&mut self, cx: &mut Context<'_>, now: Instant, id: u64) {
        if let Some((p, response)) = self.held.remove(&id) {
            self.send_answer(cx, now, p, response);
        }
    }

    /// Sends the application's answer to request `p`.
    fn send_answer(&mut self, cx: &mut Context<'_>, now: Instant, p: Pending, response: Response) {
        let max_szx = cx.config.max_block_szx;
        if let Some(budget) = p.budget {
            return self.respond_unverified(cx, now, &p, response, budget);
        }
        let mut q_rest = None;
        let mut response = if p.qblock2.is_empty() {
            self.blockwise_response(cx, now, p.key.clone(), p.block2, response, max_szx, false)
        } else {
            let (first, rest) = self.q_first_response(cx, now, &p, response);
            q_rest = rest;
            first
        };
        if let Some(obs) = p.observation {
            match self.observations.get_mut(&obs) {
                Some(o)
                    if response.code.is_success()
                        && response.options.contains(OptionNumber::OBSERVE) =>
                {
                    o.established = true;
                    o.seq = (o.seq + 1) & 0x00ff_ffff;
                    response.options.set_uint(OptionNumber::OBSERVE, o.seq);
                }
                _ => self.end_observation(cx, obs),
            }
        }
        if let Some(echo) = p.block1_echo {
            response.options.set_block(OptionNumber::BLOCK1, echo);
        }
        if p.multicast && response.code.is_error() {
            cx.msg.dedup.set_reply(p.peer, p.mid, Seen::Silent);
            return;
        }
        let msg = self.pending_reply(cx, now, &p, Type::Con, response);
        if msg.ty == Type::Con {
            cx.msg
                .send_con(now, p.peer, &msg, Purpose::SeparateResponse, cx.config);
        } else {
            let seen = cx.msg.reply_with(p.peer, msg);
            cx.msg.dedup.set_reply(p.peer, p.mid, seen);
        }
        if let Some(rest) = q_rest {
            self.q_after_first(cx, now, &p, rest);
        }
    }
}

/// Group requests of unverified peers the application works on at once: their time is
/// charged when they are answered, so a burst admitted before that would overdraw the
/// share by this many answers' time at most.
const UNVERIFIED_GROUP_WORK_AT_ONCE: usize = 4;

/// Marks a request answered (or dropped) by a stage of [`ServerLayer::on_request`]:
/// nothing more is done with it.
pub(super) struct Answered;

/// A request body assembled from blocks (Block1 or Q-Block1), and the Block1 option its
/// answer echoes.
#[derive(Default)]
struct Assembled {
    bytes: Option<Bytes>,
    block1_echo: Option<BlockOpt>,
}

/// How long a client partway through a stored representation may go without asking for
/// a block before a newer notification's representation takes its place: the longest
/// first retransmission timeout (ACK_TIMEOUT × ACK_RANDOM_FACTOR), so a block request lost
/// once still finds the representation it began.
fn block_pause(config: &crate::config::EndpointConfig) -> std::time::Duration {
    config.ack_timeout.mul_f64(config.ack_random_factor)
}
