//! The client side's state: the requests this endpoint sends and their peers; see
//! `client` for what happens to them.
//!
//! The client side: requests this endpoint sends. Each is a sequence of *steps*, one
//! message exchange each (the whole request, a Block1 block, a Block2 block); the message
//! layer carries a step's CON, this layer decides the next step from the response:
//! transparent Block1 upload, Block2 reassembly (or streaming) that resumes from the block
//! it lacks, Observe registrations and their notifications, multicast collection. Each
//! peer's requests are admitted by its congestion controller (`congestion`).

use std::collections::VecDeque;
use std::net::SocketAddr;
use std::time::Instant;

use bytes::Bytes;

use super::congestion::Nstart;
use super::message::{MessageLayer, Outbox};
use super::qblock::{QDown, QUp};
use super::types::{Event, Request, RequestError, RequestId, Response};
use super::window::Window;
use crate::config::Transfer;

use crate::msg::{BlockHead, BlockOpt, Message, OptionNumber, Options, Outgoing, Token, Type};
use crate::peer_key::{FastMap, MidKey, PeerKey};

/// Streamed bodies are handed over in pieces of at least this many bytes (the last one
/// may be shorter).
pub(super) const STREAM_PIECE: usize = 64 << 10;

/// One exchange of a client request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Step {
    /// The whole payload in one message.
    Whole,
    /// Block1 upload of the block at this byte offset.
    Upload { offset: usize },
    /// Block2 request for block `num` of size `2^(szx+4)`.
    Download { num: u32, szx: u8 },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Waiting {
    /// Not started (queued behind NSTART).
    Queued,
    /// CON sent, no ACK yet.
    Ack(u16),
    /// ACKed empty; waiting for the separate response. Or a NON sent, waiting for the
    /// response (carrying the NON's transmission count).
    Response { non_tx: Option<u8>, mid: u16 },
    /// Observing (RFC 7641): the first response arrived, notifications follow; carries
    /// the last Observe sequence number.
    Observing(u32),
    /// A multicast request collecting responses until its deadline.
    Collecting,
    /// A windowed download's block requests are in flight (see `window`).
    Window,
}

pub(super) struct ClientRequest {
    pub(super) peer: SocketAddr,
    pub(super) req: Request,
    pub(super) token: Token,
    pub(super) szx1: u8,
    pub(super) step: Step,
    pub(super) waiting: Waiting,
    pub(super) generation: u32,
    pub(super) failures: u8,
    pub(super) restarts: u8,
    /// Echo challenges (RFC 9175) answered by sending the step again.
    pub(super) echoes: u8,
    /// Block2 reassembly: body so far (empty when streamed), the bytes received, the
    /// ETag, the first block's options.
    pub(super) body: Vec<u8>,
    pub(super) received: usize,
    pub(super) etag: Option<Vec<u8>>,
    pub(super) first_options: Option<Options>,
    /// The user set Block2 in the request: random access, no reassembly.
    pub(super) user_block2: bool,
    /// The request carries Observe 0 (a registration).
    pub(super) observe: bool,
    /// When its armed [`TimerKind::RequestAck`] fires. Each block's CON does not push a
    /// timer of its own: the armed one fires, finds the CON then awaited and re-arms for
    /// its due time. So a transfer arms about one timer per ACK_TIMEOUT instead of one per
    /// block, and retransmissions still go out exactly when due.
    pub(super) ack_timer: Option<Instant>,
    /// The request's options encoded around Block2, for the blocks of a download.
    pub(super) block_head: Option<BlockHead>,
    /// A windowed download in progress, and when its armed timer fires.
    pub(super) window: Option<Window>,
    pub(super) window_timer: Option<Instant>,
    /// A response body fetched, or a request body sent, with Q-Block (RFC 9177).
    pub(super) qdown: Option<QDown>,
    pub(super) qup: Option<QUp>,
}

