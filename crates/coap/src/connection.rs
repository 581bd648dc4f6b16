//! One CoAP connection over a reliable transport (RFC 8323: TCP, or WebSockets with
//! [`Connection::websocket`]), sans-IO, for either end: bytes in with [`Connection::handle`], bytes out with
//! [`Connection::poll_transmit`], what happened out with [`Connection::poll_event`].
//! A server takes the peer's requests from [`ConnectionEvent::Request`] and answers them
//! with [`Connection::respond`]; a client sends its own with
//! [`Connection::send_request`] and gets [`ConnectionEvent::Response`] or
//! [`ConnectionEvent::Failed`] for each, and calls [`Connection::handle_timeout`] at
//! [`Connection::poll_timeout`]. Both roles share one type because the signalling is the
//! same for both, and RFC 8323 lets either end of a connection send requests.
//!
//! What it does of the signalling (§5): it sends its CSM first, with its
//! Max-Message-Size; it takes the peer's first message to be a CSM and aborts otherwise;
//! it answers a Ping with a Pong carrying the Ping's token and no Custody (it does not
//! wait for the answers to earlier requests); a Release or an Abort from the peer closes
//! it. A frame it cannot read, one over its Max-Message-Size, or a signalling message with
//! an unknown critical option makes it send an Abort and close.
//!
//! As a client: each request gets a fresh token, from a counter: unique on the
//! connection, which is what matching needs (over a stream an off-path attacker cannot
//! inject a response, the reason RFC 7252 §5.3.1 asks for random tokens over UDP). Requests
//! wait until the peer's CSM has come, so that they are measured against its
//! Max-Message-Size (one over it fails with [`RequestError::RequestTooLarge`]); a
//! response is matched by its token, and one whose token no waiting request has is
//! ignored; a body over the body limit ([`Connection::with_body_limit`]) fails with
//! [`RequestError::TooLarge`], as the UDP client's does. Each request gives up at its
//! [`Request::timeout`] ([`DEFAULT_RESPONSE_TIMEOUT`] when it has none). When the
//! connection closes, every request still waiting fails with
//! [`RequestError::ConnectionClosed`]. [`Connection::ping`] sends a Ping and reports its
//! Pong (one without the Ping's token, as libcoap 4.3.5 sends, answers the oldest Ping).
//!
//! Observe (RFC 7641 as RFC 8323 §7 has it over reliable transports): as a server it
//! passes a registration's answer and each notification on as the caller gives them,
//! Observe option and all (keeping observations is the caller's, who knows the resources:
//! coap-net's stream server); as a client, a request registering (GET or FETCH with
//! Observe 0) whose answer is a 2.xx with Observe stays matched to its token, with no
//! timeout any more, and every later response of that token is reported as a
//! notification until one comes without Observe or with an error code, or
//! [`Connection::cancel_observation`] deregisters. Notifications carry no type and need
//! no acknowledgement (§7.2); their Observe values are not used for ordering, since the
//! stream keeps it (§7.1).
//!
//! What it does not do yet: block-wise transfer and BERT (it announces no
//! Block-Wise-Transfer; an answer over the peer's Max-Message-Size becomes a 5.00 with a
//! diagnostic, a request over it fails), Pings of its own to keep a connection alive.

use std::collections::{HashMap, VecDeque};
use std::time::{Duration, Instant};

use bytes::Bytes;

use crate::config::Limits;
use crate::endpoint::{Request, RequestError, Response};
use crate::msg::signal::{Abort, Csm, Release, Signal};
use crate::msg::stream::{self, Decoded, Frame};
use crate::msg::{Code, OptionNumber, Options, Token};

/// How long a request without [`Request::timeout`] waits for its response: the UDP
/// client's wait for a separate response (MAX_TRANSMIT_WAIT, RFC 7252 §4.8.2, 93 s).
pub const DEFAULT_RESPONSE_TIMEOUT: Duration = Duration::from_secs(93);

/// How a connection's frames are delimited.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Framing {
    /// TCP (or TLS): each frame carries its length (§3.2).
    Stream,
    /// WebSockets: each message is one frame, whose length the message gives (§4.2).
    WebSocket,
}

impl Framing {
    /// The bytes `frame` takes on the wire, as Max-Message-Size counts them.
    fn size(self, frame: &Frame) -> usize {
        match self {
            Self::Stream => frame.encoded_len(),
            Self::WebSocket => frame.ws_encoded_len(),
        }
    }
}

/// A request the peer sent.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StreamRequest {
    /// Its token: [`Connection::respond`] takes it back.
    pub token: Token,
    /// Method code.
    pub method: Code,
    /// Options (malformed elective options already dropped).
    pub options: Options,
    /// Body.
    pub payload: Bytes,
}

/// Why a connection closed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Closed {
    /// The peer sent a Release (§5.5).
    Released,
    /// The peer sent an Abort (§5.6), with its diagnostic payload.
    AbortedByPeer(String),
    /// This side sent an Abort, for this reason.
    Aborted(String),
    /// This side sent a Release ([`Connection::release`]), for this reason.
    ReleasedHere(String),
    /// The stream ended without either ([`Connection::handle_end`]).
    Ended,
}

/// What the connection tells its owner.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ConnectionEvent {
    /// A request to answer with [`Connection::respond`] (boxed: the other event is
    /// small).
    Request(Box<StreamRequest>),
    /// The response to this side's request of this token (boxed, as a request is).
    Response(Token, Box<Response>),
    /// This side's request (or Ping) of this token failed: no response (or Pong) will be
    /// reported.
    Failed(Token, RequestError),
    /// The Pong to this side's Ping of this token.
    Pong(Token),
    /// The connection is over: send what [`Connection::poll_transmit`] still has, then
    /// close the stream.
    Closed(Closed),
}

