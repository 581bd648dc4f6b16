//! `coapcam get -o FILE`: the body is streamed into a temporary file beside FILE and
//! renamed to FILE only when it arrived whole.

use std::net::{SocketAddr, UdpSocket};
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread;
use std::time::Duration;

use bytes::Bytes;
use coap::{BlockOpt, Code, Message, OptionNumber, Type};

use crate::support::LIMIT;
use crate::support::{self, COAPCAM, Proc, TempDir};

fn get(uri: &str, out: &Path, extra: &[&str]) -> support::Finished {
    let mut args = vec!["get", uri, "-o", out.to_str().expect("UTF-8 path")];
    args.extend_from_slice(extra);
    Proc::run(COAPCAM, &args, LIMIT)
}

/// Names in `dir` other than `keep`.
fn leftovers(dir: &Path, keep: &str) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("listing {}: {e}", dir.display()))
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter(|n| n != keep)
        .collect()
}

#[test]
fn get_o_streams_a_10_mb_body_into_file_bit_exact_and_replaces_an_old_file() {
    let served = TempDir::new("get-served");
    let want = support::random_file(&served.join("big.bin"), 10_032_012, 11);
    let (_server, addr) = support::our_server(served.path(), false);
    let out_dir = TempDir::new("get-out");
    let out = out_dir.join("big.bin");
    std::fs::write(&out, b"an older file").expect("writing the old file");
    get(
        &format!("coap://{addr}/files/big.bin"),
        &out,
        &["--block-size", "1024"],
    )
    .expect_success("coapcam get -o");
    support::assert_file_is(&out, &want);
    assert_eq!(leftovers(out_dir.path(), "big.bin"), Vec::<String>::new());
}

/// What the fake server does after `blocks` good blocks of 1024 bytes.
#[derive(Clone, Copy)]
enum Then {
    /// Answers with another ETag.
    ChangeEtag,
    /// Stops answering.
    Silence,
    /// Answers 5.03 Service Unavailable with a diagnostic.
    Unavailable,
    /// Goes on (ETag 1), every block announcing this Size2 instead of the body's 1 MB.
    Size2(u32),
}

/// A server that answers GETs block by block (ETag 1, always more to come) for `blocks`
/// blocks, then misbehaves; it stops when the returned flag is set.
fn misbehaving_server(blocks: u32, then: Then) -> (SocketAddr, Arc<AtomicBool>) {
    let socket = UdpSocket::bind("127.0.0.1:0").expect("binding the fake server");
    socket
        .set_read_timeout(Some(Duration::from_millis(100)))
        .expect("read timeout");
    let addr = socket.local_addr().expect("local address");
    let stop = Arc::new(AtomicBool::new(false));
    let stopped = stop.clone();
    thread::spawn(move || {
        let mut buf = [0u8; 2048];
        while !stopped.load(Ordering::SeqCst) {
            let Ok((n, peer)) = socket.recv_from(&mut buf) else {
                continue;
            };
            let Ok(req) = Message::decode(&buf[..n]) else {
                continue;
            };
            let num = req.options.block2().map_or(0, |b| b.num);
            let etag = match then {
                _ if num < blocks => 1u8,
                Then::Size2(_) => 1,
                Then::ChangeEtag => 2,
                Then::Silence => continue,
                Then::Unavailable => {
                    let reply = Message {
                        ty: Type::Ack,
                        code: Code::SERVICE_UNAVAILABLE,
                        message_id: req.message_id,
                        token: req.token,
                        options: coap::Options::new(),
                        payload: Bytes::from_static(b"the camera is busy"),
                    };
                    let _ = socket.send_to(&reply.encode(), peer);
                    continue;
                }
            };
            let mut options = coap::Options::new();
            options.set(OptionNumber::ETAG, vec![etag]);
            let size2 = match then {
                Then::Size2(size2) => size2,
                _ => 1024 * 1000,
            };
            options.set_uint(OptionNumber::SIZE2, size2);
            let more = true;
            options.set_block(OptionNumber::BLOCK2, BlockOpt { num, more, szx: 6 });
            let reply = Message {
                ty: Type::Ack,
                code: Code::CONTENT,
                message_id: req.message_id,
                token: req.token,
                options,
                payload: Bytes::from(vec![0x5a; 1024]),
            };
            let _ = socket.send_to(&reply.encode(), peer);
        }
    });
    (addr, stop)
}

