//! TLS for stream connections (RFC 8323: `coaps+tcp` and `coaps+ws`), through OpenSSL as
//! DTLS is, with the same pre-shared keys ([`Psk`]): a server
//! takes the identities its key store knows, a client presents one identity and its key.
//! This module only builds OpenSSL's context and runs its handshake on a TCP stream
//! (tokio-openssl's adapter); the TLS itself is OpenSSL's.
//!
//! Versions: TLS 1.2 with the PSK suites DTLS uses, and TLS 1.3 with an external PSK
//! (OpenSSL feeds the same PSK callbacks into TLS 1.3's `psk_dhe_ke` handshake, a PSK
//! bound to SHA-256, so only the SHA-256 suites of TLS 1.3 are offered). Whichever both
//! ends allow is taken: 1.3 between two OpenSSL 3 ends. There are no certificates: a
//! handshake without a key the other end knows fails.
//!
//! `coaps+tcp` carries the ALPN protocol ID `coap` that RFC 8323 registers: a client
//! offers it, and a server takes it when offered and refuses a client
//! offering only other protocols (RFC 7301 §3.2's `no_application_protocol`); a client
//! offering none is served (libcoap's PSK clients send no ALPN). `coaps+ws` runs HTTP
//! over TLS, so no `coap` ALPN there.

use std::io;
use std::pin::Pin;
use std::sync::Arc;

use openssl::ssl::{
    AlpnError, Ssl, SslContext, SslContextBuilder, SslMethod, SslOptions, SslVersion,
    select_next_proto,
};
use tokio::net::TcpStream;
use tokio_openssl::SslStream;

use crate::dtls::{Psk, identity_index, present_key, serve_keys};

/// TLS 1.2's PSK suites: the ones DTLS offers (RFC 7925 §4.2's mandatory CCM_8 first),
/// then the larger GCM one.
const CIPHERS: &str =
    "PSK-AES128-CCM8:PSK-AES128-GCM-SHA256:PSK-AES128-CBC-SHA256:PSK-AES256-GCM-SHA384";

/// TLS 1.3's suites that fit a PSK bound to SHA-256 (OpenSSL's callbacks make such one).
const CIPHERSUITES: &str = "TLS_AES_128_GCM_SHA256:TLS_CHACHA20_POLY1305_SHA256";

/// The ALPN protocol ID of CoAP over TLS (RFC 8323), in ALPN's wire form.
const ALPN_COAP: &[u8] = b"\x04coap";

/// One end's TLS: OpenSSL's context with its keys, made once and used for each of its
/// connections.
pub(crate) struct Tls {
    ctx: SslContext,
}

impl std::fmt::Debug for Tls {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Tls").finish_non_exhaustive()
    }
}

impl Tls {
    /// The TLS of `psk`'s role, with the ALPN protocol `coap` when `alpn` (`coaps+tcp`;
    /// not `coaps+ws`, which speaks HTTP first).
    pub(crate) fn new(psk: &Psk, alpn: bool) -> io::Result<Arc<Self>> {
        let err = |e: openssl::error::ErrorStack| io::Error::other(format!("TLS setup: {e}"));
        let mut b = SslContextBuilder::new(SslMethod::tls()).map_err(err)?;
        b.set_min_proto_version(Some(SslVersion::TLS1_2))
            .map_err(err)?;
        b.set_cipher_list(CIPHERS).map_err(err)?;
        b.set_ciphersuites(CIPHERSUITES).map_err(err)?;
        // No resumption: every connection proves the key anew.
        b.set_options(SslOptions::NO_TICKET);
        match psk {
            Psk::Server(keys) => {
                serve_keys(&mut b, keys).map_err(err)?;
                if alpn {
                    b.set_alpn_select_callback(|_, offered| {
                        select_next_proto(ALPN_COAP, offered).ok_or(AlpnError::ALERT_FATAL)
                    });
                }
            }
            Psk::Client { identity, key } => {
                present_key(&mut b, identity, key);
                if alpn {
                    b.set_alpn_protos(ALPN_COAP).map_err(err)?;
                }
            }
        }
        Ok(Arc::new(Self { ctx: b.build() }))
    }

    /// A server's handshake on `stream`: the TLS stream and the PSK identity the client
    /// presented.
    pub(crate) async fn accept(
        &self,
        stream: TcpStream,
    ) -> io::Result<(SslStream<TcpStream>, Option<Arc<str>>)> {
        let mut tls = self.stream(stream)?;
        Pin::new(&mut tls)
            .accept()
            .await
            .map_err(|e| handshake_error(&e))?;
        let identity = identity_index()
            .ok()
            .and_then(|i| tls.ssl().ex_data(i).cloned());
        let cipher = tls.ssl().current_cipher().map(|c| c.name());
        let version = tls.ssl().version_str();
        tracing::debug!(version, cipher, identity = ?identity, "TLS accepted");
        Ok((tls, identity))
    }

    /// A client's handshake on `stream`.
    pub(crate) async fn connect(&self, stream: TcpStream) -> io::Result<SslStream<TcpStream>> {
        let mut tls = self.stream(stream)?;
        Pin::new(&mut tls)
            .connect()
            .await
            .map_err(|e| handshake_error(&e))?;
        let cipher = tls.ssl().current_cipher().map(|c| c.name());
        let version = tls.ssl().version_str();
        tracing::debug!(version, cipher, "TLS connected");
        Ok(tls)
    }

    fn stream(&self, stream: TcpStream) -> io::Result<SslStream<TcpStream>> {
        let ssl = Ssl::new(&self.ctx).map_err(io::Error::other)?;
        SslStream::new(ssl, stream).map_err(io::Error::other)
    }
}

/// A failed handshake as an I/O error saying so (most often a key or identity the other
/// end does not know).
fn handshake_error(e: &openssl::ssl::Error) -> io::Error {
    let kind = match e.io_error() {
        Some(io) => io.kind(),
        None => io::ErrorKind::PermissionDenied,
    };
    io::Error::new(kind, format!("TLS handshake failed: {e}"))
}
