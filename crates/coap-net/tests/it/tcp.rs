//! `coap+tcp` (RFC 8323) through `TcpServer`: the CSM exchange, a request through the
//! router, Ping and Pong, and Release, byte by byte over a real socket; our `coap+tcp`
//! client against it (a 2.76 MB body in one message, the body limit, requests side by
//! side on one connection, timeouts, a connection that closes); and libcoap 4.3.5's
//! `coap-client` and `coap-server` on the other end.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use coap::msg::signal::{Csm, Release, Signal};
use coap::msg::stream::{self, Decoded, Frame};
use coap::{Code, EndpointConfig, Limits, Request, RequestError, Response};
use coap_net::{Client, Resource, Router, TcpServer, handler, tcp};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use crate::within;

pub(crate) fn hello_router() -> Arc<Router> {
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
    TcpServer::bind(addr, hello_router(), tcp::StreamLimits::default())
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

/// libcoap 4.3.5's `coap-client` or `coap-server` (`bin`; `../shared/peers/build-libcoap.sh`
/// builds them, into `COAPCAM_LIBCOAP435` or the script's default folder), or `None`
/// after saying why it is missing. Missing in CI (`CI=true`) fails the test.
pub(crate) fn libcoap435(bin: &str) -> Option<PathBuf> {
    let dir = std::env::var_os("COAPCAM_LIBCOAP435").map_or_else(
        || {
            let home = std::env::var_os("HOME").unwrap_or_default();
            PathBuf::from(home).join(".cache/coapcam-peers/libcoap-4.3.5/build")
        },
        PathBuf::from,
    );
    let path = dir.join(bin);
    if path.is_file() {
        return Some(path);
    }
    let why = format!(
        "{} is missing (../shared/peers/build-libcoap.sh builds it)",
        path.display()
    );
    assert!(std::env::var("CI").as_deref() != Ok("true"), "{why}");
    eprintln!("SKIP: {why}");
    None
}

#[tokio::test]
async fn libcoap_4_3_5_coap_client_gets_over_tcp() {
    let Some(client) = libcoap435("coap-client") else {
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
                tokio::time::sleep(Duration::from_millis(5)).await;
                n.fetch_sub(1, Ordering::SeqCst);
                Response::new(Code::CONTENT)
            }
        })),
    );
    let addr = "127.0.0.1:0".parse().unwrap_or_else(|_| unreachable!());
    let server = TcpServer::bind(addr, router, tcp::StreamLimits::default())
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

// ------------------------------------------------------------------ the server's bounds

/// A server of `/hello` and `/slow` (answers after 600 ms) within `limits`.
async fn bounded_server(limits: tcp::StreamLimits) -> TcpServer {
    let router = hello_router();
    router.add(
        "/slow",
        Resource::new().get(handler(|_| async {
            tokio::time::sleep(Duration::from_millis(600)).await;
            Response::new(Code::CONTENT).with_payload("slow")
        })),
    );
    let addr = "127.0.0.1:0".parse().unwrap_or_else(|_| unreachable!());
    TcpServer::bind(addr, router, limits)
        .await
        .unwrap_or_else(|e| panic!("bind: {e}"))
}

/// A connection to `server` that sent its CSM and GET `path` (token 0x07), and the
/// frames that came back until the answer: the server's CSM, then the answer, or a
/// Release when the server turned it away.
async fn ask(server: &TcpServer, path: &str) -> (TcpStream, Vec<u8>, Frame) {
    let mut s = TcpStream::connect(server.local_addr())
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let mut out = vec![0x00, 0xe1, 0x11 + ((path.len() as u8) << 4), 0x01, 0x07];
    out.push(0xb0 + path.len() as u8);
    out.extend_from_slice(path.as_bytes());
    // An IO error here is the server closing first, when it turns the connection away.
    let _ = s.write_all(&out).await;
    let mut buf = Vec::new();
    let csm = next_frame(&mut s, &mut buf).await;
    assert_eq!(csm.code, Code::CSM);
    let answer = next_frame(&mut s, &mut buf).await;
    (s, buf, answer)
}