impl ClientRequest {
    /// Sends the message of the current step with message ID `mid`: the request's options
    /// with the step's block option (and Size1 on an upload's first block) set over them,
    /// encoded from the request in place.
    pub(super) fn send_step(&mut self, mid: u16, outbox: &mut Outbox) {
        let block = |num, more, szx| BlockOpt { num, more, szx }.as_uint();
        // A windowed download's block requests are NON: their loss is found and repaired
        // by the window, not by CON retransmission.
        let ty = if self.req.confirmable && self.window.is_none() {
            Type::Con
        } else {
            Type::Non
        };
        let mut uints = [(OptionNumber(0), 0); 3];
        let mut set = 0;
        if let (Step::Upload { .. }, true) = (self.step, self.qup.is_some()) {
            // Block 0 of a Q-Block1 body, a CON that finds out whether the server knows
            // Q-Block1; the rest goes as NONs (`qclient`).
            self.send_qup_block(0, ty, mid, self.token, outbox);
            return;
        }
        let payload: &[u8] = match self.step {
            Step::Download { num, szx } => {
                // Every block of a download is the same request but for Block2.
                let options = &self.req.options;
                let head = self
                    .block_head
                    .get_or_insert_with(|| BlockHead::new(options, OptionNumber::BLOCK2));
                let header = (ty, self.req.method, mid, self.token);
                let value = block(num, false, szx);
                outbox.send_with(self.peer, 0, |out| {
                    head.encode_into(out, header, value, &[])
                });
                return;
            }
            Step::Whole if self.may_qblock() => {
                // RFC 9177 §4.4: the whole body, set by set.
                let szx = self.req.block_szx.unwrap_or(self.szx1);
                uints[set] = (OptionNumber::Q_BLOCK2, block(0, true, szx));
                set += 1;
                &self.req.payload
            }
            Step::Whole => {
                if let (Some(szx), false) = (self.req.block_szx, self.user_block2) {
                    uints[set] = (OptionNumber::BLOCK2, block(0, false, szx));
                    set += 1;
                }
                if self.may_window() {
                    // RFC 7959 §4: Size2 0 asks for the size, which a window needs to
                    // know how many blocks to ask for.
                    uints[set] = (OptionNumber::SIZE2, 0);
                    set += 1;
                }
                &self.req.payload
            }
            Step::Upload { offset } => {
                let size = BlockOpt::size_of(self.szx1);
                let end = (offset + size).min(self.req.payload.len());
                let more = end < self.req.payload.len();
                uints[0] = (
                    OptionNumber::BLOCK1,
                    block((offset / size) as u32, more, self.szx1),
                );
                set = 1;
                if offset == 0 {
                    // RFC 7959 §4: Size1 tells the server the whole size up front.
                    uints[1] = (OptionNumber::SIZE1, self.req.payload.len() as u32);
                    set = 2;
                }
                &self.req.payload[offset.min(end)..end]
            }
        };
        let msg = Outgoing {
            ty,
            code: self.req.method,
            message_id: mid,
            token: self.token,
            options: &self.req.options,
            uints: &uints[..set],
            payload,
        };
        outbox.send(self.peer, &msg);
    }

    /// Appends the next block of a download (`more`: not the last; `size`: the block
    /// size) to the body, and queues the stream pieces and progress events it completes.
    pub(super) fn append(
        &mut self,
        id: u64,
        payload: &[u8],
        more: bool,
        size: usize,
        limit: usize,
        events: &mut VecDeque<Event>,
    ) -> Result<(), RequestError> {
        if self.received + payload.len() > limit {
            return Err(RequestError::TooLarge { limit });
        }
        if more && payload.len() != size {
            return Err(RequestError::Protocol(
                "Block2 payload size does not match SZX",
            ));
        }
        let total = self
            .first_options
            .as_ref()
            .and_then(|o| o.uint(OptionNumber::SIZE2))
            .map(|v| v as usize);
        let (stream, progress) = (self.req.stream, self.req.progress);
        let before = self.received;
        self.received += payload.len();
        let done = self.received;
        if !more && total.is_some_and(|t| t != done) && (stream || self.window.is_some()) {
            return Err(RequestError::Protocol(
                "the body does not have the size Size2 announced",
            ));
        }
        self.body.extend_from_slice(payload);
        // A streamed body leaves in pieces of STREAM_PIECE bytes (and the rest at the end):
        // one hand-over to the reader per piece, not per block.
        if stream && (self.body.len() >= STREAM_PIECE || !more) {
            // The next piece gets its room at once rather than growing block by block.
            let room = if more { STREAM_PIECE + size } else { 0 };
            let data = Bytes::from(std::mem::replace(&mut self.body, Vec::with_capacity(room)));
            events.push_back(Event::BodyChunk {
                id: RequestId(id),
                offset: done - data.len(),
                data,
                total,
            });
        }
        // Progress at most every 64 KiB (and at the end), so watching costs nothing.
        if progress && (before >> 16 != done >> 16 || !more) {
            events.push_back(Event::Progress {
                id: RequestId(id),
                done,
                total,
            });
        }
        Ok(())
    }

