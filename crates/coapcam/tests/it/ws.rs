//! CoAP over WebSockets (RFC 8323 §4) end to end: `coapcam serve --bind-ws` answered over
//! `coap+ws` by our own commands through `coap+ws://` URIs (`discover`, a 2,764,810-byte
//! color grab in one message with `post`, `grab`), which reach it through the same client
//! seam as every other scheme, and by libcoap 4.3.5's `coap-client` (discovery filtered
//! to one link, and `/time`: its WebSocket reader takes messages of 1,472 bytes at most).

use std::net::SocketAddr;

use crate::support::{self, COAPCAM, LIMIT, Peer, Proc, SN, TempDir};

/// The bytes of a 1280x720 color grab in the thesis packet (docs/resources.md).
const COLOR_BYTES: usize = 2_764_810;

/// `coapcam serve` (the built-in synthetic scene) on 127.0.0.1 over UDP and WebSockets:
/// the process and its WebSocket address.
fn serve_ws(dir: &TempDir) -> (Proc, SocketAddr) {
    let state = dir.join("state");
    let mut p = Proc::spawn(
        COAPCAM,
        &[
            "serve",
            "--bind",
            "127.0.0.1:0",
            "--bind-ws",
            "127.0.0.1:0",
            "--state-dir",
            state.to_str().expect("UTF-8 path"),
            "--duration",
            "120",
        ],
    );
    let ws = p.stderr_line(LIMIT, |l| {
        l.strip_prefix("coapcam: serving coap+ws on ")
            .and_then(|a| a.trim().parse().ok())
    });
    (p, ws)
}

#[test]
fn our_commands_reach_serve_bind_ws_through_coap_ws_uris() {
    let dir = TempDir::new("ws-ours");
    let (_server, ws) = serve_ws(&dir);

    let found = Proc::run(COAPCAM, &["discover", &format!("coap+ws://{ws}")], LIMIT)
        .expect_success("coapcam discover coap+ws://");
    let listed = found.stdout_text();
    assert!(listed.contains(&format!("/cams/{SN}/color")), "{listed}");

    let out = dir.join("color.bin");
    let uri = format!("coap+ws://{ws}/cams/{SN}/color");
    Proc::run(
        COAPCAM,
        &["post", &uri, "-o", out.to_str().expect("UTF-8 path")],
        LIMIT,
    )
    .expect_success("coapcam post coap+ws://");
    let bytes = std::fs::read(&out).expect("the grab");
    assert_eq!(bytes.len(), COLOR_BYTES);
    // The color packet's header: type 1, then width and height (u16, network order).
    assert_eq!(bytes[..5], [1, 0x05, 0x00, 0x02, 0xd0]);

    let png = dir.join("color.png");
    let server = format!("coap+ws://{ws}");
    Proc::run(
        COAPCAM,
        &[
            "grab",
            "color",
            "--server",
            &server,
            "-o",
            png.to_str().expect("UTF-8 path"),
        ],
        LIMIT,
    )
    .expect_success("coapcam grab color --server coap+ws://");
    let picture = std::fs::read(&png).expect("the picture");
    assert_eq!(picture[..8], *b"\x89PNG\r\n\x1a\n");
}

#[test]
fn libcoap435_client_discovers_and_reads_the_time_over_websockets_from_serve_bind_ws() {
    let test = "libcoap435_client_discovers_and_reads_the_time_over_websockets_from_serve_bind_ws";
    if !support::available(test, &[Peer::Libcoap435]) {
        return;
    }
    let dir = TempDir::new("ws-libcoap");
    let (_server, ws) = serve_ws(&dir);
    let client = support::libcoap435("coap-client");
    let client = client.to_str().expect("UTF-8 path");

    let core = Proc::run(
        client,
        &[
            "-m",
            "get",
            "-B",
            "30",
            &format!("coap+ws://{ws}/.well-known/core?rt=coapcam.time"),
        ],
        LIMIT,
    )
    .expect_success("coap-client GET /.well-known/core over WebSockets");
    let links = core.stdout_text();
    assert!(links.starts_with("</time>"), "{links}");

    let time = Proc::run(
        client,
        &["-m", "get", "-B", "30", &format!("coap+ws://{ws}/time")],
        LIMIT,
    )
    .expect_success("coap-client GET /time over WebSockets");
    let text = time.stdout_text();
    assert!(text.starts_with("{\"unix_us\":"), "{text}");
}

#[test]
fn our_client_reads_and_writes_aiocoap_server_over_websockets() {
    let test = "our_client_reads_and_writes_aiocoap_server_over_websockets";
    if !support::available(test, &[Peer::AiocoapWs]) {
        return;
    }
    let dir = TempDir::new("ws-aiocoap-server");
    let (path, big) = crate::tcp::aiocoap_big_file(&dir);
    let (_server, addrs) = support::aiocoap_server_on_all(Some(&path));
    let ws = addrs
        .ws
        .expect("aiocoap listens on WebSockets with websockets installed");
    crate::tcp::our_client_against_aiocoap("coap+ws", ws, &dir, &big);
}

#[test]
fn aiocoap_client_discovers_and_reads_a_camera_over_websockets_from_serve_bind_ws() {
    let test = "aiocoap_client_discovers_and_reads_a_camera_over_websockets_from_serve_bind_ws";
    if !support::available(test, &[Peer::AiocoapWs]) {
        return;
    }
    let dir = TempDir::new("ws-aiocoap-client");
    let (_server, ws) = serve_ws(&dir);
    crate::tcp::aiocoap_client_against_serve("coap+ws", ws);
}

#[test]
fn aiocoap_observes_a_live_stream_of_serve_bind_ws() {
    let test = "aiocoap_observes_a_live_stream_of_serve_bind_ws";
    if !support::available(test, &[Peer::AiocoapWs]) {
        return;
    }
    let dir = TempDir::new("ws-aiocoap-observe");
    let (_server, ws) = serve_ws(&dir);
    crate::tcp::aiocoap_observes_serve("coap+ws", ws);
}