/// Reads to the end of `s`, which must carry nothing more.
async fn closed(mut s: TcpStream, buf: Vec<u8>) {
    let mut rest = Vec::new();
    // A reset (the server closed with our bytes unread) is an end too.
    let _ = s.read_to_end(&mut rest).await;
    assert!(rest.is_empty() && buf.is_empty(), "{buf:02x?} {rest:02x?}");
}

#[tokio::test]
async fn a_connection_beyond_the_limit_is_released_saying_why_and_a_freed_place_is_taken() {
    let limits = tcp::StreamLimits {
        max_connections: 2,
        ..tcp::StreamLimits::default()
    };
    let server = bounded_server(limits).await;
    within(async {
        let (first, _, answer) = ask(&server, "hello").await;
        assert_eq!(&answer.payload[..], b"hello tcp");
        let (_second, _, answer) = ask(&server, "hello").await;
        assert_eq!(&answer.payload[..], b"hello tcp");

        let (third, buf, release) = ask(&server, "hello").await;
        assert_eq!(
            Signal::decode(&release),
            Ok(Signal::Release(Release {
                alternative_addresses: Vec::new(),
                hold_off_s: Some(5),
            }))
        );
        let why = String::from_utf8_lossy(&release.payload).into_owned();
        assert_eq!(why, "the server has 2 connections open, its limit");
        closed(third, buf).await;

        // The first one goes: its place is taken (once the server has seen it go).
        drop(first);
        let mut tries = 0;
        loop {
            let (_s, _, answer) = ask(&server, "hello").await;
            if answer.code == Code::CONTENT {
                break;
            }
            tries += 1;
            assert!(tries < 50, "no place freed: {answer:?}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
}

#[tokio::test]
async fn an_idle_connection_is_released_and_one_with_a_request_in_flight_is_not() {
    let limits = tcp::StreamLimits {
        idle_timeout: Duration::from_millis(200),
        ..tcp::StreamLimits::default()
    };
    let server = bounded_server(limits).await;
    within(async {
        let (idle, mut buf, answer) = ask(&server, "hello").await;
        let answered = std::time::Instant::now();
        assert_eq!(&answer.payload[..], b"hello tcp");
        let mut idle = idle;
        let release = next_frame(&mut idle, &mut buf).await;
        let waited = answered.elapsed();
        assert_eq!(
            Signal::decode(&release),
            Ok(Signal::Release(Release::default()))
        );
        assert_eq!(&release.payload[..], b"idle for 0.2 s");
        assert!(waited >= Duration::from_millis(190), "{waited:?}");
        closed(idle, buf).await;

        // Its handler takes 600 ms, three idle timeouts: the answer comes all the same.
        let asked = std::time::Instant::now();
        let (mut busy, mut buf, answer) = ask(&server, "slow").await;
        assert_eq!(&answer.payload[..], b"slow");
        assert!(asked.elapsed() >= Duration::from_millis(600));
        let release = next_frame(&mut busy, &mut buf).await;
        assert_eq!(release.code, Code::RELEASE);
        closed(busy, buf).await;
    })
    .await;
}

// ------------------------------------------------------------------ our client

/// The length of a 1280x720 color grab in the thesis packet (docs/resources.md).
pub(crate) const FRAME_BYTES: usize = 2_764_810;

/// A server with `/hello`, `/frame` (FRAME_BYTES of a pattern), `/slow` (answers after
/// 2 s), `/peer` (the requester's address, so a test sees which connection asked) and
/// `/local` (whether the request counts as this machine's).
async fn frame_server() -> TcpServer {
    let router = hello_router();
    router.add(
        "/frame",
        Resource::new().get(handler(|_| async {
            Response::new(Code::CONTENT).with_payload(pattern())
        })),
    );
    router.add(
        "/slow",
        Resource::new().get(handler(|_| async {
            tokio::time::sleep(Duration::from_secs(2)).await;
            Response::new(Code::CONTENT)
        })),
    );
    router.add(
        "/peer",
        Resource::new().get(handler(|ctx| async move {
            Response::new(Code::CONTENT).with_payload(ctx.request.peer.to_string())
        })),
    );
    router.add(
        "/local",
        Resource::new().get(handler(|ctx| async move {
            Response::new(Code::CONTENT).with_payload(ctx.request.loopback.to_string())
        })),
    );
    let addr = "127.0.0.1:0".parse().unwrap_or_else(|_| unreachable!());
    TcpServer::bind(addr, router, tcp::StreamLimits::default())
        .await
        .unwrap_or_else(|e| panic!("bind: {e}"))
}

pub(crate) fn pattern() -> Vec<u8> {
    (0..FRAME_BYTES).map(|i| (i % 251) as u8).collect()
}

pub(crate) fn get(path: &str) -> Request {
    let mut r = Request::new(Code::GET, path);
    r.timeout = Some(Duration::from_secs(10));
    r
}

/// A `coap+tcp` client taking bodies of up to `limit` bytes.
fn tcp_client(limit: usize) -> Client {
    let config = EndpointConfig {
        limits: Limits {
            client_body_bytes: limit,
            ..Limits::default()
        },
        ..EndpointConfig::default()
    };
    Client::tcp(&config)
}

#[tokio::test]
async fn our_client_gets_a_resource_and_a_2_76_mb_frame_in_one_message() {
    let server = frame_server().await;
    let client = tcp_client(Limits::default().client_body_bytes);
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
        // One message: no Block2, and every byte.
        assert!(frame.options.block2().is_none());
        assert!(
            frame.payload[..] == pattern()[..],
            "{} bytes",
            frame.payload.len()
        );
        assert_eq!(client.ping(peer).await.ok(), Some(()));
        // A peer on loopback is this machine: TCP's handshake proved its address.
        let local = client
            .send(peer, get("/local"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(&local.payload[..], b"true");
    })
    .await;
}

#[tokio::test]
async fn a_body_over_the_client_limit_fails_too_large_and_the_connection_stays() {
    let server = frame_server().await;
    let client = tcp_client(1 << 20);
    let peer = server.local_addr();
    within(async {
        let before = client
            .send(peer, get("/peer"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let refused = client.send(peer, get("/frame")).await;
        assert!(
            matches!(
                refused,
                Err(coap_net::Error::Request(RequestError::TooLarge {
                    limit: 1_048_576
                }))
            ),
            "{refused:?}"
        );
        let after = client
            .send(peer, get("/peer"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(before.payload, after.payload, "one connection throughout");
    })
    .await;
}

#[tokio::test]
async fn requests_side_by_side_share_one_connection_and_time_out_alone() {
    let server = frame_server().await;
    let client = tcp_client(1 << 20);
    let peer = server.local_addr();
    within(async {
        let mut slow = get("/slow");
        slow.timeout = Some(Duration::from_millis(300));
        let started = std::time::Instant::now();
        let slow = {
            let client = client.clone();
            tokio::spawn(async move { client.send(peer, slow).await })
        };
        let asked: Vec<_> = (0..20)
            .map(|_| {
                let client = client.clone();
                tokio::spawn(async move { client.send(peer, get("/peer")).await })
            })
            .collect();
        let mut seen = Vec::new();
        for one in asked {
            let answer = one.await.unwrap_or_else(|e| panic!("{e}"));
            seen.push(answer.unwrap_or_else(|e| panic!("{e}")).payload);
        }
        let slow = slow.await.unwrap_or_else(|e| panic!("{e}"));
        assert!(
            matches!(slow, Err(coap_net::Error::Request(RequestError::Timeout))),
            "{slow:?}"
        );
        let took = started.elapsed();
        assert!(took < Duration::from_millis(1500), "{took:?}");
        seen.dedup();
        assert_eq!(seen.len(), 1, "one connection: {seen:?}");
    })
    .await;
}

#[tokio::test]
async fn nothing_listening_fails_at_once_and_a_closed_connection_is_replaced() {
    let client = tcp_client(1 << 20);
    within(async {
        // A port nobody listens on: connection refused.
        let gone = {
            let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap_or_else(|e| panic!("{e}"));
            l.local_addr().unwrap_or_else(|e| panic!("{e}"))
        };
        let refused = client.send(gone, get("/hello")).await;
        assert!(
            matches!(refused, Err(coap_net::Error::Io(_))),
            "{refused:?}"
        );

        // A server that answers one request per connection, then closes it.
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let peer: SocketAddr = listener.local_addr().unwrap_or_else(|e| panic!("{e}"));
        tokio::spawn(async move {
            for n in 0u8..3 {
                let Ok((mut s, _)) = listener.accept().await else {
                    return;
                };
                let mut buf = Vec::new();
                let _csm = next_frame(&mut s, &mut buf).await;
                let _ = s.write_all(&Frame::new(Code::CSM).encode()).await;
                let request = next_frame(&mut s, &mut buf).await;
                let mut out = Vec::new();
                let answer = Frame {
                    token: request.token,
                    payload: vec![n].into(),
                    ..Frame::new(Code::CONTENT)
                };
                answer.encode_into(&mut out);
                let _ = s.write_all(&out).await;
                let _ = s.shutdown().await;
            }
        });
        for n in 0u8..3 {
            // Between requests the client notices the close and opens a new connection.
            tokio::time::sleep(Duration::from_millis(50)).await;
            let r = client
                .send(peer, get("/x"))
                .await
                .unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(&r.payload[..], [n]);
        }
    })
    .await;
}

#[tokio::test]
async fn a_request_sent_when_the_server_closes_fails_connection_closed() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let peer: SocketAddr = listener.local_addr().unwrap_or_else(|e| panic!("{e}"));
    tokio::spawn(async move {
        let Ok((mut s, _)) = listener.accept().await else {
            return;
        };
        let mut buf = Vec::new();
        let _csm = next_frame(&mut s, &mut buf).await;
        let _ = s.write_all(&Frame::new(Code::CSM).encode()).await;
        let _request = next_frame(&mut s, &mut buf).await;
        // An Abort instead of an answer.
        let _ = s.write_all(&Frame::new(Code::ABORT).encode()).await;
    });
    let client = tcp_client(1 << 20);
    within(async {
        let failed = client.send(peer, get("/x")).await;
        assert!(
            matches!(
                failed,
                Err(coap_net::Error::Request(RequestError::ConnectionClosed))
            ),
            "{failed:?}"
        );
    })
    .await;
}

#[tokio::test]
async fn multicast_over_tcp_is_refused_not_sent_over_udp_and_observe_goes_over_tcp() {
    let client = tcp_client(1 << 20);
    // Nothing listens on TCP port 9 here: the observation fails to connect.
    let peer: SocketAddr = "127.0.0.1:9".parse().unwrap_or_else(|_| unreachable!());
    let observed = client.observe(peer, get("/x")).await;
    assert!(
        matches!(observed, Err(coap_net::Error::Io(_))),
        "{observed:?}"
    );
    let group: SocketAddr = "224.0.1.187:5683"
        .parse()
        .unwrap_or_else(|_| unreachable!());
    let answers = client.multicast(group, get("/x")).await;
    assert!(matches!(
        answers,
        Err(coap_net::Error::Unsupported("multicast"))
    ));
}

// ---------------------------------------------------------- libcoap's coap-server

/// libcoap 4.3.5's `coap-server` on a free port of 127.0.0.1 (UDP and TCP), killed on
/// drop.
struct LibcoapServer {
    child: std::process::Child,
    addr: SocketAddr,
}

impl Drop for LibcoapServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Starts `coap-server -A 127.0.0.1 -p PORT` and waits (10 s at most) until our client
/// gets its `/` over TCP; tries another port when the first was taken meanwhile.
async fn libcoap_server(bin: PathBuf, client: &Client) -> LibcoapServer {
    for _ in 0..5 {
        let port = {
            let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap_or_else(|e| panic!("{e}"));
            l.local_addr().unwrap_or_else(|e| panic!("{e}")).port()
        };
        let child = std::process::Command::new(&bin)
            .args(["-A", "127.0.0.1", "-p", &port.to_string()])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("{}: {e}", bin.display()));
        let mut server = LibcoapServer {
            child,
            addr: SocketAddr::from(([127, 0, 0, 1], port)),
        };
        for _ in 0..100 {
            let mut probe = get("/");
            probe.timeout = Some(Duration::from_millis(500));
            if client.send(server.addr, probe).await.is_ok() {
                return server;
            }
            if server.child.try_wait().ok().flatten().is_some() {
                break;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        drop(server);
    }
    panic!("libcoap's coap-server did not start");
}

#[tokio::test]
async fn our_client_gets_from_libcoap_4_3_5_coap_server_over_tcp() {
    let Some(bin) = libcoap435("coap-server") else {
        return;
    };
    let client = tcp_client(1 << 20);
    let server = libcoap_server(bin, &client).await;
    within(async {
        let index = client
            .send(server.addr, get("/"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(index.code, Code::CONTENT);
        let text = String::from_utf8_lossy(&index.payload);
        assert!(text.contains("libcoap"), "{text}");
        let core = client
            .send(server.addr, get("/.well-known/core"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let links = String::from_utf8_lossy(&core.payload);
        assert!(links.contains("</time>"), "{links}");
        let missing = client
            .send(server.addr, get("/no/such/thing"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(missing.code, Code::NOT_FOUND);
        assert_eq!(client.ping(server.addr).await.ok(), Some(()));
    })
    .await;
}

/// A router with `/counter`, observable: its GET answers the counter's value, and its
/// observations' ends are counted in `ended`.
fn counter_router(
    count: &Arc<std::sync::atomic::AtomicU32>,
    ended: &Arc<std::sync::atomic::AtomicU32>,
) -> Arc<Router> {
    use std::sync::atomic::Ordering;
    let router = Router::new();
    let (count, ended) = (count.clone(), ended.clone());
    router.add(
        "/counter",
        Resource::new()
            .get(handler(move |_| {
                let n = count.load(Ordering::SeqCst);
                async move { Response::new(Code::CONTENT).with_payload(n.to_string()) }
            }))
            .observable()
            .on_observation_end(Arc::new(move |_, _| {
                ended.fetch_add(1, Ordering::SeqCst);
            })),
    );
    router
}

/// RFC 7641 over RFC 8323 §7: a registration over the connection gets a notification
/// for each change the router is told of (and none for a change to another path); the
/// client's deregistration (a GET with Observe 1, when its observation is dropped) ends
/// it on the server while the connection stays, and so does the connection's end (the
/// server's, here), which ends the client's observation too.
#[tokio::test]
async fn rfc8323_7_observe_notifies_over_the_connection_and_ends_with_a_deregistration_or_it() {
    use std::sync::atomic::{AtomicU32, Ordering};
    let (count, ended) = (Arc::new(AtomicU32::new(0)), Arc::new(AtomicU32::new(0)));
    let router = counter_router(&count, &ended);
    let addr = "127.0.0.1:0".parse().unwrap_or_else(|_| unreachable!());
    let server = TcpServer::bind(addr, router.clone(), tcp::StreamLimits::default())
        .await
        .unwrap_or_else(|e| panic!("bind: {e}"));
    let client = tcp_client(1 << 20);
    let ended_at = |n: u32| {
        let ended = ended.clone();
        async move {
            while ended.load(Ordering::SeqCst) < n {
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        }
    };
    within(async {
        let mut obs = client
            .observe(server.local_addr(), get("/counter"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let first = obs.next().await.expect("the answer").expect("a 2.05");
        assert_eq!(first.payload, "0");
        assert!(first.options.contains(coap::OptionNumber::OBSERVE));
        for n in 1..=3u32 {
            count.store(n, Ordering::SeqCst);
            router.changed("/elsewhere");
            router.changed("/counter");
            let r = obs.next().await.expect("a notification").expect("a 2.05");
            assert_eq!(r.payload, n.to_string());
            assert!(r.options.contains(coap::OptionNumber::OBSERVE));
        }
        drop(obs);
        ended_at(1).await;
        // The connection is still the same one, and answers.
        let r = client
            .send(server.local_addr(), get("/counter"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.payload, "3");
        assert!(!r.options.contains(coap::OptionNumber::OBSERVE));

        // A second observation, and the server goes: its connections end, and their
        // observations with them.
        let mut obs = client
            .observe(server.local_addr(), get("/counter"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(obs.next().await.is_some_and(|r| r.is_ok()));
        drop(server);
        ended_at(2).await;
        assert!(obs.next().await.is_none_or(|r| r.is_err()));
    })
    .await;
}
