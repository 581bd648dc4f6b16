//! CoAP over TLS with pre-shared keys (`coaps+tcp`, `coaps+ws`; RFC 8323) end to end:
//! `coapcam serve --bind-tls --bind-wss --psk-file` reached by our own commands through
//! `coaps+tcp://` and `coaps+ws://` URIs (discovery, a 2,764,810-byte color grab in one
//! message, the identity's role deciding a write), a wrong key and a missing key refused;
//! Debian's libcoap 4.3.1 (`coap-client-openssl`, `coap-server-openssl`) over
//! `coaps+tcp`, both directions; and libcoap 4.3.5 built with OpenSSL
//! (`scripts/build-libcoap-openssl.sh`; 4.3.1 has no WebSockets) over `coaps+ws` and
//! `coaps+tcp`, both directions, with small bodies over WebSockets (its WebSocket reader
//! takes messages of at most 1,472 bytes, docs/testing.md).

use std::net::SocketAddr;

use crate::support::{
    self, COAPCAM, LIBCOAP_DTLS_CLIENT, LIMIT, Peer, Proc, SN, TempDir, assert_file_is, random_file,
};

/// The bytes of a 1280x720 color grab in the thesis packet (docs/resources.md).
const COLOR_BYTES: usize = 2_764_810;

const IDENTITIES: &str =
    "# coapcam test identities\nalice secret-of-alice configure\nbob secret-of-bob read\n";

const BOB: [&str; 4] = ["--psk-identity", "bob", "--psk-key", "secret-of-bob"];

/// `coapcam serve` (the built-in synthetic scene, and DIR/files writable at /files) on
/// 127.0.0.1 over TLS and WebSockets over TLS with the test identities: the process and
/// its `coaps+tcp` and `coaps+ws` addresses.
fn serve_tls(dir: &TempDir) -> (Proc, SocketAddr, SocketAddr) {
    let psk = dir.join("psk.txt");
    std::fs::write(&psk, IDENTITIES).expect("writing the identities");
    let files = dir.join("files");
    std::fs::create_dir_all(&files).expect("mkdir files");
    let state = dir.join("state");
    let mut p = Proc::spawn(
        COAPCAM,
        &[
            "serve",
            "--bind",
            "127.0.0.1:0",
            "--bind-tls",
            "127.0.0.1:0",
            "--bind-wss",
            "127.0.0.1:0",
            "--psk-file",
            psk.to_str().expect("UTF-8 path"),
            "--static",
            files.to_str().expect("UTF-8 path"),
            "--writable",
            "--state-dir",
            state.to_str().expect("UTF-8 path"),
            "--duration",
            "120",
        ],
    );
    let tls = p.stderr_line(LIMIT, |l| {
        l.strip_prefix("coapcam: serving coaps+tcp on ")
            .and_then(|a| a.trim().parse().ok())
    });
    let wss = p.stderr_line(LIMIT, |l| {
        l.strip_prefix("coapcam: serving coaps+ws on ")
            .and_then(|a| a.trim().parse().ok())
    });
    (p, tls, wss)
}

/// `coapcam ARGS... KEY...`.
fn ours(args: &[&str], key: &[&str]) -> support::Finished {
    let mut all = args.to_vec();
    all.extend_from_slice(key);
    Proc::run(COAPCAM, &all, LIMIT)
}

#[test]
fn our_commands_reach_serve_bind_tls_and_bind_wss_through_coaps_uris() {
    let dir = TempDir::new("tls-ours");
    let (_server, tls, wss) = serve_tls(&dir);
    let upload = dir.join("up.bin");
    let body = random_file(&upload, 3_000, 11);
    let up = upload.to_str().expect("UTF-8 path");

    for base in [format!("coaps+tcp://{tls}"), format!("coaps+ws://{wss}")] {
        let found = ours(&["discover", &base], &BOB).expect_success("coapcam discover");
        let listed = found.stdout_text();
        assert!(
            listed.contains(&format!("/cams/{SN}/color")),
            "{base}: {listed}"
        );

        let out = dir.join("color.bin");
        let uri = format!("{base}/cams/{SN}/color");
        let out_path = out.to_str().expect("UTF-8 path");
        ours(&["post", &uri, "-o", out_path], &BOB).expect_success("coapcam post color");
        let bytes = std::fs::read(&out).expect("the grab");
        assert_eq!(bytes.len(), COLOR_BYTES, "{base}");
        // The color packet's header: type 1, then width and height (u16, network order).
        assert_eq!(bytes[..5], [1, 0x05, 0x00, 0x02, 0xd0], "{base}");

        // The identity reaches the server's rules: bob may read, not write, even from
        // this machine; alice (configure) may.
        let file = format!("{base}/files/new.bin");
        let f = ours(&["put", &file, "--file", up], &BOB);
        let said = format!("{}{}", f.stdout_text(), f.stderr);
        assert!(said.contains("4.03"), "{base}: {said}");
        let alice = ["--psk-identity", "alice", "--psk-key", "secret-of-alice"];
        ours(&["put", &file, "--file", up], &alice).expect_success("coapcam put as alice");
        assert_file_is(&dir.join("files").join("new.bin"), &body);
        std::fs::remove_file(dir.join("files").join("new.bin")).expect("rm");

        // A wrong key: the handshake fails, and the command says so.
        let wrong = ["--psk-identity", "bob", "--psk-key", "guessed"];
        let f = ours(&["get", &format!("{base}/time"), "--timeout", "10"], &wrong);
        assert_eq!(f.status.code(), Some(1), "{base}: {}", f.stderr);
        assert!(
            f.stderr.contains("TLS handshake failed"),
            "{base}: {}",
            f.stderr
        );
    }

    // No key at all: refused before anything is sent, saying what is missing.
    for (scheme, addr) in [("coaps+tcp", tls), ("coaps+ws", wss)] {
        let f = ours(&["get", &format!("{scheme}://{addr}/time")], &[]);
        assert_eq!(f.status.code(), Some(1), "{}", f.stderr);
        let wanted = format!("{scheme}:// needs a pre-shared key: --psk-identity ID --psk-key KEY");
        assert!(f.stderr.contains(&wanted), "{}", f.stderr);
    }
}

