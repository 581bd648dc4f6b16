//! Interop with libcoap 4.3.1 (Debian libcoap3-bin) and aiocoap (PyPI), both directions:
//! our client (`coapcam get|put|post|delete|discover`) against their servers
//! (`coap-server-notls`, `tests/peers/aiocoap_server.py`), and their clients
//! (`coap-client-notls`, `aiocoap-client`) against ours (`coapcam serve --static`).
//!
//! Each test: discovery with a filter; GET, PUT, POST, DELETE; a 10,032,012-byte Block2
//! download, bit-exact; a 3,500-byte Block1 upload, checked bit-exact on the server side;
//! NON requests; Observe with 5 notifications; a transfer through `coapcam netem` at 10 %
//! loss, bit-exact.
//!
//! The 10 % loss transfers carry the full 2,764,810 bytes. With RFC 7252's default
//! ACK_TIMEOUT of 2 s every stop-and-wait client waits 2-3 s per lost datagram: 2,701
//! exchanges at 10 % loss each way lose ~19 % of them, ~25-35 minutes. Our client is
//! therefore run with `--ack-timeout-ms 10` (the transmission parameters are configurable,
//! RFC 7252 §4.8, and a loopback round trip is well under a millisecond): ~20 s. Their
//! clients have no such setting, so their 2,764,810-byte runs are `#[ignore]`d (run them
//! with `cargo test -p coapcam --test it -- --ignored interop::`), and the default run
//! carries a 24,576-byte body through the same 10 % loss in their direction.
//!
//! Peers missing: the test fails in CI (`CI=true`), and is skipped with a loud message
//! locally (see `support::available`).

use std::path::Path;
use std::thread;
use std::time::Duration;

use crate::support::{
    self, AIOCOAP_CLIENT, COAPCAM, LIBCOAP_CLIENT, Peer, Proc, Station, TempDir, assert_file_is,
    assert_same, random_file, station,
};

const BIG: usize = 10_032_012;
const UPLOAD: usize = 3_500;
const LOSSY_FULL: usize = 2_764_810;
const LOSSY_SMALL: usize = 24_576;
const LOSS: f64 = 0.1;

/// Bound of a quick exchange.
const QUICK: Duration = Duration::from_secs(20);
/// Bound of a 10 MB transfer (aiocoap's client takes ~30 s: it reassembles with `bytes +=`).
const BULK: Duration = Duration::from_secs(120);
/// Bound of a small transfer at 10 % loss (a lost exchange costs 2-3 s, a doubly lost 6-9 s).
const LOSSY: Duration = Duration::from_secs(150);
/// Bound of a 2,764,810-byte transfer at 10 % loss with their clients' 2 s ACK timeout
/// (~25-35 min expected).
const LOSSY_LONG: Duration = Duration::from_secs(3600);
/// Bound of a 2,764,810-byte transfer at 10 % loss with our client's 10 ms ACK timeout.
const LOSSY_FAST: Duration = Duration::from_secs(300);
/// Our client's ACK timeout through netem (RFC 7252 §4.8 lets it be set to the link).
const FAST_ACK: &[&str] = &["--block-size", "1024", "--ack-timeout-ms", "10"];

fn secs(d: Duration) -> String {
    d.as_secs().to_string()
}

/// Our client's verb, e.g. `coapcam get URI ARGS...`, bounded by `limit`.
fn ours(verb: &str, uri: &str, args: &[&str], limit: Duration) -> support::Finished {
    let timeout = secs(limit.saturating_sub(Duration::from_secs(5)));
    let mut all = vec![verb, uri, "--timeout", &timeout];
    all.extend_from_slice(args);
    Proc::run(COAPCAM, &all, limit)
}

/// `coapcam get URI -o FILE`, must succeed; returns the body.
fn our_get(uri: &str, out: &Path, args: &[&str], limit: Duration) -> Vec<u8> {
    let mut all = vec!["-o", out.to_str().expect("UTF-8 path")];
    all.extend_from_slice(args);
    ours("get", uri, &all, limit).expect_success(&format!("coapcam get {uri}"));
    std::fs::read(out).unwrap_or_else(|e| panic!("reading {}: {e}", out.display()))
}

fn code_of(f: &support::Finished) -> String {
    let lines = f.json_lines();
    assert_eq!(lines.len(), 1, "one response expected: {lines:?}");
    lines[0]["code"].as_str().unwrap_or_default().to_string()
}

/// The links of `coapcam discover --query Q`.
fn our_discover(addr: &str, query: &str) -> Vec<String> {
    let f = ours(
        "discover",
        &format!("coap://{addr}"),
        &["--query", query, "--json"],
        QUICK,
    )
    .expect_success("coapcam discover");
    // One JSON object per link, one per line.
    f.json_lines()
        .iter()
        .map(|l| l["target"].as_str().expect("target").to_string())
        .collect()
}

/// `coapcam get URI --observe 5 --json`: the first response and 5 notifications, each with
/// an Observe option, in order. Returns the payloads.
fn our_observe(uri: &str) -> Vec<String> {
    let f = ours("get", uri, &["--observe", "5", "--json"], QUICK)
        .expect_success(&format!("coapcam get {uri} --observe 5"));
    let lines = f.json_lines();
    assert_eq!(
        lines.len(),
        6,
        "the response and 5 notifications: {lines:?}"
    );
    let mut last: Option<u64> = None;
    for l in &lines {
        assert_eq!(l["code"], "2.05", "{l}");
        let seq = l["observe"]
            .as_u64()
            .unwrap_or_else(|| panic!("no Observe option: {l}"));
        if let Some(prev) = last {
            // RFC 7641 §3.4: newer within the 24-bit sequence space.
            let ahead = (seq.wrapping_sub(prev)) & 0xff_ffff;
            assert!(ahead > 0 && ahead < 1 << 23, "Observe {prev} then {seq}");
        }
        last = Some(seq);
    }
    lines
        .iter()
        .map(|l| l["payload"].as_str().unwrap_or_default().to_string())
        .collect()
}

