//! Answering a received request at once, and remembering the answer for its duplicates
//! (RFC 7252 §4.5): what every stage of the server that answers a request itself uses.

use std::net::SocketAddr;
use std::time::Instant;

use super::context::Context;
use super::server_state::Incoming;
use super::types::Response;
use crate::dedup::{Fingerprint, Seen};
use crate::msg::{Message, Type};

/// Remembers what answered `req` for its duplicates (RFC 7252 §4.5).
pub(super) fn remember(cx: &mut Context<'_>, now: Instant, req: &Incoming<'_>, seen: Seen) {
    let key = (req.peer, req.msg.message_id);
    let limits = cx.limits();
    (cx.msg.dedup).insert(
        now,
        key,
        Fingerprint::of(&req.msg),
        req.expires,
        seen,
        limits,
    );
}

/// Answers a request at once and remembers the answer for its duplicates.
pub(super) fn answer(cx: &mut Context<'_>, now: Instant, req: &Incoming<'_>, response: Response) {
    let seen = reply(cx, now, req, response);
    remember(cx, now, req, seen);
}

/// Sends a response to a request right away (piggybacked on the ACK of a CON, or as a
/// NON to a NON) and returns what to remember for duplicates. Error responses to
/// multicast requests are suppressed (RFC 7390 §2.7).
pub(super) fn reply(
    cx: &mut Context<'_>,
    now: Instant,
    req: &Incoming<'_>,
    response: Response,
) -> Seen {
    match reply_message(cx, now, req.peer, &req.msg, req.multicast, response) {
        Some(msg) => cx.msg.reply_with(req.peer, msg),
        None => Seen::Silent,
    }
}

/// The type and message ID of a reply to `req` from `peer`: a piggybacked ACK to a CON, a
/// NON with a new message ID otherwise.
pub(super) fn reply_header(
    cx: &mut Context<'_>,
    now: Instant,
    peer: SocketAddr,
    req: &Message,
) -> (Type, u16) {
    match req.ty {
        Type::Con => (Type::Ack, req.message_id),
        _ => (Type::Non, cx.msg.next_mid(now, peer)),
    }
}

/// The message that answers `req` right away; `None` when nothing is sent (an error
/// response to a multicast request).
pub(super) fn reply_message(
    cx: &mut Context<'_>,
    now: Instant,
    peer: SocketAddr,
    req: &Message,
    multicast: bool,
    response: Response,
) -> Option<Message> {
    if multicast && response.code.is_error() {
        return None;
    }
    let (ty, mid) = reply_header(cx, now, peer, req);
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
