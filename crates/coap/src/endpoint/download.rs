//! The behaviour of a windowed Block2 download (its state is `window::Window`): started
//! when block 0 arrives with `more`, fed by the responses to its block requests, driven
//! by its timer, and handed back to stop-and-wait when the server does not play along.

use std::time::{Duration, Instant};

use bytes::Bytes;

use super::client_state::ClientLayer;
use super::client_state::{Step, Waiting};
use super::congestion::SendState;
use super::context::Context;
use super::message::{Path, TimerKind};
use super::types::{RequestError, Response};
use super::window::{Arrival, Window};
use crate::config::Transfer;
use crate::msg::{BlockOpt, Code, Message, OptionNumber};

impl ClientLayer {
    /// Block 0 of request `id` arrived (block size exponent `szx`, last block `last` if
    /// Size2 told): the rest comes through a window.
    pub(super) fn start_window(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        szx: u8,
        last: Option<u32>,
    ) {
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        r.window = Some(Window::new(now, last));
        r.waiting = Waiting::Window;
        r.step = Step::Download { num: 1, szx };
        r.generation += 1;
        self.window_pump(cx, now, id);
    }

    /// Sends the block requests the controller admits now, then arms the window's timer.
    pub(super) fn window_pump(&mut self, cx: &mut Context<'_>, now: Instant, id: u64) {
        let mut paced = None;
        loop {
            let Some(r) = self.requests.get(&id) else {
                return;
            };
            let peer = r.peer;
            let next = r.window.as_ref().and_then(Window::next_block);
            let mid_wait = cx.msg.mid_free_at(now, peer);
            let cc = cx.msg.path(now, peer).controller(now, cx.config);
            let (Some(num), None) = (next, mid_wait) else {
                // Nothing to ask for (the tail of the body, or the reorder buffer full),
                // or every message ID to the peer was used within EXCHANGE_LIFETIME (wait
                // for the next): if the controller would have let a request go, what it
                // measures now is the sender's shortage, not the path's rate.
                if cc.in_flight() < cc.window() && cc.next_send(now).is_none() {
                    cc.on_app_limited(now);
                }
                paced = paced.or(mid_wait);
                break;
            };
            if cc.in_flight() >= cc.window() {
                break;
            }
            if let Some(at) = cc.next_send(now) {
                paced = Some(at);
                break;
            }
            let state = cc.on_sent(now);
            let mid = cx.msg.next_mid(now, peer);
            let Some(r) = self.requests.get_mut(&id) else {
                return;
            };
            let Step::Download { szx, .. } = r.step else {
                return;
            };
            r.step = Step::Download { num, szx };
            r.send_step(mid, &mut cx.msg.outbox);
            if let Some(w) = r.window.as_mut() {
                w.on_sent(num, state);
            }
        }
        self.arm_window(cx, now, id, paced);
    }

    /// The round trip the loss delay grows from (`SRTT + 4 RTTVAR`) and the probe
    /// timeout, from the path.
    fn window_timing(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
    ) -> Option<(Duration, Duration)> {
        let peer = self.requests.get(&id)?.peer;
        let default = cx.config.ack_timeout;
        let rtt = &cx.msg.path(now, peer).rtt;
        let base = rtt.srtt().map_or(default, |srtt| srtt + rtt.rttvar() * 4);
        Some((base, rtt.pto(default)))
    }

    /// Arms the window's timer for its loss or probe time, or `paced` (when pacing
    /// holds back a request) if earlier.
    fn arm_window(&mut self, cx: &mut Context<'_>, now: Instant, id: u64, paced: Option<Instant>) {
        let Some((_, pto)) = self.window_timing(cx, now, id) else {
            return;
        };
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        let Some(w) = &r.window else { return };
        let at = match (w.timer(pto), paced) {
            (Some(a), Some(b)) => a.min(b),
            (Some(at), None) | (None, Some(at)) => at,
            // Nothing in flight, yet blocks to ask for: the peer's window is full with
            // another download's requests (NSTART above 1). Look again in a while.
            (None, None) if w.next_block().is_some() => now + pto,
            (None, None) => return,
        };
        if r.window_timer
            .is_some_and(|armed| armed <= at && armed > now)
        {
            return;
        }
        r.window_timer = Some(at);
        cx.msg.schedule(at, TimerKind::Window { id, at });
    }

