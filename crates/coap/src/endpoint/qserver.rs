//! The server side of RFC 9177: a response body sent with Q-Block2 set by set, and a
//! request body received with Q-Block1 in any order (the state is in `qblock`).
//!
//! Q-Block2: the first request is answered by the application; its body is stored (as
//! for Block2) and the blocks its Q-Block2 options ask for go out at once, as NONs to a
//! NON request. A CON request gets one block, piggybacked (as libcoap does: the RFC's
//! CON bursts would need NSTART above 1). Later requests ('Continue', missing blocks)
//! are served from the store. The next set goes on a 'Continue', or NON_TIMEOUT_RANDOM
//! after the last one.
//!
//! Q-Block1: blocks are written where they belong in a body of Size1 bytes, with a bitmap
//! of those received. A whole set (and none missing before it) is confirmed with 2.31; a
//! set that starts with blocks missing before it gets a 4.08 listing them at once, and so
//! does a set whose last block arrives with blocks of it missing, and a body that stops
//! arriving, after NON_RECEIVE_TIMEOUT. The whole body goes to the application as one
//! request, answered to the token of its last block.

use std::net::SocketAddr;
use std::time::Instant;

use bytes::Bytes;
use rand_core::RngCore;

use super::context::Context;
use super::message::TimerKind;
use super::qblock::{
    self, MISSING_BLOCKS_CBOR_SEQ, NON_MAX_RETRANSMIT, QSend, QUpload, asked_blocks, continue_set,
    last_block, stale_after,
};
use super::reply::answer;
use super::server_state::ServerLayer;
use super::server_state::{Incoming, Pending, past_end, unreadable};
use super::types::Response;
use crate::block::{self, BlockKey, Slice, Source, Storing};
use crate::msg::{BlockOpt, Code, Message, OptionNumber, Token, Type};

/// How the first block of a Q-Block2 answer goes: piggybacked on the ACK of a CON
/// request (then it is the only one), or as NONs.
#[derive(Clone, Copy)]
enum Reply {
    Ack(u16),
    Non,
}

/// What [`Endpoint::on_q_request`] leaves to the usual request path.
pub(super) enum QNext {
    /// Answered (or dropped) here.
    Done,
    /// To the application, with the body assembled from Q-Block1 blocks, if any.
    Dispatch(Option<Bytes>),
}

impl ServerLayer {
    /// A request with Q-Block1 or Q-Block2 options, its blocks kept under `key`.
    pub(super) fn on_q_request(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        req: &Incoming<'_>,
        key: &BlockKey,
    ) -> QNext {
        let msg = &req.msg;
        if req.multicast {
            // RFC 9177 §4.8: multicast requests with Q-Block2 are ignored (and Q-Block1
            // has no use there).
            return QNext::Done;
        }
        let refuse = |code, text| Response::diagnostic(code, text);
        if msg.options.block1().is_some() || msg.options.block2().is_some() {
            let r = refuse(Code::BAD_OPTION, "Q-Block and Block options in one request");
            answer(cx, now, req, r);
            return QNext::Done;
        }
        if let Some(q) = req.q1 {
            return match self.on_q_block1(cx, now, req, key, q) {
                Some(body) => QNext::Dispatch(Some(body)),
                None => QNext::Done,
            };
        }
        if req.q2.iter().any(|b| b.num > 0) {
            if self.q_block2_from_store(cx, now, req, key) {
                return QNext::Done;
            }
            if !matches!(msg.code, Code::GET | Code::FETCH) {
                let r = refuse(
                    Code::REQUEST_ENTITY_INCOMPLETE,
                    "the representation is no longer stored; ask for block 0 again",
                );
                answer(cx, now, req, r);
                return QNext::Done;
            }
        }
        QNext::Dispatch(None)
    }

