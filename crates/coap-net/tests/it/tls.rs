//! `coaps+tcp` and `coaps+ws` (RFC 8323 over TLS with pre-shared keys) through
//! `TcpServer::bind_tls` and `bind_wss`: our client against them (a GET naming the PSK
//! identity, a 2.76 MB body in one message, a Ping), a wrong key and an unknown identity
//! refused, the ALPN protocol `coap`, TLS 1.3, a connection that never finishes its
//! handshake closed after the idle timeout, and one beyond the connection limit released.

use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

use coap::msg::signal::{Release, Signal};
use coap::msg::stream::{self, Decoded};
use coap::{Code, EndpointConfig, Request, Response};
use coap_net::{Client, Psk, Resource, Router, TcpServer, handler, tcp};
use openssl::ssl::{Ssl, SslContext, SslMethod, SslVersion};
use tokio::io::AsyncReadExt;
use tokio::net::TcpStream;
use tokio_openssl::SslStream;

use crate::tcp::{FRAME_BYTES, get, pattern};
use crate::within;

/// The ALPN offer of a `coaps+tcp` client: `coap` alone.
const ALPN: &[u8] = b"\x04coap";

fn keys() -> Psk {
    Psk::Server(Arc::new(|identity: &[u8]| match identity {
        b"alice" => Some(b"secret-of-alice".to_vec()),
        _ => None,
    }))
}

fn key(identity: &str, key: &str) -> Psk {
    Psk::Client {
        identity: identity.as_bytes().to_vec(),
        key: key.as_bytes().to_vec(),
    }
}

/// `/who` (the request's PSK identity) and `/frame` (FRAME_BYTES of a pattern).
fn router() -> Arc<Router> {
    let router = Router::new();
    router.add(
        "/who",
        Resource::new().get(handler(|ctx| async move {
            let who = ctx.request.identity.as_deref().unwrap_or("nobody");
            Response::new(Code::CONTENT).with_payload(who.to_string())
        })),
    );
    router.add(
        "/frame",
        Resource::new().get(handler(|_| async {
            Response::new(Code::CONTENT).with_payload(pattern())
        })),
    );
    router
}

async fn tls_server(websocket: bool, limits: tcp::StreamLimits) -> TcpServer {
    let addr = "127.0.0.1:0".parse().unwrap_or_else(|_| unreachable!());
    let bound = if websocket {
        TcpServer::bind_wss(addr, router(), limits, &keys()).await
    } else {
        TcpServer::bind_tls(addr, router(), limits, &keys()).await
    };
    bound.unwrap_or_else(|e| panic!("bind: {e}"))
}

fn client(websocket: bool, psk: &Psk) -> Client {
    let config = EndpointConfig::default();
    let made = if websocket {
        Client::wss(&config, psk)
    } else {
        Client::tls(&config, psk)
    };
    made.unwrap_or_else(|e| panic!("{e}"))
}