// ---------------------------------------------------------------------------------------
// Our client -> libcoap's coap-server-notls

fn libcoap_put(uri: &str, file: &Path) {
    Proc::run(
        LIBCOAP_CLIENT,
        &[
            "-m",
            "put",
            "-b",
            "1024",
            "-B",
            "60",
            "-f",
            file.to_str().expect("UTF-8 path"),
            uri,
        ],
        BULK,
    )
    .expect_success(&format!("coap-client-notls -m put {uri}"));
}

fn libcoap_get(uri: &str, out: &Path, extra: &[&str], limit: Duration) -> support::Finished {
    let b = secs(limit.saturating_sub(Duration::from_secs(5)));
    let mut args = vec!["-b", "1024", "-B", &b, "-o", out.to_str().expect("UTF-8")];
    args.extend_from_slice(extra);
    args.push(uri);
    Proc::run(LIBCOAP_CLIENT, &args, limit)
}

#[test]
fn our_client_libcoap_server_discovery_filter() {
    if !support::available(
        "our_client_libcoap_server_discovery_filter",
        &[Peer::Libcoap],
    ) {
        return;
    }
    let (_server, addr) = support::libcoap_server();
    let addr = addr.to_string();
    assert_eq!(our_discover(&addr, "rt=ticks"), ["/time"]);
    assert_eq!(our_discover(&addr, "rt=tick*"), ["/time"]);
    assert_eq!(our_discover(&addr, "href=/ex*"), ["/example_data"]);
    let all = our_discover(&addr, "ct=0");
    assert!(all.len() >= 4, "{all:?}");
}

#[test]
fn our_client_libcoap_server_get_put_post_delete() {
    if !support::available(
        "our_client_libcoap_server_get_put_post_delete",
        &[Peer::Libcoap],
    ) {
        return;
    }
    let (_server, addr) = support::libcoap_server();
    let uri = format!("coap://{addr}/interop");
    // libcoap's -d: a PUT to an unknown path creates a dynamic resource (2.01), then
    // replaces it (2.04); POST replaces its body too; DELETE removes it.
    let put = ours("put", &uri, &["--payload", "first", "--json"], QUICK);
    assert_eq!(code_of(&put.expect_success("put")), "2.01");
    let put = ours("put", &uri, &["--payload", "second", "--json"], QUICK);
    assert_eq!(code_of(&put.expect_success("put")), "2.04");
    let get = ours("get", &uri, &[], QUICK).expect_success("get");
    assert_eq!(get.stdout_text(), "second\n");
    let post = ours("post", &uri, &["--payload", "third", "--json"], QUICK);
    assert_eq!(code_of(&post.expect_success("post")), "2.04");
    let get = ours("get", &uri, &[], QUICK).expect_success("get");
    assert_eq!(get.stdout_text(), "third\n");
    let delete = ours("delete", &uri, &["--json"], QUICK);
    assert_eq!(code_of(&delete.expect_success("delete")), "2.02");
    let gone = ours("get", &uri, &[], QUICK);
    assert_eq!(gone.status.code(), Some(3), "{gone:?}");
    assert!(gone.stderr.contains("4.04"), "{gone:?}");
}

#[test]
fn our_client_libcoap_server_block2_10032012_bytes() {
    if !support::available(
        "our_client_libcoap_server_block2_10032012_bytes",
        &[Peer::Libcoap],
    ) {
        return;
    }
    let dir = TempDir::new("lc-block2");
    let body = random_file(&dir.join("big"), BIG, 1);
    let (_server, addr) = support::libcoap_server();
    let uri = format!("coap://{addr}/big");
    libcoap_put(&uri, &dir.join("big"));
    let got = our_get(&uri, &dir.join("got"), &["--block-size", "1024"], BULK);
    assert_same(&got, &body, "10,032,012 bytes from libcoap");
}

#[test]
fn our_client_libcoap_server_block1_3500_bytes() {
    if !support::available(
        "our_client_libcoap_server_block1_3500_bytes",
        &[Peer::Libcoap],
    ) {
        return;
    }
    let dir = TempDir::new("lc-block1");
    let body = random_file(&dir.join("up"), UPLOAD, 2);
    let (_server, addr) = support::libcoap_server();
    let uri = format!("coap://{addr}/up");
    let put = ours(
        "put",
        &uri,
        &[
            "--file",
            dir.join("up").to_str().expect("UTF-8"),
            "--block-size",
            "1024",
            "--json",
        ],
        QUICK,
    );
    assert_eq!(code_of(&put.expect_success("put 3,500 bytes")), "2.01");
    // Read back with libcoap's own client: what the server stored.
    libcoap_get(&uri, &dir.join("back"), &[], QUICK).expect_success("coap-client get");
    assert_file_is(&dir.join("back"), &body);
}

#[test]
fn our_client_libcoap_server_non() {
    if !support::available("our_client_libcoap_server_non", &[Peer::Libcoap]) {
        return;
    }
    let (_server, addr) = support::libcoap_server();
    let uri = format!("coap://{addr}/non");
    let put = ours(
        "put",
        &uri,
        &["--non", "--payload", "non-put", "--json"],
        QUICK,
    );
    assert_eq!(code_of(&put.expect_success("NON put")), "2.01");
    let get = ours("get", &uri, &["--non"], QUICK).expect_success("NON get");
    assert_eq!(get.stdout_text(), "non-put\n");
    let get = ours(
        "get",
        &format!("coap://{addr}/example_data"),
        &["--non", "--json"],
        QUICK,
    );
    assert_eq!(code_of(&get.expect_success("NON get")), "2.05");
}

