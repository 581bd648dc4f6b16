//! CoAP over TCP (RFC 8323) end to end: `coapcam serve --bind-tcp` answered over
//! `coap+tcp` by libcoap 4.3.5's `coap-client` (discovery, and a 1280x720 color grab of
//! 2,764,810 bytes in one message) and by our own commands through `coap+tcp://` URIs
//! (`discover`, `post`, `grab`, `measure --prepare`, whose configuration changes are
//! accepted from this machine over TCP too), which reach it through the same client seam
//! as `coap://` ones.

use std::net::SocketAddr;

use crate::support::{self, COAPCAM, LIMIT, Peer, Proc, SN, TempDir};

/// The bytes of a 1280x720 color grab in the thesis packet (docs/resources.md).
const COLOR_BYTES: usize = 2_764_810;

/// `coapcam serve` (the built-in synthetic scene) on 127.0.0.1 over UDP and TCP: the
/// process and its TCP address.
fn serve_tcp(dir: &TempDir) -> (Proc, SocketAddr) {
    let state = dir.join("state");
    let mut p = Proc::spawn(
        COAPCAM,
        &[
            "serve",
            "--bind",
            "127.0.0.1:0",
            "--bind-tcp",
            "127.0.0.1:0",
            "--state-dir",
            state.to_str().expect("UTF-8 path"),
            "--duration",
            "120",
        ],
    );
    let tcp = p.stderr_line(LIMIT, |l| {
        l.strip_prefix("coapcam: serving coap+tcp on ")
            .and_then(|a| a.trim().parse().ok())
    });
    (p, tcp)
}

/// The color packet's header: type 1, then width and height (u16, network order).
#[track_caller]
fn assert_color_1280x720(bytes: &[u8]) {
    assert_eq!(bytes.len(), COLOR_BYTES);
    assert_eq!(bytes[..5], [1, 0x05, 0x00, 0x02, 0xd0]);
}

#[test]
fn libcoap435_client_discovers_and_grabs_color_over_tcp_from_serve_bind_tcp() {
    let test = "libcoap435_client_discovers_and_grabs_color_over_tcp_from_serve_bind_tcp";
    if !support::available(test, &[Peer::Libcoap435]) {
        return;
    }
    let dir = TempDir::new("tcp-libcoap");
    let (_server, tcp) = serve_tcp(&dir);
    let client = support::libcoap435("coap-client");
    let client = client.to_str().expect("UTF-8 path");

    let core = Proc::run(
        client,
        &[
            "-m",
            "get",
            "-B",
            "30",
            &format!("coap+tcp://{tcp}/.well-known/core"),
        ],
        LIMIT,
    )
    .expect_success("coap-client GET /.well-known/core over TCP");
    let links = core.stdout_text();
    assert!(links.contains(&format!("</cams/{SN}/color>")), "{links}");

    // coap-client announces a Max-Message-Size of 8,388,864 bytes: the frame comes whole.
    let out = dir.join("color.bin");
    Proc::run(
        client,
        &[
            "-m",
            "post",
            "-B",
            "60",
            "-o",
            out.to_str().expect("UTF-8 path"),
            &format!("coap+tcp://{tcp}/cams/{SN}/color"),
        ],
        LIMIT,
    )
    .expect_success("coap-client POST /cams/SN/color over TCP");
    let bytes = std::fs::read(&out).expect("the grab");
    assert_color_1280x720(&bytes);
}

