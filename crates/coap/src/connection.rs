//! The server side of one CoAP connection over a reliable byte stream (RFC 8323, TCP),
//! sans-IO: bytes in with [`Connection::handle`], requests out with
//! [`Connection::poll_event`], answers in with [`Connection::respond`], bytes out with
//! [`Connection::poll_transmit`].
//!
//! What it does of the signalling (§5): it sends its CSM first, with its
//! Max-Message-Size; it takes the peer's first message to be a CSM and aborts otherwise;
//! it answers a Ping with a Pong carrying the Ping's token and no Custody (it does not
//! wait for the answers to earlier requests); a Release or an Abort from the peer closes
//! it. A frame it cannot read, one over its Max-Message-Size, or a signalling message with
//! an unknown critical option makes it send an Abort and close.
//!
//! What it does not do yet: send requests (a response from the peer is ignored), send
//! Pings or keep any timer, Observe (a registration is served as a plain GET and the
//! answer's Observe option removed, so the client knows it is not registered, RFC 7641
//! §4.1), block-wise transfer and BERT (it announces no Block-Wise-Transfer; an answer
//! over the peer's Max-Message-Size becomes a 5.00 with a diagnostic).

use std::collections::VecDeque;

use bytes::Bytes;

use crate::endpoint::Response;
use crate::msg::signal::{Abort, Csm, Signal};
use crate::msg::stream::{self, Decoded, Frame};
use crate::msg::{Code, OptionNumber, Options, Token};

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
}

/// What the connection tells its owner.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ConnectionEvent {
    /// A request to answer with [`Connection::respond`] (boxed: the other event is
    /// small).
    Request(Box<StreamRequest>),
    /// The connection is over: send what [`Connection::poll_transmit`] still has, then
    /// close the stream.
    Closed(Closed),
}

/// One connection's state.
#[derive(Debug)]
pub struct Connection {
    /// The largest frame this side accepts, announced in its CSM.
    max_message_size: u32,
    /// Bytes received and not yet a whole frame.
    inbound: Vec<u8>,
    /// Frames to send, encoded.
    outbound: Vec<u8>,
    events: VecDeque<ConnectionEvent>,
    /// The peer's settings, once its CSM came.
    peer: Option<Csm>,
    closed: bool,
}

impl Connection {
    /// A connection that accepts frames of up to `max_message_size` bytes; its CSM is the
    /// first thing to send.
    pub fn new(max_message_size: u32) -> Self {
        let csm = Signal::Csm(Csm {
            max_message_size: Some(max_message_size),
            block_wise_transfer: false,
        });
        Self {
            max_message_size,
            inbound: Vec::new(),
            outbound: csm.to_frame(Token::EMPTY, Bytes::new()).encode(),
            events: VecDeque::new(),
            peer: None,
            closed: false,
        }
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

    /// Takes bytes received from the stream: every whole frame among them is handled.
    pub fn handle(&mut self, bytes: &[u8]) {
        if self.closed {
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
        if !frame.code.is_request() {
            // 0.00 is ignored (§3.4); responses answer nothing this side sent.
            return;
        }
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
            }
            Signal::Ping { .. } => {
                let pong = Signal::Pong { custody: false };
                pong.to_frame(frame.token, Bytes::new())
                    .encode_into(&mut self.outbound);
            }
            Signal::Pong { .. } => {}
            Signal::Release(_) => self.close(Closed::Released),
            Signal::Abort(_) => {
                let text = String::from_utf8_lossy(&frame.payload).into_owned();
                self.close(Closed::AbortedByPeer(text));
            }
        }
    }

    /// Sends an Abort with `reason` as its diagnostic, and closes.
    fn abort(&mut self, reason: String, bad_csm_option: Option<OptionNumber>) {
        let abort = Signal::Abort(Abort { bad_csm_option });
        abort
            .to_frame(Token::EMPTY, Bytes::copy_from_slice(reason.as_bytes()))
            .encode_into(&mut self.outbound);
        self.close(Closed::Aborted(reason));
    }

    fn close(&mut self, why: Closed) {
        self.closed = true;
        self.events.push_back(ConnectionEvent::Closed(why));
    }

    /// Answers the request of `token`. Its Observe option is removed (no Observe over
    /// streams yet); an answer larger than the peer's Max-Message-Size is replaced by a
    /// 5.00 that says so.
    pub fn respond(&mut self, token: Token, response: &Response) {
        if !self.closed {
            self.send(token, response);
        }
    }

    fn send(&mut self, token: Token, response: &Response) {
        let mut options = response.options.clone();
        options.remove(OptionNumber::OBSERVE);
        let payload = match &response.source {
            None => Some(response.payload.clone()),
            Some(source) => source.read(0..source.len()),
        };
        let limit = self.peer.map_or(Csm::DEFAULT_MAX_MESSAGE_SIZE, |p| {
            p.max_message_size_or_default()
        }) as usize;
        let failure = |text: String| {
            let frame = Frame {
                code: Code::INTERNAL_SERVER_ERROR,
                token,
                options: Options::new(),
                payload: Bytes::from(text),
            };
            // Without its diagnostic when even that is too large.
            if frame.encoded_len() > limit {
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
        let frame = if frame.encoded_len() > limit {
            let size = frame.encoded_len();
            failure(format!(
                "the answer takes {size} bytes, over the {limit} of Max-Message-Size"
            ))
        } else {
            frame
        };
        frame.encode_into(&mut self.outbound);
    }

    /// The next event.
    pub fn poll_event(&mut self) -> Option<ConnectionEvent> {
        self.events.pop_front()
    }

    /// The bytes to write to the stream, if any.
    pub fn poll_transmit(&mut self) -> Option<Vec<u8>> {
        (!self.outbound.is_empty()).then(|| std::mem::take(&mut self.outbound))
    }
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
        // No Observe over streams yet: 2.05 with the marker and "hi", Len 3.
        assert_eq!(
            c.poll_transmit(),
            Some(vec![0x31, 0x45, 0x05, 0xff, b'h', b'i'])
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
}
