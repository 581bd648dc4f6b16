//! The server side's state: requests received and waiting for their answer, uploads
//! being assembled, stored representations, observations served; see `server` for what
//! happens to them.
//!
//! The server side: requests this endpoint receives. Block1 uploads are assembled before
//! the application sees them; a response larger than one block is stored and its later
//! blocks are cut from the store (the application never sees a Block2 continuation);
//! answers go piggybacked on the ACK, or separately after an empty ACK; Observe
//! registrations and notifications (RFC 7641).

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::time::Instant;

use super::qblock::{QSend, QUpload};
use super::types::Response;
use crate::block::{self, Block1Assembler, BlockKey, ServerCache, Slice, Source};
use crate::msg::{BlockOpt, Code, OptionNumber, Options, Token};
use crate::peer_key::FastMap;

/// A received request waiting for the application's response.
pub(super) struct Pending {
    pub(super) peer: SocketAddr,
    pub(super) mid: u16,
    pub(super) token: Token,
    pub(super) confirmable: bool,
    pub(super) acked: bool,
    pub(super) multicast: bool,
    pub(super) block2: Option<BlockOpt>,
    pub(super) block1_echo: Option<BlockOpt>,
    /// The peer's address is not verified: the answer may be at most this many bytes
    /// (three times the request, RFC 9175 §2.4).
    pub(super) budget: Option<usize>,
    pub(super) key: BlockKey,
    pub(super) observation: Option<u64>,
    /// The request's Q-Block2 options (RFC 9177): the response goes with Q-Block2.
    pub(super) qblock2: Vec<BlockOpt>,
    /// A multicast request's answer leaves no earlier (its leisure, RFC 7252 §8.2).
    pub(super) not_before: Option<Instant>,
}

/// An observation this endpoint serves.
pub(super) struct Observation {
    pub(super) peer: SocketAddr,
    pub(super) token: Token,
    pub(super) key: BlockKey,
    pub(super) established: bool,
    pub(super) seq: u32,
    pub(super) sent: u32,
    /// Message ID of the last NON notification, so a Reset to it ends the observation.
    pub(super) last_mid: Option<u16>,
    /// A CON notification is unacknowledged: the next waits (RFC 7641 §4.5.2).
    pub(super) in_flight: bool,
    /// The newest notification that came while one was in flight; it goes on the ACK.
    pub(super) queued: Option<Response>,
}

/// The server side's state.
pub(super) struct ServerLayer {
    pub(super) pending: FastMap<u64, Pending>,
    pub(super) block1: Block1Assembler,
    pub(super) block2: ServerCache,
    pub(super) observations: FastMap<u64, Observation>,
    /// Answers to multicast requests waiting for the end of their leisure.
    pub(super) held: FastMap<u64, (Pending, Response)>,
    /// Bodies being sent with Q-Block2, set by set.
    pub(super) qsends: FastMap<u64, QSend>,
    /// Bodies being received with Q-Block1, and their ids by request.
    pub(super) quploads: FastMap<u64, QUpload>,
    pub(super) qupload_ids: BTreeMap<BlockKey, u64>,
    /// When the armed [`TimerKind::Sweep`](super::message::TimerKind) fires: the first
    /// time an upload or a stored representation may have been idle for its lifetime.
    pub(super) sweep_at: Option<Instant>,
}

impl ServerLayer {
    /// Requests handed to the application and not answered on the wire yet (answers
    /// held for their leisure included).
    pub(super) fn unanswered(&self) -> usize {
        self.pending.len() + self.held.len()
    }

    /// Whether received request `id` still waits for the empty ACK of a CON.
    pub(super) fn awaits_separate_ack(&self, id: u64) -> bool {
        self.pending
            .get(&id)
            .is_some_and(|p| !p.acked && p.confirmable)
    }

    /// The observation whose last NON notification to `peer` had message ID `mid`.
    pub(super) fn notified_with(&self, peer: SocketAddr, mid: u16) -> Option<u64> {
        self.observations
            .iter()
            .find(|(_, o)| o.peer == peer && o.last_mid == Some(mid))
            .map(|(id, _)| *id)
    }

    pub(super) fn new() -> Self {
        Self {
            pending: FastMap::default(),
            block1: Block1Assembler::new(),
            block2: ServerCache::new(),
            observations: FastMap::default(),
            held: FastMap::default(),
            qsends: FastMap::default(),
            quploads: FastMap::default(),
            qupload_ids: BTreeMap::new(),
            sweep_at: None,
        }
    }
}

/// Block `num` of a representation as a response, with Block2, and Size2 on block 0
/// (RFC 7959 §4); 4.02 when the block starts past the end; `None` when the body's source
/// could not be read.
pub(super) fn block2_response(
    code: Code,
    options: Options,
    body: &Source,
    num: u32,
    szx: u8,
) -> Option<Response> {
    let (payload, opt) = match block::slice(&*body.0, num, szx) {
        Slice::Block(payload, opt) => (payload, opt),
        Slice::PastEnd => return Some(past_end()),
        Slice::Unreadable => return None,
    };
    let mut options = options;
    options.set_block(OptionNumber::BLOCK2, opt);
    if num == 0 {
        options.set_uint(OptionNumber::SIZE2, body.0.len() as u32);
    }
    Some(Response::with_parts(code, options, payload))
}

/// The answer to a block that starts past the end of the body (RFC 7959 §2.2).
pub(super) fn past_end() -> Response {
    Response::diagnostic(
        Code::BAD_OPTION,
        "Block2 number beyond the end of the representation",
    )
}

/// The answer when a body's source cannot be read as it was (the file is changing): try
/// again in a second (RFC 7252 §5.9.3.4).
pub(super) fn unreadable() -> Response {
    let mut r = Response::diagnostic(
        Code::SERVICE_UNAVAILABLE,
        "the representation changed while it was read; try again",
    );
    r.options.set_uint(OptionNumber::MAX_AGE, 1);
    r
}
