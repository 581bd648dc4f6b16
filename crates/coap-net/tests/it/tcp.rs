//! `coap+tcp` (RFC 8323) through `TcpServer`: the CSM exchange, a request through the
//! router, Ping and Pong, and Release, byte by byte over a real socket; and libcoap
//! 4.3.5's `coap-client` fetching a resource over TCP.

use std::path::PathBuf;
use std::sync::Arc;

use coap::msg::signal::{Csm, Signal};
use coap::msg::stream::{self, Decoded, Frame};
use coap::{Code, Response};
use coap_net::{Resource, Router, TcpServer, handler, tcp};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use crate::within;

fn hello_router() -> Arc<Router> {
    let router = Router::new();
    router.add(
        "/hello",
        Resource::new().get(handler(|_| async {
            Response::new(Code::CONTENT).with_payload("hello tcp")
        })),
    );
    router
}

async fn tcp_server() -> TcpServer {
    let addr = "127.0.0.1:0".parse().unwrap_or_else(|_| unreachable!());
    TcpServer::bind(addr, hello_router(), tcp::DEFAULT_MAX_MESSAGE_SIZE)
        .await
        .unwrap_or_else(|e| panic!("bind: {e}"))
}

/// Reads from `stream` until `buf` holds a whole frame, and takes it.
async fn next_frame(stream: &mut TcpStream, buf: &mut Vec<u8>) -> Frame {
    loop {
        match stream::decode(buf, 1 << 20) {
            Ok(Decoded::Frame { frame, consumed }) => {
                buf.drain(..consumed);
                return frame;
            }
            Ok(Decoded::Incomplete { .. }) => {}
            Err(e) => panic!("{e}"),
        }
        let mut chunk = [0u8; 4096];
        let n = stream
            .read(&mut chunk)
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(n > 0, "the server closed with {buf:02x?} unread");
        buf.extend_from_slice(&chunk[..n]);
    }
}

#[tokio::test]
async fn rfc8323_csm_request_ping_and_release_over_a_socket() {
    let server = tcp_server().await;
    within(async {
        let mut s = TcpStream::connect(server.local_addr())
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        // An empty CSM, then GET /hello with token 0x07: Uri-Path (11), 5 bytes.
        let mut out = vec![0x00, 0xe1, 0x61, 0x01, 0x07, 0xb5];
        out.extend_from_slice(b"hello");
        s.write_all(&out).await.unwrap_or_else(|e| panic!("{e}"));
        let mut buf = Vec::new();

        let csm = next_frame(&mut s, &mut buf).await;
        assert_eq!(
            Signal::decode(&csm),
            Ok(Signal::Csm(Csm {
                max_message_size: Some(tcp::DEFAULT_MAX_MESSAGE_SIZE),
                block_wise_transfer: false,
            }))
        );
        let answer = next_frame(&mut s, &mut buf).await;
        assert_eq!(answer.code, Code::CONTENT);
        assert_eq!(answer.token.as_bytes(), [0x07]);
        assert_eq!(&answer.payload[..], b"hello tcp");

        // A Ping with Custody and token 0x42: a Pong with that token.
        s.write_all(&[0x11, 0xe2, 0x42, 0x20])
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let pong = next_frame(&mut s, &mut buf).await;
        assert_eq!(pong.encode(), [0x01, 0xe3, 0x42]);

        // A Release: the server closes its side.
        s.write_all(&[0x00, 0xe4])
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let mut rest = Vec::new();
        s.read_to_end(&mut rest)
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(rest.is_empty(), "{rest:02x?}");
    })
    .await;
}