    /// Answers a request for blocks of a body stored for Q-Block2; false when none is.
    fn q_block2_from_store(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        req: &Incoming<'_>,
        key: &BlockKey,
    ) -> bool {
        let (peer, msg, q2) = (req.peer, &req.msg, &req.q2[..]);
        let limits = cx.limits();
        let mp = cx.config.payloads_per_set();
        let szx = q2[0].szx.min(cx.config.max_block_szx);
        let len = self.block2.with_stored(now, key, limits, |s| {
            s.q_options.is_some().then(|| s.body.0.len())
        });
        let Some(Some(len)) = len else {
            return false;
        };
        let last = last_block(len, szx);
        let Some(nums) = asked_blocks(q2, mp, last) else {
            let r = Response::diagnostic(
                Code::BAD_REQUEST,
                "Q-Block2 options must have increasing block numbers",
            );
            answer(cx, now, req, r);
            return true;
        };
        if nums.is_empty() {
            answer(cx, now, req, past_end());
            return true;
        }
        let to = Dest {
            peer,
            key,
            token: msg.token,
            szx,
        };
        if let Some(set) = continue_set(q2, mp) {
            self.q_continue(cx, now, &to, set, last);
        }
        let reply = match msg.ty {
            Type::Con => Reply::Ack(msg.message_id),
            _ => Reply::Non,
        };
        if !self.q_send_blocks(cx, now, &to, reply, &nums) {
            // The stored source can no longer be read as it was.
            self.block2.remove(key);
            answer(cx, now, req, unreadable());
        }
        true
    }

    /// Sends blocks `nums` of the body stored for `to`: only the first, piggybacked,
    /// after a CON request. False when the body is gone or cannot be read.
    fn q_send_blocks(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        to: &Dest<'_>,
        reply: Reply,
        nums: &[u32],
    ) -> bool {
        let &Dest {
            peer,
            key,
            token,
            szx,
        } = to;
        let limits = cx.limits();
        let nums = match reply {
            Reply::Ack(_) => &nums[..nums.len().min(1)],
            Reply::Non => nums,
        };
        let msg = &mut *cx.msg;
        let sent = self.block2.with_stored(now, key, limits, |s| {
            let Some(options) = &s.q_options else {
                return false;
            };
            for &num in nums {
                let Slice::Block(payload, opt) = block::slice(&*s.body.0, num, szx) else {
                    return false;
                };
                let mut options = options.clone();
                options.set_block(OptionNumber::Q_BLOCK2, opt);
                let (ty, message_id) = match reply {
                    Reply::Ack(mid) => (Type::Ack, mid),
                    Reply::Non => (Type::Non, msg.next_mid(now, peer)),
                };
                let m = Message {
                    ty,
                    code: s.code,
                    message_id,
                    token,
                    options,
                    payload,
                };
                msg.send(peer, &m);
            }
            true
        });
        sent == Some(true)
    }

    /// A 'Continue' for set `set` of the body stored for `to`, whose last block is
    /// `last`: the next set is the one after, due NON_TIMEOUT_RANDOM from now unless
    /// another 'Continue' comes first. The time since the set before went out, if a
    /// request asked for it, is a round trip.
    fn q_continue(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        to: &Dest<'_>,
        set: u32,
        last: u32,
    ) {
        let &Dest {
            peer,
            key,
            token,
            szx,
        } = to;
        let found = self
            .qsends
            .iter()
            .find(|(_, q)| q.peer == peer && &q.key == key)
            .map(|(&id, _)| id);
        let id = match found {
            Some(id) => id,
            None => {
                let id = cx.new_id();
                let timeout = self.q_non_timeout(cx, peer);
                let q = QSend {
                    peer,
                    key: key.clone(),
                    token,
                    szx,
                    next_set: set,
                    last,
                    sent_at: now,
                    asked: false,
                    timeout,
                    at: now,
                };
                self.qsends.insert(id, q);
                id
            }
        };
        let Some(q) = self.qsends.get_mut(&id) else {
            return;
        };
        if q.next_set == set && q.asked && set > 0 {
            let rtt = now.saturating_duration_since(q.sent_at);
            cx.msg.path(now, peer).rtt.on_plausible_sample(now, rtt);
        }
        q.next_set = q.next_set.max(set + 1);
        q.token = token;
        q.sent_at = now;
        q.asked = true;
        self.arm_qset(cx, id);
    }