/// A request or Ping this side sent and the peer has not answered.
#[derive(Debug)]
struct Outstanding {
    /// When it fails with [`RequestError::Timeout`].
    deadline: Instant,
    /// A Ping, answered by a Pong rather than a response.
    ping: bool,
    /// A request registering an observation (GET or FETCH with Observe 0).
    registers: bool,
    /// Its registration was accepted: every response of its token is a notification,
    /// and it no longer times out.
    observing: bool,
}

/// One connection's state.
#[derive(Debug)]
pub struct Connection {
    /// The largest frame this side accepts, announced in its CSM.
    max_message_size: u32,
    /// How frames are delimited on the wire.
    framing: Framing,
    /// Bytes received and not yet a whole frame (over TCP).
    inbound: Vec<u8>,
    /// Frames to send, encoded (over TCP).
    outbound: Vec<u8>,
    /// Messages to send, one frame each (over WebSockets).
    messages: VecDeque<Vec<u8>>,
    events: VecDeque<ConnectionEvent>,
    /// The peer's settings, once its CSM came.
    peer: Option<Csm>,
    closed: bool,
    /// The largest response body this side takes.
    body_limit: usize,
    /// This side's requests and Pings not answered yet, by token.
    outstanding: HashMap<Token, Outstanding>,
    /// Requests that wait for the peer's CSM, in the order they were sent.
    waiting: Vec<Frame>,
    /// The last token given out.
    last_token: u64,
}

impl Connection {
    /// A connection over TCP that accepts frames of up to `max_message_size` bytes; its
    /// CSM is the first thing to send. As a client it takes response bodies of up to
    /// [`Limits::client_body_bytes`]'s default.
    pub fn new(max_message_size: u32) -> Self {
        Self::with_framing(max_message_size, Framing::Stream)
    }

    /// The same over WebSockets (§4): [`Connection::handle`] takes one whole WebSocket
    /// message at a time and [`Connection::poll_transmit`] gives one, each a frame
    /// without its length ([`Frame::encode_ws`]). Max-Message-Size counts a message's
    /// bytes.
    pub fn websocket(max_message_size: u32) -> Self {
        Self::with_framing(max_message_size, Framing::WebSocket)
    }

    fn with_framing(max_message_size: u32, framing: Framing) -> Self {
        let csm = Signal::Csm(Csm {
            max_message_size: Some(max_message_size),
            block_wise_transfer: false,
        });
        let mut c = Self {
            max_message_size,
            framing,
            inbound: Vec::new(),
            outbound: Vec::new(),
            messages: VecDeque::new(),
            events: VecDeque::new(),
            peer: None,
            closed: false,
            body_limit: Limits::default().client_body_bytes,
            outstanding: HashMap::new(),
            waiting: Vec::new(),
            last_token: 0,
        };
        c.emit(&csm.to_frame(Token::EMPTY, Bytes::new()));
        c
    }

    /// Queues `frame` to be sent, framed for the connection's transport.
    fn emit(&mut self, frame: &Frame) {
        match self.framing {
            Framing::Stream => frame.encode_into(&mut self.outbound),
            Framing::WebSocket => self.messages.push_back(frame.encode_ws()),
        }
    }

    /// The same connection taking response bodies of up to `bytes` (the endpoint's
    /// [`Limits::client_body_bytes`]); a larger one fails its request with
    /// [`RequestError::TooLarge`].
    #[must_use]
    pub fn with_body_limit(mut self, bytes: usize) -> Self {
        self.body_limit = bytes;
        self
    }

    /// The peer's capabilities and settings, once its CSM came (options it left out
    /// keep their defaults).
    pub fn peer_csm(&self) -> Option<Csm> {
        self.peer
    }

    /// Whether the connection is over (its [`ConnectionEvent::Closed`] was queued).
    pub fn is_closed(&self) -> bool {
        self.closed
    }

    /// Takes bytes received: over TCP any part of the stream, every whole frame among
    /// them handled; over WebSockets one whole message.
    pub fn handle(&mut self, bytes: &[u8]) {
        if self.closed {
            return;
        }
        if self.framing == Framing::WebSocket {
            match stream::decode_ws(bytes, self.max_message_size as usize) {
                Ok(frame) => self.frame(frame),
                Err(e) => self.abort(e.to_string(), None),
            }
            return;
        }
        self.inbound.extend_from_slice(bytes);
        let mut at = 0;
        while !self.closed {
            let limit = self.max_message_size as usize;
            match stream::decode(&self.inbound[at..], limit) {
                Ok(Decoded::Incomplete { .. }) => break,
                Ok(Decoded::Frame { frame, consumed }) => {
                    at += consumed;
                    self.frame(frame);
                }
                Err(e) => self.abort(e.to_string(), None),
            }
        }
        if self.closed {
            self.inbound = Vec::new();
        } else {
            self.inbound.drain(..at);
        }
    }

    fn frame(&mut self, frame: Frame) {
        if self.peer.is_none() && frame.code != Code::CSM {
            return self.abort(format!("first message {} is not a CSM", frame.code), None);
        }
        if frame.code.is_signal() {
            return self.signal(frame);
        }
        if frame.code.is_request() {
            return self.request(frame);
        }
        // 0.00 is ignored (§3.4).
        if frame.code != Code::EMPTY {
            self.response(frame);
        }
    }

    fn request(&mut self, frame: Frame) {
        let mut options = frame.options;
        if let Some(bad) = options.first_bad_critical() {
            let text = format!("bad option {}", bad.0);
            return self.send(frame.token, &Response::diagnostic(Code::BAD_OPTION, &text));
        }
        options.drop_bad_elective();
        self.events
            .push_back(ConnectionEvent::Request(Box::new(StreamRequest {
                token: frame.token,
                method: frame.code,
                options,
                payload: frame.payload,
            })));
    }