fn check_interrupted(then: Then, what: &str) {
    let (addr, stop) = misbehaving_server(20, then);
    let dir = TempDir::new("get-interrupted");
    let fresh = dir.join("fresh.bin");
    let f = get(
        &format!("coap://{addr}/body"),
        &fresh,
        &["--block-size", "1024", "--timeout", "2"],
    );
    assert!(
        !f.status.success(),
        "{what}: exit 0 with an incomplete body"
    );
    assert!(!fresh.exists(), "{what}: a truncated file was left behind");
    assert_eq!(leftovers(dir.path(), "fresh.bin"), Vec::<String>::new());

    // A file that was there before the failed transfer is left as it was.
    let old = dir.join("old.bin");
    std::fs::write(&old, b"keep me").expect("writing the old file");
    let f = get(
        &format!("coap://{addr}/body"),
        &old,
        &["--block-size", "1024", "--timeout", "2"],
    );
    assert!(
        !f.status.success(),
        "{what}: exit 0 with an incomplete body"
    );
    support::assert_file_is(&old, b"keep me");
    assert_eq!(leftovers(dir.path(), "old.bin"), Vec::<String>::new());
    stop.store(true, Ordering::SeqCst);
}

#[test]
fn get_o_whose_etag_changes_mid_transfer_fails_and_leaves_no_file() {
    check_interrupted(Then::ChangeEtag, "ETag change");
}

#[test]
fn get_o_from_a_server_that_stops_answering_fails_and_leaves_no_file() {
    check_interrupted(Then::Silence, "silent server");
}

#[test]
fn get_from_a_server_whose_size2_ends_within_the_first_block_fails_at_once() {
    // Block 0 says more is to come and Size2 says the body ends within it: the client
    // fails on the contradiction, not after --timeout.
    for size2 in [1, 1024] {
        let (addr, stop) = misbehaving_server(1000, Then::Size2(size2));
        let dir = TempDir::new("get-size2");
        let out = dir.join("out.bin");
        let uri = format!("coap://{addr}/body");
        let flags = ["--block-size", "1024", "--timeout", "20"];
        for to_file in [true, false] {
            let f = if to_file {
                get(&uri, &out, &flags)
            } else {
                let mut args = vec!["get", uri.as_str()];
                args.extend_from_slice(&flags);
                Proc::run(COAPCAM, &args, LIMIT)
            };
            assert!(!f.status.success(), "Size2 {size2}: exit 0");
            assert!(
                f.stderr.contains("Size2"),
                "Size2 {size2}, to a file {to_file}: {}",
                f.stderr
            );
            assert!(!out.exists(), "a file was left behind");
        }
        stop.store(true, Ordering::SeqCst);
    }
}

#[test]
fn get_o_writes_through_a_link_and_into_a_pipe_without_replacing_them() {
    let served = TempDir::new("get-served-special");
    let want = support::random_file(&served.join("mid.bin"), 300_000, 12);
    let (_server, addr) = support::our_server(served.path(), false);
    let uri = format!("coap://{addr}/files/mid.bin");
    let dir = TempDir::new("get-special");

    // A symbolic link to a regular file: the file gets the body, the link stays a link.
    let real = dir.join("real.bin");
    std::fs::write(&real, b"old").expect("writing the linked file");
    let link = dir.join("link.bin");
    std::os::unix::fs::symlink(&real, &link).expect("symlink");
    get(&uri, &link, &[]).expect_success("coapcam get -o LINK");
    support::assert_file_is(&real, &want);
    let meta = std::fs::symlink_metadata(&link).expect("link metadata");
    assert!(meta.file_type().is_symlink(), "the link was replaced");

    // A named pipe (like /dev/stdout or /dev/null, not a regular file): written into
    // directly, never replaced.
    let fifo = dir.join("pipe");
    let made = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .expect("running mkfifo");
    assert!(made.success(), "mkfifo failed");
    let reader = {
        let fifo = fifo.clone();
        thread::spawn(move || std::fs::read(&fifo).expect("reading the pipe"))
    };
    get(&uri, &fifo, &[]).expect_success("coapcam get -o PIPE");
    let got = reader.join().expect("reader thread");
    support::assert_same(&got, &want, "body through the pipe");
    let meta = std::fs::symlink_metadata(&fifo).expect("pipe metadata");
    assert!(
        std::os::unix::fs::FileTypeExt::is_fifo(&meta.file_type()),
        "the pipe was replaced"
    );
    let mut left = leftovers(dir.path(), "real.bin");
    left.sort();
    assert_eq!(left, ["link.bin", "pipe"]);
}