#[test]
fn our_client_libcoap_server_observe_5() {
    if !support::available("our_client_libcoap_server_observe_5", &[Peer::Libcoap]) {
        return;
    }
    let (_server, addr) = support::libcoap_server();
    // /time notifies every second with the time of day.
    let payloads = our_observe(&format!("coap://{addr}/time"));
    assert!(payloads.iter().all(|p| !p.is_empty()), "{payloads:?}");
}

/// Our client -> netem (10 % loss) -> libcoap server, 2,764,810 bytes, bit-exact.
///
/// Interop difference (libcoap 4.3.1's server): it releases the state of a Block2 transfer
/// (its `lg_xmit`) 93 s (MAX_TRANSMIT_WAIT) after the transfer began, however actively the
/// client is asking for blocks: in RFC 7959 mode `coap_handle_request_send_block` never
/// refreshes `last_sent`. The next block request runs the resource handler again, and the
/// new transfer state carries a new ETag (libcoap numbers them 0x01, 0x02, ...). Trace
/// (`coap-server-notls -v 7`, 2,764,810 bytes, netem seed 1, our client with the default
/// 2 s ACK timeout): "lg_xmit ... initialized" at 06:57:43.027, "released" at
/// 06:59:16.027, initialized again 2 s later, released 93.000 s after that, and so on; the
/// responses went out with ETag 0x01 (125 blocks), 0x02 (125), 0x03 (155), 0x04 (156),
/// 0x05 (73). So no block-wise download from libcoap 4.3.1 that lasts longer than 93 s can
/// complete with a client that checks the ETag (RFC 7959 §2.4): ours restarts from block 0
/// on each change, 4 times, then exits 1 with "representation changed during a block-wise
/// transfer" (after ~490 s); aiocoap's fails with ResourceChanged
/// (anchor measurements, observation 5). Through the window (the default) the transfer
/// takes a few seconds and completes.
#[test]
fn our_client_libcoap_server_netem_10pct_loss_2764810_bytes() {
    let test = "our_client_libcoap_server_netem_10pct_loss_2764810_bytes";
    if !support::available(test, &[Peer::Libcoap]) {
        return;
    }
    let seed = 12;
    let dir = TempDir::new("lc-lossy");
    let body = random_file(&dir.join("body"), LOSSY_FULL, seed);
    let (_server, addr) = support::libcoap_server();
    libcoap_put(&format!("coap://{addr}/body"), &dir.join("body"));
    let (_netem, lossy) = support::netem(addr, LOSS, seed);
    get_windowed(&format!("coap://{lossy}/body"), &dir.join("got"), &body);
}

/// `coapcam get URI -o OUT --json` through a lossy link: the body arrives whole, and
/// through a window (many blocks in flight, lost ones found and asked for again), as
/// `--json` reports it.
fn get_windowed(uri: &str, out: &Path, body: &[u8]) {
    let mut args = vec!["-o", out.to_str().expect("UTF-8"), "--json"];
    args.extend_from_slice(FAST_ACK);
    let f = ours("get", uri, &args, LOSSY_FAST).expect_success(&format!("coapcam get {uri}"));
    assert_file_is(out, body);
    let path = &f.json()["transfer"];
    let count = |k: &str| path[k].as_u64().unwrap_or_default();
    assert!(count("max_window") > 1, "{path}");
    assert!(count("blocks_lost") > 0, "{path}");
}

// ---------------------------------------------------------------------------------------
// RFC 9177 Q-Block with libcoap 4.3.5 (built from source), through netem with 5 % loss

/// Bytes of the Q-Block interop bodies (98 blocks, ten sets of MAX_PAYLOADS).
const Q_BODY: usize = 100_000;
const Q_LOSS: f64 = 0.05;

/// Our client -> libcoap 4.3.5's server (`-L 5`): a Q-Block1 PUT and a Q-Block2 GET of
/// what it stored, through netem with 5 % loss; both bit-exact.
///
/// libcoap 4.3.5's server gives up an upload (4.08 "Too many missing blocks", no list)
/// when a fourth run of received blocks opens: three blocks lost in one set do it (about
/// one body in ten at 5 % loss: seed 21 loses blocks 60, 64 and 68; not seed 23). It
/// asks for missing blocks only after 4 s, so the PUT takes about 4 s per set that lost
/// a block.
#[test]
fn our_client_libcoap435_server_q_block1_and_q_block2_netem_5pct_loss() {
    let test = "our_client_libcoap435_server_q_block1_and_q_block2_netem_5pct_loss";
    if !support::available(test, &[Peer::Libcoap435]) {
        return;
    }
    let dir = TempDir::new("lc435-q");
    let body = random_file(&dir.join("body"), Q_BODY, 21);
    let (_server, addr) = support::libcoap435_server();
    let (_netem, lossy) = support::netem(addr, Q_LOSS, 23);
    let uri = format!("coap://{lossy}/body");
    let file = dir.join("body");
    let put = [
        "--file",
        file.to_str().expect("UTF-8"),
        "--transfer",
        "q-block",
    ];
    ours("put", &uri, &put, LOSSY).expect_success("coapcam put --transfer q-block");
    let out = dir.join("got");
    let get = [
        "-o",
        out.to_str().expect("UTF-8"),
        "--transfer",
        "q-block",
        "--json",
    ];
    let f = ours("get", &uri, &get, LOSSY).expect_success("coapcam get --transfer q-block");
    assert_file_is(&out, &body);
    let path = &f.json()["transfer"];
    assert!(
        path["block_requests"].as_u64().unwrap_or_default() > 1,
        "{path}"
    );
}

