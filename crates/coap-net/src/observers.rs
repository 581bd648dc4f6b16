//! The observations a peer registered on one stream connection (RFC 7641 as RFC 8323 §7
//! has it over reliable transports), kept by the connection's task in `tcp.rs`.
//!
//! Over UDP the [`Server`](crate::Server) keeps every observation of an endpoint and the
//! endpoint numbers, confirms and retransmits the notifications. Over a stream an
//! observation belongs to its connection: it ends with it (the peer can no longer be
//! reached under that token, RFC 8323 §7.4), the stream delivers notifications reliably
//! and in order, so there is nothing to confirm or reorder (§7.1, §7.2), and the only way
//! for a client to end one early is a request with the observation's token (a GET with
//! Observe 1, RFC 7641 §3.6), since there is no Reset. So each connection keeps its own,
//! and learns which paths changed from the router ([`Router::changed`](crate::Router::changed)).
//!
//! A notification is the registration's GET run again, as over UDP. One runs per
//! observation at a time: a change while it runs marks the observation to run once more
//! when it is done, so notifications leave in the order their handlers read the
//! resource, and a resource that changes faster than its handler answers is notified at
//! the handler's pace with its newest state. A representation the observer already has
//! (the same code, Content-Format and ETag, or body without an ETag) is not sent again.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};

use bytes::Bytes;
use coap::{Code, ContentFormat, IncomingRequest, ObservationId, OptionNumber, Response, Token};

use crate::router::{ObservationEnd, Router};

/// How many observations one connection keeps. A registration beyond them is answered
/// as a plain GET, without Observe (RFC 7641 §4.1: the server need not keep it).
pub(crate) const MAX_OBSERVATIONS: usize = 64;

/// The numbers of stream observations, shared by every connection of the process:
/// [`ObservationId`]s name an observer to the resources (a live stream keys its
/// subscribers by address and observation), so a stream's must not be one a UDP
/// endpoint gives (those count up from 0) or another connection's. They count down from
/// the top.
static NEXT_ID: AtomicU64 = AtomicU64::new(u64::MAX);

/// One observation.
struct Observation {
    id: ObservationId,
    path: String,
    /// The registration, run again for each notification.
    request: IncomingRequest,
    /// What the observer has: the registration's answer, then the last notification.
    last: Sent,
    /// The Observe value of the last notification. RFC 8323 §7.1 lets it be empty over
    /// a stream; it counts up anyway, for a client that looks at it.
    seq: u32,
    /// Told when the observation ends.
    ended: Option<ObservationEnd>,
    /// A notification's handler runs.
    running: bool,
    /// The resource changed again while it ran.
    again: bool,
}

/// A notification to run: the registration of observation `id`, under `token`.
pub(crate) struct Due {
    pub(crate) token: Token,
    pub(crate) id: ObservationId,
    pub(crate) request: IncomingRequest,
}

/// One connection's observations, by token. Dropped (the connection is over), it tells
/// each observed resource that its observation ended.
pub(crate) struct Observers {
    peer: SocketAddr,
    by_token: HashMap<Token, Observation>,
    /// Registrations whose answer is being made, by token: a request of the same token
    /// meanwhile (a deregistration) takes its token out, and the answer keeps nothing.
    registering: HashMap<Token, ObservationId>,
}

impl Observers {
    pub(crate) fn new(peer: SocketAddr) -> Self {
        Self {
            peer,
            by_token: HashMap::new(),
            registering: HashMap::new(),
        }
    }

    pub(crate) fn is_empty(&self) -> bool {
        self.by_token.is_empty()
    }

    /// A request of `token` came: a deregistration (RFC 7641 §3.6) or the token used
    /// again, which ends the observation of that token either way. Returns the
    /// [`ObservationId`] a registration (`registers`: a GET with Observe 0) is to carry,
    /// unless the connection keeps [`MAX_OBSERVATIONS`] already.
    pub(crate) fn request(&mut self, token: Token, registers: bool) -> Option<ObservationId> {
        if let Some(gone) = self.by_token.remove(&token) {
            self.end(gone);
        }
        self.registering.remove(&token);
        let room = self.by_token.len() + self.registering.len() < MAX_OBSERVATIONS;
        let id =
            (registers && room).then(|| ObservationId(NEXT_ID.fetch_sub(1, Ordering::Relaxed)))?;
        self.registering.insert(token, id);
        Some(id)
    }

