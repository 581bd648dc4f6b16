//! The client side of RFC 9177: a response body fetched with Q-Block2 and a request body
//! sent with Q-Block1 (their state, [`QDown`] and [`QUp`], lives in the request).
//!
//! Q-Block2: the first request carries Q-Block2 0 with M (a CON: RFC 9177 §4.1 requires
//! finding out with a CON whether the server knows the option; a 4.02 means it does not,
//! and the request goes on as a windowed RFC 7959 download). A server answers a CON with
//! block 0 only, so the rest of the first set is asked for with a NON. Each whole set is
//! confirmed with a 'Continue' for the next; blocks of a later set arriving with earlier
//! ones missing, or NON_RECEIVE_TIMEOUT without a block, ask for the missing ones (at
//! most MAX_PAYLOADS per request, one Q-Block2 option each). Every request has a new
//! token. Blocks are delivered in order; those that arrive early wait.
//!
//! Q-Block1: block 0 goes as a CON (the same test; a 4.02 sends the body with Block1
//! instead), the others as NONs, MAX_PAYLOADS at a time, with Request-Tag and Size1 in
//! each. A 2.31 sends the next set; a 4.08 listing missing blocks sends them again;
//! NON_TIMEOUT_RANDOM without either sends the next set anyway, or, once all went, the
//! last block again (NON_MAX_RETRANSMIT times).

use std::collections::BTreeMap;
use std::time::Instant;

use bytes::Bytes;
use rand_core::RngCore;

use super::client_state::ClientLayer;
use super::client_state::{Step, Waiting};
use super::context::Context;
use super::message::TimerKind;
use super::qblock::{self, MISSING_BLOCKS_CBOR_SEQ, NON_MAX_RETRANSMIT, QDown, QUp};
use super::types::{RequestError, Response};
use crate::config::EndpointConfig;
use crate::config::Transfer;
use crate::msg::{BlockOpt, Code, Message, OptionNumber, Options, Outgoing, Token, Type};

impl super::client_state::ClientRequest {
    /// Sends block `num` of the request's Q-Block1 body (with Request-Tag, and Size1 in
    /// every block, RFC 9177 §4.3, §4.6).
    pub(super) fn send_qup_block(
        &self,
        num: u32,
        ty: Type,
        mid: u16,
        token: Token,
        outbox: &mut super::message::Outbox,
    ) {
        let Some(u) = self.qup.as_ref() else { return };
        let size = BlockOpt::size_of(u.szx);
        let len = self.req.payload.len();
        let start = (num as usize * size).min(len);
        let end = (start + size).min(len);
        let opt = BlockOpt {
            num,
            more: num + 1 < u.blocks,
            szx: u.szx,
        };
        let uints = [
            (OptionNumber::Q_BLOCK1, opt.as_uint()),
            (OptionNumber::SIZE1, len as u32),
        ];
        let out = Outgoing {
            ty,
            code: self.req.method,
            message_id: mid,
            token,
            options: &u.options,
            uints: &uints,
            payload: &self.req.payload[start..end],
        };
        outbox.send(self.peer, &out);
    }
}

impl ClientLayer {
    /// The first response to a request that asked for Q-Block2 carries Q-Block2 `q` with
    /// more to come: the body is fetched set by set.
    pub(super) fn start_qdown(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        msg: &Message,
        payload: &[u8],
        q: BlockOpt,
    ) {
        let limit = cx.config.limits.client_body_bytes;
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        let Some(total) = msg.options.uint(OptionNumber::SIZE2).map(|t| t as usize) else {
            return self.fail(
                cx,
                now,
                id,
                RequestError::Protocol("Q-Block2 response without Size2"),
            );
        };
        if total > limit {
            return self.fail(cx, now, id, RequestError::TooLarge { limit });
        }
        if q.num != 0 {
            return self.fail(
                cx,
                now,
                id,
                RequestError::Protocol("first Q-Block2 response is not block 0"),
            );
        }
        let mut first = msg.options.clone();
        first.remove(OptionNumber::Q_BLOCK2);
        r.etag = msg.options.etag().map(<[u8]>::to_vec);
        r.first_options = Some(first);
        if !r.req.stream {
            r.body.reserve(total);
        }
        let last = qblock::last_block(total, q.szx);
        r.qdown = Some(QDown {
            szx: q.szx,
            last,
            total,
            got: vec![false; last as usize + 1],
            ahead: BTreeMap::new(),
            next_deliver: 0,
            asked_sets: 1,
            seen_set: 0,
            continued_at: None,
            heard: now,
            tries: 0,
            at: None,
            tokens: Vec::new(),
        });
        r.waiting = Waiting::Window;
        r.generation += 1;
        let con = msg.ty == Type::Ack;
        self.on_qdown_block(cx, now, id, msg, payload);
        if con && self.requests.get(&id).is_some_and(|r| r.qdown.is_some()) {
            // The server answered the CON with block 0 alone: ask for the rest of the set.
            self.qdown_ask(
                cx,
                now,
                id,
                &[BlockOpt {
                    num: 1,
                    more: true,
                    szx: q.szx,
                }],
            );
        }
    }

