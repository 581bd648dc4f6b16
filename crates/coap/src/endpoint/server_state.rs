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
use super::verify::AddressCheck;
use crate::block::{self, Block1Assembler, BlockKey, ServerCache, Slice, Source};
use crate::config::EndpointConfig;
use crate::msg::{BlockOpt, Code, Message, OptionNumber, Options, Token, Type};
use crate::peer_key::FastMap;

/// A received request, and what its options say, read once: what the stages of the
/// server's `on_request` and the Q-Block server read.
pub(super) struct Incoming<'p> {
    pub(super) peer: SocketAddr,
    pub(super) msg: Message,
    /// The payload, still in the datagram.
    pub(super) payload: &'p [u8],
    /// Sent to a multicast group (then no error answers, RFC 7390 §2.7).
    pub(super) multicast: bool,
    pub(super) con: bool,
    /// When its message ID is forgotten: EXCHANGE_LIFETIME (CON) or NON_LIFETIME after
    /// it arrived.
    pub(super) expires: Instant,
    pub(super) block1: Option<BlockOpt>,
    pub(super) block2: Option<BlockOpt>,
    /// Block2 for a block after the first, without Block1: served from the store.
    pub(super) continuation: bool,
    /// RFC 9177: its Q-Block2 options (repeatable) and Q-Block1.
    pub(super) q2: Vec<BlockOpt>,
    pub(super) q1: Option<BlockOpt>,
    /// Once the address is checked: at most this many bytes may answer an unverified
    /// peer's group request (three times the request, RFC 9175 §2.4).
    pub(super) budget: Option<usize>,
}

impl<'p> Incoming<'p> {
    /// Request `msg` from `peer`, arrived at `now`.
    pub(super) fn read(
        config: &EndpointConfig,
        now: Instant,
        peer: SocketAddr,
        msg: Message,
        payload: &'p [u8],
        multicast: bool,
    ) -> Self {
        let con = msg.ty == Type::Con;
        let (block1, block2) = (msg.options.block1(), msg.options.block2());
        let q2 = (msg.options.values(OptionNumber::Q_BLOCK2))
            .filter_map(BlockOpt::decode)
            .collect();
        let q1 = msg.options.block(OptionNumber::Q_BLOCK1);
        let lifetime = if con {
            config.exchange_lifetime
        } else {
            config.non_lifetime
        };
        Self {
            peer,
            payload,
            multicast,
            con,
            expires: now + lifetime,
            block1,
            block2,
            continuation: matches!((block2, block1), (Some(b2), None) if b2.num > 0),
            q2,
            q1,
            budget: None,
            msg,
        }
    }

    /// It has Q-Block options.
    pub(super) fn is_qblock(&self) -> bool {
        !self.q2.is_empty() || self.q1.is_some()
    }

    /// Its blocks are served from the store or assembled with duplicates found by block
    /// number (Q-Block1, or Q-Block2 past block 0), not deduplicated by message ID.
    pub(super) fn q_stateless(&self) -> bool {
        self.q1.is_some() || self.q2.iter().any(|b| b.num > 0)
    }

    /// What its blocks are kept under: the peer, the method and the options that tell
    /// one body from another.
    pub(super) fn block_key(&self) -> BlockKey {
        BlockKey {
            peer: self.peer,
            method: self.msg.code,
            options: self.msg.options.block_key(),
        }
    }
}

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
    /// A group request of a peer whose address is not verified: the answer may be at
    /// most this many bytes (three times the request, RFC 9175 §2.4).
    pub(super) budget: Option<usize>,
    /// When it was handed to the application.
    pub(super) since: Instant,
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
    /// RFC 9175 address verification: asked first about every request.
    pub(super) verify: AddressCheck,
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

    /// Group requests of unverified peers that the application is working on.
    pub(super) fn unverified_group_work(&self) -> usize {
        self.pending.values().filter(|p| p.budget.is_some()).count()
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
            verify: AddressCheck::new(),
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
