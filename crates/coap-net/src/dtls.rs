//! DTLS 1.2 with pre-shared keys (RFC 7252 §9.1, `coaps://`), through OpenSSL. This
//! module never implements DTLS itself: per peer it keeps one OpenSSL session whose
//! "socket" is a pair of datagram queues, feeds it the datagrams that arrive, and sends
//! what it writes. The endpoint above sees only the plaintext CoAP messages.
//!
//! OpenSSL keeps the handshake's retransmission timer itself and acts on it when the
//! handshake is driven, so while any handshake is under way the driver ticks every
//! [`HANDSHAKE_TICK`]. A server keeps at most [`MAX_SESSIONS`] sessions, and drops one
//! idle for [`IDLE`] to make room; a handshake that has not finished in [`HANDSHAKE_LIMIT`]
//! is dropped.

use std::collections::{HashMap, VecDeque};
use std::io::{self, Read, Write};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use openssl::ssl::{
    ErrorCode, HandshakeError, MidHandshakeSslStream, Ssl, SslContext, SslContextBuilder,
    SslMethod, SslOptions, SslStream,
};

/// How often handshakes in progress are driven (OpenSSL's own timer starts at 1 s).
const HANDSHAKE_TICK: Duration = Duration::from_millis(250);
/// A handshake not finished by then is dropped (OpenSSL has sent its flight four times by
/// then: after 0, 1, 3 and 7 s).
const HANDSHAKE_LIMIT: Duration = Duration::from_secs(15);
/// Sessions a server keeps at once.
const MAX_SESSIONS: usize = 4096;
/// A session unused this long may be dropped to make room for a new one.
const IDLE: Duration = Duration::from_secs(600);
/// The largest DTLS record, so that a record and its UDP/IP headers fit a 1280-byte
/// IPv6 path (RFC 7252 §4.6).
const MTU: u32 = 1152;
/// Messages a session keeps for its peer until the handshake is done.
const WAITING_MAX: usize = 64;
/// RFC 7252 §9.1.3.1's mandatory suite first, then the GCM and CBC ones libcoap offers.
const CIPHERS: &str = "PSK-AES128-CCM8:PSK-AES128-GCM-SHA256:PSK-AES128-CBC-SHA256";

/// The keys of a DTLS server: the key of each PSK identity it accepts.
pub type KeyStore = Arc<dyn Fn(&[u8]) -> Option<Vec<u8>> + Send + Sync>;

/// A DTLS role with its keys.
#[derive(Clone)]
pub enum Psk {
    /// A server accepting the identities `keys` knows.
    Server(KeyStore),
    /// A client presenting an identity and its key.
    Client {
        /// The PSK identity.
        identity: Vec<u8>,
        /// The key.
        key: Vec<u8>,
    },
}

impl std::fmt::Debug for Psk {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Server(_) => f.write_str("Psk::Server"),
            Self::Client { identity, .. } => f
                .debug_struct("Psk::Client")
                .field("identity", &String::from_utf8_lossy(identity))
                .finish_non_exhaustive(),
        }
    }
}

/// The datagrams a session reads and writes.
#[derive(Debug, Default)]
struct Queues {
    incoming: VecDeque<Vec<u8>>,
    outgoing: Vec<Vec<u8>>,
}

impl Read for Queues {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let Some(d) = self.incoming.pop_front() else {
            return Err(io::ErrorKind::WouldBlock.into());
        };
        let n = d.len().min(buf.len());
        buf[..n].copy_from_slice(&d[..n]);
        Ok(n)
    }
}

impl Write for Queues {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.outgoing.push(buf.to_vec());
        Ok(buf.len())
    }

    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

enum State {
    Handshaking(MidHandshakeSslStream<Queues>),
    Open(SslStream<Queues>),
    /// Between the two, while the handshake is driven.
    Gone,
}

struct Session {
    state: State,
    started: Instant,
    last_used: Instant,
    /// Plaintext to send once the handshake is done.
    waiting: Vec<Vec<u8>>,
    /// The peer's PSK identity (on a server, once the handshake chose it).
    identity: Option<Arc<str>>,
}

/// What one call produced: plaintext messages received, datagrams to send.
#[derive(Debug, Default)]
pub(crate) struct Output {
    pub(crate) received: Vec<Vec<u8>>,
    pub(crate) send: Vec<Vec<u8>>,
    /// The handshake failed (a wrong key or an unknown identity): the session is gone.
    pub(crate) failed: bool,
}

/// The DTLS layer of one socket.
pub(crate) struct Dtls {
    ctx: SslContext,
    server: bool,
    sessions: HashMap<SocketAddr, Session>,
}

impl std::fmt::Debug for Dtls {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Dtls")
            .field("server", &self.server)
            .field("sessions", &self.sessions.len())
            .finish()
    }
}

