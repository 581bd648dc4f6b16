//! Load: 200 concurrent clients (`coapcam bench load`: discovery, uploads, grabs and
//! observers, a quarter each) against one `coapcam serve` for 60 s. Every transfer must
//! complete bit-exact (uploads read back, grabs decoded, discovery identical, each
//! observer holding the final measurement), and the server's peak resident memory must
//! stay under [`RSS_BOUND`].

use std::time::Duration;

use crate::support::{COAPCAM, Proc, TempDir};

/// The server's peak RSS may not pass this. What it holds by its limits: grabs in
/// progress (`--grab-memory 64` MiB here), representations stored for Block2 (256 MiB),
/// uploads being assembled (64 MiB), the deduplication store (16 MiB); plus the program,
/// the scene, each camera's latest frames, the threads' stacks and the allocator's slack.
const RSS_BOUND: u64 = 768 << 20;

/// The server's peak resident set (VmHWM), from /proc.
fn peak_rss(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("/proc status");
    let kb: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmHWM");
    kb * 1024
}

#[test]
fn two_hundred_clients_for_a_minute_lose_nothing_within_the_memory_bound() {
    let dir = TempDir::new("load");
    let files = dir.join("files");
    std::fs::create_dir(&files).expect("mkdir");
    let state = dir.join("state");
    let mut server = Proc::spawn(
        COAPCAM,
        &[
            "serve",
            "--bind",
            "127.0.0.1:0",
            "--static",
            files.to_str().expect("UTF-8 path"),
            "--writable",
            "--state-dir",
            state.to_str().expect("UTF-8 path"),
            "--grab-memory",
            "64",
            "--duration",
            "400",
        ],
    );
    let addr = server.stderr_line(Duration::from_secs(30), |l| {
        l.strip_prefix("coapcam: serving on ")
            .and_then(|a| a.trim().parse::<std::net::SocketAddr>().ok())
    });
    let pid = server.pid();
    let uri = format!("coap://{addr}");
    let load = Proc::run(
        COAPCAM,
        &[
            "bench",
            "load",
            "--server",
            &uri,
            "--clients",
            "200",
            "--duration",
            "60",
        ],
        Duration::from_secs(300),
    );
    let peak = peak_rss(pid);
    let report = load.json();
    eprintln!("{report:#}\nserver peak RSS {} MiB", peak >> 20);
    assert!(
        load.status.success(),
        "bench load failed: {report:#}\n{}",
        load.stderr
    );
    assert_eq!(
        report["failures"].as_array().map(Vec::len),
        Some(0),
        "{report:#}"
    );
    for (role, field) in [
        ("discovery", "mismatches"),
        ("uploads", "mismatches"),
        ("grabs", "undecodable"),
        ("observers", "behind_at_end"),
    ] {
        assert_eq!(report[role][field], 0, "{role} {field}");
    }
    for (role, field) in [
        ("discovery", "requests"),
        ("uploads", "transfers"),
        ("grabs", "depth"),
        ("grabs", "measurements"),
        ("observers", "notifications"),
    ] {
        assert!(
            report[role][field].as_u64().unwrap_or(0) > 0,
            "{role} {field}"
        );
    }
    assert!(
        peak < RSS_BOUND,
        "server peak RSS {} MiB, bound {} MiB",
        peak >> 20,
        RSS_BOUND >> 20
    );
    server.interrupt();
}
