//! Clients off the server's machine (RFC 9175 §2.4), inside a private network namespace
//! (`scripts/netns-run`, which `scripts/test.sh` uses): the server binds fd00::2, which
//! is not loopback, so every client is unverified until it returns an Echo value. Tests
//! may send only to loopback or inside their own namespace, hence the namespace.

use std::net::{SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

use coap::{Code, Message, OptionNumber, Token, Type};

use crate::support::{
    self, AIOCOAP_CLIENT, COAPCAM, LIBCOAP_CLIENT, LIMIT, Peer, Proc, TempDir, assert_file_is,
    random_file, serve_at,
};

fn in_namespace(test: &str) -> bool {
    let ok = std::env::var("COAPCAM_NETNS").is_ok_and(|v| v == "1");
    if !ok {
        eprintln!("SKIP {test}: off-host tests run only inside scripts/netns-run");
    }
    ok
}

/// Sends `msg` from `socket` to `server`; returns the replies that come within 500 ms.
fn exchange(socket: &UdpSocket, server: SocketAddr, msg: &Message) -> Vec<Vec<u8>> {
    socket.send_to(&msg.encode(), server).expect("send");
    socket
        .set_read_timeout(Some(Duration::from_millis(100)))
        .expect("timeout");
    let mut replies = Vec::new();
    let until = Instant::now() + Duration::from_millis(500);
    let mut buf = [0u8; 2048];
    while Instant::now() < until {
        if let Ok((n, from)) = socket.recv_from(&mut buf)
            && from == server
        {
            replies.push(buf[..n].to_vec());
        }
    }
    replies
}

fn get(path: &str, mid: u16) -> Message {
    let mut msg = Message::empty(Type::Con, mid);
    msg.code = Code::GET;
    msg.token = Token::new(&[1, 2, 3, mid as u8]).unwrap_or_default();
    msg.options.set_path(path);
    msg
}

#[test]
#[ignore = "off-host: run inside scripts/netns-run (scripts/test.sh does)"]
fn offhost_clients_answer_the_echo_challenge_and_unverified_answers_stay_small() {
    let test = "offhost_clients_answer_the_echo_challenge";
    if !in_namespace(test)
        || !support::available(test, &[Peer::Libcoap, Peer::Libcoap435, Peer::Aiocoap])
    {
        return;
    }
    let dir = TempDir::new("offhost");
    let files = dir.join("files");
    std::fs::create_dir(&files).expect("mkdir");
    let body = random_file(&files.join("five.bin"), 5000, 9);
    let files_arg = files.to_str().expect("UTF-8 path");
    let (_server, addr) = serve_at("[fd00::2]:0", &dir.join("state"), &["--static", files_arg]);
    let uri = |path: &str| format!("coap://[fd00::2]:{}{path}", addr.port());

    // A raw client: discovery (1,585 bytes, 42x a request before) gets only the
    // challenge; the same request with the Echo value gets the first block.
    let socket = UdpSocket::bind("[fd00::3]:0").expect("bind fd00::3");
    let request = get("/.well-known/core", 1);
    let replies = exchange(&socket, addr, &request);
    let sent = request.encode().len();
    let got: usize = replies.iter().map(Vec::len).sum();
    eprintln!(
        "unverified discovery: {sent} B sent, {got} B back ({:.2}x)",
        got as f64 / sent as f64
    );
    assert!(got <= 3 * sent, "{got} B back for a {sent}-byte request");
    let challenge = Message::decode(&replies[0]).expect("a CoAP reply");
    assert_eq!(challenge.code, Code::UNAUTHORIZED);
    let echo = challenge
        .options
        .first(OptionNumber::ECHO)
        .expect("an Echo option")
        .to_vec();
    let mut again = get("/.well-known/core", 2);
    again.options.set(OptionNumber::ECHO, &echo);
    let replies = exchange(&socket, addr, &again);
    let answer = Message::decode(&replies[0]).expect("a CoAP reply");
    assert_eq!(answer.code, Code::CONTENT);
    assert!(answer.options.block2().is_some_and(|b| b.more));
    // Verified now: the next request is answered without an Echo.
    let replies = exchange(&socket, addr, &get("/.well-known/core", 3));
    assert_eq!(
        Message::decode(&replies[0]).expect("reply").code,
        Code::CONTENT
    );

    // libcoap's clients (4.3.1 and 4.3.5) repeat the request with the Echo value.
    let out = dir.join("libcoap435.bin");
    let lc435 = support::libcoap435("coap-client");
    let f = Proc::run(
        lc435.to_str().expect("UTF-8 path"),
        &[
            "-a",
            "fd00::4",
            "-v",
            "7",
            "-o",
            out.to_str().expect("UTF-8"),
            &uri("/files/five.bin"),
        ],
        LIMIT,
    )
    .expect_success("libcoap 4.3.5 coap-client");
    assert_file_is(&out, &body);
    let log = f.stdout_text();
    assert!(
        log.contains("c:4.01") && log.contains("Echo:"),
        "no Echo exchange: {log}"
    );
    let out = dir.join("libcoap431.bin");
    Proc::run(
        LIBCOAP_CLIENT,
        &[
            "-a",
            "fd00::5",
            "-o",
            out.to_str().expect("UTF-8"),
            &uri("/files/five.bin"),
        ],
        LIMIT,
    )
    .expect_success("libcoap 4.3.1 coap-client-notls");
    assert_file_is(&out, &body);

    // Ours: a POST grab of every camera, from another unverified address.
    let out = dir.join("cloud.bin");
    Proc::run(
        COAPCAM,
        &[
            "post",
            &uri("/cams/pointclouds"),
            "-o",
            out.to_str().expect("UTF-8"),
        ],
        LIMIT,
    )
    .expect_success("coapcam post");
    let n = std::fs::metadata(&out).expect("the cloud").len();
    assert!(n > 1_000_000, "{n} bytes");

    // aiocoap 0.4.17's client does not answer Echo: it gets the challenge, and the
    // whole answer from a server started with --no-address-check.
    let f = Proc::run(AIOCOAP_CLIENT, &[&uri("/files/five.bin")], LIMIT);
    assert!(f.stdout_text().contains("4.01") || f.stderr.contains("4.01"));
    let (_open, open_addr) = serve_at(
        "[fd00::2]:0",
        &dir.join("state-open"),
        &["--no-cameras", "--static", files_arg, "--no-address-check"],
    );
    let f = Proc::run(
        AIOCOAP_CLIENT,
        &[&format!(
            "coap://[fd00::2]:{}/files/five.bin",
            open_addr.port()
        )],
        LIMIT,
    )
    .expect_success("aiocoap-client");
    assert_eq!(f.stdout, body, "aiocoap's body");
}
