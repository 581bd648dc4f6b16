//! DTLS 1.2 with pre-shared keys (RFC 7252 §9.1, `coaps://`), through OpenSSL. This
//! module never implements DTLS itself: per peer it keeps one OpenSSL session whose
//! "socket" is a pair of datagram queues, feeds it the datagrams that arrive, and sends
//! what it writes. The endpoint above sees only the plaintext CoAP messages.
//!
//! OpenSSL keeps the handshake's retransmission timer itself and acts on it when the
//! handshake is driven, so while any handshake is under way the driver ticks every
//! `HANDSHAKE_TICK`. A server keeps at most `MAX_SESSIONS` sessions, and drops one
//! idle for `IDLE` to make room; a handshake that has not finished in `HANDSHAKE_LIMIT`
//! is dropped.
//!
//! A server opens a session only for a peer that proved its address (RFC 6347 §4.2.1): a
//! ClientHello without a valid cookie is answered here, without any state, by a
//! HelloVerifyRequest carrying a cookie that is a keyed MAC of the peer's address and the
//! time, smaller than the ClientHello. Only the ClientHello that returns it opens a
//! session, at most `MAX_HANDSHAKES` of them handshaking at once. OpenSSL's own cookie
//! exchange is on in that session and is walked through its first step with the
//! ClientHello minus its cookie, so that its message numbers follow the exchange the
//! client saw (`cookie`).

use std::collections::{HashMap, VecDeque};
use std::hash::{BuildHasher, RandomState};
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
/// Handshakes a server runs at once (each for a peer that returned a cookie).
const MAX_HANDSHAKES: usize = 256;
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
    /// A server's cookies: the MAC key and when its clock started.
    cookies: cookie::Maker,
}

impl std::fmt::Debug for Dtls {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Dtls")
            .field("server", &self.server)
            .field("sessions", &self.sessions.len())
            .finish()
    }
}

/// The identity OpenSSL's server callback saw, kept in the session's extra data (DTLS's
/// and TLS's).
pub(crate) fn identity_index()
-> Result<openssl::ex_data::Index<Ssl, Arc<str>>, openssl::error::ErrorStack> {
    static INDEX: std::sync::OnceLock<openssl::ex_data::Index<Ssl, Arc<str>>> =
        std::sync::OnceLock::new();
    if let Some(i) = INDEX.get() {
        return Ok(*i);
    }
    let i = Ssl::new_ex_index()?;
    Ok(*INDEX.get_or_init(|| i))
}

/// Makes `b` a server that accepts the identities `keys` knows, each with its key, and
/// keeps the identity a session presented at [`identity_index`] (DTLS's and TLS's).
pub(crate) fn serve_keys(
    b: &mut SslContextBuilder,
    keys: &KeyStore,
) -> Result<(), openssl::error::ErrorStack> {
    let index = identity_index()?;
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
    Ok(())
}

/// Makes `b` a client that presents `identity` and its `key` (DTLS's and TLS's).
pub(crate) fn present_key(b: &mut SslContextBuilder, identity: &[u8], key: &[u8]) {
    let (identity, key) = (identity.to_vec(), key.to_vec());
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
}