    /// A response to one of a Q-Block2 body's requests.
    pub(super) fn on_qdown_response(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        msg: &mut Message,
        payload: &[u8],
    ) {
        if !msg.code.is_success() || !msg.options.contains(OptionNumber::Q_BLOCK2) {
            // An error in the middle of the body (the representation went away, the
            // server is busy): the server's answer.
            let response = super::client_state::take_response(msg, payload);
            return self.complete(cx, now, id, response);
        }
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if msg.options.etag() != r.etag.as_deref() {
            // RFC 9177 §4.4: the representation changed; the partial body is stale.
            return self.fail(cx, now, id, RequestError::RepresentationChanged);
        }
        self.on_qdown_block(cx, now, id, msg, payload);
    }

    /// Block `msg` of a Q-Block2 body arrived.
    fn on_qdown_block(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        msg: &Message,
        payload: &[u8],
    ) {
        let limit = cx.config.limits.client_body_bytes;
        let mp = cx.config.payloads_per_set();
        let Some(q) = msg.options.block(OptionNumber::Q_BLOCK2) else {
            return;
        };
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        let peer = r.peer;
        let Some(d) = r.qdown.as_mut() else { return };
        let size = BlockOpt::size_of(d.szx);
        if q.szx != d.szx
            || q.num > d.last
            || payload.len() != d.total.saturating_sub(q.num as usize * size).min(size)
            || q.more != (q.num < d.last)
        {
            return self.fail(
                cx,
                now,
                id,
                RequestError::Protocol("the Q-Block2 block does not fit Size2"),
            );
        }
        if d.got[q.num as usize] {
            return;
        }
        d.got[q.num as usize] = true;
        d.heard = now;
        d.tries = 0;
        let set = q.num / mp;
        let mut sample = None;
        if set + 1 == d.asked_sets
            && let Some(at) = d.continued_at.take()
        {
            sample = Some(now.saturating_duration_since(at));
        }
        let new_set = set > d.seen_set;
        d.seen_set = d.seen_set.max(set);
        let last = d.last;
        if q.num != d.next_deliver {
            d.ahead.insert(q.num, payload.to_vec());
        } else {
            let mut block: Option<Vec<u8>> = None;
            let mut num = q.num;
            loop {
                let data = block.as_deref().unwrap_or(payload);
                if let Err(e) = r.append(id, data, num < last, size, limit, cx.events) {
                    return self.fail(cx, now, id, e);
                }
                num += 1;
                let Some(d) = r.qdown.as_mut() else { return };
                d.next_deliver = num;
                block = d.ahead.remove(&num);
                if block.is_none() {
                    break;
                }
            }
        }
        if let Some(rtt) = sample {
            cx.msg.path(now, peer).rtt.on_plausible_sample(now, rtt);
        }
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        let Some(d) = r.qdown.as_ref() else { return };
        if d.next_deliver > d.last {
            let body = Bytes::from(std::mem::take(&mut r.body));
            let options = r.first_options.take().unwrap_or_default();
            let response = Response::with_parts(msg.code, options, body);
            return self.complete(cx, now, id, response);
        }
        let szx = d.szx;
        let asked_end = (d.asked_sets * mp).min(d.last + 1);
        let mut latest_whole = (d.asked_sets - 1) * mp..asked_end;
        if latest_whole.all(|n| d.got[n as usize]) && asked_end <= d.last {
            // RFC 9177 §7.2: the latest set is whole: 'Continue' with the next.
            let next = d.asked_sets;
            if let Some(d) = r.qdown.as_mut() {
                d.asked_sets += 1;
                d.continued_at = Some(now);
            }
            self.qdown_ask(
                cx,
                now,
                id,
                &[BlockOpt {
                    num: next * mp,
                    more: true,
                    szx,
                }],
            );
        } else if new_set {
            // A new set began with blocks missing before it: ask for them at once.
            let missing = self.qdown_missing(cx.config, id, set * mp);
            if !missing.is_empty() {
                self.qdown_ask(cx, now, id, &missing);
            }
        }
        self.arm_qdown(cx, now, id);
    }