#[test]
fn our_commands_reach_serve_bind_tcp_through_coap_tcp_uris() {
    let dir = TempDir::new("tcp-ours");
    let (_server, tcp) = serve_tcp(&dir);

    let found = Proc::run(COAPCAM, &["discover", &format!("coap+tcp://{tcp}")], LIMIT)
        .expect_success("coapcam discover coap+tcp://");
    let listed = found.stdout_text();
    assert!(listed.contains(&format!("/cams/{SN}/color")), "{listed}");

    let out = dir.join("color.bin");
    let uri = format!("coap+tcp://{tcp}/cams/{SN}/color");
    Proc::run(
        COAPCAM,
        &["post", &uri, "-o", out.to_str().expect("UTF-8 path")],
        LIMIT,
    )
    .expect_success("coapcam post coap+tcp://");
    assert_color_1280x720(&std::fs::read(&out).expect("the grab"));

    let png = dir.join("color.png");
    let server = format!("coap+tcp://{tcp}");
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
    .expect_success("coapcam grab color --server coap+tcp://");
    let picture = std::fs::read(&png).expect("the picture");
    assert_eq!(picture[..8], *b"\x89PNG\r\n\x1a\n");

    let f = Proc::run(
        COAPCAM,
        &["measure", "--server", &server, "--prepare", "--json"],
        LIMIT,
    )
    .expect_success("coapcam measure --prepare over TCP");
    let m = f.json();
    assert_eq!(m["parcel"], "measured", "{m}");
    assert_eq!(m["length_mm"], 400.0, "{m}");

    // Observe over the stream: the live color stream's first frame and two notifications,
    // the observation ended with the connection.
    let uri = format!("coap+tcp://{tcp}/cams/{SN}/color/live?fps=5");
    let f = Proc::run(COAPCAM, &["get", &uri, "--observe", "2", "--json"], LIMIT)
        .expect_success("coapcam get --observe over coap+tcp://");
    let lines = f.json_lines();
    assert_eq!(lines.len(), 3, "the answer and 2 notifications: {lines:?}");
    for l in &lines {
        assert_eq!(l["code"], "2.05", "{l}");
        assert!(l["observe"].is_u64(), "no Observe option: {l}");
        assert!(l["size_bytes"].as_u64() > Some(1000), "a JPEG frame: {l}");
    }
    assert_live_streams_end(&server);
}