    /// Schedules the next set of body `id`, or forgets the body when every set went.
    fn arm_qset(&mut self, cx: &mut Context<'_>, id: u64) {
        let mp = cx.config.payloads_per_set();
        let Some(q) = self.qsends.get_mut(&id) else {
            return;
        };
        if q.next_set > q.last / mp {
            self.qsends.remove(&id);
            return;
        }
        q.at = q.sent_at + q.timeout;
        let at = q.at;
        cx.msg.schedule(at, TimerKind::QSet { id, at });
    }

    /// NON_TIMEOUT_RANDOM for a new body to `peer`.
    fn q_non_timeout(&mut self, cx: &mut Context<'_>, peer: SocketAddr) -> std::time::Duration {
        let unit = cx.msg.unit();
        let c = cx.config;
        qblock::non_timeout(
            cx.msg.estimate(peer),
            c.ack_timeout,
            c.ack_random_factor,
            unit,
        )
    }

    /// NON_TIMEOUT_RANDOM passed without a 'Continue': the next set goes.
    pub(super) fn on_qset_timer(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        at: Instant,
    ) {
        let mp = cx.config.payloads_per_set();
        let Some(q) = self.qsends.get_mut(&id).filter(|q| q.at == at) else {
            return;
        };
        let (peer, key, token, szx) = (q.peer, q.key.clone(), q.token, q.szx);
        let set = q.next_set;
        q.next_set += 1;
        q.sent_at = now;
        q.asked = false;
        let nums: Vec<u32> = (set * mp..=((set + 1) * mp - 1).min(q.last)).collect();
        let to = Dest {
            peer,
            key: &key,
            token,
            szx,
        };
        if !self.q_send_blocks(cx, now, &to, Reply::Non, &nums) {
            self.qsends.remove(&id);
            return;
        }
        self.arm_qset(cx, id);
    }

    /// The response to a request with Q-Block2 options: the first block it asks for, with
    /// the body stored and the blocks after it sent by [`Endpoint::q_after_first`].
    /// Returns the response and what remains to send (blocks, and whether a set
    /// follows by timer).
    pub(super) fn q_first_response(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        p: &Pending,
        mut response: Response,
    ) -> (Response, Option<QRest>) {
        let limits = cx.limits();
        let mp = cx.config.payloads_per_set();
        let szx = p.qblock2[0].szx.min(cx.config.max_block_szx);
        let size = BlockOpt::size_of(szx);
        if !response.code.is_success() {
            // An error is no Q-Block body: sent as any answer, a body larger than a block
            // cut with Block2 (it was sent whole, past the path's MTU, before fuzzing
            // found it).
            let key = p.key.clone();
            return (
                self.blockwise_response(cx, now, key, None, response, szx, false),
                None,
            );
        }
        let body = match response.source.take() {
            Some(source) => source,
            None => Source::new(std::mem::take(&mut response.payload)),
        };
        let len = body.0.len();
        if len > size << 20 || u32::try_from(len).is_err() {
            let r = Response::diagnostic(
                Code::INTERNAL_SERVER_ERROR,
                "the representation is too large for block-wise transfer at this block size",
            );
            return (r, None);
        }
        let last = last_block(len, szx);
        let Some(nums) = asked_blocks(&p.qblock2, mp, last) else {
            let r = Response::diagnostic(
                Code::BAD_REQUEST,
                "Q-Block2 options must have increasing block numbers",
            );
            return (r, None);
        };
        let Some(&first) = nums.first() else {
            return (past_end(), None);
        };
        if response.options.etag().is_none() {
            let etag = cx.msg.rng.next_u32().to_be_bytes();
            response.options.set(OptionNumber::ETAG, etag);
        }
        // RFC 9177 §4.6: Size2, exactly, in every block.
        response.options.set_uint(OptionNumber::SIZE2, len as u32);
        let (payload, opt) = match block::slice(&*body.0, first, szx) {
            Slice::Block(payload, opt) => (payload, opt),
            Slice::PastEnd => return (past_end(), None),
            Slice::Unreadable => return (unreadable(), None),
        };
        let mut options = response.options.clone();
        options.set_block(OptionNumber::Q_BLOCK2, opt);
        let first_response =
            Response::with_parts(response.code, options, Bytes::copy_from_slice(&payload));
        if len <= size {
            return (first_response, None);
        }
        self.arm_sweep(cx, now + cx.config.limits.blockwise_lifetime);
        self.block2.insert(
            now,
            p.key.clone(),
            response.code,
            response.options,
            body,
            Storing::QBlock2,
            limits,
        );
        let sets = last / mp + 1;
        // A request for the whole body (block 0 with M) starts its sets; the set after
        // the last block asked for goes by timer unless the client asks first.
        let next_set = p
            .qblock2
            .iter()
            .any(|b| b.more)
            .then(|| nums[nums.len() - 1] / mp + 1)
            .filter(|&s| s < sets);
        let rest = QRest {
            nums: nums[1..].to_vec(),
            szx,
            next_set,
            last,
        };
        (first_response, Some(rest))
    }

