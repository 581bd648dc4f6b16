//! `coap+ws` (RFC 8323 §4) through `TcpServer::bind_ws`: our client against it (a GET, a
//! 2.76 MB body in one message, a Ping), the handshake's path and subprotocol, the
//! connection limit, and libcoap 4.3.5's `coap-client` on the other end.

use std::net::SocketAddr;
use std::time::Duration;

use coap::{Code, EndpointConfig, Response};
use coap_net::{Client, Resource, TcpServer, handler, tcp};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::http::{HeaderValue, StatusCode, header};

use crate::tcp::{FRAME_BYTES, get, hello_router, libcoap435, pattern};
use crate::within;

/// A `coap+ws` server of `/hello` and `/frame` (FRAME_BYTES of a pattern) within `limits`.
async fn ws_server(limits: tcp::StreamLimits) -> TcpServer {
    let router = hello_router();
    router.add(
        "/frame",
        Resource::new().get(handler(|_| async {
            Response::new(Code::CONTENT).with_payload(pattern())
        })),
    );
    let addr = "127.0.0.1:0".parse().unwrap_or_else(|_| unreachable!());
    TcpServer::bind_ws(addr, router, limits)
        .await
        .unwrap_or_else(|e| panic!("bind: {e}"))
}

#[tokio::test]
async fn our_client_gets_a_resource_and_a_2_76_mb_frame_in_one_websocket_message() {
    let server = ws_server(tcp::StreamLimits::default()).await;
    let client = Client::ws(&EndpointConfig::default());
    let peer = server.local_addr();
    within(async {
        let hello = client
            .send(peer, get("/hello"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            (hello.code, &hello.payload[..]),
            (Code::CONTENT, &b"hello tcp"[..])
        );
        let frame = client
            .send(peer, get("/frame"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(frame.code, Code::CONTENT);
        assert!(frame.options.block2().is_none());
        assert_eq!(frame.payload.len(), FRAME_BYTES);
        assert!(frame.payload[..] == pattern()[..]);
        assert_eq!(client.ping(peer).await.ok(), Some(()));
    })
    .await;
}

/// The HTTP status with which the server answers a WebSocket handshake for `path`,
/// asking for `protocol` when given: 101 when it switches.
async fn handshake(peer: SocketAddr, path: &str, protocol: Option<&'static str>) -> StatusCode {
    let stream = TcpStream::connect(peer)
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let mut request = format!("ws://{peer}{path}")
        .into_client_request()
        .unwrap_or_else(|e| panic!("{e}"));
    if let Some(protocol) = protocol {
        let value = HeaderValue::from_static(protocol);
        request
            .headers_mut()
            .insert(header::SEC_WEBSOCKET_PROTOCOL, value);
    }
    match tokio_tungstenite::client_async(request, stream).await {
        Ok((_, response)) => response.status(),
        Err(tokio_tungstenite::tungstenite::Error::Http(response)) => response.status(),
        Err(e) => panic!("{e}"),
    }
}

#[tokio::test]
async fn rfc8323_4_1_the_endpoint_is_well_known_coap_with_the_subprotocol_coap() {
    let server = ws_server(tcp::StreamLimits::default()).await;
    let peer = server.local_addr();
    within(async {
        let switched = handshake(peer, "/.well-known/coap", Some("coap")).await;
        assert_eq!(switched, StatusCode::SWITCHING_PROTOCOLS);
        let elsewhere = handshake(peer, "/coap", Some("coap")).await;
        assert_eq!(elsewhere, StatusCode::NOT_FOUND);
        let no_protocol = handshake(peer, "/.well-known/coap", None).await;
        assert_eq!(no_protocol, StatusCode::BAD_REQUEST);
    })
    .await;
}

#[tokio::test]
async fn a_websocket_beyond_the_connection_limit_is_answered_503() {
    let limits = tcp::StreamLimits {
        max_connections: 1,
        ..tcp::StreamLimits::default()
    };
    let server = ws_server(limits).await;
    let peer = server.local_addr();
    within(async {
        let client = Client::ws(&EndpointConfig::default());
        let hello = client.send(peer, get("/hello")).await;
        assert_eq!(hello.ok().map(|r| r.code), Some(Code::CONTENT));
        let full = handshake(peer, "/.well-known/coap", Some("coap")).await;
        assert_eq!(full, StatusCode::SERVICE_UNAVAILABLE);
        // The first client's connection goes: the place is taken again.
        drop(client);
        let mut tries = 0;
        while handshake(peer, "/.well-known/coap", Some("coap")).await
            != StatusCode::SWITCHING_PROTOCOLS
        {
            tries += 1;
            assert!(tries < 50, "no place freed");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
}

/// libcoap 4.3.5's client reads WebSocket messages of at most 1,472 bytes, though its CSM
/// announces a Max-Message-Size of 8,388,864 (a 2.76 MB answer ends its connection with
/// a WebSocket Close 1009, "packet size bigger than provided data space"): a small one.
#[tokio::test]
async fn libcoap_4_3_5_coap_client_gets_over_websockets() {
    let Some(client) = libcoap435("coap-client") else {
        return;
    };
    let server = ws_server(tcp::StreamLimits::default()).await;
    let uri = format!("coap+ws://{}/hello", server.local_addr());
    let output = within(tokio::task::spawn_blocking(move || {
        std::process::Command::new(client)
            .args(["-m", "get", "-B", "10", &uri])
            .output()
    }))
    .await
    .unwrap_or_else(|e| panic!("{e}"))
    .unwrap_or_else(|e| panic!("coap-client: {e}"));
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stdout}\n{stderr}");
    assert_eq!(stdout.trim_end(), "hello tcp", "{stderr}");
}
