//! The server side's behaviour: requests this endpoint receives, answered piggybacked or
//! separately, block-wise, observed (the state is in `server_state`).

use std::net::SocketAddr;
use std::time::Instant;

use bytes::Bytes;
use rand_core::RngCore;

use super::Endpoint;
use super::message::{Purpose, TimerKind};
use super::qserver::QNext;
use super::server_state::{Observation, Pending, block2_response, past_end, unreadable};
use super::types::{Event, IncomingId, IncomingRequest, ObservationId, Response};
use crate::block::{self, Block1Outcome, BlockKey, Slice, Source};
use crate::config::Limits;
use crate::dedup::{Fingerprint, Seen};
use crate::msg::{BlockOpt, Code, Message, OptionNumber, Token, Type};

impl Endpoint {
    /// A request of `size` bytes; its `payload` stays in the datagram until it is copied
    /// where it goes (an upload's block into the body being assembled).
    pub(super) fn on_request(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        mut msg: Message,
        payload: &[u8],
        size: usize,
        multicast: bool,
    ) {
        let limits = self.config.limits.clone();
        let con = msg.ty == Type::Con;
        let block2 = msg.options.block2();
        let block1 = msg.options.block1();
        // A Block2 continuation is looked up in the store before deduplication: the store
        // answers a duplicate just as well, and the message ID of a long transfer's
        // continuation may come round again to that of its first block, whose reply the
        // dedup store keeps (the token is the same).
        let continuation = matches!((block2, block1), (Some(b2), None) if b2.num > 0);
        // RFC 9177: Q-Block2 options (repeatable) and Q-Block1. Their blocks are served
        // from the store or assembled with duplicates found by block number, so they skip
        // deduplication as Block2 continuations do.
        let q2: Vec<BlockOpt> = msg
            .options
            .values(OptionNumber::Q_BLOCK2)
            .filter_map(BlockOpt::decode)
            .collect();
        let q1 = msg.options.block(OptionNumber::Q_BLOCK1);
        let q_stateless = q1.is_some() || q2.iter().any(|b| b.num > 0);
        if !continuation && !q_stateless && self.replay_duplicate(now, peer, &msg, &limits) {
            return;
        }
        let lifetime = if con {
            self.config.exchange_lifetime
        } else {
            self.config.non_lifetime
        };
        let expires = now + lifetime;

        // RFC 9175 §2.4: an unverified peer gets at most three times `size`. What would
        // send it more, keep state for it, or change state waits for an Echo round trip.
        let verified = !self.config.verify_addresses
            || self.verify.is_verified(
                now,
                peer,
                msg.options.first(OptionNumber::ECHO),
                limits.verified_lifetime,
                limits.verified_peers,
            );
        let budget = (!verified).then_some(3 * size);
        if !verified
            && (!matches!(msg.code, Code::GET | Code::FETCH)
                || msg.options.uint(OptionNumber::OBSERVE) == Some(0)
                || block1.is_some()
                || continuation
                || q1.is_some()
                || !q2.is_empty())
        {
            let header = self.reply_header(&msg);
            let challenge = self.challenge(now, peer, msg.token, header, 3 * size);
            let seen = match challenge {
                Some(reply) => self.reply_with(peer, reply),
                // A CON gets a Reset rather than waiting for an answer that never comes.
                None if con => self.reply_with(peer, Message::empty(Type::Rst, msg.message_id)),
                None => Seen::Silent,
            };
            let key = (peer, msg.message_id);
            let limits = &self.config.limits;
            (self.msg.dedup).insert(now, key, Fingerprint::of(&msg), expires, seen, limits);
            return;
        }

        if let Some(bad) = msg.options.first_bad_critical() {
            if continuation && self.replay_duplicate(now, peer, &msg, &limits) {
                return;
            }
            // RFC 7252 §5.4.1: 4.02 for a CON request; a NON one is rejected.
            let seen = if con {
                let text = format!("unrecognized or malformed critical option {}", bad.0);
                let mut response = Response::diagnostic(Code::BAD_OPTION, &text);
                if budget.is_some() {
                    // The diagnostic could be many times a short request.
                    response.payload = Bytes::new();
                }
                self.reply(peer, &msg, multicast, response)
            } else if multicast {
                Seen::Silent
            } else {
                self.reply_with(peer, Message::empty(Type::Rst, msg.message_id))
            };
            self.msg.dedup.insert(
                now,
                (peer, msg.message_id),
                Fingerprint::of(&msg),
                expires,
                seen,
                &limits,
            );
            return;
        }
        msg.options.drop_bad_elective();
        let key = BlockKey {
            peer,
            method: msg.code,
            options: msg.options.block_key(),
        };

        let mut assembled = None;
        if !q2.is_empty() || q1.is_some() {
            match self.on_q_request(now, peer, &msg, payload, multicast, &key, &q2, q1, expires) {
                QNext::Done => return,
                QNext::Dispatch(body) => assembled = body,
            }
        }

        // A Block2 continuation is served from the stored representation; the application
        // never sees it (a POST grab must not grab again).
        if let (Some(b2), true) = (block2, continuation) {
            // A GET falls through when nothing is stored: it is safe, so the application
            // renders it again and the block is cut from the new representation (its ETag
            // tells the client whether the blocks still fit).
            let szx = b2.szx.min(self.config.max_block_szx);
            let (ty, mid) = self.reply_header(&msg);
            // Stored for this peer, or for a request this peer sent to a group.
            let group_key;
            let stored_key = if self.server.block2.contains(&key) {
                &key
            } else {
                group_key = key.for_group();
                &group_key
            };
            let stored = self
                .server
                .block2
                .with_stored(now, stored_key, &limits, |s| {
                    if s.q_options.is_some() {
                        // Stored for Q-Block2: not a body to cut Block2 blocks from.
                        return Slice::Unreadable;
                    }
                    let slice = block::slice(&*s.body.0, b2.num, szx);
                    if let Slice::Block(payload, opt) = &slice {
                        // The block goes out as the stored options, encoded once, around this
                        // Block2.
                        let header = (ty, s.code, mid, msg.token);
                        self.msg.outbox.send_with(peer, payload.len(), |out| {
                            s.head.encode_into(out, header, opt.as_uint(), payload);
                        });
                    }
                    slice
                });
            match stored {
                // Served from the store, which is idempotent (RFC 7252 §4.5 allows
                // relaxing deduplication then): a duplicate is cut again from the same
                // bytes, and a 10 MB transfer leaves no 10,000 dedup entries behind.
                Some(Slice::Block(..)) => return,
                // RFC 7959 §2.2: a block past the end is a bad option.
                Some(Slice::PastEnd) => {
                    if let Some(reply) = self.reply_message(&msg, multicast, past_end()) {
                        self.msg.send(peer, &reply);
                    }
                    return;
                }
                // The stored source can no longer be read as it was: as if nothing were
                // stored.
                Some(Slice::Unreadable) => self.server.block2.remove(stored_key),
                None => {}
            }
            if self.replay_duplicate(now, peer, &msg, &limits) {
                return;
            }
            if !matches!(msg.code, Code::GET | Code::FETCH) {
                let response = Response::diagnostic(
                    Code::REQUEST_ENTITY_INCOMPLETE,
                    "the representation is no longer stored; repeat the request from block 0",
                );
                self.answer(now, peer, &msg, multicast, expires, response);
                return;
            }
        }

        let mut block1_echo = None;
        if let Some(b1) = block1 {
            let size1 = msg.options.uint(OptionNumber::SIZE1);
            let outcome =
                self.server
                    .block1
                    .handle(now, key.clone(), b1, size1, payload, &self.config);
            self.arm_sweep(now + limits.blockwise_lifetime);
            let response = match outcome {
                Block1Outcome::Continue(opt) => {
                    let mut r = Response::new(Code::CONTINUE);
                    r.options.set_block(OptionNumber::BLOCK1, opt);
                    Some(r)
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
                    Some(r)
                }
                Block1Outcome::Complete(body, echo) => {
                    assembled = Some(body);
                    block1_echo = Some(echo);
                    None
                }
            };
            if let Some(response) = response {
                self.answer(now, peer, &msg, multicast, expires, response);
                return;
            }
        }

        if self.server.unanswered() >= limits.pending_requests {
            let mut r = Response::new(Code::SERVICE_UNAVAILABLE);
            r.options.set_uint(OptionNumber::MAX_AGE, 1);
            self.answer(now, peer, &msg, multicast, expires, r);
            return;
        }
        let id = self.new_id();
        let observation = self.observe_option(peer, &msg, &key);
        // RFC 7252 §8.2: a random instant within Leisure from now, drawn here so that the
        // draws follow the requests' order.
        let leisure = self.config.leisure;
        let not_before =
            (multicast && !leisure.is_zero()).then(|| now + leisure.mul_f64(self.msg.unit()));
        self.server.pending.insert(
            id,
            Pending {
                peer,
                mid: msg.message_id,
                token: msg.token,
                confirmable: con,
                acked: false,
                multicast,
                block2,
                block1_echo,
                budget,
                // A response to a group request is stored for the client's port, whatever
                // address its unicast follow-ups come from.
                key: if multicast { key.for_group() } else { key },
                observation,
                qblock2: if observation.is_none() {
                    q2
                } else {
                    Vec::new()
                },
                not_before,
            },
        );
        self.msg.dedup.insert(
            now,
            (peer, msg.message_id),
            Fingerprint::of(&msg),
            expires,
            Seen::Pending(id),
            &limits,
        );
        if con {
            self.msg.schedule(
                now + self.config.separate_ack_delay,
                TimerKind::SeparateAck { id },
            );
        }
        self.events.push_back(Event::Request(IncomingRequest {
            id: IncomingId(id),
            peer,
            method: msg.code,
            options: msg.options,
            payload: assembled.unwrap_or_else(|| Bytes::copy_from_slice(payload)),
            multicast,
            confirmable: con,
            observe: observation.map(ObservationId),
            identity: None,
        }));
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
    fn pending_reply(&mut self, p: &Pending, late: Type, response: Response) -> Message {
        let (ty, message_id) = match (p.confirmable, p.acked) {
            (true, false) => (Type::Ack, p.mid),
            (true, true) => (late, self.msg.next_mid()),
            (false, _) => (Type::Non, self.msg.next_mid()),
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

    /// Answers request `p` of an unverified peer: the response when it fits in `budget`
    /// bytes and one block, the Echo challenge otherwise. Nothing is stored for the peer,
    /// and an answer after the empty ACK goes as a NON: a CON would be sent up to five
    /// times to an address nobody verified.
    fn respond_unverified(&mut self, now: Instant, p: &Pending, response: Response, budget: usize) {
        let source = response.source.is_some();
        let answer = self.pending_reply(p, Type::Non, response);
        let (ty, mid) = (answer.ty, answer.message_id);
        let fits = !source
            && answer.payload.len() <= BlockOpt::size_of(self.config.max_block_szx)
            && answer.encoded_len() <= budget;
        let reply = if !fits {
            self.challenge(now, p.peer, p.token, (ty, mid), budget)
                .or_else(|| (ty == Type::Ack).then(|| Message::empty(Type::Rst, mid)))
        } else if p.multicast && answer.code.is_error() {
            None
        } else {
            Some(answer)
        };
        let seen = match reply {
            Some(m) => self.reply_with(p.peer, m),
            None => Seen::Silent,
        };
        self.msg.dedup.set_reply(p.peer, p.mid, seen);
    }

    /// Makes sure the sweep runs no later than `at`.
    pub(super) fn arm_sweep(&mut self, at: Instant) {
        if self.server.sweep_at.is_some_and(|armed| armed <= at) {
            return;
        }
        self.server.sweep_at = Some(at);
        self.msg.schedule(at, TimerKind::Sweep { at });
    }

    /// Drops the uploads and stored representations idle for their lifetime, so what an
    /// idle server holds shrinks without a request to trigger it, and arms the next sweep
    /// for the first of the rest to run out.
    pub(super) fn on_sweep_timer(&mut self, now: Instant, at: Instant) {
        if self.server.sweep_at != Some(at) {
            return;
        }
        self.server.sweep_at = None;
        let limits = &self.config.limits;
        self.server.block1.expire_all(now, limits);
        self.server.block2.expire(now, limits);
        let oldest = [self.server.block1.oldest(), self.server.block2.oldest()];
        if let Some(first) = oldest.into_iter().flatten().min() {
            self.arm_sweep(first + limits.blockwise_lifetime);
        }
    }

    /// Answers a duplicate message as the first one was answered (RFC 7252 §4.5); whether
    /// `msg` was one.
    pub(super) fn replay_duplicate(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        msg: &Message,
        limits: &Limits,
    ) -> bool {
        let Some(seen) =
            self.msg
                .dedup
                .check(now, peer, msg.message_id, Fingerprint::of(msg), limits)
        else {
            return false;
        };
        match seen.clone() {
            Seen::Replied(m) => self.msg.send(peer, &m),
            Seen::Pending(id) if msg.ty == Type::Con => self.ack_pending(id),
            Seen::Pending(_) | Seen::Silent => {}
        }
        true
    }

    /// RFC 7641 §2, §3.6: a GET or FETCH with Observe 0 registers (or re-registers, same
    /// peer and token) an observation; Observe 1 deregisters.
    pub(super) fn observe_option(
        &mut self,
        peer: SocketAddr,
        msg: &Message,
        key: &BlockKey,
    ) -> Option<u64> {
        if !matches!(msg.code, Code::GET | Code::FETCH) {
            return None;
        }
        let value = msg.options.uint(OptionNumber::OBSERVE)?;
        let existing = self
            .server
            .observations
            .iter()
            .find(|(_, o)| o.peer == peer && o.token == msg.token)
            .map(|(id, _)| *id);
        match (value, existing) {
            (0, Some(id)) => Some(id),
            (0, None) if self.server.observations.len() < self.config.limits.observations => {
                let id = self.new_id();
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
                self.server.observations.insert(id, o);
                Some(id)
            }
            (1, Some(id)) => {
                self.end_observation(id);
                None
            }
            _ => None,
        }
    }

    pub(super) fn end_observation(&mut self, id: u64) {
        if self.server.observations.remove(&id).is_some() {
            self.events.push_back(Event::ObservationEnded {
                id: ObservationId(id),
            });
        }
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
        let limits = self.config.limits.clone();
        let interval = self.config.notify_con_interval;
        let szx = self.config.max_block_szx;
        let Some(o) = self
            .server
            .observations
            .get_mut(&id.0)
            .filter(|o| o.established)
        else {
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
        let mut response = self.blockwise_response(now, key, None, response, &limits, szx);
        let success = response.code.is_success();
        if success {
            response.options.set_uint(OptionNumber::OBSERVE, seq);
        }
        let ty = if con { Type::Con } else { Type::Non };
        let msg = Message {
            ty,
            code: response.code,
            message_id: self.msg.next_mid(),
            token,
            options: response.options,
            payload: response.payload,
        };
        if con {
            self.msg
                .send_con(now, peer, &msg, Purpose::Notification(id.0), &self.config);
            if let Some(o) = self.server.observations.get_mut(&id.0) {
                o.in_flight = true;
            }
        } else {
            self.msg.send(peer, &msg);
            if let Some(o) = self.server.observations.get_mut(&id.0) {
                o.last_mid = Some(msg.message_id);
            }
        }
        if !success {
            self.end_observation(id.0);
        }
        true
    }

    /// Cuts a response into its first (or requested) block when it does not fit one, adding
    /// an ETag and storing the representation for the continuations.
    pub(super) fn blockwise_response(
        &mut self,
        now: Instant,
        key: BlockKey,
        block2: Option<BlockOpt>,
        mut response: Response,
        limits: &Limits,
        max_szx: u8,
    ) -> Response {
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
            let etag = self.msg.rng.next_u32().to_be_bytes();
            response.options.set(OptionNumber::ETAG, etag);
        }
        let Some(mut block) =
            block2_response(response.code, response.options.clone(), &body, num, szx)
        else {
            return unreadable();
        };
        if len > BlockOpt::size_of(szx) {
            self.arm_sweep(now + limits.blockwise_lifetime);
            self.server.block2.insert(
                now,
                key,
                response.code,
                response.options,
                body,
                false,
                limits,
            );
        }
        // The reply is remembered for duplicates for EXCHANGE_LIFETIME; a slice would keep
        // the whole representation (or a source's read-ahead window) alive that long.
        block.payload = Bytes::copy_from_slice(&block.payload);
        block
    }

    /// Answers a request at once and remembers the answer for its duplicates.
    pub(super) fn answer(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        req: &Message,
        multicast: bool,
        expires: Instant,
        response: Response,
    ) {
        let seen = self.reply(peer, req, multicast, response);
        let limits = &self.config.limits;
        self.msg.dedup.insert(
            now,
            (peer, req.message_id),
            Fingerprint::of(req),
            expires,
            seen,
            limits,
        );
    }

    /// Sends a response to a request right away (piggybacked on the ACK of a CON, or as a
    /// NON to a NON) and returns what to remember for duplicates. Error responses to
    /// multicast requests are suppressed (RFC 7390 §2.7).
    pub(super) fn reply(
        &mut self,
        peer: SocketAddr,
        req: &Message,
        multicast: bool,
        response: Response,
    ) -> Seen {
        match self.reply_message(req, multicast, response) {
            Some(msg) => self.reply_with(peer, msg),
            None => Seen::Silent,
        }
    }

    /// The type and message ID of a reply to `req`: a piggybacked ACK to a CON, a NON
    /// with a new message ID otherwise.
    pub(super) fn reply_header(&mut self, req: &Message) -> (Type, u16) {
        match req.ty {
            Type::Con => (Type::Ack, req.message_id),
            _ => (Type::Non, self.msg.next_mid()),
        }
    }

    /// The message that answers `req` right away; `None` when nothing is sent (an error
    /// response to a multicast request).
    pub(super) fn reply_message(
        &mut self,
        req: &Message,
        multicast: bool,
        response: Response,
    ) -> Option<Message> {
        if multicast && response.code.is_error() {
            return None;
        }
        let (ty, mid) = self.reply_header(req);
        let msg = Message {
            ty,
            code: response.code,
            message_id: mid,
            token: req.token,
            options: response.options,
            payload: response.payload,
        };
        Some(msg)
    }

    /// Sends a reply and keeps the message (not its encoding, which shares a chunk with
    /// other messages) to send again for duplicates.
    pub(super) fn reply_with(&mut self, peer: SocketAddr, msg: Message) -> Seen {
        self.msg.send(peer, &msg);
        Seen::Replied(Box::new(msg))
    }

    pub(super) fn on_separate_ack_timer(&mut self, _now: Instant, id: u64) {
        self.ack_pending(id);
    }

    /// Sends the empty ACK of a CON request whose response is not ready (RFC 7252 §5.2.2).
    pub(super) fn ack_pending(&mut self, id: u64) {
        let Some(p) = self.server.pending.get_mut(&id) else {
            return;
        };
        if p.acked || !p.confirmable {
            return;
        }
        p.acked = true;
        let (peer, mid) = (p.peer, p.mid);
        let seen = self.reply_with(peer, Message::empty(Type::Ack, mid));
        self.msg.dedup.set_reply(peer, mid, seen);
    }

    /// Answers a request from [`Event::Request`]. A body larger than one block is stored
    /// and sent with Block2 (ETag and Size2 added); later blocks are served from the store.
    /// Answering an unknown or already answered id does nothing.
    /// The answer to a multicast request waits for the end of its leisure (RFC 7252
    /// §8.2), held by the endpoint.
    pub fn respond(&mut self, now: Instant, id: IncomingId, response: Response) {
        let Some(p) = self.server.pending.remove(&id.0) else {
            return;
        };
        if let Some(at) = p.not_before.filter(|&at| at > now) {
            self.server.held.insert(id.0, (p, response));
            self.msg.schedule(at, TimerKind::Leisure { id: id.0 });
            return;
        }
        self.send_answer(now, p, response);
    }

    /// The leisure of held answer `id` is over: it goes.
    pub(super) fn on_leisure_timer(&mut self, now: Instant, id: u64) {
        if let Some((p, response)) = self.server.held.remove(&id) {
            self.send_answer(now, p, response);
        }
    }

    /// Sends the application's answer to request `p`.
    fn send_answer(&mut self, now: Instant, p: Pending, response: Response) {
        let limits = self.config.limits.clone();
        let max_szx = self.config.max_block_szx;
        if let Some(budget) = p.budget {
            return self.respond_unverified(now, &p, response, budget);
        }
        let mut q_rest = None;
        let mut response = if p.qblock2.is_empty() {
            self.blockwise_response(now, p.key.clone(), p.block2, response, &limits, max_szx)
        } else {
            let (first, rest) = self.q_first_response(now, &p, response);
            q_rest = rest;
            first
        };
        if let Some(obs) = p.observation {
            match self.server.observations.get_mut(&obs) {
                Some(o)
                    if response.code.is_success()
                        && response.options.contains(OptionNumber::OBSERVE) =>
                {
                    o.established = true;
                    o.seq = (o.seq + 1) & 0x00ff_ffff;
                    response.options.set_uint(OptionNumber::OBSERVE, o.seq);
                }
                _ => self.end_observation(obs),
            }
        }
        if let Some(echo) = p.block1_echo {
            response.options.set_block(OptionNumber::BLOCK1, echo);
        }
        if p.multicast && response.code.is_error() {
            self.msg.dedup.set_reply(p.peer, p.mid, Seen::Silent);
            return;
        }
        let msg = self.pending_reply(&p, Type::Con, response);
        if msg.ty == Type::Con {
            self.msg
                .send_con(now, p.peer, &msg, Purpose::SeparateResponse, &self.config);
        } else {
            let seen = self.reply_with(p.peer, msg);
            self.msg.dedup.set_reply(p.peer, p.mid, seen);
        }
        if let Some(rest) = q_rest {
            self.q_after_first(now, &p, rest);
        }
    }
}