    /// A response: to a request of this side's that waits for it (or a notification of
    /// an observation it registered), or ignored.
    fn response(&mut self, frame: Frame) {
        let Some(waiting) = self.outstanding.get_mut(&frame.token).filter(|o| !o.ping) else {
            return;
        };
        // RFC 7641 §3.2: a 2.xx with Observe says the registration holds; anything else
        // ends it (§3.3.2 for an error, and a plain answer says it was not made).
        let observed = frame.code.is_success() && frame.options.contains(OptionNumber::OBSERVE);
        if waiting.registers && observed {
            waiting.observing = true;
        } else {
            self.outstanding.remove(&frame.token);
        }
        let event = if frame.payload.len() > self.body_limit {
            let limit = self.body_limit;
            ConnectionEvent::Failed(frame.token, RequestError::TooLarge { limit })
        } else {
            let response = Response::with_parts(frame.code, frame.options, frame.payload);
            ConnectionEvent::Response(frame.token, Box::new(response))
        };
        self.events.push_back(event);
    }

    fn signal(&mut self, frame: Frame) {
        let signal = match Signal::decode(&frame) {
            Ok(signal) => signal,
            Err(e) => {
                if let Some(abort) = e.abort() {
                    self.abort(e.to_string(), abort.bad_csm_option);
                }
                return;
            }
        };
        match signal {
            Signal::Csm(csm) => {
                let mut peer = self.peer.unwrap_or_default();
                peer.max_message_size = csm.max_message_size.or(peer.max_message_size);
                peer.block_wise_transfer |= csm.block_wise_transfer;
                self.peer = Some(peer);
                for frame in std::mem::take(&mut self.waiting) {
                    self.transmit_request(frame);
                }
            }
            Signal::Ping { .. } => {
                let pong = Signal::Pong { custody: false };
                self.emit(&pong.to_frame(frame.token, Bytes::new()));
            }
            Signal::Pong { .. } => {
                if let Some(ping) = self.ping_answered_by(frame.token) {
                    self.outstanding.remove(&ping);
                    self.events.push_back(ConnectionEvent::Pong(ping));
                }
            }
            Signal::Release(_) => self.close(Closed::Released),
            Signal::Abort(_) => {
                let text = String::from_utf8_lossy(&frame.payload).into_owned();
                self.close(Closed::AbortedByPeer(text));
            }
        }
    }

    /// The Ping a Pong of `token` answers: the one of that token, else the oldest one
    /// waiting (libcoap 4.3.5 answers every Ping with a Pong of an empty token).
    fn ping_answered_by(&self, token: Token) -> Option<Token> {
        if self.outstanding.get(&token).is_some_and(|o| o.ping) {
            return Some(token);
        }
        self.outstanding
            .iter()
            .filter(|(_, o)| o.ping)
            .map(|(t, _)| *t)
            .min_by_key(token_order)
    }

    /// Sends an Abort with `reason` as its diagnostic, and closes.
    fn abort(&mut self, reason: String, bad_csm_option: Option<OptionNumber>) {
        let abort = Signal::Abort(Abort { bad_csm_option });
        let diagnostic = Bytes::copy_from_slice(reason.as_bytes());
        self.emit(&abort.to_frame(Token::EMPTY, diagnostic));
        self.close(Closed::Aborted(reason));
    }

    /// Ends the connection from this side (§5.5): sends a Release with `reason` as its
    /// diagnostic and Hold-Off `hold_off_s` (how many seconds the peer should wait before
    /// it connects again), and closes. A server uses it to turn a connection away and to
    /// end an idle one.
    pub fn release(&mut self, reason: &str, hold_off_s: Option<u32>) {
        if self.closed {
            return;
        }
        let release = Signal::Release(Release {
            alternative_addresses: Vec::new(),
            hold_off_s,
        });
        let diagnostic = Bytes::copy_from_slice(reason.as_bytes());
        self.emit(&release.to_frame(Token::EMPTY, diagnostic));
        self.close(Closed::ReleasedHere(reason.to_owned()));
    }

    /// Closes: every request and Ping still waiting fails (in the order of their tokens), then
    /// [`ConnectionEvent::Closed`].
    fn close(&mut self, why: Closed) {
        self.closed = true;
        self.waiting.clear();
        let mut left: Vec<(Token, Outstanding)> = self.outstanding.drain().collect();
        left.sort_by_key(|(token, _)| token_order(token));
        for (token, _) in left {
            let failed = ConnectionEvent::Failed(token, RequestError::ConnectionClosed);
            self.events.push_back(failed);
        }
        self.events.push_back(ConnectionEvent::Closed(why));
    }

    /// The peer's Max-Message-Size: its CSM's, or the default until that comes.
    fn peer_limit(&self) -> usize {
        self.peer.map_or(Csm::DEFAULT_MAX_MESSAGE_SIZE, |p| {
            p.max_message_size_or_default()
        }) as usize
    }

    /// A token no request or Ping of this side's has had on this connection.
    fn fresh_token(&mut self) -> Token {
        self.last_token += 1;
        let bytes = self.last_token.to_be_bytes();
        let zeros = self.last_token.leading_zeros() as usize / 8;
        // Eight bytes at most: always a token.
        Token::new(&bytes[zeros..]).unwrap_or_default()
    }