/// `GET /cams/live` of the server at `server` (a URI without a path) until it reports no
/// stream left: an observation over a stream ends with its connection. Bounded: 100
/// reads, 100 ms apart.
#[track_caller]
pub(crate) fn assert_live_streams_end(server: &str) {
    let uri = format!("{server}/cams/live");
    let mut report = serde_json::Value::Null;
    for _ in 0..100 {
        report = Proc::run(COAPCAM, &["get", &uri], LIMIT)
            .expect_success("coapcam get /cams/live")
            .json();
        if report["streams"] == 0 {
            return;
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    panic!("the live stream outlived its observer's connection: {report}");
}

/// aiocoap's observer (`tests/peers/aiocoap_observe.py`, the aiocoap library) on the live
/// color stream of `serve` over `scheme` at `addr`: registered, it gets two notifications
/// and cancels; the stream ends once its connection has.
pub(crate) fn aiocoap_observes_serve(scheme: &str, addr: SocketAddr) {
    let uri = format!("{scheme}://{addr}/cams/{SN}/color/live?fps=5");
    let observer = support::script("aiocoap_observe.py");
    Proc::run("python3", &[&observer, &uri, "2"], LIMIT)
        .expect_success("aiocoap_observe.py on the live color stream");
    assert_live_streams_end(&format!("{scheme}://{addr}"));
}

#[test]
fn aiocoap_observes_a_live_stream_of_serve_bind_tcp() {
    let test = "aiocoap_observes_a_live_stream_of_serve_bind_tcp";
    if !support::available(test, &[Peer::Aiocoap]) {
        return;
    }
    let dir = TempDir::new("tcp-aiocoap-observe");
    let (_server, tcp) = serve_tcp(&dir);
    aiocoap_observes_serve("coap+tcp", tcp);
}

#[test]
fn our_client_observes_aiocoap_server_over_tcp() {
    let test = "our_client_observes_aiocoap_server_over_tcp";
    if !support::available(test, &[Peer::Aiocoap]) {
        return;
    }
    let (_server, addrs) = support::aiocoap_server_on_all(None);
    // /counter counts up every 250 ms and notifies each step.
    let uri = format!("coap+tcp://{}/counter", addrs.tcp);
    let f = Proc::run(COAPCAM, &["get", &uri, "--observe", "3", "--json"], LIMIT)
        .expect_success("coapcam get --observe coap+tcp:// from aiocoap");
    let lines = f.json_lines();
    assert_eq!(lines.len(), 4, "the answer and 3 notifications: {lines:?}");
    let counts: Vec<u64> = lines
        .iter()
        .map(|l| {
            assert_eq!(l["code"], "2.05", "{l}");
            let text = l["payload"].as_str().unwrap_or_default();
            text.parse().unwrap_or_else(|e| panic!("{text:?}: {e}"))
        })
        .collect();
    assert!(counts.windows(2).all(|w| w[0] < w[1]), "{counts:?}");
}

/// The bytes of `/big` on aiocoap's server in the stream tests: over its 1,024-byte
/// blocks, so that it answers in Block2 blocks.
const AIOCOAP_BIG: usize = 300_000;

/// Our client against `tests/peers/aiocoap_server.py` over `scheme` (`coap+tcp` or
/// `coap+ws`) at `addr`: discovery, a PUT read back, a POST echoed, and a GET of
/// [`AIOCOAP_BIG`] bytes which aiocoap sends in Block2 blocks over a stream too (it does
/// unless its peer's CSM announces Block-Wise-Transfer): returned whole, bit-exact.
pub(crate) fn our_client_against_aiocoap(
    scheme: &str,
    addr: SocketAddr,
    dir: &TempDir,
    big: &[u8],
) {
    let at = |path: &str| format!("{scheme}://{addr}{path}");
    let core = Proc::run(COAPCAM, &["get", &at("/.well-known/core")], LIMIT)
        .expect_success("coapcam get /.well-known/core from aiocoap");
    let links = core.stdout_text();
    assert!(
        links.contains("</counter>;ct=\"0\";rt=\"interop.counter\";obs"),
        "{links}"
    );

    Proc::run(
        COAPCAM,
        &["put", &at("/store"), "--payload", "stored over a stream"],
        LIMIT,
    )
    .expect_success("coapcam put /store to aiocoap");
    let back = Proc::run(COAPCAM, &["get", &at("/store")], LIMIT)
        .expect_success("coapcam get /store from aiocoap");
    assert_eq!(back.stdout_text().trim(), "stored over a stream");
    let echo = Proc::run(
        COAPCAM,
        &["post", &at("/echo"), "--payload", "echoed"],
        LIMIT,
    )
    .expect_success("coapcam post /echo to aiocoap");
    assert_eq!(echo.stdout_text().trim(), "echoed");

    let out = dir.join("big.bin");
    Proc::run(
        COAPCAM,
        &["get", &at("/big"), "-o", out.to_str().expect("UTF-8 path")],
        LIMIT,
    )
    .expect_success("coapcam get /big from aiocoap");
    let got = std::fs::read(&out).expect("the body");
    assert_eq!(got.len(), big.len(), "bytes of /big");
    assert!(
        got == big,
        "the body of /big differs from what aiocoap served"
    );
}

/// [`AIOCOAP_BIG`] bytes that are not one byte repeated, written to `dir/big`.
pub(crate) fn aiocoap_big_file(dir: &TempDir) -> (std::path::PathBuf, Vec<u8>) {
    let big: Vec<u8> = (0..AIOCOAP_BIG).map(|i| (i * 7 % 251) as u8).collect();
    let path = dir.join("big");
    std::fs::write(&path, &big).expect("write the body of /big");
    (path, big)
}

#[test]
fn our_client_reads_and_writes_aiocoap_server_over_tcp() {
    let test = "our_client_reads_and_writes_aiocoap_server_over_tcp";
    if !support::available(test, &[Peer::Aiocoap]) {
        return;
    }
    let dir = TempDir::new("tcp-aiocoap-server");
    let (path, big) = aiocoap_big_file(&dir);
    let (_server, addrs) = support::aiocoap_server_on_all(Some(&path));
    our_client_against_aiocoap("coap+tcp", addrs.tcp, &dir, &big);
}

/// aiocoap's `aiocoap-client` against `serve` over `scheme` at `addr`: discovery, and a
/// camera's color settings. Not a grab: aiocoap announces a Max-Message-Size of 1 MiB
/// and our server answers a frame over it with 5.00 (it does no block-wise over streams).
pub(crate) fn aiocoap_client_against_serve(scheme: &str, addr: SocketAddr) {
    let at = |path: &str| format!("{scheme}://{addr}{path}");
    let core = Proc::run(support::AIOCOAP_CLIENT, &[&at("/.well-known/core")], LIMIT)
        .expect_success("aiocoap-client GET /.well-known/core");
    let links = core.stdout_text();
    assert!(
        links.contains(&format!("</cams/{SN}/color>;rt=\"rgbd.color\"")),
        "{links}"
    );
    let settings = Proc::run(
        support::AIOCOAP_CLIENT,
        &[&at(&format!("/cams/{SN}/color-settings"))],
        LIMIT,
    )
    .expect_success("aiocoap-client GET color-settings");
    let json = settings.json();
    assert_eq!(json["width"], 1280, "{json}");
    assert_eq!(json["height"], 720, "{json}");
}

#[test]
fn aiocoap_client_discovers_and_reads_a_camera_over_tcp_from_serve_bind_tcp() {
    let test = "aiocoap_client_discovers_and_reads_a_camera_over_tcp_from_serve_bind_tcp";
    if !support::available(test, &[Peer::Aiocoap]) {
        return;
    }
    let dir = TempDir::new("tcp-aiocoap-client");
    let (_server, tcp) = serve_tcp(&dir);
    aiocoap_client_against_serve("coap+tcp", tcp);
}