    /// The step's CON is answered (by a piggybacked or a separate response): its exchange
    /// is over, nothing more to retransmit.
    pub(super) fn end_exchange(&self, msg: &mut MessageLayer) {
        if let Waiting::Ack(mid) = self.waiting {
            msg.exchanges.remove(&MidKey(self.peer, mid));
        }
    }

    /// Whether a response in blocks is asked for with Q-Block2.
    pub(super) fn may_qblock(&self) -> bool {
        self.req.transfer == Some(Transfer::QBlock)
            && !self.user_block2
            && !self.observe
            && !self.req.multicast
    }

    /// Whether a response in blocks may be fetched with a window.
    pub(super) fn may_window(&self) -> bool {
        self.req.transfer == Some(Transfer::Window)
            && !self.user_block2
            && !self.observe
            && !self.req.multicast
    }

    pub(super) fn step_has_block_option(&self) -> bool {
        match self.step {
            Step::Whole => self.req.block_szx.is_some() || self.user_block2,
            Step::Upload { .. } | Step::Download { .. } => true,
        }
    }
}

/// The requests of one peer: how many are outstanding, the queue behind them, and the
/// controller that says how many may be.
pub(super) struct Peer {
    pub(super) active: usize,
    pub(super) queue: VecDeque<u64>,
    pub(super) controller: Nstart,
}

impl Peer {
    pub(super) fn new(controller: Nstart) -> Self {
        Self {
            active: 0,
            queue: VecDeque::new(),
            controller,
        }
    }
}

/// The client side's state.
#[derive(Default)]
pub(super) struct ClientLayer {
    pub(super) requests: FastMap<u64, ClientRequest>,
    pub(super) by_token: FastMap<Token, u64>,
    pub(super) peers: FastMap<PeerKey, Peer>,
}

impl ClientLayer {
    /// Whether request `id`'s ACK timer is the one armed for `at`.
    pub(super) fn ack_timer_is(&self, id: u64, at: Instant) -> bool {
        self.requests
            .get(&id)
            .is_some_and(|r| r.ack_timer == Some(at))
    }

    /// Whether request `id`'s window timer is the one armed for `at`.
    pub(super) fn window_timer_is(&self, id: u64, at: Instant) -> bool {
        self.requests
            .get(&id)
            .is_some_and(|r| r.window_timer == Some(at))
    }

    /// Request `id`'s Q-Block2 download, if it has one.
    pub(super) fn qdown_mut(&mut self, id: u64) -> Option<&mut QDown> {
        self.requests.get_mut(&id)?.qdown.as_mut()
    }

    /// Request `id`'s Q-Block1 upload, if it has one.
    pub(super) fn qup_mut(&mut self, id: u64) -> Option<&mut QUp> {
        self.requests.get_mut(&id)?.qup.as_mut()
    }

    /// Whether request `id` is still at step `generation`.
    pub(super) fn step_is(&self, id: u64, generation: u32) -> bool {
        self.requests
            .get(&id)
            .is_some_and(|r| r.generation == generation)
    }

    /// What request `id` waits for, if it still runs.
    pub(super) fn waiting(&self, id: u64) -> Option<Waiting> {
        self.requests.get(&id).map(|r| r.waiting)
    }
}

/// A received response: the code and options taken out of its message, and a copy of
/// its payload.
pub(super) fn take_response(msg: &mut Message, payload: &[u8]) -> Response {
    let options = std::mem::take(&mut msg.options);
    Response::with_parts(msg.code, options, Bytes::copy_from_slice(payload))
}

/// RFC 7641 §3.4: whether Observe value `v2` is newer than `v1` (24-bit serial arithmetic).
pub(super) fn is_newer(v1: u32, v2: u32) -> bool {
    const HALF: u32 = 1 << 23;
    (v1 < v2 && v2 - v1 < HALF) || (v1 > v2 && v1 - v2 > HALF)
}