    /// Sends `request` to the peer; its answer comes as [`ConnectionEvent::Response`] or
    /// [`ConnectionEvent::Failed`] with the token returned. It leaves once the peer's
    /// CSM has come (at once, when it has). Its type, block size and transfer mode do
    /// not apply to a stream.
    pub fn send_request(&mut self, now: Instant, request: &Request) -> Token {
        let token = self.fresh_token();
        if self.closed {
            let failed = ConnectionEvent::Failed(token, RequestError::ConnectionClosed);
            self.events.push_back(failed);
            return token;
        }
        let timeout = request.timeout.unwrap_or(DEFAULT_RESPONSE_TIMEOUT);
        let deadline = now + timeout;
        let registers = matches!(request.method, Code::GET | Code::FETCH)
            && request.options.uint(OptionNumber::OBSERVE) == Some(0);
        let pending = Outstanding {
            deadline,
            ping: false,
            registers,
            observing: false,
        };
        self.outstanding.insert(token, pending);
        let frame = Frame {
            code: request.method,
            token,
            options: request.options.clone(),
            payload: request.payload.clone(),
        };
        if self.peer.is_some() {
            self.transmit_request(frame);
        } else {
            self.waiting.push(frame);
        }
        token
    }

    /// Writes a request that waited for the peer's CSM, or fails it when it is larger
    /// than the peer takes (or timed out meanwhile).
    fn transmit_request(&mut self, frame: Frame) {
        if !self.outstanding.contains_key(&frame.token) {
            return;
        }
        let limit = self.peer_limit();
        if self.framing.size(&frame) > limit {
            self.outstanding.remove(&frame.token);
            let failed = RequestError::RequestTooLarge { limit };
            self.events
                .push_back(ConnectionEvent::Failed(frame.token, failed));
            return;
        }
        self.emit(&frame);
    }

    /// Sends a Ping (§5.4); [`ConnectionEvent::Pong`] with the token returned reports
    /// its answer, or [`ConnectionEvent::Failed`] its timeout (`now + timeout`) or the
    /// connection's end.
    pub fn ping(&mut self, now: Instant, timeout: Duration) -> Token {
        let token = self.fresh_token();
        if !self.closed {
            let ping = Outstanding {
                deadline: now + timeout,
                ping: true,
                registers: false,
                observing: false,
            };
            self.outstanding.insert(token, ping);
            let frame = Signal::Ping { custody: false }.to_frame(token, Bytes::new());
            self.emit(&frame);
        }
        token
    }

    /// When [`Connection::handle_timeout`] is next due: the earliest deadline of a
    /// request or Ping not answered yet (an accepted observation has none).
    pub fn poll_timeout(&self) -> Option<Instant> {
        (self.outstanding.values())
            .filter(|o| !o.observing)
            .map(|o| o.deadline)
            .min()
    }

    /// Whether this side's request of `token` registered an observation that holds: its
    /// later responses are notifications.
    pub fn is_observing(&self, token: Token) -> bool {
        self.outstanding.get(&token).is_some_and(|o| o.observing)
    }

    /// Ends this side's observation of `token` (RFC 7641 §3.6, the only way over a
    /// stream, RFC 8323 §7.4: there is no Reset): sends `request`, the registration's,
    /// with Observe 1 under the same token, and forgets the token, so the answer to
    /// that and any notification still on its way are ignored. Nothing is sent for a
    /// token that is not observing.
    pub fn cancel_observation(&mut self, token: Token, request: &Request) {
        if self.outstanding.get(&token).is_none_or(|o| !o.observing) {
            return;
        }
        self.outstanding.remove(&token);
        if self.closed {
            return;
        }
        let mut options = request.options.clone();
        options.set_uint(OptionNumber::OBSERVE, 1);
        let frame = Frame {
            code: request.method,
            token,
            options,
            payload: request.payload.clone(),
        };
        if self.framing.size(&frame) <= self.peer_limit() {
            self.emit(&frame);
        }
    }

    /// Fails every request and Ping whose deadline has passed with
    /// [`RequestError::Timeout`]. Calling it early does nothing.
    pub fn handle_timeout(&mut self, now: Instant) {
        let mut late: Vec<Token> = self
            .outstanding
            .iter()
            .filter(|(_, o)| !o.observing && o.deadline <= now)
            .map(|(token, _)| *token)
            .collect();
        late.sort_by_key(token_order);
        for token in late {
            self.outstanding.remove(&token);
            let failed = ConnectionEvent::Failed(token, RequestError::Timeout);
            self.events.push_back(failed);
        }
        let outstanding = &self.outstanding;
        self.waiting.retain(|f| outstanding.contains_key(&f.token));
    }

    /// The stream ended (the peer closed it, or reading or writing failed) without a
    /// Release or an Abort: closes, failing every request still waiting.
    pub fn handle_end(&mut self) {
        if !self.closed {
            self.close(Closed::Ended);
        }
    }

    /// Answers the request of `token`, or sends a notification of the observation of
    /// `token`: as given, Observe option included (whoever keeps the observations
    /// removes it from an answer to a registration it did not keep, RFC 7641 §4.1). An
    /// answer larger than the peer's Max-Message-Size is replaced by a 5.00 that says so.
    pub fn respond(&mut self, token: Token, response: &Response) {
        if !self.closed {
            self.send(token, response);
        }
    }

    fn send(&mut self, token: Token, response: &Response) {
        let options = response.options.clone();
        let payload = match &response.source {
            None => Some(response.payload.clone()),
            Some(source) => source.read(0..source.len()),
        };
        let (limit, framing) = (self.peer_limit(), self.framing);
        let failure = |text: String| {
            let frame = Frame {
                code: Code::INTERNAL_SERVER_ERROR,
                token,
                options: Options::new(),
                payload: Bytes::from(text),
            };
            // Without its diagnostic when even that is too large.
            if framing.size(&frame) > limit {
                Frame {
                    payload: Bytes::new(),
                    ..frame
                }
            } else {
                frame
            }
        };
        let frame = match payload {
            None => failure("the body can no longer be read".to_owned()),
            Some(payload) => Frame {
                code: response.code,
                token,
                options,
                payload,
            },
        };
        let size = framing.size(&frame);
        let frame = if size > limit {
            failure(format!(
                "the answer takes {size} bytes, over the {limit} of Max-Message-Size"
            ))
        } else {
            frame
        };
        self.emit(&frame);
    }