/// libcoap 4.3.5's client (`-L 5 -N`) -> netem (5 % loss) -> our server: a Q-Block1 PUT
/// into `--static --writable`, then a Q-Block2 GET of it; both bit-exact.
///
/// Interop difference: the GET goes without loss. Through loss libcoap 4.3.5's client
/// sometimes exits 0 having written one isolated 1,024-byte block instead of the body
/// (2 of 3 local runs and a CI run at 5 %, seed 22; the same against libcoap's own server
/// in the anchor measurements and in `coapcam bench transfer`), a bug on its side. Our
/// server's Q-Block2 through loss is covered by our own client (the simulator tests).
#[test]
fn libcoap435_client_our_server_q_block1_and_q_block2_netem_5pct_loss() {
    let test = "libcoap435_client_our_server_q_block1_and_q_block2_netem_5pct_loss";
    if !support::available(test, &[Peer::Libcoap435]) {
        return;
    }
    let dir = TempDir::new("lc435c-q");
    let files = dir.join("files");
    std::fs::create_dir_all(&files).expect("mkdir");
    let body = random_file(&dir.join("body"), Q_BODY, 22);
    let (_server, addr) = support::our_server(&files, true);
    let (_netem, lossy) = support::netem(addr, Q_LOSS, 22);
    let client = support::libcoap435("coap-client");
    let client = client.to_str().expect("UTF-8");
    let uri = format!("coap://{lossy}/files/body");
    let up = dir.join("body");
    let put = [
        "-L",
        "5",
        "-N",
        "-b",
        "1024",
        "-m",
        "put",
        "-f",
        up.to_str().expect("UTF-8"),
        &uri,
    ];
    Proc::run(client, &put, LOSSY).expect_success("coap-client -L 5 -N put");
    assert_file_is(&files.join("body"), &body);
    let out = dir.join("got");
    let direct = format!("coap://{addr}/files/body");
    let get = [
        "-L",
        "5",
        "-N",
        "-b",
        "1024",
        "-o",
        out.to_str().expect("UTF-8"),
        &direct,
    ];
    Proc::run(client, &get, LOSSY).expect_success("coap-client -L 5 -N get");
    assert_file_is(&out, &body);
}

// ---------------------------------------------------------------------------------------
// Our client -> tests/peers/aiocoap_server.py

#[test]
fn our_client_aiocoap_server_discovery_filter() {
    if !support::available(
        "our_client_aiocoap_server_discovery_filter",
        &[Peer::Aiocoap],
    ) {
        return;
    }
    let (_server, addr) = support::aiocoap_server(None);
    let addr = addr.to_string();
    assert_eq!(our_discover(&addr, "rt=interop.counter"), ["/counter"]);
    assert_eq!(our_discover(&addr, "rt=interop.s*"), ["/store"]);
    assert_eq!(our_discover(&addr, "href=/b*"), ["/big"]);
}

#[test]
fn our_client_aiocoap_server_get_put_post_delete() {
    if !support::available(
        "our_client_aiocoap_server_get_put_post_delete",
        &[Peer::Aiocoap],
    ) {
        return;
    }
    let (_server, addr) = support::aiocoap_server(None);
    let uri = format!("coap://{addr}/store");
    let empty = ours("get", &uri, &[], QUICK);
    assert_eq!(empty.status.code(), Some(3), "{empty:?}");
    assert!(empty.stderr.contains("4.04"), "{empty:?}");
    let put = ours("put", &uri, &["--payload", "first", "--json"], QUICK);
    assert_eq!(code_of(&put.expect_success("put")), "2.01");
    let put = ours("put", &uri, &["--payload", "second", "--json"], QUICK);
    assert_eq!(code_of(&put.expect_success("put")), "2.04");
    let get = ours("get", &uri, &[], QUICK).expect_success("get");
    assert_eq!(get.stdout_text(), "second\n");
    let post = ours("post", &uri, &["--payload", "third", "--json"], QUICK);
    assert_eq!(code_of(&post.expect_success("post")), "2.01");
    let get = ours("get", &uri, &[], QUICK).expect_success("get");
    assert_eq!(get.stdout_text(), "third\n");
    let echo = ours(
        "post",
        &format!("coap://{addr}/echo"),
        &["--payload", "echoed"],
        QUICK,
    );
    assert_eq!(echo.expect_success("post /echo").stdout_text(), "echoed\n");
    let delete = ours("delete", &uri, &["--json"], QUICK);
    assert_eq!(code_of(&delete.expect_success("delete")), "2.02");
    let gone = ours("get", &uri, &[], QUICK);
    assert_eq!(gone.status.code(), Some(3), "{gone:?}");
    assert!(gone.stderr.contains("4.04"), "{gone:?}");
}

#[test]
fn our_client_aiocoap_server_block2_10032012_bytes() {
    if !support::available(
        "our_client_aiocoap_server_block2_10032012_bytes",
        &[Peer::Aiocoap],
    ) {
        return;
    }
    let dir = TempDir::new("aio-block2");
    let body = random_file(&dir.join("big"), BIG, 3);
    let (_server, addr) = support::aiocoap_server(Some(&dir.join("big")));
    let got = our_get(
        &format!("coap://{addr}/big"),
        &dir.join("got"),
        &["--block-size", "1024"],
        BULK,
    );
    assert_same(&got, &body, "10,032,012 bytes from aiocoap");
}

#[test]
fn our_client_aiocoap_server_block1_3500_bytes() {
    if !support::available(
        "our_client_aiocoap_server_block1_3500_bytes",
        &[Peer::Aiocoap],
    ) {
        return;
    }
    let dir = TempDir::new("aio-block1");
    let body = random_file(&dir.join("up"), UPLOAD, 4);
    let (_server, addr) = support::aiocoap_server(None);
    let uri = format!("coap://{addr}/store");
    let put = ours(
        "put",
        &uri,
        &[
            "--file",
            dir.join("up").to_str().expect("UTF-8"),
            "--block-size",
            "1024",
            "--json",
        ],
        QUICK,
    );
    assert_eq!(code_of(&put.expect_success("put 3,500 bytes")), "2.01");
    // Read back with aiocoap's own client: what the server stored.
    let back = Proc::run(
        AIOCOAP_CLIENT,
        &["--no-pretty-print", "--no-color", &uri],
        QUICK,
    )
    .expect_success("aiocoap-client get");
    assert_same(&back.stdout, &body, "3,500 bytes stored by aiocoap");
}