    /// The window's timer: declares lost what is late, gives up after MAX_TRANSMIT_SPAN
    /// without a block, and sends what may go now.
    pub(super) fn on_window_timer(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        at: Instant,
    ) {
        let Some((rtt, pto)) = self.window_timing(cx, now, id) else {
            return;
        };
        let give_up = cx.config.max_transmit_span();
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        if r.window_timer != Some(at) {
            return;
        }
        r.window_timer = None;
        let peer = r.peer;
        let Some(w) = r.window.as_mut() else { return };
        if w.awaiting() && now.saturating_duration_since(w.heard) > give_up {
            return self.fail(cx, now, id, RequestError::Timeout);
        }
        let lost = w.on_timer(now, rtt, pto);
        let probes = w.probes;
        // The requests declared lost leave the window now: they are no longer in flight,
        // whatever happens next (a fallback forgets only those still in flight).
        if let Some(cc) = cx.msg.path(now, peer).existing_controller() {
            cc.on_lost(now, lost);
        }
        if probes >= 3 {
            // Three probe timeouts in a row without a block: a server that ignores NON
            // requests (or answers them as if they were CONs), or a path gone quiet. The
            // rest goes stop-and-wait, with CONs and their retransmissions.
            return self.window_fallback(cx, now, id);
        }
        self.window_pump(cx, now, id);
    }

    /// A response to one of the window's block requests.
    pub(super) fn on_window_response(
        &mut self,
        cx: &mut Context<'_>,
        now: Instant,
        id: u64,
        msg: &Message,
        payload: &[u8],
    ) {
        let limit = cx.config.limits.client_body_bytes;
        let Some((rtt, _)) = self.window_timing(cx, now, id) else {
            return;
        };
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        let Step::Download { szx, .. } = r.step else {
            return;
        };
        let b2 = msg
            .options
            .block2()
            .filter(|b| msg.code.is_success() && b.szx == szx);
        let Some(b2) = b2 else {
            let size_unknown = r
                .first_options
                .as_ref()
                .is_none_or(|o| o.uint(OptionNumber::SIZE2).is_none());
            if size_unknown && matches!(msg.code, Code::BAD_OPTION | Code::BAD_REQUEST) {
                // Without Size2 the window asks past the end until the last block
                // arrives; such a request is refused (4.02, RFC 7959 §2.2; aiocoap says
                // 4.00), and forgotten once the last block is known.
                return;
            }
            // An error, or blocks of another size: the server does not serve blocks out
            // of order as asked. The rest goes stop-and-wait, which handles either.
            return self.window_fallback(cx, now, id);
        };
        if msg.options.etag() != r.etag.as_deref() {
            // RFC 7959 §2.4: the representation changed; start over (a few times at
            // most), or fail a streamed body whose pieces are gone already.
            if r.restarts >= 4 || r.req.stream {
                return self.fail(cx, now, id, RequestError::RepresentationChanged);
            }
            self.end_window(cx, now, id);
            let Some(r) = self.requests.get_mut(&id) else {
                return;
            };
            r.restarts += 1;
            r.body.clear();
            r.received = 0;
            r.first_options = None;
            r.step = Step::Download { num: 0, szx };
            return self.send_step(cx, now, id);
        }
        let total = r
            .first_options
            .as_ref()
            .and_then(|o| o.uint(OptionNumber::SIZE2))
            .map(|t| t as usize);
        let size = b2.size();
        let peer = r.peer;
        let Some(w) = r.window.as_mut() else { return };
        let mut forgotten = 0;
        if !b2.more && w.last().is_none() {
            forgotten = w.set_last(b2.num);
        }
        // The size a block must have: a whole block but for the last, which holds what
        // Size2 leaves (at most a block, if the size is not known).
        let size_ok = match (total, w.last()) {
            (Some(total), _) => payload.len() == total.saturating_sub(b2.offset()).min(size),
            (None, Some(last)) if b2.num == last => payload.len() <= size,
            (None, _) => payload.len() == size,
        };
        if w.last()
            .is_some_and(|last| b2.num <= last && b2.more == (b2.num == last))
        {
            return self.fail(
                cx,
                now,
                id,
                RequestError::Protocol("Block2 says more after the last block, or none before"),
            );
        }
        let mut lost = 0;
        let (arrival, sample) = w.on_block(now, b2.num, rtt, || lost += 1);
        if arrival != Arrival::Duplicate && !size_ok {
            return self.fail(
                cx,
                now,
                id,
                RequestError::Protocol("the block does not have the size Size2 implies"),
            );
        }
        learn(
            cx.msg.path(now, peer),
            now,
            arrival,
            sample,
            (lost, forgotten),
        );
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        match arrival {
            Arrival::Duplicate => return,
            Arrival::Ahead => {
                if let Some(w) = r.window.as_mut() {
                    w.keep(b2.num, payload);
                }
            }
            Arrival::Next => {
                let mut block = None;
                let mut num = b2.num;
                loop {
                    let data = block.as_deref().unwrap_or(payload);
                    let more = r.window.as_ref().and_then(Window::last) != Some(num);
                    if let Err(e) = r.append(id, data, more, size, limit, cx.events) {
                        return self.fail(cx, now, id, e);
                    }
                    num += 1;
                    block = r.window.as_mut().and_then(Window::delivered);
                    if block.is_none() {
                        break;
                    }
                }
            }
        }
        if r.window.as_ref().is_some_and(Window::complete) {
            self.end_window(cx, now, id);
            let Some(r) = self.requests.get_mut(&id) else {
                return;
            };
            let body = Bytes::from(std::mem::take(&mut r.body));
            let options = r.first_options.take().unwrap_or_default();
            let response = Response::with_parts(msg.code, options, body);
            return self.complete(cx, now, id, response);
        }
        self.window_pump(cx, now, id);
    }

