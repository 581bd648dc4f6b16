//! `coapcam serve` stops cleanly on SIGTERM and SIGINT: exit status 0, well before the
//! `--duration` (120 s) that would stop it otherwise, even while it hashes a large file.

use std::process::Command;
use std::time::{Duration, Instant};

use coap::Code;

use crate::support::{self, COAPCAM, Proc};
use crate::support::{LIMIT, SN, TempDir, client, runtime, send, serve};

/// Longest wait for the process to exit; far below the server's 120 s `--duration`.
const EXIT_BOUND: Duration = Duration::from_secs(30);

#[test]
fn serve_exits_with_status_0_on_sigterm_and_sigint() {
    for signal in ["TERM", "INT"] {
        let state = TempDir::new(&format!("signal-{signal}"));
        let (mut server, addr) = serve(state.path());
        runtime().block_on(async {
            let r = send(
                &client(),
                addr,
                Code::GET,
                &format!("/cams/{SN}/depth-settings"),
                b"",
                None,
            )
            .await;
            assert_eq!(r.code, Code::CONTENT, "serving before SIG{signal}");
        });
        let pid = server.process().id().to_string();
        let sent = Command::new("kill")
            .args(["-s", signal, &pid])
            .status()
            .expect("running kill");
        assert!(sent.success(), "kill -s {signal} {pid}");
        let deadline = Instant::now() + EXIT_BOUND;
        let status = loop {
            match server.process().try_wait().expect("waiting for coapcam") {
                Some(status) => break status,
                None if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(20)),
                None => panic!("coapcam serve still runs {EXIT_BOUND:?} after SIG{signal}"),
            }
        };
        assert_eq!(status.code(), Some(0), "SIG{signal}: {status}");
    }
}

#[test]
fn a_file_being_hashed_holds_up_neither_requests_nor_the_stop() {
    let dir = TempDir::new("signal-hashing");
    std::fs::write(dir.join("small.txt"), b"small").expect("writing small.txt");
    let (mut server, addr) = support::our_server(dir.path(), false);
    // Sparse: it takes no disk space, but its ETag means reading and hashing 64 GiB, far
    // longer than this test runs. It is routed once hashed.
    std::fs::File::create(dir.join("huge.bin"))
        .and_then(|f| f.set_len(64 << 30))
        .expect("creating a sparse huge.bin");
    // A rescan (every 200 ms) is hashing it by now.
    std::thread::sleep(Duration::from_secs(1));
    let small = Proc::run(
        COAPCAM,
        &["get", &format!("coap://{addr}/files/small.txt")],
        LIMIT,
    )
    .expect_success("GET while a file is hashed");
    assert_eq!(small.stdout_text().trim_end(), "small");
    let links = Proc::run(COAPCAM, &["discover", &format!("coap://{addr}")], LIMIT)
        .expect_success("discover while a file is hashed");
    let links = links.stdout_text();
    assert!(links.contains("</files/small.txt>"), "{links}");
    assert!(
        !links.contains("huge.bin"),
        "the GET waited until huge.bin was hashed: {links}"
    );
    let stopped = server.interrupt();
    assert_eq!(stopped.status.code(), Some(0), "{}", stopped.stderr);
}

#[test]
fn a_server_started_after_kill_9_removes_the_temporary_files_left_behind() {
    let state = TempDir::new("leftovers");
    let path = format!("/cams/{SN}/application-config");
    let (mut server, addr) = serve(state.path());
    let before = runtime().block_on(async {
        let c = client();
        let doc = send(&c, addr, Code::GET, &path, b"", None).await.payload;
        let r = send(&c, addr, Code::PUT, &path, &doc, None).await;
        assert_eq!(r.code, Code::CHANGED);
        doc
    });
    let pid = server.process().id();
    server.process().kill().expect("kill -9");
    let _ = server.process().wait();
    // What ten writes cut off by the kill leave: their temporary files; and one of a
    // process that still runs (this test), which must stay.
    let dir = state.path().join(SN);
    let left: Vec<_> = (0..10)
        .map(|n| dir.join(format!(".application-config.json.{pid}.{n}.tmp")))
        .collect();
    for file in &left {
        std::fs::write(file, b"{ half a docum").expect("a leftover");
    }
    let live = dir.join(format!(".color-settings.json.{}.0.tmp", std::process::id()));
    std::fs::write(&live, b"{").expect("a live writer's file");

    let (_server, addr) = serve(state.path());
    for file in &left {
        assert!(!file.exists(), "{} is still there", file.display());
    }
    assert!(
        live.exists(),
        "a running process's temporary file was removed"
    );
    let doc = runtime().block_on(async {
        send(&client(), addr, Code::GET, &path, b"", None)
            .await
            .payload
    });
    assert_eq!(doc, before, "the stored document is intact");
}

#[test]
fn serve_runs_with_a_fixed_malloc_threshold_so_its_limits_hold() {
    let state = TempDir::new("malloc");
    let (mut server, _addr) = serve(state.path());
    let pid = server.process().id();
    let environ = std::fs::read(format!("/proc/{pid}/environ")).expect("the environment");
    let vars: Vec<&[u8]> = environ.split(|b| *b == 0).collect();
    assert!(
        vars.contains(&&b"MALLOC_MMAP_THRESHOLD_=131072"[..]),
        "glibc's mmap threshold is not fixed: freed frames stay resident"
    );
}