#[test]
fn our_client_aiocoap_server_non() {
    if !support::available("our_client_aiocoap_server_non", &[Peer::Aiocoap]) {
        return;
    }
    let (_server, addr) = support::aiocoap_server(None);
    let uri = format!("coap://{addr}/store");
    let put = ours(
        "put",
        &uri,
        &["--non", "--payload", "non-put", "--json"],
        QUICK,
    );
    assert_eq!(code_of(&put.expect_success("NON put")), "2.01");
    let get = ours("get", &uri, &["--non"], QUICK).expect_success("NON get");
    assert_eq!(get.stdout_text(), "non-put\n");
    let echo = ours(
        "post",
        &format!("coap://{addr}/echo"),
        &["--non", "--payload", "non-echo"],
        QUICK,
    );
    assert_eq!(echo.expect_success("NON post").stdout_text(), "non-echo\n");
}

#[test]
fn our_client_aiocoap_server_observe_5() {
    if !support::available("our_client_aiocoap_server_observe_5", &[Peer::Aiocoap]) {
        return;
    }
    let (_server, addr) = support::aiocoap_server(None);
    // /counter counts up every 250 ms and notifies each step.
    let payloads = our_observe(&format!("coap://{addr}/counter"));
    let counts: Vec<u64> = payloads
        .iter()
        .map(|p| p.parse().unwrap_or_else(|e| panic!("{p:?}: {e}")))
        .collect();
    assert!(counts.windows(2).all(|w| w[0] < w[1]), "{counts:?}");
}

/// Our client -> netem (10 % loss) -> aiocoap server, 2,764,810 bytes, bit-exact.
#[test]
fn our_client_aiocoap_server_netem_10pct_loss_2764810_bytes() {
    let test = "our_client_aiocoap_server_netem_10pct_loss_2764810_bytes";
    if !support::available(test, &[Peer::Aiocoap]) {
        return;
    }
    let seed = 22;
    let dir = TempDir::new("aio-lossy");
    let body = random_file(&dir.join("body"), LOSSY_FULL, seed);
    let (_server, addr) = support::aiocoap_server(Some(&dir.join("body")));
    let (_netem, lossy) = support::netem(addr, LOSS, seed);
    get_windowed(&format!("coap://{lossy}/big"), &dir.join("got"), &body);
}

// ---------------------------------------------------------------------------------------
// Their clients -> our `coapcam serve --no-cameras --static DIR --writable`

/// A client program of a peer, driven the same way in every test below.
#[derive(Clone, Copy)]
enum TheirClient {
    Libcoap,
    Aiocoap,
}

impl TheirClient {
    fn peer(self) -> Peer {
        match self {
            Self::Libcoap => Peer::Libcoap,
            Self::Aiocoap => Peer::Aiocoap,
        }
    }

    /// Runs one request: METHOD URI with an optional payload file or text, NON or CON.
    /// Returns what the client printed; the body is on standard output.
    fn request(
        self,
        method: &str,
        uri: &str,
        payload: Option<Payload<'_>>,
        non: bool,
        limit: Duration,
    ) -> support::Finished {
        let b = secs(limit.saturating_sub(Duration::from_secs(5)));
        let mut args: Vec<String> = Vec::new();
        match self {
            Self::Libcoap => {
                args.extend(["-m", method, "-b", "1024", "-B", &b, "-o", "-"].map(String::from));
                match payload {
                    Some(Payload::Text(t)) => args.extend(["-e".into(), t.into()]),
                    Some(Payload::File(f)) => {
                        args.extend(["-f".into(), f.to_str().expect("UTF-8").into()]);
                    }
                    None => {}
                }
                if non {
                    args.push("-N".into());
                }
            }
            Self::Aiocoap => {
                args.extend(["--no-pretty-print", "--no-color", "-m", method].map(String::from));
                match payload {
                    Some(Payload::Text(t)) => args.extend(["--payload".into(), t.into()]),
                    Some(Payload::File(f)) => {
                        args.extend(["--payload".into(), format!("@{}", f.display())]);
                    }
                    None => {}
                }
                if non {
                    args.push("--non".into());
                }
            }
        }
        args.push(uri.into());
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        Proc::run(self.program(), &args, limit)
    }

    fn program(self) -> &'static str {
        match self {
            Self::Libcoap => LIBCOAP_CLIENT,
            Self::Aiocoap => AIOCOAP_CLIENT,
        }
    }

    fn name(self) -> &'static str {
        match self {
            Self::Libcoap => "libcoap",
            Self::Aiocoap => "aiocoap",
        }
    }
}