/// The cookie a server's session sends and expects, in the session's extra data.
fn cookie_index() -> Result<openssl::ex_data::Index<Ssl, Vec<u8>>, openssl::error::ErrorStack> {
    static INDEX: std::sync::OnceLock<openssl::ex_data::Index<Ssl, Vec<u8>>> =
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
        let server = match psk {
            Psk::Server(keys) => {
                // The session's cookie exchange: the cookie the peer already returned
                // (checked before the session was made) is the one OpenSSL sends and
                // expects.
                let cookie_index = cookie_index().map_err(err)?;
                b.set_options(SslOptions::COOKIE_EXCHANGE);
                b.set_cookie_generate_cb(move |ssl, out| {
                    let cookie = ssl.ex_data(cookie_index).cloned().unwrap_or_default();
                    let n = cookie.len().min(out.len());
                    out[..n].copy_from_slice(&cookie[..n]);
                    Ok(n)
                });
                b.set_cookie_verify_cb(move |ssl, got| {
                    ssl.ex_data(cookie_index)
                        .is_some_and(|c| !c.is_empty() && c.as_slice() == got)
                });
                serve_keys(&mut b, keys).map_err(err)?;
                true
            }
            Psk::Client { identity, key } => {
                present_key(&mut b, identity, key);
                false
            }
        };
        Ok(Self {
            ctx: b.build(),
            server,
            sessions: HashMap::new(),
            cookies: cookie::Maker::new(),
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
            if !self.server {
                return Output::default();
            }
            return self.open(now, peer, datagram);
        }
        if let Some(s) = self.sessions.get_mut(&peer) {
            s.last_used = now;
        }
        self.drive(peer, Some(datagram))
    }

    /// A datagram from a peer without a session: a ClientHello whose cookie proves the
    /// peer's address opens one; one without gets a HelloVerifyRequest and leaves no state;
    /// anything else is dropped.
    fn open(&mut self, now: Instant, peer: SocketAddr, datagram: &[u8]) -> Output {
        let Some(hello) = cookie::ClientHello::parse(datagram) else {
            return Output::default();
        };
        if !self.cookies.is_good(now, peer, hello.cookie()) {
            let verify = hello.verify_request(&self.cookies.make(now, peer));
            return Output {
                send: vec![verify],
                ..Output::default()
            };
        }
        let handshaking = (self.sessions.values())
            .filter(|s| matches!(s.state, State::Handshaking(_)))
            .count();
        if handshaking >= MAX_HANDSHAKES || !self.make_room(now) {
            // The client sends its ClientHello again after its timer.
            tracing::debug!(%peer, handshaking, "no room for another DTLS handshake");
            return Output::default();
        }
        let Some(session) = self.session(now, true, hello.cookie()) else {
            return Output::default();
        };
        self.sessions.insert(peer, session);
        // OpenSSL's own exchange, first step: its HelloVerifyRequest is the one the client
        // has had already.
        let first = self.drive(peer, Some(&hello.without_cookie()));
        if first.failed {
            return first;
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
            let Some(session) = self.session(now, false, &[]) else {
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

    /// A new session, its handshake started (a client's first flight is in its queue); a
    /// server's with the `cookie` its peer returned.
    fn session(&self, now: Instant, accept: bool, cookie: &[u8]) -> Option<Session> {
        let mut ssl = Ssl::new(&self.ctx).ok()?;
        ssl.set_mtu(MTU).ok()?;
        if accept {
            ssl.set_ex_data(cookie_index().ok()?, cookie.to_vec());
        }
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

/// RFC 6347 §4.2.1's stateless cookie exchange, before OpenSSL sees anything: the
/// ClientHello read from a datagram, the cookie made and checked, the HelloVerifyRequest
/// written.
mod cookie {
    use super::{BuildHasher, Instant, RandomState, SocketAddr};

    /// Seconds a cookie stays good (made in this period or the one before).
    const PERIOD_SECS: u64 = 30;
    /// Record header: type, version, epoch, sequence number, length.
    const RECORD: usize = 13;
    /// Handshake header: type, length, message sequence, fragment offset and length.
    const HANDSHAKE: usize = 12;
    /// What a cookie is: 16 bytes of keyed MAC.
    const COOKIE_LEN: usize = 16;

    /// Makes and checks cookies: a keyed SipHash of the peer's address and the period.
    pub(super) struct Maker {
        key: RandomState,
        epoch: Option<Instant>,
    }

    impl Maker {
        pub(super) fn new() -> Self {
            Self {
                key: RandomState::new(),
                epoch: None,
            }
        }

        fn period(&mut self, now: Instant) -> u64 {
            let epoch = *self.epoch.get_or_insert(now);
            now.saturating_duration_since(epoch).as_secs() / PERIOD_SECS
        }

        fn mac(&self, peer: SocketAddr, period: u64) -> [u8; COOKIE_LEN] {
            let mut out = [0u8; COOKIE_LEN];
            out[..8].copy_from_slice(&self.key.hash_one((peer, period, 0u8)).to_be_bytes());
            out[8..].copy_from_slice(&self.key.hash_one((peer, period, 1u8)).to_be_bytes());
            out
        }

        /// The cookie for `peer` now.
        pub(super) fn make(&mut self, now: Instant, peer: SocketAddr) -> [u8; COOKIE_LEN] {
            let period = self.period(now);
            self.mac(peer, period)
        }

        /// Whether `cookie` was made for `peer` in this period or the one before.
        pub(super) fn is_good(&mut self, now: Instant, peer: SocketAddr, cookie: &[u8]) -> bool {
            let period = self.period(now);
            [Some(period), period.checked_sub(1)]
                .into_iter()
                .flatten()
                .any(|p| cookie == self.mac(peer, p))
        }
    }

    /// A datagram that is one unfragmented ClientHello record of epoch 0.
    pub(super) struct ClientHello<'a> {
        datagram: &'a [u8],
        /// Where the cookie's length byte is.
        cookie_at: usize,
    }

    impl<'a> ClientHello<'a> {
        pub(super) fn parse(datagram: &'a [u8]) -> Option<Self> {
            let record = datagram.get(..RECORD)?;
            let length = usize::from(u16::from_be_bytes([record[11], record[12]]));
            // Handshake (22), DTLS 1.x (254, x), epoch 0, the datagram's only record.
            if record[0] != 22 || record[1] != 254 || record[3..5] != [0, 0] {
                return None;
            }
            if datagram.len() != RECORD + length {
                return None;
            }
            let h = datagram.get(RECORD..RECORD + HANDSHAKE)?;
            let u24 =
                |b: &[u8]| usize::from(b[0]) << 16 | usize::from(b[1]) << 8 | usize::from(b[2]);
            let body_len = u24(&h[1..4]);
            // A ClientHello (1), whole: fragment offset 0 and length the message's.
            if h[0] != 1 || u24(&h[6..9]) != 0 || u24(&h[9..12]) != body_len {
                return None;
            }
            if RECORD + HANDSHAKE + body_len != datagram.len() {
                return None;
            }
            // client_version (2), random (32), session_id (length byte and bytes).
            let session_at = RECORD + HANDSHAKE + 34;
            let session_len = usize::from(*datagram.get(session_at)?);
            let cookie_at = session_at + 1 + session_len;
            let cookie_len = usize::from(*datagram.get(cookie_at)?);
            datagram.get(cookie_at + 1 + cookie_len)?;
            Some(Self {
                datagram,
                cookie_at,
            })
        }

        pub(super) fn cookie(&self) -> &'a [u8] {
            let len = usize::from(self.datagram[self.cookie_at]);
            &self.datagram[self.cookie_at + 1..self.cookie_at + 1 + len]
        }

        /// The HelloVerifyRequest with `cookie`: record sequence number the ClientHello's,
        /// message sequence 0, version DTLS 1.0 (RFC 6347 §4.2.1).
        pub(super) fn verify_request(&self, cookie: &[u8]) -> Vec<u8> {
            let body = 3 + cookie.len();
            let mut out = Vec::with_capacity(RECORD + HANDSHAKE + body);
            out.extend_from_slice(&[22, 254, 255]);
            out.extend_from_slice(&self.datagram[3..11]);
            out.extend_from_slice(&((HANDSHAKE + body) as u16).to_be_bytes());
            let body24 = [0, 0, body as u8];
            out.push(3);
            out.extend_from_slice(&body24);
            out.extend_from_slice(&[0, 0, 0, 0, 0]);
            out.extend_from_slice(&body24);
            out.extend_from_slice(&[254, 255, cookie.len() as u8]);
            out.extend_from_slice(cookie);
            out
        }

        /// The same ClientHello as its client's first, without the cookie: message
        /// sequence 0 and the record sequence number before this one's.
        pub(super) fn without_cookie(&self) -> Vec<u8> {
            let d = self.datagram;
            let cookie_len = usize::from(d[self.cookie_at]);
            let mut out = Vec::with_capacity(d.len() - cookie_len);
            out.extend_from_slice(&d[..self.cookie_at]);
            out.push(0);
            out.extend_from_slice(&d[self.cookie_at + 1 + cookie_len..]);
            let seq = u64::from_be_bytes([0, 0, d[5], d[6], d[7], d[8], d[9], d[10]]);
            out[5..11].copy_from_slice(&seq.saturating_sub(1).to_be_bytes()[2..]);
            let record_len = out.len() - RECORD;
            out[11..13].copy_from_slice(&(record_len as u16).to_be_bytes());
            let body = (record_len - HANDSHAKE) as u32;
            out[RECORD + 1..RECORD + 4].copy_from_slice(&body.to_be_bytes()[1..]);
            out[RECORD + 4..RECORD + 6].copy_from_slice(&[0, 0]);
            out[RECORD + 9..RECORD + 12].copy_from_slice(&body.to_be_bytes()[1..]);
            out
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn server() -> Dtls {
        let keys: KeyStore = Arc::new(|id: &[u8]| (id == b"alice").then(|| b"secret".to_vec()));
        Dtls::new(&Psk::Server(keys)).expect("a DTLS server")
    }

    fn client() -> Dtls {
        Dtls::new(&Psk::Client {
            identity: b"alice".to_vec(),
            key: b"secret".to_vec(),
        })
        .expect("a DTLS client")
    }

    const SERVER: SocketAddr =
        SocketAddr::new(std::net::IpAddr::V4(std::net::Ipv4Addr::LOCALHOST), 5684);

    fn peer(n: u32) -> SocketAddr {
        SocketAddr::from((std::net::Ipv4Addr::from(0xc000_0200 + n), 40_000))
    }

    /// A client's first flight: its ClientHello.
    fn hello(now: Instant) -> Vec<u8> {
        let mut c = client();
        let mut flight = c.send(now, SERVER, b"request");
        assert_eq!(flight.len(), 1, "one datagram");
        flight.remove(0)
    }

    /// Runs a handshake between `c` (at `at`) and `s` and sends `message`; whether it
    /// arrived.
    fn talk(s: &mut Dtls, c: &mut Dtls, at: SocketAddr, now: Instant, message: &[u8]) -> bool {
        let mut to_server = c.send(now, SERVER, message);
        for _ in 0..20 {
            let mut to_client = Vec::new();
            for d in to_server.drain(..) {
                let out = s.receive(now, at, &d);
                if out.received.iter().any(|m| m == message) {
                    return true;
                }
                to_client.extend(out.send);
            }
            for d in to_client {
                to_server.extend(c.receive(now, SERVER, &d).send);
            }
            if to_server.is_empty() {
                return false;
            }
        }
        false
    }

    #[test]
    fn rfc6347_4_2_1_a_spoofed_client_hello_draws_less_than_it_and_leaves_no_state() {
        let now = Instant::now();
        let mut s = server();
        let hello = hello(now);
        let out = s.receive(now, peer(1), &hello);
        let sent: usize = out.send.iter().map(Vec::len).sum();
        assert_eq!(out.send.len(), 1, "one HelloVerifyRequest");
        assert!(
            sent < hello.len(),
            "{sent} B back for a {}-byte ClientHello",
            hello.len()
        );
        assert_eq!(out.send[0][13], 3, "a HelloVerifyRequest");
        assert!(s.sessions.is_empty(), "no state for an unproven address");
        // Nothing is sent again: there is nothing to retransmit.
        assert!(s.poll_timeout(now).is_none());
        let (later, gave_up) = s.handle_timeout(now + Duration::from_secs(20));
        assert!(later.is_empty() && gave_up.is_empty());
    }

    #[test]
    fn spoofed_hellos_open_nothing_and_a_real_client_still_gets_in() {
        let now = Instant::now();
        let mut s = server();
        let hello = hello(now);
        let mut back = 0;
        for n in 0..4200 {
            back += s.receive(now, peer(n), &hello).send.len();
        }
        assert_eq!(back, 4200, "one HelloVerifyRequest each");
        assert!(s.sessions.is_empty(), "{} sessions", s.sessions.len());
        // A client that answers the cookie gets a session and its message through.
        let mut c = client();
        assert!(talk(&mut s, &mut c, peer(9999), now, b"hello, server"));
        assert_eq!(s.sessions.len(), 1);
        // A cookie made for one address does not open a session for another.
        let mut c2 = client();
        let first = c2.send(now, SERVER, b"x").remove(0);
        let verify = s.receive(now, peer(1), &first).send.remove(0);
        let second = c2.receive(now, SERVER, &verify).send.remove(0);
        let out = s.receive(now, peer(2), &second);
        assert_eq!(s.sessions.len(), 1, "a cookie taken to another address");
        assert_eq!(out.send.len(), 1, "it gets a HelloVerifyRequest of its own");
        assert!(!s.receive(now, peer(1), &second).send.is_empty());
        assert_eq!(s.sessions.len(), 2, "the address it was made for");
    }
}