    /// Sends what remains of a Q-Block2 answer after its first block (nothing after a
    /// CON request: the client asks for each block).
    pub(super) fn q_after_first(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        p: &Pending,
        rest: QRest,
    ) {
        if p.confirmable {
            return;
        }
        let to = Dest {
            peer: p.peer,
            key: &p.key,
            token: p.token,
            szx: rest.szx,
        };
        let sent = self.q_send_blocks(cx, now, &to, Reply::Non, &rest.nums);
        let Some(next_set) = rest.next_set.filter(|_| sent) else {
            return;
        };
        let id = cx.new_id();
        let timeout = self.q_non_timeout(cx, p.peer);
        let q = QSend {
            peer: p.peer,
            key: p.key.clone(),
            token: p.token,
            szx: rest.szx,
            next_set,
            last: rest.last,
            sent_at: now,
            asked: true,
            timeout,
            at: now,
        };
        self.qsends.insert(id, q);
        self.arm_qset(cx, id);
    }

    /// The upload a block of a body sent with Q-Block1 belongs to, made if it is the
    /// first (its id, and the body's blocks); `None` when the block was answered here
    /// (refused) or dropped (its body was handed over already).
    fn q_upload_for(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        req: &Incoming<'_>,
        key: &BlockKey,
        q: BlockOpt,
    ) -> Option<(u64, u32)> {
        let (msg, payload) = (&req.msg, req.payload);
        let limits = cx.limits();
        let size1 = msg
            .options
            .uint(OptionNumber::SIZE1)
            .filter(|_| msg.options.contains(OptionNumber::REQUEST_TAG));
        let Some(size1) = size1 else {
            // RFC 9177 §4.3.
            let r = Response::diagnostic(Code::BAD_REQUEST, "Q-Block1 needs Request-Tag and Size1");
            answer(cx, now, req, r);
            return None;
        };
        let size1 = size1 as usize;
        let size = q.size();
        let blocks = size1.div_ceil(size).max(1) as u32;
        let existing = self.qupload_ids.get(key).copied();
        if existing.is_some_and(|id| self.quploads.get(&id).is_some_and(|u| u.done)) {
            // A block of a body already handed over (sent again, or late): dropped.
            return None;
        }
        if size1 > limits.block1_peer_bytes {
            let mut r = Response::diagnostic(Code::REQUEST_ENTITY_TOO_LARGE, "body too large");
            r.options
                .set_uint(OptionNumber::SIZE1, limits.block1_peer_bytes as u32);
            answer(cx, now, req, r);
            return None;
        }
        if existing.is_none() && self.quploads_full(cx, now, size1) {
            let mut r = Response::diagnostic(Code::SERVICE_UNAVAILABLE, "too many uploads");
            r.options.set_uint(OptionNumber::MAX_AGE, 5);
            answer(cx, now, req, r);
            return None;
        }
        let expected = size1.saturating_sub(q.offset()).min(size);
        let fits = q.num < blocks
            && q.more == (q.num + 1 < blocks)
            && payload.len() == expected
            && existing.is_none_or(|id| {
                self.quploads
                    .get(&id)
                    .is_some_and(|u| u.got.len() == blocks as usize && u.szx == q.szx)
            });
        if !fits {
            let r = Response::diagnostic(
                Code::BAD_REQUEST,
                "the Q-Block1 block does not fit the body's Size1 or its first blocks",
            );
            answer(cx, now, req, r);
            return None;
        }
        let id = match existing {
            Some(id) => id,
            None => {
                let id = cx.new_id();
                let u = QUpload {
                    key: key.clone(),
                    body: vec![0; size1],
                    got: vec![false; blocks as usize],
                    count: 0,
                    szx: q.szx,
                    token: msg.token,
                    reported: None,
                    heard: now,
                    continued_at: None,
                    at: now,
                    tries: 0,
                    listed: Vec::new(),
                    done: false,
                };
                self.quploads.insert(id, u);
                self.qupload_ids.insert(key.clone(), id);
                id
            }
        };
        Some((id, blocks))
    }