#[derive(Clone, Copy)]
enum Payload<'a> {
    Text(&'a str),
    File(&'a Path),
}

/// Our server with a writable static directory holding big.bin, hello.txt and extra.
struct Ours {
    dir: TempDir,
    _server: Proc,
    addr: std::net::SocketAddr,
}

fn start_ours(tag: &str, files: &[(&str, &[u8])]) -> Ours {
    let dir = TempDir::new(tag);
    for (name, body) in files {
        std::fs::write(dir.join(name), body).expect("writing a served file");
    }
    let (server, addr) = support::our_server(dir.path(), true);
    Ours {
        dir,
        _server: server,
        addr,
    }
}

fn their_discovery(client: TheirClient) {
    let ours = start_ours(
        "disc",
        &[("big.bin", b"b"), ("blue.txt", b"c"), ("hello.txt", b"h")],
    );
    let uri = format!("coap://{}/.well-known/core?href=/files/b*", ours.addr);
    let f = client
        .request("get", &uri, None, false, QUICK)
        .expect_success("discovery");
    let text = f.stdout_text();
    let mut targets: Vec<&str> = text
        .trim()
        .split(',')
        .map(|l| l.split(';').next().unwrap_or_default())
        .collect();
    targets.sort_unstable();
    assert_eq!(targets, ["</files/big.bin>", "</files/blue.txt>"], "{text}");
    let uri = format!("coap://{}/.well-known/core?title=hello.txt", ours.addr);
    let f = client
        .request("get", &uri, None, false, QUICK)
        .expect_success("discovery");
    assert!(
        f.stdout_text().trim().starts_with("</files/hello.txt>;"),
        "{}",
        f.stdout_text()
    );
    assert!(!f.stdout_text().contains(','), "{}", f.stdout_text());
}

fn their_get_put_post_delete(client: TheirClient) {
    let ours = start_ours("crud", &[("hello.txt", b"hello\n")]);
    let base = format!("coap://{}", ours.addr);
    let f = client.request(
        "get",
        &format!("{base}/files/hello.txt"),
        None,
        false,
        QUICK,
    );
    assert_eq!(f.expect_success("get").stdout, b"hello\n");

    let new = format!("{base}/files/new.txt");
    client
        .request("put", &new, Some(Payload::Text("put-body")), false, QUICK)
        .expect_success("put");
    assert_file_is(&ours.dir.join("new.txt"), b"put-body");
    let f = client.request("get", &new, None, false, QUICK);
    assert_eq!(f.expect_success("get").stdout, b"put-body");

    client
        .request(
            "post",
            &format!("{base}/files"),
            Some(Payload::Text("post-body")),
            false,
            QUICK,
        )
        .expect_success("post");
    let uploads: Vec<_> = std::fs::read_dir(ours.dir.path())
        .expect("listing the served directory")
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with("upload-"))
        .collect();
    assert_eq!(uploads.len(), 1, "one file created by POST");
    assert_file_is(&uploads[0].path(), b"post-body");

    client
        .request("delete", &new, None, false, QUICK)
        .expect_success("delete");
    assert!(!ours.dir.join("new.txt").exists(), "DELETE removed new.txt");
    let f = client.request("get", &new, None, false, QUICK);
    // libcoap's client exits 0 on 4.04 (it prints the code); aiocoap's exits 1.
    assert!(f.stdout.is_empty(), "{f:?}");
    assert!(f.stderr.contains("4.04"), "{f:?}");
}

fn their_block2_download(client: TheirClient) {
    let body = support::random_bytes(BIG, 5);
    let ours = start_ours("block2", &[("big.bin", &body)]);
    let uri = format!("coap://{}/files/big.bin", ours.addr);
    let f = client
        .request("get", &uri, None, false, BULK)
        .expect_success("10,032,012-byte GET");
    assert_same(
        &f.stdout,
        &body,
        &format!("10,032,012 bytes to {}", client.name()),
    );
}

fn their_block1_upload(client: TheirClient) {
    let ours = start_ours("block1", &[]);
    let src = TempDir::new("block1-src");
    let body = random_file(&src.join("up.bin"), UPLOAD, 6);
    let uri = format!("coap://{}/files/up.bin", ours.addr);
    client
        .request(
            "put",
            &uri,
            Some(Payload::File(&src.join("up.bin"))),
            false,
            QUICK,
        )
        .expect_success("3,500-byte PUT");
    assert_file_is(&ours.dir.join("up.bin"), &body);
}

fn their_non(client: TheirClient) {
    let ours = start_ours("non", &[("hello.txt", b"hello\n")]);
    let base = format!("coap://{}", ours.addr);
    let f = client.request("get", &format!("{base}/files/hello.txt"), None, true, QUICK);
    assert_eq!(f.expect_success("NON get").stdout, b"hello\n");
    client
        .request(
            "put",
            &format!("{base}/files/non.txt"),
            Some(Payload::Text("non-put")),
            true,
            QUICK,
        )
        .expect_success("NON put");
    assert_file_is(&ours.dir.join("non.txt"), b"non-put");
}

/// Their client observes /files/obs.txt while the file is rewritten 8 times, 300 ms apart;
/// our server polls the directory every 200 ms and notifies each change.
///
/// aiocoap's observer is `tests/peers/aiocoap_observe.py` (the aiocoap library), not
/// `aiocoap-client --observe`: aiocoap-client 0.4.17 cancels the observation when the
/// first response arrives and never prints a notification, with any server (checked
/// against libcoap's /time too). See the script's docstring.
fn their_observe(client: TheirClient) {
    let ours = start_ours("observe", &[("obs.txt", b"n0\n")]);
    let uri = format!("coap://{}/files/obs.txt", ours.addr);
    let mut observer = match client {
        TheirClient::Libcoap => Proc::spawn(LIBCOAP_CLIENT, &["-s", "20", "-B", "20", &uri]),
        TheirClient::Aiocoap => Proc::spawn(
            "python3",
            &[&support::script("aiocoap_observe.py"), &uri, "5"],
        ),
    };
    // The first response: the observation is registered.
    observer.stdout_line(QUICK, |l| l.ends_with("n0").then_some(()));
    for n in 1..=8 {
        thread::sleep(Duration::from_millis(300));
        let tmp = ours.dir.join(".obs.tmp");
        std::fs::write(&tmp, format!("n{n}\n")).expect("writing obs.txt");
        std::fs::rename(&tmp, ours.dir.join("obs.txt")).expect("replacing obs.txt");
    }
    let f = match client {
        // libcoap's client observes for its -s seconds: stop it once the last write is
        // seen.
        TheirClient::Libcoap => {
            observer.stdout_line(QUICK, |l| l.ends_with("n8").then_some(()));
            observer.kill()
        }
        // The script ends by itself after 5 notifications.
        TheirClient::Aiocoap => observer
            .wait(QUICK)
            .expect("aiocoap_observe.py did not end")
            .expect_success("aiocoap_observe.py"),
    };
    let printed = f.stdout_text();
    let seen: Vec<u32> = printed
        .lines()
        .filter_map(|l| l.split_whitespace().last()?.strip_prefix('n')?.parse().ok())
        .collect();
    assert_eq!(seen.first(), Some(&0), "{printed}");
    let notified = &seen[1..];
    assert!(notified.len() >= 5, "at least 5 notifications: {printed}");
    assert!(
        notified.windows(2).all(|w| w[0] < w[1]),
        "in order: {seen:?}"
    );
    if matches!(client, TheirClient::Libcoap) {
        assert_eq!(notified.last(), Some(&8), "the last state: {seen:?}");
    }
}

