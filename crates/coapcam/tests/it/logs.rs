//! What `coapcam serve` logs: the peer's text escaped, and at `RUST_LOG=info` the cameras
//! arriving and leaving and each configuration change.

use std::net::SocketAddr;

use coap::Code;

use crate::support::{COAPCAM, LIMIT, Proc, SN, TempDir, client, runtime, send};

/// `coapcam serve` on a free port of 127.0.0.1 with `RUST_LOG` set, its address, and the
/// lines it logged before it said where it serves.
fn server(state: &TempDir, rust_log: &str, extra: &[&str]) -> (Proc, SocketAddr, Vec<String>) {
    let dir = state.path().to_str().expect("UTF-8 path");
    let mut args = vec![
        "serve",
        "--bind",
        "127.0.0.1:0",
        "--state-dir",
        dir,
        "--duration",
        "60",
    ];
    args.extend_from_slice(extra);
    let mut p = Proc::spawn_with_env(COAPCAM, &args, &[("RUST_LOG", rust_log)]);
    let before = std::cell::RefCell::new(Vec::new());
    let addr = p.stderr_line(LIMIT, |l| {
        let addr = l
            .strip_prefix("coapcam: serving on ")
            .and_then(|a| a.trim().parse().ok());
        if addr.is_none() {
            before.borrow_mut().push(l.to_owned());
        }
        addr
    });
    (p, addr, before.into_inner())
}

#[test]
fn a_path_with_newlines_and_escapes_cannot_forge_log_lines() {
    let state = TempDir::new("logs-forge");
    let (mut p, addr, _) = server(&state, "info", &["--no-cameras"]);
    let forged = "x\ncoapcam: warning: forged: admin logged in\u{1b}[2J";
    runtime().block_on(async {
        let r = send(&client(), addr, Code::GET, &format!("/{forged}"), b"", None).await;
        assert_eq!(r.code, Code::NOT_FOUND);
    });
    let refused = p.stderr_line(LIMIT, |l| {
        l.contains("request refused").then(|| l.to_owned())
    });
    assert!(
        refused.contains(r"x\ncoapcam: warning: forged"),
        "{refused}"
    );
    assert!(!refused.contains('\u{1b}'), "{refused:?}");
    let finished = p.kill();
    assert!(
        !finished
            .stderr
            .lines()
            .any(|l| l.starts_with("coapcam: warning: forged")),
        "{}",
        finished.stderr
    );
}

/// `GET path` over HTTP/1.1 on a connection of its own: the answer's status line.
fn http_get(addr: SocketAddr, path: &str) -> String {
    use std::io::{Read as _, Write as _};
    let mut stream = std::net::TcpStream::connect(addr).expect("connecting over HTTP");
    stream.set_read_timeout(Some(LIMIT)).expect("timeout");
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .expect("asking");
    let mut answer = String::new();
    stream.read_to_string(&mut answer).expect("the answer");
    answer.lines().next().unwrap_or_default().to_owned()
}

/// Issue 51, item 13: a 4.04 (or any 4.xx) is the answer the client asked for, not a
/// fault of the server: at the default level (warnings) it is not logged, at
/// `RUST_LOG=info` it is; asked directly or through the HTTP proxy (`/hc/`), whose 404 was
/// a server WARN.
#[test]
fn a_client_error_is_no_warning() {
    for (level, logged) in [("warn", false), ("info", true)] {
        let state = TempDir::new("logs-4xx");
        let (mut p, addr, before) = server(&state, level, &["--http", "127.0.0.1:0"]);
        let http: SocketAddr = before
            .iter()
            .find_map(|l| l.strip_prefix("coapcam: HTTP on http://"))
            .and_then(|a| a.split('/').next())
            .and_then(|a| a.parse().ok())
            .unwrap_or_else(|| panic!("no HTTP address in {before:?}"));
        runtime().block_on(async {
            let r = send(&client(), addr, Code::GET, "/nope", b"", None).await;
            assert_eq!(r.code, Code::NOT_FOUND);
            let color = format!("/cams/{SN}/color");
            let r = send(&client(), addr, Code::GET, &color, b"", None).await;
            assert_eq!(r.code, Code::NOT_FOUND, "no frame grabbed yet");
        });
        let status = http_get(http, &format!("/hc/coap://{addr}/nope"));
        assert!(status.starts_with("HTTP/1.1 404"), "{status}");
        // Logged before the answer was sent, if at all.
        let finished = p.kill();
        let refused = finished
            .stderr
            .lines()
            .filter(|l| l.contains("4.04"))
            .collect::<Vec<_>>();
        assert_eq!(
            refused.len(),
            if logged { 3 } else { 0 },
            "{level}: {refused:?}"
        );
        // Information: the commands' prefix and no level (issue 51, item 13: the log's
        // lines had a format of their own).
        assert!(
            refused
                .iter()
                .all(|l| l.starts_with("coapcam: ") && !l.contains("warning")),
            "{refused:?}"
        );
    }
}

#[test]
fn info_logs_cameras_and_configuration_changes() {
    let state = TempDir::new("logs-info");
    let (mut p, addr, before) = server(&state, "info", &[]);
    assert!(
        before
            .iter()
            .any(|l| l.contains("camera connected") && l.contains(SN)),
        "{before:?}"
    );
    runtime().block_on(async {
        let path = format!("/cams/{SN}/application-config");
        let doc = send(&client(), addr, Code::GET, &path, b"", None).await;
        let r = send(&client(), addr, Code::PUT, &path, &doc.payload, None).await;
        assert_eq!(r.code, Code::CHANGED);
    });
    p.stderr_line(LIMIT, |l| {
        (l.contains("application-config") && l.contains("changed")).then_some(())
    });
}