#[tokio::test]
async fn rfc8323_5_3_a_request_before_the_csm_is_aborted() {
    let server = tcp_server().await;
    within(async {
        let mut s = TcpStream::connect(server.local_addr())
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let mut out = vec![0x61, 0x01, 0x07, 0xb5];
        out.extend_from_slice(b"hello");
        s.write_all(&out).await.unwrap_or_else(|e| panic!("{e}"));
        let mut buf = Vec::new();
        let _csm = next_frame(&mut s, &mut buf).await;
        let abort = next_frame(&mut s, &mut buf).await;
        assert_eq!(abort.code, Code::ABORT);
        let mut rest = Vec::new();
        s.read_to_end(&mut rest)
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(rest.is_empty() && buf.is_empty());
    })
    .await;
}

/// libcoap 4.3.5's `coap-client` ( `../shared/peers/build-libcoap.sh`; its folder in
/// `COAPCAM_LIBCOAP435` or the script's default), or `None` after saying why it is missing.
/// Missing in CI (`CI=true`) fails the test.
fn libcoap435_client() -> Option<PathBuf> {
    let dir = std::env::var_os("COAPCAM_LIBCOAP435").map_or_else(
        || {
            let home = std::env::var_os("HOME").unwrap_or_default();
            PathBuf::from(home).join(".cache/coapcam-peers/libcoap-4.3.5/build")
        },
        PathBuf::from,
    );
    let client = dir.join("coap-client");
    if client.is_file() {
        return Some(client);
    }
    let why = format!(
        "{} is missing (../shared/peers/build-libcoap.sh builds it)",
        client.display()
    );
    assert!(std::env::var("CI").as_deref() != Ok("true"), "{why}");
    eprintln!("SKIP: {why}");
    None
}

#[tokio::test]
async fn libcoap_4_3_5_coap_client_gets_over_tcp() {
    let Some(client) = libcoap435_client() else {
        return;
    };
    let server = tcp_server().await;
    let uri = format!("coap+tcp://{}/hello", server.local_addr());
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

#[tokio::test]
async fn pipelined_requests_are_all_answered_with_at_most_max_in_flight_handlers() {
    use std::sync::atomic::{AtomicUsize, Ordering};
    let (now, most) = (Arc::new(AtomicUsize::new(0)), Arc::new(AtomicUsize::new(0)));
    let router = Router::new();
    let (n, m) = (now.clone(), most.clone());
    router.add(
        "/slow",
        Resource::new().get(handler(move |_| {
            let (n, m) = (n.clone(), m.clone());
            async move {
                m.fetch_max(n.fetch_add(1, Ordering::SeqCst) + 1, Ordering::SeqCst);
                tokio::time::sleep(std::time::Duration::from_millis(5)).await;
                n.fetch_sub(1, Ordering::SeqCst);
                Response::new(Code::CONTENT)
            }
        })),
    );
    let addr = "127.0.0.1:0".parse().unwrap_or_else(|_| unreachable!());
    let server = TcpServer::bind(addr, router, tcp::DEFAULT_MAX_MESSAGE_SIZE)
        .await
        .unwrap_or_else(|e| panic!("bind: {e}"));
    within(async {
        let mut s = TcpStream::connect(server.local_addr())
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        // An empty CSM, then 100 GETs of /slow in one write, tokens 0-99.
        let mut out = vec![0x00, 0xe1];
        for token in 0..100u8 {
            out.extend_from_slice(&[0x51, 0x01, token, 0xb4]);
            out.extend_from_slice(b"slow");
        }
        s.write_all(&out).await.unwrap_or_else(|e| panic!("{e}"));
        let mut buf = Vec::new();
        let _csm = next_frame(&mut s, &mut buf).await;
        let mut tokens = Vec::new();
        for _ in 0..100 {
            let answer = next_frame(&mut s, &mut buf).await;
            assert_eq!(answer.code, Code::CONTENT);
            tokens.extend_from_slice(answer.token.as_bytes());
        }
        tokens.sort_unstable();
        assert_eq!(tokens, (0..100).collect::<Vec<u8>>());
    })
    .await;
    let most = most.load(Ordering::SeqCst);
    assert!(
        (2..=tcp::MAX_IN_FLIGHT).contains(&most),
        "{most} handlers at once"
    );
}