/// A GET naming alice, the frame whole in one message, a Ping; then a wrong key and an
/// unknown identity, each refused in the handshake.
async fn our_client_over_tls(websocket: bool) {
    let server = tls_server(websocket, tcp::StreamLimits::default()).await;
    let peer = server.local_addr();
    let alice = client(websocket, &key("alice", "secret-of-alice"));
    within(async {
        let who = alice
            .send(peer, get("/who"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((who.code, &who.payload[..]), (Code::CONTENT, &b"alice"[..]));
        let frame = alice
            .send(peer, get("/frame"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(frame.code, Code::CONTENT);
        assert!(frame.options.block2().is_none());
        assert_eq!(frame.payload.len(), FRAME_BYTES);
        assert!(frame.payload[..] == pattern()[..]);
        assert_eq!(alice.ping(peer).await.ok(), Some(()));

        for (identity, wrong) in [("alice", "guessed"), ("mallory", "secret-of-alice")] {
            let refused = client(websocket, &key(identity, wrong));
            let mut request = Request::new(Code::GET, "/who");
            request.timeout = Some(Duration::from_secs(5));
            let e = refused
                .send(peer, request)
                .await
                .expect_err("a key the server does not know");
            assert!(e.to_string().contains("TLS handshake failed"), "{e}");
        }
    })
    .await;
}

#[tokio::test]
async fn our_client_over_coaps_tcp_names_its_identity_gets_2_76_mb_and_pings() {
    our_client_over_tls(false).await;
}

#[tokio::test]
async fn our_client_over_coaps_ws_names_its_identity_gets_2_76_mb_and_pings() {
    our_client_over_tls(true).await;
}

/// A handshake with `peer` as alice offering `alpn` (ALPN's wire form; none when empty):
/// the protocol the server chose and the TLS version, or why it failed.
async fn raw_handshake(peer: SocketAddr, alpn: &[u8]) -> Result<(Option<Vec<u8>>, String), String> {
    let tls = raw_tls(peer, alpn).await?;
    let chosen = tls.ssl().selected_alpn_protocol().map(<[u8]>::to_vec);
    Ok((chosen, tls.ssl().version_str().to_string()))
}

/// A TLS connection to `peer` as alice offering `alpn`, its handshake done.
async fn raw_tls(peer: SocketAddr, alpn: &[u8]) -> Result<SslStream<TcpStream>, String> {
    let mut ctx = SslContext::builder(SslMethod::tls_client()).map_err(|e| e.to_string())?;
    ctx.set_psk_client_callback(|_, _, id, key| {
        id[..6].copy_from_slice(b"alice\0");
        key[..15].copy_from_slice(b"secret-of-alice");
        Ok(15)
    });
    ctx.set_min_proto_version(Some(SslVersion::TLS1_2))
        .map_err(|e| e.to_string())?;
    if !alpn.is_empty() {
        ctx.set_alpn_protos(alpn).map_err(|e| e.to_string())?;
    }
    let ssl = Ssl::new(&ctx.build()).map_err(|e| e.to_string())?;
    let tcp = TcpStream::connect(peer).await.map_err(|e| e.to_string())?;
    let mut tls = SslStream::new(ssl, tcp).map_err(|e| e.to_string())?;
    Pin::new(&mut tls)
        .connect()
        .await
        .map_err(|e| e.to_string())?;
    Ok(tls)
}

#[tokio::test]
async fn coaps_tcp_takes_the_alpn_protocol_coap_over_tls_1_3_and_refuses_others() {
    let server = tls_server(false, tcp::StreamLimits::default()).await;
    let peer = server.local_addr();
    within(async {
        let offered = raw_handshake(peer, b"\x02h2\x04coap").await;
        assert_eq!(offered, Ok((Some(b"coap".to_vec()), "TLSv1.3".to_string())));
        // A client offering no ALPN at all (libcoap's PSK clients) is served.
        let none = raw_handshake(peer, b"").await;
        assert_eq!(none, Ok((None, "TLSv1.3".to_string())));
        // One offering only another protocol is not.
        let other = raw_handshake(peer, b"\x08http/1.1").await;
        assert!(other.is_err(), "{other:?}");
    })
    .await;
}

#[tokio::test]
async fn a_tls_handshake_not_begun_within_the_idle_timeout_is_closed() {
    let limits = tcp::StreamLimits {
        idle_timeout: Duration::from_millis(300),
        ..tcp::StreamLimits::default()
    };
    for websocket in [false, true] {
        let server = tls_server(websocket, limits).await;
        within(async {
            let mut silent = TcpStream::connect(server.local_addr())
                .await
                .unwrap_or_else(|e| panic!("{e}"));
            let started = tokio::time::Instant::now();
            let mut byte = [0u8; 1];
            let n = silent.read(&mut byte).await.unwrap_or(0);
            assert_eq!(n, 0, "the server wrote to a client that sent nothing");
            assert!(started.elapsed() >= Duration::from_millis(250));
        })
        .await;
    }
}

#[tokio::test]
async fn a_tls_server_needs_the_identities_and_a_client_a_key() {
    let addr = "127.0.0.1:0".parse().unwrap_or_else(|_| unreachable!());
    let limits = tcp::StreamLimits::default();
    let as_client = key("alice", "secret-of-alice");
    let e = TcpServer::bind_tls(addr, router(), limits, &as_client)
        .await
        .expect_err("a client's key is no server's");
    assert_eq!(e.kind(), std::io::ErrorKind::InvalidInput);
    let e = Client::tls(&EndpointConfig::default(), &keys()).expect_err("no client key");
    assert_eq!(e.kind(), std::io::ErrorKind::InvalidInput);
}

#[tokio::test]
async fn a_tls_connection_beyond_the_limit_gets_its_handshake_and_a_release_saying_why() {
    let limits = tcp::StreamLimits {
        max_connections: 1,
        ..tcp::StreamLimits::default()
    };
    let server = tls_server(false, limits).await;
    let peer = server.local_addr();
    let alice = client(false, &key("alice", "secret-of-alice"));
    within(async {
        let who = alice.send(peer, get("/who")).await;
        assert_eq!(who.ok().map(|r| r.code), Some(Code::CONTENT));
        // The second connection: the CSM, then a Release with a Hold-Off, then the end.
        let mut second = raw_tls(peer, ALPN).await.unwrap_or_else(|e| panic!("{e}"));
        let mut bytes = Vec::new();
        let _ = second.read_to_end(&mut bytes).await;
        let mut frames = Vec::new();
        while let Ok(Decoded::Frame { frame, consumed }) = stream::decode(&bytes, 1 << 20) {
            bytes.drain(..consumed);
            frames.push(frame);
        }
        assert_eq!(frames.len(), 2, "{frames:?}");
        assert!(matches!(Signal::decode(&frames[0]), Ok(Signal::Csm(_))));
        assert_eq!(
            Signal::decode(&frames[1]),
            Ok(Signal::Release(Release {
                alternative_addresses: Vec::new(),
                hold_off_s: Some(5),
            }))
        );
        let why = String::from_utf8_lossy(&frames[1].payload).into_owned();
        assert_eq!(why, "the server has 1 connections open, its limit");
    })
    .await;
}