    /// The first MAX_PAYLOADS missing blocks below `end`, as Q-Block2 options without M.
    fn qdown_missing(&self, config: &EndpointConfig, id: u64, end: u32) -> Vec<BlockOpt> {
        let mp = config.payloads_per_set() as usize;
        let Some(d) = self.requests.get(&id).and_then(|r| r.qdown.as_ref()) else {
            return Vec::new();
        };
        (0..end.min(d.last + 1))
            .filter(|&n| !d.got[n as usize])
            .take(mp)
            .map(|num| BlockOpt {
                num,
                more: false,
                szx: d.szx,
            })
            .collect()
    }

    /// Sends a NON request for the body with these Q-Block2 options and a new token.
    fn qdown_ask(&mut self, cx: &mut Context<'_>, now: Instant, id: u64, opts: &[BlockOpt]) {
        let Some(peer) = self.requests.get(&id).map(|r| r.peer) else {
            return;
        };
        let token = self.new_token(cx);
        let mid = cx.msg.next_mid(now, peer);
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        let mut options = r.req.options.clone();
        for o in opts {
            options.push(OptionNumber::Q_BLOCK2, o.encode());
        }
        let msg = Message {
            ty: Type::Non,
            code: r.req.method,
            message_id: mid,
            token,
            options,
            payload: r.req.payload.clone(),
        };
        let peer = r.peer;
        if let Some(d) = r.qdown.as_mut() {
            d.tokens.push(token);
        }
        self.by_token.insert(token, id);
        cx.msg.send(peer, &msg);
        let stats = &mut cx.msg.path(now, peer).stats;
        stats.block_requests += 1;
        if !matches!(opts, [o] if o.more) {
            // Missing blocks asked for again.
            stats.blocks_lost += opts.len() as u64;
        }
    }

    /// Arms the body's timer NON_RECEIVE_TIMEOUT after its last block.
    fn arm_qdown(&mut self, cx: &mut Context<'_>, _now: Instant, id: u64) {
        let ack = cx.config.ack_timeout;
        let Some(peer) = self.requests.get(&id).map(|r| r.peer) else {
            return;
        };
        let estimate = cx.msg.estimate(peer);
        let Some(d) = self.qdown_mut(id) else {
            return;
        };
        let at = d.heard + qblock::receive_timeout(estimate, ack, d.tries);
        d.at = Some(at);
        cx.msg.schedule(at, TimerKind::QClient { id, at });
    }

    /// NON_RECEIVE_TIMEOUT without a block: ask for what is missing of the sets asked for
    /// (a lost 'Continue' shows as a whole set missing), NON_MAX_RETRANSMIT times.
    fn on_qdown_timer(&mut self, cx: &mut Context<'_>, now: Instant, id: u64) {
        let mp = cx.config.payloads_per_set();
        let Some(d) = self.qdown_mut(id) else {
            return;
        };
        if d.tries >= NON_MAX_RETRANSMIT {
            return self.fail(cx, now, id, RequestError::Timeout);
        }
        d.tries += 1;
        d.heard = now;
        let end = d.asked_sets * mp;
        let missing = self.qdown_missing(cx.config, id, end);
        if !missing.is_empty() {
            self.qdown_ask(cx, now, id, &missing);
        }
        self.arm_qdown(cx, now, id);
    }