/// The identity OpenSSL's server callback saw, kept in the session's extra data.
fn identity_index() -> Result<openssl::ex_data::Index<Ssl, Arc<str>>, openssl::error::ErrorStack> {
    static INDEX: std::sync::OnceLock<openssl::ex_data::Index<Ssl, Arc<str>>> =
        std::sync::OnceLock::new();
    if let Some(i) = INDEX.get() {
        return Ok(*i);
    }
    let i = Ssl::new_ex_index()?;
    Ok(*INDEX.get_or_init(|| i))
}

impl Dtls {
    pub(crate) fn new(psk: &Psk) -> io::Result<Self> {
        let err = |e: openssl::error::ErrorStack| io::Error::other(format!("DTLS setup: {e}"));
        let mut b = SslContextBuilder::new(SslMethod::dtls()).map_err(err)?;
        b.set_cipher_list(CIPHERS).map_err(err)?;
        b.set_options(SslOptions::NO_QUERY_MTU | SslOptions::NO_TICKET);
        let index = identity_index().map_err(err)?;
        let server = match psk {
            Psk::Server(keys) => {
                let keys = keys.clone();
                b.set_psk_server_callback(move |ssl, identity, out| {
                    let identity = identity.unwrap_or_default();
                    let Some(key) = keys(identity).filter(|k| k.len() <= out.len()) else {
                        // Unknown identity: the handshake fails.
                        return Ok(0);
                    };
                    out[..key.len()].copy_from_slice(&key);
                    let name: Arc<str> = String::from_utf8_lossy(identity).into();
                    ssl.set_ex_data(index, name);
                    Ok(key.len())
                });
                true
            }
            Psk::Client { identity, key } => {
                let (identity, key) = (identity.clone(), key.clone());
                b.set_psk_client_callback(move |_ssl, _hint, id_out, key_out| {
                    // The identity goes out NUL-terminated.
                    if identity.len() >= id_out.len() || key.len() > key_out.len() {
                        return Ok(0);
                    }
                    id_out[..identity.len()].copy_from_slice(&identity);
                    id_out[identity.len()] = 0;
                    key_out[..key.len()].copy_from_slice(&key);
                    Ok(key.len())
                });
                false
            }
        };
        Ok(Self {
            ctx: b.build(),
            server,
            sessions: HashMap::new(),
        })
    }

    /// The PSK identity of `peer`'s session, once it is open.
    pub(crate) fn identity(&self, peer: SocketAddr) -> Option<Arc<str>> {
        self.sessions
            .get(&peer)
            .filter(|s| matches!(s.state, State::Open(_)))
            .and_then(|s| s.identity.clone())
    }

    /// When the handshakes in progress must be driven next.
    pub(crate) fn poll_timeout(&self, now: Instant) -> Option<Instant> {
        self.sessions
            .values()
            .any(|s| matches!(s.state, State::Handshaking(_)))
            .then(|| now + HANDSHAKE_TICK)
    }

    /// Drives the handshakes in progress (OpenSSL retransmits when its timer is due) and
    /// drops those that took too long: the datagrams to send, and the peers whose
    /// handshake was given up.
    pub(crate) fn handle_timeout(
        &mut self,
        now: Instant,
    ) -> (Vec<(SocketAddr, Vec<u8>)>, Vec<SocketAddr>) {
        let mut out = Vec::new();
        let mut gave_up = Vec::new();
        let peers: Vec<SocketAddr> = self
            .sessions
            .iter()
            .filter(|(_, s)| matches!(s.state, State::Handshaking(_)))
            .map(|(p, _)| *p)
            .collect();
        for peer in peers {
            let timed_out = self
                .sessions
                .get(&peer)
                .is_some_and(|s| now.saturating_duration_since(s.started) > HANDSHAKE_LIMIT);
            if timed_out {
                tracing::debug!(%peer, "DTLS handshake timed out");
                self.sessions.remove(&peer);
                gave_up.push(peer);
                continue;
            }
            let o = self.drive(peer, None);
            out.extend(o.send.into_iter().map(|d| (peer, d)));
        }
        (out, gave_up)
    }

    /// A datagram from `peer`: the plaintext messages it carried and what to send back.
    pub(crate) fn receive(&mut self, now: Instant, peer: SocketAddr, datagram: &[u8]) -> Output {
        if !self.sessions.contains_key(&peer) {
            if !self.server || !self.make_room(now) {
                return Output::default();
            }
            let Some(session) = self.session(now, true) else {
                return Output::default();
            };
            self.sessions.insert(peer, session);
        }
        if let Some(s) = self.sessions.get_mut(&peer) {
            s.last_used = now;
        }
        self.drive(peer, Some(datagram))
    }