    /// The next event.
    pub fn poll_event(&mut self) -> Option<ConnectionEvent> {
        self.events.pop_front()
    }

    /// What to send, if anything: over TCP the bytes to write to the stream, all at
    /// once; over WebSockets the next message (call again for the one after).
    pub fn poll_transmit(&mut self) -> Option<Vec<u8>> {
        match self.framing {
            Framing::Stream => {
                (!self.outbound.is_empty()).then(|| std::mem::take(&mut self.outbound))
            }
            Framing::WebSocket => self.messages.pop_front(),
        }
    }
}

/// The order in which tokens of [`Connection::fresh_token`] were given out: shorter
/// first, then by their bytes.
fn token_order(token: &Token) -> (usize, [u8; 8]) {
    let mut bytes = [0; 8];
    bytes[..token.len()].copy_from_slice(token.as_bytes());
    (token.len(), bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn csm_then(bytes: &[u8]) -> Vec<u8> {
        let mut all = vec![0x00, 0xe1];
        all.extend_from_slice(bytes);
        all
    }

    fn request(c: &mut Connection) -> StreamRequest {
        match c.poll_event() {
            Some(ConnectionEvent::Request(r)) => *r,
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn rfc8323_5_3_the_server_sends_its_csm_first() {
        let mut c = Connection::new(1152);
        // Max-Message-Size (2) 1152, two bytes: Len 3.
        assert_eq!(c.poll_transmit(), Some(vec![0x30, 0xe1, 0x22, 0x04, 0x80]));
        assert_eq!(c.poll_transmit(), None);
    }

    #[test]
    fn a_get_split_across_reads_becomes_one_request_and_its_answer_a_frame() {
        let mut c = Connection::new(1152);
        let _csm = c.poll_transmit();
        // GET, token 0x05, Uri-Path "cams".
        let bytes = csm_then(&[0x51, 0x01, 0x05, 0xb4, b'c', b'a', b'm', b's']);
        c.handle(&bytes[..4]);
        assert_eq!(c.poll_event(), None);
        c.handle(&bytes[4..]);
        let r = request(&mut c);
        assert_eq!(
            (r.method, r.options.path_string()),
            (Code::GET, "/cams".into())
        );
        let token = r.token;
        let mut answer = Response::new(Code::CONTENT).with_payload(&b"hi"[..]);
        answer.options.set_uint(OptionNumber::OBSERVE, 3);
        c.respond(token, &answer);
        // 2.05, Observe (6) 3, the marker and "hi": Len 5.
        assert_eq!(
            c.poll_transmit(),
            Some(vec![0x51, 0x45, 0x05, 0x61, 0x03, 0xff, b'h', b'i'])
        );
    }

    #[test]
    fn rfc8323_5_4_a_ping_is_answered_with_a_pong() {
        let mut c = Connection::new(1152);
        let _csm = c.poll_transmit();
        c.handle(&csm_then(&[0x11, 0xe2, 0x42, 0x20]));
        assert_eq!(c.poll_transmit(), Some(vec![0x01, 0xe3, 0x42]));
        assert!(!c.is_closed());
    }

    #[test]
    fn rfc8323_5_3_a_first_message_other_than_a_csm_aborts() {
        let mut c = Connection::new(1152);
        let _csm = c.poll_transmit();
        c.handle(&[0x01, 0x01, 0x05]);
        let out = c.poll_transmit().unwrap();
        // An Abort (7.05) without options, with a diagnostic.
        assert_eq!(&out[..1], &[0xd0]);
        assert_eq!(out[2], 0xe5);
        assert!(matches!(
            c.poll_event(),
            Some(ConnectionEvent::Closed(Closed::Aborted(_)))
        ));
        assert!(c.is_closed());
        c.handle(&[0x00, 0xe1]);
        assert_eq!(c.poll_transmit(), None);
    }

    #[test]
    fn rfc8323_5_3_an_unknown_critical_csm_option_aborts_naming_it() {
        let mut c = Connection::new(1152);
        let _csm = c.poll_transmit();
        // A CSM with option 3, critical and unknown.
        c.handle(&[0x10, 0xe1, 0x30]);
        let out = c.poll_transmit().unwrap();
        let Ok(Decoded::Frame { frame, .. }) = stream::decode(&out, 1 << 16) else {
            panic!("an Abort");
        };
        assert_eq!(
            Signal::decode(&frame),
            Ok(Signal::Abort(Abort {
                bad_csm_option: Some(OptionNumber(3))
            }))
        );
    }

    #[test]
    fn an_oversize_frame_aborts_and_an_oversize_answer_is_a_5_00() {
        let mut c = Connection::new(64);
        let _csm = c.poll_transmit();
        // The peer allows 16 bytes; a CONTENT of 20 bytes does not fit.
        c.handle(&[0x20, 0xe1, 0x21, 16, 0x01, 0x01, 7]);
        let r = request(&mut c);
        c.respond(
            r.token,
            &Response::new(Code::CONTENT).with_payload(vec![1; 20]),
        );
        let out = c.poll_transmit().unwrap();
        assert_eq!(out[1], Code::INTERNAL_SERVER_ERROR.0);
        assert_eq!(
            c.peer_csm().map(|p| p.max_message_size_or_default()),
            Some(16)
        );
        // A header announcing 100 bytes, over this side's 64.
        c.handle(&[0xd0, 100 - 13, 0x02]);
        assert!(c.poll_transmit().is_some_and(|o| o.contains(&0xe5)));
        assert!(c.is_closed());
    }

    #[test]
    fn rfc8323_5_5_a_release_closes() {
        let mut c = Connection::new(1152);
        c.handle(&csm_then(&[0x00, 0xe4]));
        assert_eq!(
            c.poll_event(),
            Some(ConnectionEvent::Closed(Closed::Released))
        );
    }

    #[test]
    fn rfc8323_5_5_a_release_of_this_side_follows_the_csm_and_closes() {
        let mut c = Connection::new(1152);
        c.release("idle", Some(10));
        let out = c.poll_transmit().unwrap_or_default();
        // The CSM (5 bytes), then 7.04 with Hold-Off (4) 10 and "idle": Len 7.
        assert_eq!(
            &out[5..],
            &[0x70, 0xe4, 0x41, 10, 0xff, b'i', b'd', b'l', b'e']
        );
        assert_eq!(
            c.poll_event(),
            Some(ConnectionEvent::Closed(Closed::ReleasedHere("idle".into())))
        );
        assert!(c.is_closed());
        c.release("again", None);
        assert_eq!((c.poll_transmit(), c.poll_event()), (None, None));
    }

    #[test]
    fn rfc8323_4_over_websockets_a_message_is_a_frame_without_its_length() {
        let mut c = Connection::websocket(1152);
        // The CSM: Len 0, then Max-Message-Size (2) 1152 in two bytes.
        assert_eq!(c.poll_transmit(), Some(vec![0x00, 0xe1, 0x22, 0x04, 0x80]));
        // The peer's empty CSM and a GET /cams (token 0x05), one message each; and a
        // Ping (token 0x42) whose Pong is a message of its own after the answer.
        c.handle(&[0x00, 0xe1]);
        c.handle(&[0x01, 0x01, 0x05, 0xb4, b'c', b'a', b'm', b's']);
        c.handle(&[0x01, 0xe2, 0x42]);
        let r = request(&mut c);
        assert_eq!(r.options.path_string(), "/cams");
        c.respond(
            r.token,
            &Response::new(Code::CONTENT).with_payload(&b"hi"[..]),
        );
        assert_eq!(c.poll_transmit(), Some(vec![0x01, 0xe3, 0x42]));
        assert_eq!(
            c.poll_transmit(),
            Some(vec![0x01, 0x45, 0x05, 0xff, b'h', b'i'])
        );
        assert_eq!(c.poll_transmit(), None);
        // A message with a length in its first byte is a TCP frame, not ours: Abort.
        c.handle(&[0x31, 0x01, 0x05, 0xff, 1, 2]);
        let abort = c.poll_transmit().unwrap_or_default();
        assert_eq!(abort.get(1), Some(&Code::ABORT.0));
        assert!(c.is_closed());
    }

    // ------------------------------------------------------------ the client side

    /// The bytes of a server's CSM announcing `max` as its Max-Message-Size (4 bytes).
    fn server_csm(max: u32) -> Vec<u8> {
        let csm = Signal::Csm(Csm {
            max_message_size: Some(max),
            block_wise_transfer: false,
        });
        csm.to_frame(Token::EMPTY, Bytes::new()).encode()
    }

    /// A response frame of `code` with `token` and `payload`.
    fn answer(code: Code, token: &[u8], payload: &[u8]) -> Vec<u8> {
        Frame {
            code,
            token: Token::new(token).unwrap_or_default(),
            options: Options::new(),
            payload: Bytes::copy_from_slice(payload),
        }
        .encode()
    }

    fn get(path: &str) -> Request {
        Request::new(Code::GET, path)
    }

    /// A client connection whose CSM is taken and which has the server's.
    fn client(max: u32) -> Connection {
        let mut c = Connection::new(1 << 24);
        let _csm = c.poll_transmit();
        c.handle(&server_csm(max));
        c
    }

    #[test]
    fn rfc8323_5_3_requests_wait_for_the_peers_csm_then_go_with_fresh_tokens() {
        let now = crate::test_epoch();
        let mut c = Connection::new(1 << 24);
        let _csm = c.poll_transmit();
        let first = c.send_request(now, &get("/hello"));
        let second = c.send_request(now, &get("/hello"));
        assert_eq!((first.as_bytes(), second.as_bytes()), (&[1][..], &[2][..]));
        assert_eq!(c.poll_transmit(), None);
        c.handle(&server_csm(1152));
        // GET, Uri-Path (11) "hello": Len 6, TKL 1; both, in order.
        let get = |t| [&[0x61, 0x01, t, 0xb5][..], b"hello"].concat();
        assert_eq!(c.poll_transmit(), Some([get(1), get(2)].concat()));
        assert_eq!(c.poll_event(), None);
    }

    #[test]
    fn responses_are_matched_by_token_and_an_unknown_token_is_ignored() {
        let now = crate::test_epoch();
        let mut c = client(1152);
        let first = c.send_request(now, &get("/a"));
        let second = c.send_request(now, &get("/b"));
        let _requests = c.poll_transmit();
        c.handle(&answer(Code::CONTENT, &[9], b"stray"));
        c.handle(&answer(Code::NOT_FOUND, second.as_bytes(), b""));
        c.handle(&answer(Code::CONTENT, first.as_bytes(), b"a"));
        // The first answer again: its request is done, so it is unknown now.
        c.handle(&answer(Code::CONTENT, first.as_bytes(), b"a"));
        let mut events = Vec::new();
        while let Some(e) = c.poll_event() {
            events.push(e);
        }
        let expected = vec![
            ConnectionEvent::Response(second, Box::new(Response::new(Code::NOT_FOUND))),
            ConnectionEvent::Response(
                first,
                Box::new(Response::new(Code::CONTENT).with_payload(&b"a"[..])),
            ),
        ];
        assert_eq!(events, expected);
        assert_eq!(c.poll_timeout(), None);
        assert!(!c.is_closed());
    }

    #[test]
    fn a_body_over_the_body_limit_fails_too_large_as_over_udp() {
        let now = crate::test_epoch();
        let mut c = client(1152).with_body_limit(4);
        let big = c.send_request(now, &get("/big"));
        let fits = c.send_request(now, &get("/fits"));
        c.handle(&answer(Code::CONTENT, big.as_bytes(), b"12345"));
        c.handle(&answer(Code::CONTENT, fits.as_bytes(), b"1234"));
        assert_eq!(
            c.poll_event(),
            Some(ConnectionEvent::Failed(
                big,
                RequestError::TooLarge { limit: 4 }
            ))
        );
        assert!(matches!(
            c.poll_event(),
            Some(ConnectionEvent::Response(t, r)) if t == fits && r.payload.len() == 4
        ));
    }

    #[test]
    fn rfc8323_5_3_1_a_request_over_the_peers_max_message_size_is_not_sent() {
        let now = crate::test_epoch();
        let mut c = client(16);
        // GET with token 0x01 and 20 bytes of payload: 24 bytes, over 16.
        let too_big = c.send_request(now, &get("/").with_payload(vec![7; 20]));
        // First byte, code, token, marker and 11 bytes: 15 (one more byte of payload
        // takes an extended length byte too: 17).
        let fits = c.send_request(now, &get("/").with_payload(vec![7; 11]));
        assert_eq!(
            c.poll_event(),
            Some(ConnectionEvent::Failed(
                too_big,
                RequestError::RequestTooLarge { limit: 16 }
            ))
        );
        let out = c.poll_transmit().unwrap_or_default();
        assert_eq!((out.len(), out.get(2)), (15, fits.as_bytes().first()));
    }

    #[test]
    fn a_request_fails_at_its_timeout_and_its_late_answer_is_ignored() {
        let now = crate::test_epoch();
        let mut c = client(1152);
        let mut quick = get("/quick");
        quick.timeout = Some(Duration::from_secs(2));
        let quick = c.send_request(now, &quick);
        let _patient = c.send_request(now, &get("/patient"));
        assert_eq!(c.poll_timeout(), Some(now + Duration::from_secs(2)));
        c.handle_timeout(now + Duration::from_millis(1999));
        assert_eq!(c.poll_event(), None);
        c.handle_timeout(now + Duration::from_secs(2));
        assert_eq!(
            c.poll_event(),
            Some(ConnectionEvent::Failed(quick, RequestError::Timeout))
        );
        // The one without a timeout waits DEFAULT_RESPONSE_TIMEOUT.
        assert_eq!(c.poll_timeout(), Some(now + DEFAULT_RESPONSE_TIMEOUT));
        c.handle(&answer(Code::CONTENT, quick.as_bytes(), b"late"));
        assert_eq!(c.poll_event(), None);
    }

    #[test]
    fn a_request_waiting_for_the_csm_times_out_and_is_never_sent() {
        let now = crate::test_epoch();
        let mut c = Connection::new(1 << 24);
        let _csm = c.poll_transmit();
        let mut request = get("/x");
        request.timeout = Some(Duration::from_secs(1));
        let token = c.send_request(now, &request);
        c.handle_timeout(now + Duration::from_secs(1));
        assert_eq!(
            c.poll_event(),
            Some(ConnectionEvent::Failed(token, RequestError::Timeout))
        );
        c.handle(&server_csm(1152));
        assert_eq!(c.poll_transmit(), None);
    }

    #[test]
    fn rfc8323_5_4_a_client_answers_pings_and_gets_pongs_for_its_own() {
        let now = crate::test_epoch();
        let mut c = client(1152);
        c.handle(&[0x01, 0xe2, 0x42]);
        assert_eq!(c.poll_transmit(), Some(vec![0x01, 0xe3, 0x42]));
        let ping = c.ping(now, Duration::from_secs(5));
        assert_eq!(c.poll_transmit(), Some(vec![0x01, 0xe2, 0x01]));
        // A response with the Ping's token is not its answer; a Pong is.
        c.handle(&answer(Code::CONTENT, ping.as_bytes(), b""));
        assert_eq!(c.poll_event(), None);
        c.handle(&[0x01, 0xe3, 0x01]);
        assert_eq!(c.poll_event(), Some(ConnectionEvent::Pong(ping)));
        // A Pong without the token (as libcoap 4.3.5 sends it, with Custody) answers
        // the oldest Ping; with none waiting it is ignored.
        let (older, newer) = (
            c.ping(now, Duration::from_secs(5)),
            c.ping(now, Duration::from_secs(5)),
        );
        let _pings = c.poll_transmit();
        c.handle(&[0x10, 0xe3, 0x20]);
        assert_eq!(c.poll_event(), Some(ConnectionEvent::Pong(older)));
        c.handle(&[0x10, 0xe3, 0x20]);
        assert_eq!(c.poll_event(), Some(ConnectionEvent::Pong(newer)));
        c.handle(&[0x10, 0xe3, 0x20]);
        assert_eq!(c.poll_event(), None);
        // A Ping left unanswered fails at its deadline.
        let unanswered = c.ping(now, Duration::from_secs(5));
        c.handle_timeout(now + Duration::from_secs(5));
        assert_eq!(
            c.poll_event(),
            Some(ConnectionEvent::Failed(unanswered, RequestError::Timeout))
        );
        assert_eq!(c.poll_timeout(), None);
    }

    /// A response frame of `code` with `token`, Observe `seq` and `payload`.
    fn notification(code: Code, token: Token, seq: u32, payload: &[u8]) -> Vec<u8> {
        let mut options = Options::new();
        options.set_uint(OptionNumber::OBSERVE, seq);
        Frame {
            code,
            token,
            options,
            payload: Bytes::copy_from_slice(payload),
        }
        .encode()
    }

    fn observe(path: &str) -> Request {
        let mut r = get(path);
        r.options.set_uint(OptionNumber::OBSERVE, 0);
        r
    }

    fn payloads(c: &mut Connection, token: Token) -> Vec<Vec<u8>> {
        let mut got = Vec::new();
        while let Some(e) = c.poll_event() {
            match e {
                ConnectionEvent::Response(t, r) if t == token => got.push(r.payload.to_vec()),
                other => panic!("{other:?}"),
            }
        }
        got
    }

    #[test]
    fn rfc7641_an_accepted_registration_reports_notifications_without_a_timeout() {
        let now = crate::test_epoch();
        let mut c = client(1152);
        let token = c.send_request(now, &observe("/n"));
        let _request = c.poll_transmit();
        c.handle(&notification(Code::CONTENT, token, 0, b"0"));
        // RFC 8323 §7.1: the Observe value is not an order; a smaller one still counts.
        c.handle(&notification(Code::CONTENT, token, 5, b"1"));
        c.handle(&notification(Code::CONTENT, token, 2, b"2"));
        assert_eq!(payloads(&mut c, token), [b"0", b"1", b"2"]);
        assert_eq!(c.poll_timeout(), None);
        c.handle_timeout(now + Duration::from_secs(3600));
        assert_eq!(c.poll_event(), None);

        // Cancelled: a GET with Observe 1 under the same token; what follows is ignored.
        c.cancel_observation(token, &observe("/n"));
        let mut options = Options::new();
        options.set_uint(OptionNumber::OBSERVE, 1);
        options.set_path("/n");
        let deregister = Frame {
            code: Code::GET,
            token,
            options,
            payload: Bytes::new(),
        };
        assert_eq!(c.poll_transmit(), Some(deregister.encode()));
        c.handle(&notification(Code::CONTENT, token, 3, b"3"));
        c.handle(&answer(Code::CONTENT, token.as_bytes(), b"plain"));
        assert_eq!(c.poll_event(), None);
    }

    #[test]
    fn rfc7641_3_2_an_answer_without_observe_or_an_error_ends_the_observation() {
        let now = crate::test_epoch();
        let mut c = client(1152);
        // Not registered: the plain answer is the only one.
        let plain = c.send_request(now, &observe("/p"));
        c.handle(&answer(Code::CONTENT, plain.as_bytes(), b"once"));
        c.handle(&notification(Code::CONTENT, plain, 1, b"late"));
        assert_eq!(payloads(&mut c, plain), [b"once"]);
        // Registered, then a 4.04 notification: the last.
        let gone = c.send_request(now, &observe("/g"));
        c.handle(&notification(Code::CONTENT, gone, 0, b"here"));
        c.handle(&answer(Code::NOT_FOUND, gone.as_bytes(), b"gone"));
        c.handle(&notification(Code::CONTENT, gone, 2, b"late"));
        assert_eq!(payloads(&mut c, gone), [&b"here"[..], b"gone"]);
        // A GET without Observe is matched once, even if the answer carries Observe.
        let once = c.send_request(now, &get("/o"));
        c.handle(&notification(Code::CONTENT, once, 0, b"a"));
        c.handle(&notification(Code::CONTENT, once, 1, b"b"));
        assert_eq!(payloads(&mut c, once), [b"a"]);
        assert_eq!(c.poll_timeout(), None);
    }

    #[test]
    fn rfc8323_5_5_a_release_fails_the_requests_still_waiting() {
        let now = crate::test_epoch();
        let mut c = client(1152);
        let a = c.send_request(now, &get("/a"));
        let b = c.send_request(now, &get("/b"));
        let _requests = c.poll_transmit();
        c.handle(&[0x00, 0xe4]);
        let closed = |t| ConnectionEvent::Failed(t, RequestError::ConnectionClosed);
        assert_eq!(c.poll_event(), Some(closed(a)));
        assert_eq!(c.poll_event(), Some(closed(b)));
        assert_eq!(
            c.poll_event(),
            Some(ConnectionEvent::Closed(Closed::Released))
        );
        // A request on a closed connection fails at once.
        let late = c.send_request(now, &get("/c"));
        assert_eq!(c.poll_event(), Some(closed(late)));
        assert_eq!((c.poll_transmit(), c.poll_timeout()), (None, None));
    }

    #[test]
    fn the_end_of_the_stream_fails_the_requests_still_waiting() {
        let now = crate::test_epoch();
        let mut c = client(1152);
        let a = c.send_request(now, &get("/a"));
        c.handle_end();
        assert_eq!(
            c.poll_event(),
            Some(ConnectionEvent::Failed(a, RequestError::ConnectionClosed))
        );
        assert_eq!(c.poll_event(), Some(ConnectionEvent::Closed(Closed::Ended)));
        c.handle_end();
        assert_eq!(c.poll_event(), None);
    }

    #[test]
    fn tokens_are_the_shortest_bytes_of_a_counter() {
        let now = crate::test_epoch();
        let mut c = client(1152);
        let tokens: Vec<Token> = (0..300).map(|_| c.send_request(now, &get("/"))).collect();
        assert_eq!(tokens[254].as_bytes(), [0xff]);
        assert_eq!(tokens[255].as_bytes(), [0x01, 0x00]);
        let distinct: std::collections::HashSet<Token> = tokens.iter().copied().collect();
        assert_eq!(distinct.len(), 300);
    }
}