    /// A client Q-Block timer fired.
    pub(super) fn on_qclient_timer(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        at: Instant,
    ) {
        let Some(r) = self.requests.get(&id) else {
            return;
        };
        if r.qdown.as_ref().is_some_and(|d| d.at == Some(at)) {
            self.on_qdown_timer(cx, now, id);
        } else if r.qup.as_ref().is_some_and(|u| u.at == Some(at)) {
            self.on_qup_timer(cx, now, id);
        }
    }

    /// Whether request `id`'s Q-Block timer is the one armed for `at`.
    pub(super) fn qclient_timer_is(&self, id: u64, at: Instant) -> bool {
        self.requests.get(&id).is_some_and(|r| {
            r.qdown.as_ref().is_some_and(|d| d.at == Some(at))
                || r.qup.as_ref().is_some_and(|u| u.at == Some(at))
        })
    }

    /// The state of a request body sent with Q-Block1, before block 0 goes.
    pub(super) fn new_qup(
        &mut self,
        cx: &mut Context<'_>,
        szx: u8,
        req_options: &Options,
        len: usize,
        peer: std::net::SocketAddr,
    ) -> QUp {
        let mut options = req_options.clone();
        let tag = cx.msg.rng.next_u32().to_be_bytes();
        options.set(OptionNumber::REQUEST_TAG, tag);
        let unit = cx.msg.unit();
        let c = cx.config;
        let timeout = qblock::non_timeout(
            cx.msg.estimate(peer),
            c.ack_timeout,
            c.ack_random_factor,
            unit,
        );
        QUp {
            options,
            szx,
            blocks: len.div_ceil(BlockOpt::size_of(szx)).max(1) as u32,
            next_new: 1,
            probing: true,
            timeout,
            set_sent: None,
            last_sent: None,
            tries: 0,
            at: None,
            tokens: Vec::new(),
        }
    }

    /// Sends block `num` of a Q-Block1 body as a NON with a new token, or again with
    /// message ID and token `again`.
    fn qup_send_block(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        num: u32,
        again: Option<(u16, Token)>,
    ) {
        let Some(peer) = self.requests.get(&id).map(|r| r.peer) else {
            return;
        };
        let (mid, token) = match again {
            Some(x) => x,
            None => (cx.msg.next_mid(now, peer), self.new_token(cx)),
        };
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        r.send_qup_block(num, Type::Non, mid, token, &mut cx.msg.outbox);
        let Some(u) = r.qup.as_mut() else { return };
        u.last_sent = Some((num, mid, token));
        if again.is_none() {
            u.tokens.push(token);
            self.by_token.insert(token, id);
        }
    }

    /// Sends the next set of new blocks (the rest of the first set after block 0), and
    /// arms NON_TIMEOUT_RANDOM.
    fn qup_next_set(&mut self, cx: &mut Context<'_>, now: Instant, id: u64) {
        let mp = cx.config.payloads_per_set();
        let Some(u) = self.qup_mut(id) else {
            return;
        };
        u.probing = false;
        let start = u.next_new;
        let end = ((start / mp + 1) * mp).min(u.blocks);
        for num in start..end {
            self.qup_send_block(cx, now, id, num, None);
        }
        if let Some(peer) = self.requests.get(&id).map(|r| r.peer) {
            let stats = &mut cx.msg.path(now, peer).stats;
            stats.block_requests += u64::from(end.saturating_sub(start));
            stats.max_window = stats.max_window.max(u64::from(mp));
        }
        if let Some(u) = self.qup_mut(id) {
            u.next_new = u.next_new.max(end);
            u.set_sent = Some(now);
            u.tries = 0;
        }
        self.arm_qup(cx, now, id);
    }

    fn arm_qup(&mut self, cx: &mut Context<'_>, now: Instant, id: u64) {
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        r.waiting = Waiting::Window;
        let Some(u) = r.qup.as_mut() else { return };
        let at = now + u.timeout * (1 << u.tries.min(6));
        u.at = Some(at);
        cx.msg.schedule(at, TimerKind::QClient { id, at });
    }