    /// Plaintext to `peer`: the datagrams to send (none yet while a handshake runs; a
    /// client starts one).
    pub(crate) fn send(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        plaintext: &[u8],
    ) -> Vec<Vec<u8>> {
        if !self.sessions.contains_key(&peer) {
            if self.server {
                // A server answers only peers that opened a session.
                return Vec::new();
            }
            let Some(session) = self.session(now, false) else {
                return Vec::new();
            };
            self.sessions.insert(peer, session);
        }
        let Some(s) = self.sessions.get_mut(&peer) else {
            return Vec::new();
        };
        s.last_used = now;
        match &mut s.state {
            State::Open(stream) => {
                if let Err(e) = stream.ssl_write(plaintext) {
                    tracing::debug!(%peer, error = %e, "DTLS write failed");
                }
                std::mem::take(&mut stream.get_mut().outgoing)
            }
            _ => {
                // Retransmissions of a CON pile up while the handshake runs; the newest
                // WAITING_MAX are kept (the rest would be answered as duplicates anyway).
                if s.waiting.len() >= WAITING_MAX {
                    s.waiting.remove(0);
                }
                s.waiting.push(plaintext.to_vec());
                self.drive(peer, None).send
            }
        }
    }

    fn make_room(&mut self, now: Instant) -> bool {
        if self.sessions.len() < MAX_SESSIONS {
            return true;
        }
        let idle = self
            .sessions
            .iter()
            .filter(|(_, s)| now.saturating_duration_since(s.last_used) > IDLE)
            .min_by_key(|(_, s)| s.last_used)
            .map(|(p, _)| *p);
        idle.is_some_and(|p| self.sessions.remove(&p).is_some())
    }

    /// A new session, its handshake started (a client's first flight is in its queue).
    fn session(&self, now: Instant, accept: bool) -> Option<Session> {
        let mut ssl = Ssl::new(&self.ctx).ok()?;
        ssl.set_mtu(MTU).ok()?;
        let queues = Queues::default();
        let started = if accept {
            ssl.accept(queues)
        } else {
            ssl.connect(queues)
        };
        let state = match started {
            Ok(stream) => State::Open(stream),
            Err(HandshakeError::WouldBlock(mid)) => State::Handshaking(mid),
            Err(e) => {
                tracing::debug!(error = %e, "DTLS handshake could not start");
                return None;
            }
        };
        Some(Session {
            state,
            started: now,
            last_used: now,
            waiting: Vec::new(),
            identity: None,
        })
    }

    /// Feeds `datagram` (if any) to `peer`'s session and runs it as far as it goes.
    fn drive(&mut self, peer: SocketAddr, datagram: Option<&[u8]>) -> Output {
        let mut out = Output::default();
        let Some(s) = self.sessions.get_mut(&peer) else {
            return out;
        };
        let mut failed = false;
        s.state = match std::mem::replace(&mut s.state, State::Gone) {
            State::Handshaking(mut mid) => {
                if let Some(d) = datagram {
                    mid.get_mut().incoming.push_back(d.to_vec());
                }
                match mid.handshake() {
                    Ok(mut stream) => {
                        out.send.append(&mut stream.get_mut().outgoing);
                        let index = identity_index().ok();
                        s.identity = index.and_then(|i| stream.ssl().ex_data(i).cloned());
                        for p in std::mem::take(&mut s.waiting) {
                            if stream.ssl_write(&p).is_err() {
                                failed = true;
                            }
                        }
                        out.send.append(&mut stream.get_mut().outgoing);
                        State::Open(stream)
                    }
                    Err(HandshakeError::WouldBlock(mut mid)) => {
                        out.send.append(&mut mid.get_mut().outgoing);
                        State::Handshaking(mid)
                    }
                    Err(e) => {
                        tracing::debug!(%peer, error = %e, "DTLS handshake failed");
                        if let HandshakeError::Failure(mut mid) = e {
                            // The alert that tells the peer.
                            out.send.append(&mut mid.get_mut().outgoing);
                        }
                        out.failed = true;
                        failed = true;
                        State::Gone
                    }
                }
            }
            State::Open(mut stream) => {
                if let Some(d) = datagram {
                    stream.get_mut().incoming.push_back(d.to_vec());
                }
                // A record's plaintext is at most 2^14 bytes (RFC 6347 §4.1).
                let mut buf = vec![0u8; 1 << 14];
                loop {
                    match stream.ssl_read(&mut buf) {
                        Ok(n) => out.received.push(buf[..n].to_vec()),
                        Err(e) if e.code() == ErrorCode::WANT_READ => break,
                        Err(e) if e.code() == ErrorCode::ZERO_RETURN => {
                            failed = true;
                            break;
                        }
                        Err(e) => {
                            tracing::debug!(%peer, error = %e, "DTLS record dropped");
                            break;
                        }
                    }
                }
                out.send.append(&mut stream.get_mut().outgoing);
                State::Open(stream)
            }
            State::Gone => State::Gone,
        };
        if failed || matches!(s.state, State::Gone) {
            self.sessions.remove(&peer);
        }
        out
    }
}