/// Their client -> netem (10 % loss) -> our server, `len` bytes.
fn their_lossy(client: TheirClient, len: usize, seed: u64, limit: Duration) {
    let body = support::random_bytes(len, seed);
    let ours = start_ours("lossy", &[("body.bin", &body)]);
    let (_netem, lossy) = support::netem(ours.addr, LOSS, seed);
    let uri = format!("coap://{lossy}/files/body.bin");
    let f = client
        .request("get", &uri, None, false, limit)
        .expect_success("GET through 10 % loss");
    assert_same(
        &f.stdout,
        &body,
        &format!("body through 10 % loss to {}", client.name()),
    );
}

macro_rules! their_client_tests {
    ($client:expr, $($name:ident => $body:expr;)*) => {
        $(
            #[test]
            fn $name() {
                if !support::available(stringify!($name), &[$client.peer()]) {
                    return;
                }
                $body
            }
        )*
    };
}

their_client_tests! {
    TheirClient::Libcoap,
    libcoap_client_our_server_discovery_filter => their_discovery(TheirClient::Libcoap);
    libcoap_client_our_server_get_put_post_delete => their_get_put_post_delete(TheirClient::Libcoap);
    libcoap_client_our_server_block2_10032012_bytes => their_block2_download(TheirClient::Libcoap);
    libcoap_client_our_server_block1_3500_bytes => their_block1_upload(TheirClient::Libcoap);
    libcoap_client_our_server_non => their_non(TheirClient::Libcoap);
    libcoap_client_our_server_observe_5 => their_observe(TheirClient::Libcoap);
    libcoap_client_our_server_netem_10pct_loss => their_lossy(TheirClient::Libcoap, LOSSY_SMALL, 31, LOSSY);
}

their_client_tests! {
    TheirClient::Aiocoap,
    aiocoap_client_our_server_discovery_filter => their_discovery(TheirClient::Aiocoap);
    aiocoap_client_our_server_get_put_post_delete => their_get_put_post_delete(TheirClient::Aiocoap);
    aiocoap_client_our_server_block2_10032012_bytes => their_block2_download(TheirClient::Aiocoap);
    aiocoap_client_our_server_block1_3500_bytes => their_block1_upload(TheirClient::Aiocoap);
    aiocoap_client_our_server_non => their_non(TheirClient::Aiocoap);
    aiocoap_client_our_server_observe_5 => their_observe(TheirClient::Aiocoap);
    aiocoap_client_our_server_netem_10pct_loss => their_lossy(TheirClient::Aiocoap, LOSSY_SMALL, 41, LOSSY);
}

/// libcoap's client -> netem (10 % loss) -> our server, 2,764,810 bytes.
///
/// Interop difference (libcoap 4.3.1's client, not ours): its RFC 7959 client stops
/// asking for blocks about 93 s (MAX_TRANSMIT_WAIT) after the request, and at its `-B`
/// limit exits 0 with a truncated file (seed 2, measured: 137,216 of 2,764,810 bytes
/// after 150 s; libcoap's client against libcoap's own server stalls the same way, so
/// the stall is the client's). So this asserts what our side owes: every request
/// that reached our server was answered (netem's counters), what arrived is a bit-exact
/// prefix, and the whole body when libcoap does finish.
#[test]
#[ignore = "~150 s: libcoap's client stalls ~93 s into a lossy transfer and exits at its -B limit"]
fn libcoap_client_our_server_netem_10pct_loss_2764810_bytes() {
    if !support::available(
        "libcoap_client_our_server_netem_10pct_loss_2764810_bytes",
        &[Peer::Libcoap],
    ) {
        return;
    }
    let body = support::random_bytes(LOSSY_FULL, 32);
    let ours = start_ours("lossy-lc-full", &[("body.bin", &body)]);
    let (mut netem, lossy) = support::netem(ours.addr, LOSS, 32);
    let uri = format!("coap://{lossy}/files/body.bin");
    let f = TheirClient::Libcoap.request("get", &uri, None, false, Duration::from_secs(155));
    let counters = netem.interrupt_json();
    let up = &counters["up"];
    let down = &counters["down"];
    assert_eq!(
        up["forwarded"], down["received"],
        "our server answers every request it receives: {counters}"
    );
    assert!(f.stdout.len() <= body.len(), "{} bytes", f.stdout.len());
    assert_same(
        &f.stdout,
        &body[..f.stdout.len()],
        "the prefix libcoap received",
    );
    if f.stdout.len() < body.len() {
        eprintln!(
            "INTEROP DIFFERENCE: coap-client-notls exited {} with {} of {} bytes through \
             10 % loss (netem: {counters})",
            f.status,
            f.stdout.len(),
            body.len()
        );
    }
}