    /// The CON of block 0 was acknowledged without a response: the server takes Q-Block1.
    pub(super) fn qup_probe_acked(&mut self, cx: &mut Context<'_>, now: Instant, id: u64) {
        // NON_TIMEOUT_RANDOM stays the RFC's (drawn once, before any round trip was
        // known): a set sent sooner, without a 2.31, leaves more gaps than libcoap
        // 4.3.5's server tracks (it answers 4.08 "Too many missing blocks").
        self.qup_next_set(cx, now, id);
    }

    /// A response to one of a Q-Block1 body's blocks.
    pub(super) fn on_qup_response(
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
        let peer = r.peer;
        let Some(u) = r.qup.as_mut() else { return };
        if u.probing && msg.code == Code::BAD_OPTION {
            // RFC 9177 §4.1: the server does not know Q-Block1; RFC 7959 then.
            r.qup = None;
            r.req.transfer = Some(Transfer::Window);
            r.step = Step::Upload { offset: 0 };
            return self.send_step(cx, now, id);
        }
        if msg.code == Code::CONTINUE {
            let Some(q) = msg.options.block(OptionNumber::Q_BLOCK1) else {
                return;
            };
            if q.num + 1 >= u.next_new && u.next_new < u.blocks {
                if let Some(at) = u.set_sent.take() {
                    cx.msg.path(now, peer).rtt.on_sample(
                        now,
                        now.saturating_duration_since(at),
                        true,
                    );
                }
                self.qup_next_set(cx, now, id);
            }
            return;
        }
        if msg.code == Code::REQUEST_ENTITY_INCOMPLETE
            && msg.options.uint(OptionNumber::CONTENT_FORMAT) == Some(MISSING_BLOCKS_CBOR_SEQ)
        {
            let Some(missing) = qblock::decode_missing(payload) else {
                return;
            };
            u.probing = false;
            let next_new = u.next_new;
            // Blocks not sent yet are the next set, asked for early.
            let resent: Vec<u32> = missing.iter().copied().filter(|&n| n < next_new).collect();
            for &num in &resent {
                self.qup_send_block(cx, now, id, num, None);
            }
            cx.msg.path(now, peer).stats.blocks_lost += resent.len() as u64;
            if let Some(u) = self.qup_mut(id) {
                // The server is there and still assembling: the give-up count starts over.
                u.set_sent = None;
                u.tries = 0;
                if missing.iter().any(|&n| n >= next_new) && next_new < u.blocks {
                    return self.qup_next_set(cx, now, id);
                }
            }
            return self.arm_qup(cx, now, id);
        }
        // The final response (or an error): the body's answer.
        let response = super::client_state::take_response(msg, payload);
        self.complete(cx, now, id, response);
    }

    /// NON_TIMEOUT_RANDOM without a 2.31: the next set goes; once all went, the last block
    /// goes again (its message ID too, so a server that has the body answers it again),
    /// NON_MAX_RETRANSMIT times.
    fn on_qup_timer(&mut self, cx: &mut Context<'_>, now: Instant, id: u64) {
        let Some(u) = self.qup_mut(id) else {
            return;
        };
        u.at = None;
        if u.next_new < u.blocks {
            u.set_sent = None;
            if u.tries == 0 {
                // No 2.31: blocks of the set were lost, or the 2.31 was. Wait once more
                // for the server's 4.08 (RFC 9177 allows a longer wait): a set sent
                // while gaps are open adds to them, and libcoap 4.3.5's server gives up
                // an upload with more than two gaps ("Too many missing blocks").
                u.tries = 1;
                return self.arm_qup(cx, now, id);
            }
            return self.qup_next_set(cx, now, id);
        }
        if u.tries >= NON_MAX_RETRANSMIT {
            return self.fail(cx, now, id, RequestError::Timeout);
        }
        u.tries += 1;
        if let Some((num, mid, token)) = u.last_sent {
            self.qup_send_block(cx, now, id, num, Some((mid, token)));
        }
        self.arm_qup(cx, now, id);
    }
}