/// `coapcam get -o FILE` stopped by `signal` while the body arrives: the temporary file
/// goes, FILE was never created, and the exit status is 128 + the signal's number.
fn check_signal(signal: &str, status: i32) {
    let (addr, stop) = misbehaving_server(20, Then::Silence);
    let dir = TempDir::new(&format!("get-{signal}"));
    let out = dir.join("body.bin");
    let mut child = std::process::Command::new(COAPCAM)
        .args(["get", &format!("coap://{addr}/body"), "-o"])
        .arg(&out)
        .args(["--block-size", "1024", "--timeout", "60"])
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("coapcam get");
    // The temporary file appears when the transfer starts; the server's 20 blocks take
    // milliseconds (the file is written through a buffer), then it falls silent and the
    // client waits for the 21st.
    let deadline = std::time::Instant::now() + LIMIT;
    while leftovers(dir.path(), "body.bin").is_empty() {
        if let Ok(Some(status)) = child.try_wait() {
            panic!("coapcam get ended early ({status})");
        }
        assert!(
            std::time::Instant::now() < deadline,
            "no part file appeared"
        );
        thread::sleep(Duration::from_millis(20));
    }
    thread::sleep(Duration::from_millis(300));
    let killed = std::process::Command::new("kill")
        .args([&format!("-{signal}"), &child.id().to_string()])
        .status()
        .expect("kill");
    assert!(killed.success());
    let finished = child.wait_with_output().expect("its end");
    stop.store(true, Ordering::SeqCst);
    let stderr = String::from_utf8_lossy(&finished.stderr);
    assert_eq!(finished.status.code(), Some(status), "{stderr}");
    assert!(!out.exists());
    assert_eq!(leftovers(dir.path(), "body.bin"), Vec::<String>::new());
}

#[test]
fn get_o_stopped_by_sigint_or_sigterm_leaves_no_part_file() {
    check_signal("INT", 130);
    check_signal("TERM", 143);
}

#[test]
fn an_error_response_in_the_middle_of_a_transfer_is_reported_as_itself() {
    let (addr, stop) = misbehaving_server(5, Then::Unavailable);
    let dir = TempDir::new("get-unavailable");
    let out = dir.join("body.bin");
    let f = get(
        &format!("coap://{addr}/body"),
        &out,
        &["--block-size", "1024"],
    );
    stop.store(true, Ordering::SeqCst);
    assert_eq!(f.status.code(), Some(3), "{}", f.stderr);
    assert!(
        f.stderr.contains("5.03") && f.stderr.contains("the camera is busy"),
        "{}",
        f.stderr
    );
    assert!(!out.exists());
    assert_eq!(leftovers(dir.path(), "body.bin"), Vec::<String>::new());
}

#[test]
fn get_remembers_the_servers_round_trip_for_the_next_process_unless_turned_off() {
    let served = TempDir::new("get-rtt-served");
    support::random_file(&served.join("small.bin"), 3000, 5);
    let (_server, addr) = support::our_server(served.path(), false);
    let uri = format!("coap://{addr}/files/small.bin");
    let out_dir = TempDir::new("get-rtt-out");
    let out = out_dir.join("small.bin");
    let cache = TempDir::new("get-rtt-cache");
    let args = ["get", uri.as_str(), "-o", out.to_str().expect("UTF-8 path")];
    let home = cache.path().to_str().expect("UTF-8 path");
    let file = cache.join("coapcam").join("rtt.json");
    for (switch, kept) in [("off", false), ("on", true)] {
        let mut p = Proc::spawn_with_env(
            COAPCAM,
            &args,
            &[("XDG_CACHE_HOME", home), ("COAPCAM_RTT_CACHE", switch)],
        );
        p.wait(LIMIT)
            .unwrap_or_else(|| panic!("get did not finish"))
            .expect_success("coapcam get");
        assert_eq!(file.exists(), kept, "COAPCAM_RTT_CACHE={switch}");
    }
    let text = std::fs::read_to_string(&file).expect("the cache file");
    let cache: serde_json::Value = serde_json::from_str(&text).expect("JSON");
    let entry = &cache[addr.ip().to_string()];
    assert!(entry["srtt_us"].as_u64().is_some_and(|us| us > 0), "{text}");
    assert!(entry["written_unix_s"].as_u64().is_some(), "{text}");
}