    /// A block of a body sent with Q-Block1; the whole body when it is complete.
    fn on_q_block1(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        req: &Incoming<'_>,
        key: &BlockKey,
        q: BlockOpt,
    ) -> Option<Bytes> {
        let (peer, msg, payload) = (req.peer, &req.msg, req.payload);
        let mp = cx.config.payloads_per_set();
        let (id, blocks) = self.q_upload_for(cx, now, req, key, q)?;
        let u = self.quploads.get_mut(&id)?;
        let num = q.num as usize;
        let again = u.got[num];
        if !again {
            u.body[q.offset()..q.offset() + payload.len()].copy_from_slice(payload);
            u.got[num] = true;
            u.count += 1;
            if let (Some(at), 0) = (u.continued_at.take(), q.num % mp) {
                // The first block of the set a 2.31 asked for: a round trip.
                let rtt = now.saturating_duration_since(at);
                cx.msg.path(now, peer).rtt.on_plausible_sample(now, rtt);
            }
        }
        let u = self.quploads.get_mut(&id)?;
        u.token = msg.token;
        u.heard = now;
        u.tries = 0;
        if u.count == blocks {
            u.done = true;
            u.got = Vec::new();
            return Some(Bytes::from(std::mem::take(&mut u.body)));
        }
        let set = q.num / mp;
        if msg.ty == Type::Con {
            // RFC 9177 §4.3: each CON block is acknowledged; the response waits for the
            // whole body.
            cx.msg
                .send(peer, &Message::empty(Type::Ack, msg.message_id));
        } else if !again && u.set_complete(set, mp) && !u.gap_before(set, mp) {
            // RFC 9177 §7.2: a whole set, confirmed so the next goes at once.
            let last = ((set + 1) * mp - 1).min(blocks - 1);
            let mut r = Response::new(Code::CONTINUE);
            let opt = BlockOpt {
                num: last,
                more: true,
                szx: q.szx,
            };
            r.options.set_block(OptionNumber::Q_BLOCK1, opt);
            u.continued_at = Some(now);
            self.q_reply(cx, now, peer, msg.token, r);
        } else if let Some(end) = immediate_report(u, q, set, mp, again)
            && let Some(r) = q_missing_response(u, mp, end)
        {
            self.q_reply(cx, now, peer, msg.token, r);
        }
        let estimate = cx.msg.estimate(peer);
        let u = self.quploads.get_mut(&id)?;
        u.at = now + qblock::receive_timeout(estimate, cx.config.ack_timeout, 0);
        let at = u.at;
        cx.msg.schedule(at, TimerKind::QReceive { id, at });
        None
    }

    /// NON_RECEIVE_TIMEOUT passed since the last block of an incomplete body: a 4.08
    /// lists what is missing, again and again (doubling), until NON_MAX_RETRANSMIT went
    /// unanswered and [`stale_after`] passed; then the body is dropped.
    pub(super) fn on_qreceive_timer(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        at: Instant,
    ) {
        let mp = cx.config.payloads_per_set();
        let Some(peer) = self.quploads.get(&id).map(|u| u.key.peer) else {
            return;
        };
        let estimate = cx.msg.estimate(peer);
        let Some(u) = self.quploads.get_mut(&id).filter(|u| u.at == at && !u.done) else {
            return;
        };
        let stale = now.saturating_duration_since(u.heard) >= stale_after(cx.config.ack_timeout);
        if u.tries >= NON_MAX_RETRANSMIT && stale {
            let key = u.key.clone();
            self.quploads.remove(&id);
            self.qupload_ids.remove(&key);
            return;
        }
        u.tries += 1;
        let end = u.stalled_end(mp);
        let r = q_missing_response(u, mp, end);
        let token = u.token;
        u.at = now + qblock::receive_timeout(estimate, cx.config.ack_timeout, u.tries);
        let at = u.at;
        cx.msg.schedule(at, TimerKind::QReceive { id, at });
        if let Some(r) = r {
            self.q_reply(cx, now, peer, token, r);
        }
    }