#[test]
#[ignore = "~30 min: 2,701 stop-and-wait exchanges at 10 % loss, 2-3 s per loss (RFC 7252 ACK_TIMEOUT)"]
fn aiocoap_client_our_server_netem_10pct_loss_2764810_bytes() {
    if !support::available(
        "aiocoap_client_our_server_netem_10pct_loss_2764810_bytes",
        &[Peer::Aiocoap],
    ) {
        return;
    }
    their_lossy(TheirClient::Aiocoap, LOSSY_FULL, 42, LOSSY_LONG);
}

// ---------------------------------------------------------------------------------------
// libcoap's client -> the camera resource tree of `coapcam serve` (thesis Table 3.1)

/// `coap-client-notls ARGS... URI` with `-v 6`, returning the codes of the responses it
/// printed (`c:2.05`) and what it wrote to standard output.
fn libcoap_codes(args: &[&str], uri: &str) -> (Vec<String>, String) {
    libcoap_codes_of(LIBCOAP_CLIENT, args, uri)
}

/// [`libcoap_codes`] with the `coap-client` at `client`. It waits at most 100 s (`-B`)
/// for the whole answer; one that never came leaves no code, which the callers check.
fn libcoap_codes_of(client: &str, args: &[&str], uri: &str) -> (Vec<String>, String) {
    let mut all = vec!["-v", "6", "-B", "100"];
    all.extend_from_slice(args);
    all.push(uri);
    let f = Proc::run(client, &all, BULK);
    let text = format!("{}{}", f.stdout_text(), f.stderr);
    let codes = text
        .split_whitespace()
        .filter_map(|w| w.strip_prefix("c:"))
        .filter(|c| c.starts_with(['2', '4', '5']) && c.get(1..2) == Some("."))
        .map(str::to_string)
        .collect();
    (codes, text)
}

/// A grab through libcoap 4.3.5's client, block-wise: every answer 2.05. Not 4.3.1's
/// (Debian's): when the grab takes the server longer than its separate-ACK delay (1 s,
/// which a loaded machine passes), the answer is a separate response whose first block
/// 4.3.1 drops ("large body receive internal issue") and then waits out `-B` with an
/// empty file; 4.3.5 follows it.
fn libcoap_grab(uri: &str, out: &Path) {
    let client = support::libcoap435("coap-client");
    let out = out.to_str().expect("UTF-8 path");
    let args = ["-m", "post", "-b", "1024", "-o", out];
    let (codes, text) = libcoap_codes_of(client.to_str().expect("UTF-8 path"), &args, uri);
    assert!(
        !codes.is_empty() && codes.iter().all(|c| c == "2.05"),
        "libcoap's POST {uri}: no whole 2.05 answer within its 100 s:\n{text}"
    );
}

#[test]
fn libcoap_client_drives_the_camera_api() {
    let test = "libcoap_client_drives_the_camera_api";
    if !support::available(test, &[Peer::Libcoap, Peer::Libcoap435]) {
        return;
    }
    let dir = TempDir::new("cams-lc");
    let Station {
        process: server,
        coap: addr,
        ..
    } = station(&dir.join("state"), &[]);
    let sn = "840412060746";
    let base = format!("coap://{addr}");

    // Discovery with a filter finds the camera's grab resource.
    let (codes, text) = libcoap_codes(&[], &format!("{base}/.well-known/core?rt=rgbd.color"));
    assert!(codes.iter().any(|c| c == "2.05"), "{text}");
    assert!(text.contains(&format!("</cams/{sn}/color>")), "{text}");

    // A creation resource: 2.01 with Location-Path for a connected serial, 4.00 otherwise.
    let (codes, text) = libcoap_codes(&["-m", "post", "-e", sn], &format!("{base}/cams/color"));
    assert_eq!(codes, ["2.01"], "{text}");
    assert!(text.contains("Location-Path:cams"), "{text}");
    let (codes, text) = libcoap_codes(
        &["-m", "post", "-e", "12345"],
        &format!("{base}/cams/color"),
    );
    assert_eq!(codes, ["4.00"], "{text}");

    // A grab, block-wise: the thesis packet of a 1280x720 BGR8 frame.
    let color = dir.join("color.bin");
    libcoap_grab(&format!("{base}/cams/{sn}/color"), &color);
    assert_eq!(
        std::fs::metadata(&color).map(|m| m.len()).ok(),
        Some(2_764_810)
    );

    // A bad PUT changes nothing; a good one switches the mode: 921,610 bytes at 640x480.
    let settings = format!("{base}/cams/{sn}/color-settings");
    let (codes, text) = libcoap_codes(&["-m", "put", "-e", r#"{"fps": 7}"#], &settings);
    assert_eq!(codes, ["4.00"], "{text}");
    let vga = r#"{"format": "BGR8", "fps": 30, "width": 640, "height": 480}"#;
    let (codes, text) = libcoap_codes(&["-m", "put", "-e", vga], &settings);
    assert_eq!(codes, ["2.04"], "{text}");
    libcoap_grab(&format!("{base}/cams/{sn}/color"), &color);
    assert_eq!(
        std::fs::metadata(&color).map(|m| m.len()).ok(),
        Some(921_610)
    );

    // Every camera's cloud, merged: 12 + 12 x points.
    let cloud = dir.join("cloud.bin");
    libcoap_grab(&format!("{base}/cams/pointclouds"), &cloud);
    let len = std::fs::metadata(&cloud).map(|m| m.len()).unwrap_or(0);
    assert!(
        len > 12 && (len - 12).is_multiple_of(12),
        "point cloud of {len} bytes"
    );

    // A method Table 3.1 marks "-": 4.05.
    let (codes, text) = libcoap_codes(&["-m", "delete"], &format!("{base}/cams/pointclouds"));
    assert_eq!(codes, ["4.05"], "{text}");
    drop(server);
}