    /// The server refused or mangled a block asked for out of order, or answered none of
    /// the window's requests: the download goes on stop-and-wait from the next block to
    /// deliver (blocks that arrived ahead are asked for again).
    fn window_fallback(&mut self, cx: &mut Context<'_>, now: Instant, id: u64) {
        self.end_window(cx, now, id);
        if let Some(peer) = self.requests.get(&id).map(|r| r.peer) {
            cx.msg.path(now, peer).stats.window_fallbacks += 1;
        }
        // A new token, so that late answers to the window's requests (a refusal without
        // Block2 among them) are not taken for the answer to the next step.
        let token = self.new_token(cx);
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        let Step::Download { szx, .. } = r.step else {
            return;
        };
        self.by_token.remove(&r.token);
        self.by_token.insert(token, id);
        r.token = token;
        r.req.transfer = Some(Transfer::StopAndWait);
        r.step = Step::Download {
            num: (r.received / BlockOpt::size_of(szx)) as u32,
            szx,
        };
        self.send_step(cx, now, id);
    }

    /// Ends request `id`'s window, if it has one: its requests in flight are forgotten by
    /// the controller and its counters added to the path's.
    pub(super) fn end_window(&mut self, cx: &mut Context<'_>, now: Instant, id: u64) {
        let Some(r) = self.requests.get_mut(&id) else {
            return;
        };
        let Some(mut w) = r.window.take() else { return };
        r.window_timer = None;
        let path = cx.msg.path(now, r.peer);
        if let Some(cc) = path.existing_controller() {
            cc.on_abandoned(w.abandon());
        }
        let (s, t) = (&mut path.stats, w.stats);
        s.block_requests += t.requests;
        s.blocks_lost += t.lost;
        s.blocks_late += t.late;
        s.blocks_duplicate += t.duplicates;
        s.max_window = s.max_window.max(t.max_window);
    }
}

/// What the path learns from a block of its window: a round-trip sample, and what the
/// controller hears (a delivery, late or not; `lost` requests declared lost, `forgotten`
/// past the last block).
fn learn(
    path: &mut Path,
    now: Instant,
    arrival: Arrival,
    sample: Option<(SendState, Option<Duration>)>,
    (lost, forgotten): (usize, usize),
) {
    match sample {
        Some((state, rtt)) => {
            if let Some(rtt) = rtt {
                path.rtt.on_sample(now, rtt, true);
            }
            if let Some(cc) = path.existing_controller() {
                cc.on_delivered(now, &state, rtt);
            }
        }
        None if arrival != Arrival::Duplicate => {
            if let Some(cc) = path.existing_controller() {
                cc.on_late_delivery(now);
            }
        }
        None => {}
    }
    if let Some(cc) = path.existing_controller() {
        cc.on_lost(now, lost);
        cc.on_abandoned(forgotten);
    }
}