    /// Sends a NON response to the request with `token` (2.31, 4.08).
    fn q_reply(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        peer: SocketAddr,
        token: Token,
        r: Response,
    ) {
        let m = Message {
            ty: Type::Non,
            code: r.code,
            message_id: cx.msg.next_mid(now, peer),
            token,
            options: r.options,
            payload: r.payload,
        };
        cx.msg.send(peer, &m);
    }

    /// Whether a new upload of `size1` bytes would pass the bytes all uploads may hold,
    /// after forgetting those idle for NON_PARTIAL_TIMEOUT (the block-wise lifetime),
    /// finished ones included. Called for a body's first block only.
    fn quploads_full(&mut self, cx: &mut Context<'_>, now: Instant, size1: usize) -> bool {
        let lifetime = cx.config.limits.blockwise_lifetime;
        let ids = &mut self.qupload_ids;
        self.quploads.retain(|_, u| {
            let keep = now.saturating_duration_since(u.heard) < lifetime;
            if !keep {
                ids.remove(&u.key);
            }
            keep
        });
        let held: usize = self.quploads.values().map(|u| u.body.len()).sum();
        held + size1 > cx.config.limits.block1_total_bytes
    }
}

/// Where the blocks of a body stored for Q-Block2 go: the peer, the key the body is
/// stored under, the token of the request they answer, their size exponent.
struct Dest<'k> {
    peer: SocketAddr,
    key: &'k BlockKey,
    token: Token,
    szx: u8,
}

/// The rest of a Q-Block2 answer after its first block.
pub(super) struct QRest {
    nums: Vec<u32>,
    szx: u8,
    next_set: Option<u32>,
    last: u32,
}

/// Whether the block `q` (of set `set`; `again` when it had come before) calls for a
/// 4.08 at once rather than after NON_RECEIVE_TIMEOUT, and below which block it lists
/// the gaps. Blocks above the latest are not listed: they may still be on the way.
fn immediate_report(u: &mut QUpload, q: BlockOpt, set: u32, mp: u32, again: bool) -> Option<u32> {
    if u.gap_before(set, mp) && u.reported.is_none_or(|r| r < set * mp) {
        // A later set began with blocks missing before it (RFC 9177 §7.2).
        u.reported = Some(q.num);
        return Some(q.num);
    }
    if (q.num % mp == mp - 1 || !q.more) && u.reported.is_none_or(|r| r < q.num) {
        // A set's last block came with blocks of the set missing: the RFC waits
        // NON_RECEIVE_TIMEOUT for them; a block that was only reordered is sent twice.
        u.reported = Some(q.num);
        return Some(q.num);
    }
    if again && !q.more {
        // The body's last block sent again: the sender heard nothing from us.
        return Some(q.num);
    }
    if !u.listed.is_empty() && u.listed.iter().all(|&n| u.got[n as usize]) {
        // Every block the last 4.08 listed came: the next gaps.
        return Some(u.received_end());
    }
    None
}

/// A 4.08 listing the first MAX_PAYLOADS blocks below `end` that an upload lacks (RFC
/// 9177 §5), which it remembers; none when nothing is missing there.
fn q_missing_response(u: &mut QUpload, mp: u32, end: u32) -> Option<Response> {
    let listed = u.missing(end, mp as usize);
    if listed.is_empty() {
        return None;
    }
    let mut r = Response::new(Code::REQUEST_ENTITY_INCOMPLETE);
    r.options
        .set_uint(OptionNumber::CONTENT_FORMAT, MISSING_BLOCKS_CBOR_SEQ);
    let payload = Bytes::from(qblock::encode_missing(&listed));
    u.listed = listed;
    // The next set may now answer this 4.08 rather than a 2.31: no round-trip sample.
    u.continued_at = None;
    Some(r.with_payload(payload))
}