    /// The answer to `request` of `token`. A registration (its request carries its id)
    /// is kept when the resource accepted it (a 2.xx with Observe, which the router sets
    /// for an observable resource) and no request of the same token came meanwhile.
    /// Otherwise the answer's Observe option is removed, so that the client knows it is
    /// not registered (RFC 7641 §4.1). An observation the resource accepted but that is
    /// not kept is told its end.
    pub(crate) fn answered(
        &mut self,
        router: &Router,
        token: Token,
        request: IncomingRequest,
        response: &mut Response,
    ) {
        let accepted =
            response.code.is_success() && response.options.contains(OptionNumber::OBSERVE);
        let path: Vec<String> = request.options.uri_path().map(|s| s.into_owned()).collect();
        let ended = || {
            router
                .find(&path)
                .and_then(|(resource, _)| resource.observation_end().cloned())
        };
        let Some(id) = request.observe else {
            response.options.remove(OptionNumber::OBSERVE);
            return;
        };
        let current = self.registering.get(&token) == Some(&id);
        if current {
            self.registering.remove(&token);
        }
        if !(accepted && current) {
            response.options.remove(OptionNumber::OBSERVE);
            if let Some(ended) = ended().filter(|_| accepted) {
                ended(self.peer, id);
            }
            return;
        }
        let ended = ended();
        response.options.set_uint(OptionNumber::OBSERVE, 0);
        let observation = Observation {
            id,
            path: request.options.path_string(),
            request,
            last: Sent::of(response),
            seq: 0,
            ended,
            running: false,
            again: false,
        };
        if let Some(gone) = self.by_token.insert(token, observation) {
            self.end(gone);
        }
    }

    /// `path` changed: the notifications to run now (those of its observations whose
    /// handler is not running already; those are marked to run again).
    pub(crate) fn changed(&mut self, path: &str) -> Vec<Due> {
        let mut due = Vec::new();
        for (token, o) in &mut self.by_token {
            if o.path != path {
                continue;
            }
            if o.running {
                o.again = true;
                continue;
            }
            o.running = true;
            due.push(Due {
                token: *token,
                id: o.id,
                request: o.request.clone(),
            });
        }
        due
    }

    /// Every path observed: what changed when the connection lost track of the changes.
    pub(crate) fn paths(&self) -> Vec<String> {
        let mut paths: Vec<String> = self.by_token.values().map(|o| o.path.clone()).collect();
        paths.sort_unstable();
        paths.dedup();
        paths
    }

    /// The notification of observation `id` (under `token`) ran and answered `response`:
    /// what to send, if anything (numbered), and the notification to run next when the
    /// resource changed meanwhile. An error ends the observation (RFC 7641 §4.2: it
    /// goes without Observe, as the last); an observation that ended meanwhile sends
    /// nothing.
    pub(crate) fn notified(
        &mut self,
        token: Token,
        id: ObservationId,
        mut response: Response,
    ) -> (Option<Response>, Option<Due>) {
        let Some(o) = self.by_token.get_mut(&token).filter(|o| o.id == id) else {
            return (None, None);
        };
        o.running = false;
        if !response.code.is_success() {
            response.options.remove(OptionNumber::OBSERVE);
            if let Some(gone) = self.by_token.remove(&token) {
                self.end(gone);
            }
            return (Some(response), None);
        }
        let next = Sent::of(&response);
        let send = if o.last.repeats(&next) {
            None
        } else {
            o.last = next;
            o.seq = (o.seq + 1) & 0xff_ffff;
            response.options.set_uint(OptionNumber::OBSERVE, o.seq);
            Some(response)
        };
        let again = std::mem::take(&mut o.again).then(|| {
            o.running = true;
            Due {
                token,
                id,
                request: o.request.clone(),
            }
        });
        (send, again)
    }

    /// Tells `gone`'s resource that it ended.
    fn end(&self, gone: Observation) {
        if let Some(ended) = gone.ended {
            ended(self.peer, gone.id);
        }
    }
}

impl Drop for Observers {
    fn drop(&mut self) {
        for (_, gone) in std::mem::take(&mut self.by_token) {
            self.end(gone);
        }
    }
}

/// What tells one representation from another for an observer: the code, the
/// Content-Format and the ETag, and the body when there is no ETag. A body read block by
/// block (a [`Response::source`]) without an ETag is never taken for the last one.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Sent {
    code: Code,
    format: Option<ContentFormat>,
    etag: Option<Vec<u8>>,
    /// `None` when the ETag names the body, or when the body is read block by block.
    payload: Option<Bytes>,
}

impl Sent {
    pub(crate) fn of(response: &Response) -> Self {
        let etag = response.options.etag().map(<[u8]>::to_vec);
        let payload =
            (etag.is_none() && response.source.is_none()).then(|| response.payload.clone());
        Self {
            code: response.code,
            format: response.options.content_format(),
            etag,
            payload,
        }
    }

    /// Whether `next` is the representation this observer already has.
    pub(crate) fn repeats(&self, next: &Self) -> bool {
        self == next && (self.etag.is_some() || self.payload.is_some())
    }
}