#[test]
fn serve_bind_tls_needs_a_psk_file() {
    let f = Proc::run(
        COAPCAM,
        &["serve", "--no-cameras", "--bind-tls", "127.0.0.1:0"],
        LIMIT,
    );
    assert_eq!(f.status.code(), Some(2), "{}", f.stderr);
    assert!(f.stderr.contains("--psk-file"), "{}", f.stderr);
}

/// libcoap's OpenSSL client as `identity` with `key`.
fn libcoap(identity: &str, key: &str, args: &[&str]) -> support::Finished {
    let mut all = vec!["-u", identity, "-k", key, "-B", "60"];
    all.extend_from_slice(args);
    Proc::run(LIBCOAP_DTLS_CLIENT, &all, LIMIT)
}

#[test]
fn libcoap_client_over_coaps_tcp_grabs_color_and_only_a_configure_identity_writes() {
    let test = "libcoap_client_over_coaps_tcp_grabs_color_and_only_a_configure_identity_writes";
    if !support::available(test, &[Peer::Libcoap]) {
        return;
    }
    let dir = TempDir::new("tls-libcoap");
    let (_server, tls, _) = serve_tls(&dir);

    let core = libcoap(
        "bob",
        "secret-of-bob",
        &[&format!("coaps+tcp://{tls}/.well-known/core")],
    )
    .expect_success("coap-client-openssl GET /.well-known/core over TLS");
    let links = core.stdout_text();
    assert!(links.contains(&format!("</cams/{SN}/color>")), "{links}");

    // libcoap 4.3.1 announces a Max-Message-Size of 8,388,864: the frame comes whole.
    let out = dir.join("color.bin");
    libcoap(
        "bob",
        "secret-of-bob",
        &[
            "-m",
            "post",
            "-o",
            out.to_str().expect("UTF-8 path"),
            &format!("coaps+tcp://{tls}/cams/{SN}/color"),
        ],
    )
    .expect_success("coap-client-openssl POST /cams/SN/color over TLS");
    let bytes = std::fs::read(&out).expect("the grab");
    assert_eq!(bytes.len(), COLOR_BYTES);
    assert_eq!(bytes[..5], [1, 0x05, 0x00, 0x02, 0xd0]);

    let upload = dir.join("up.bin");
    let new = random_file(&upload, 3_000, 12);
    let up = upload.to_str().expect("UTF-8 path");
    let file = format!("coaps+tcp://{tls}/files/new.bin");
    let written = dir.join("files").join("new.bin");
    // A read identity may not write: 4.03.
    let f = libcoap("bob", "secret-of-bob", &["-m", "put", "-f", up, &file]);
    let said = format!("{}{}", f.stdout_text(), f.stderr);
    assert!(said.contains("4.03"), "{said}");
    assert!(!written.exists(), "a read identity wrote");
    // A wrong key gets no session.
    let f = libcoap(
        "alice",
        "guessed",
        &["-B", "5", "-m", "put", "-f", up, &file],
    );
    let said = format!("{}{}", f.stdout_text(), f.stderr);
    assert!(!said.contains("2.01"), "{said}");
    assert!(!written.exists(), "a wrong key wrote");
    // The configure identity writes.
    libcoap("alice", "secret-of-alice", &["-m", "put", "-f", up, &file])
        .expect_success("coap-client-openssl PUT over TLS");
    assert_file_is(&written, &new);
}

#[test]
fn our_client_over_coaps_tcp_against_libcoap_server() {
    let test = "our_client_over_coaps_tcp_against_libcoap_server";
    if !support::available(test, &[Peer::Libcoap]) {
        return;
    }
    let dir = TempDir::new("tls-theirs");
    // Its TLS listener shares the DTLS port, over TCP.
    let (_server, secure) = support::libcoap_dtls_server("shared-key");
    let uri = format!("coaps+tcp://{secure}/example_data");
    let key = ["--psk-identity", "carol", "--psk-key", "shared-key"];
    let upload = dir.join("up.bin");
    let body = random_file(&upload, 5_000, 13);
    let up = upload.to_str().expect("UTF-8 path");
    ours(&["put", &uri, "--file", up], &key).expect_success("coapcam put over TLS");
    let out = dir.join("got.bin");
    let out_path = out.to_str().expect("UTF-8 path");
    ours(&["get", &uri, "-o", out_path], &key).expect_success("coapcam get over TLS");
    assert_file_is(&out, &body);

    let wrong = ["--psk-identity", "carol", "--psk-key", "wrong"];
    let f = ours(&["get", &uri, "--timeout", "10"], &wrong);
    assert_eq!(f.status.code(), Some(1), "{}", f.stderr);
    assert!(f.stderr.contains("TLS handshake failed"), "{}", f.stderr);
}

#[test]
fn libcoap435_client_over_coaps_ws_and_coaps_tcp_reads_serve_bind_wss_and_bind_tls() {
    let test = "libcoap435_client_over_coaps_ws_and_coaps_tcp_reads_serve_bind_wss_and_bind_tls";
    if !support::available(test, &[Peer::Libcoap435Openssl]) {
        return;
    }
    let dir = TempDir::new("tls-libcoap435");
    let (_server, tls, wss) = serve_tls(&dir);
    let client = support::libcoap435_openssl("coap-client");
    let client = client.to_str().expect("UTF-8 path");
    let run = |args: &[&str]| {
        let mut all = vec!["-u", "bob", "-k", "secret-of-bob", "-B", "30"];
        all.extend_from_slice(args);
        Proc::run(client, &all, LIMIT)
    };
    for base in [format!("coaps+ws://{wss}"), format!("coaps+tcp://{tls}")] {
        let core = run(&[&format!("{base}/.well-known/core?rt=coapcam.time")])
            .expect_success("coap-client GET /.well-known/core over TLS");
        let links = core.stdout_text();
        assert!(links.starts_with("</time>"), "{base}: {links}");
        let time = run(&[&format!("{base}/time")]).expect_success("coap-client GET /time");
        let text = time.stdout_text();
        assert!(text.starts_with("{\"unix_us\":"), "{base}: {text}");
        // A wrong key gets nothing.
        let mut wrong = vec!["-u", "bob", "-k", "guessed", "-B", "5"];
        let uri = format!("{base}/time");
        wrong.push(&uri);
        let f = Proc::run(client, &wrong, LIMIT);
        assert!(
            !f.stdout_text().contains("unix_us"),
            "{base}: {}",
            f.stdout_text()
        );
    }
}

#[test]
fn our_client_over_coaps_ws_and_coaps_tcp_against_libcoap435_server() {
    let test = "our_client_over_coaps_ws_and_coaps_tcp_against_libcoap435_server";
    if !support::available(test, &[Peer::Libcoap435Openssl]) {
        return;
    }
    let dir = TempDir::new("tls-theirs435");
    let (_server, tls, wss) = support::libcoap435_tls_server("shared-key");
    let key = ["--psk-identity", "carol", "--psk-key", "shared-key"];
    for (n, base) in [format!("coaps+ws://{wss}"), format!("coaps+tcp://{tls}")]
        .iter()
        .enumerate()
    {
        // Under the 1,472 bytes its WebSocket reader takes.
        let upload = dir.join(&format!("up-{n}.bin"));
        let body = random_file(&upload, 1_000, 14 + n as u64);
        let up = upload.to_str().expect("UTF-8 path");
        let uri = format!("{base}/example_data");
        ours(&["put", &uri, "--file", up], &key).expect_success("coapcam put over TLS");
        let out = dir.join(&format!("got-{n}.bin"));
        let out_path = out.to_str().expect("UTF-8 path");
        ours(&["get", &uri, "-o", out_path], &key).expect_success("coapcam get over TLS");
        assert_file_is(&out, &body);

        let wrong = ["--psk-identity", "carol", "--psk-key", "wrong"];
        let f = ours(&["get", &uri, "--timeout", "10"], &wrong);
        assert_eq!(f.status.code(), Some(1), "{base}: {}", f.stderr);
        assert!(
            f.stderr.contains("TLS handshake failed"),
            "{base}: {}",
            f.stderr
        );
    }
}
