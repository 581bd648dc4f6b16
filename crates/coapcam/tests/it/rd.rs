//! The resource directory (RFC 9176): `coapcam rd` with `serve --register` on loopback
//! (registered, renewed, removed at shutdown, gone after its lifetime when killed, kept
//! across the directory's restart; simple registration); interop both ways with
//! aiocoap's and libcoap's directories and clients; and, in the private network
//! namespace (`scripts/netns-run`), three servers of a group found through the directory
//! by `discover --rd` and `measure --group --rd`.

use std::net::SocketAddr;
use std::path::Path;
use std::thread;
use std::time::{Duration, Instant};

use coap::{Code, OptionNumber, Request};
use coap_net::{Resource, Router, Server, ServerConfig, handler};
use coap_rd::registrant::{Endpoint, lookup_endpoints};
use coapcam::process::peers;

use crate::support::{
    AIOCOAP_CLIENT, COAPCAM, LIBCOAP_CLIENT, LIMIT, Peer, Proc, TempDir, available, client,
    runtime, station,
};

/// How long a registration may take to show or to go.
const SETTLE: Duration = Duration::from_secs(30);

/// `coapcam rd` on `bind` (port 0: a free one), with the address it reports.
fn start_rd(bind: &str, state: Option<&Path>) -> (Proc, SocketAddr) {
    let mut args = vec!["rd", "--bind", bind, "--duration", "150"];
    let state_text;
    match state {
        Some(dir) => {
            state_text = dir.to_str().expect("UTF-8 path").to_owned();
            args.extend(["--state-dir", &state_text]);
        }
        None => args.push("--no-state"),
    }
    let mut p = Proc::spawn(COAPCAM, &args);
    let addr = p.stderr_line(LIMIT, |l| {
        l.strip_prefix("coapcam: resource directory on ")
            .and_then(|a| a.trim().parse::<SocketAddr>().ok())
    });
    (p, addr)
}

/// `coapcam serve --register coap://RD --rd-ep EP` with more flags, on 127.0.0.1.
fn start_registered(rd: &str, ep: &str, state: &Path, extra: &[&str]) -> (Proc, SocketAddr) {
    let s = station(state, &[&["--register", rd, "--rd-ep", ep], extra].concat());
    (s.process, s.coap)
}

/// The endpoints `rd` lists for `query`.
fn endpoints(rd: SocketAddr, query: &[&str]) -> Vec<Endpoint> {
    let query: Vec<String> = query.iter().map(|q| (*q).to_owned()).collect();
    runtime().block_on(async {
        let c = client();
        lookup_endpoints(&c, rd, &query, LIMIT)
            .await
            .unwrap_or_else(|e| panic!("endpoint lookup at {rd}: {e:#}"))
    })
}

/// The names `rd` lists, sorted.
fn names(rd: SocketAddr) -> Vec<String> {
    let mut names: Vec<String> = endpoints(rd, &[]).into_iter().map(|e| e.ep).collect();
    names.sort();
    names
}

/// Polls until `rd` lists exactly `want` (sorted), at most [`SETTLE`].
fn wait_for_names(rd: SocketAddr, want: &[&str]) {
    let deadline = Instant::now() + SETTLE;
    loop {
        let got = names(rd);
        if got == want {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "{rd} lists {got:?}, not {want:?}, after {SETTLE:?}"
        );
        thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn registrations_are_renewed_removed_at_shutdown_expire_when_killed_and_outlive_a_restart() {
    let dir = TempDir::new("rd-life");
    let (mut rd_proc, rd) = start_rd("127.0.0.1:0", Some(&dir.join("rd-state")));
    let rd_uri = format!("coap://{rd}");
    // A lifetime of 6 s: renewed at 4.5 s.
    let (mut short, short_addr) = start_registered(
        &rd_uri,
        "short",
        &dir.join("s1"),
        &["--no-cameras", "--rd-lifetime", "6"],
    );
    let (mut cams, cams_addr) = start_registered(&rd_uri, "cams", &dir.join("s2"), &[]);
    wait_for_names(rd, &["cams", "short"]);
    let listed = endpoints(rd, &["ep=short"]);
    let first_location = listed[0].link.target.clone();
    assert_eq!(listed[0].addr, Some(short_addr), "{listed:?}");
    assert_eq!(listed[0].link.attr("et"), Some("coapcam.station"));
    // The cameras' resources are registered (resource lookup through the endpoint).
    let f = Proc::run(
        COAPCAM,
        &[
            "discover",
            "--rd",
            &rd_uri,
            "--query",
            "rt=rgbd.color",
            "--json",
        ],
        LIMIT,
    )
    .expect_success("discover --rd");
    let lines = f.json_lines();
    assert_eq!(lines.len(), 1, "{}", f.stdout_text());
    assert_eq!(lines[0]["ep"], "cams");
    assert_eq!(lines[0]["base"], format!("coap://{cams_addr}"));
    // A resource that goes (as a camera's do when it is unplugged) and comes back: the
    // registration follows.
    let color_links = || {
        runtime().block_on(async {
            let c = client();
            let mut get = Request::new(Code::GET, "/rd-lookup/res");
            get.options.push(OptionNumber::URI_QUERY, "ep=cams");
            get.options.push(OptionNumber::URI_QUERY, "rt=rgbd.color");
            get.timeout = Some(LIMIT);
            let r = c.send(rd, get).await.expect("resource lookup");
            coap::link_format::parse(&String::from_utf8_lossy(&r.payload))
                .expect("link-format")
                .len()
        })
    };
    let wait_links = |want: usize| {
        let deadline = Instant::now() + SETTLE;
        while color_links() != want {
            assert!(
                Instant::now() < deadline,
                "the color link count stays not {want}"
            );
            thread::sleep(Duration::from_millis(100));
        }
    };
    let color = format!("coap://{cams_addr}/cams/840412060746/color");
    Proc::run(COAPCAM, &["delete", &color], LIMIT).expect_success("DELETE color");
    wait_links(0);
    Proc::run(
        COAPCAM,
        &[
            "post",
            &format!("coap://{cams_addr}/cams/color"),
            "--payload",
            "840412060746",
        ],
        LIMIT,
    )
    .expect_success("POST /cams/color");
    wait_links(1);
    // Three lifetimes later the short one is still there, at the same location: renewed.
    thread::sleep(Duration::from_secs(18));
    let again = endpoints(rd, &["ep=short"]);
    assert_eq!(
        again.first().map(|e| e.link.target.clone()),
        Some(first_location),
        "{again:?}"
    );
    // Killed, it cannot remove its registration: gone once its lifetime ended.
    short.kill();
    wait_for_names(rd, &["cams"]);
    // Interrupted, it removes its own.
    let f = cams.interrupt();
    assert!(f.status.success(), "{}", f.stderr);
    assert_eq!(names(rd), Vec::<String>::new());
    let f = Proc::run(COAPCAM, &["discover", "--rd", &rd_uri], LIMIT);
    assert_eq!(f.status.code(), Some(4), "{}", f.stderr);
    // A registration outlives the directory's restart (killed itself, the server
    // cannot register again meanwhile).
    let (mut kept, _) = start_registered(
        &rd_uri,
        "kept",
        &dir.join("s3"),
        &["--no-cameras", "--rd-lifetime", "600"],
    );
    wait_for_names(rd, &["kept"]);
    kept.kill();
    rd_proc.interrupt();
    let (_rd_again, rd2) = start_rd(&rd.to_string(), Some(&dir.join("rd-state")));
    assert_eq!(rd2, rd);
    assert_eq!(names(rd), ["kept"]);
}

/// Issue 51, item 12: a second server registering a name another server holds (as the
/// servers of one host on their own addresses do by default, all named after the host)
/// is told that the name is taken and how to choose its own; the first stays listed.
#[test]
fn a_name_another_server_holds_is_refused_with_how_to_choose_one() {
    let dir = TempDir::new("rd-taken");
    let (_rd_proc, rd) = start_rd("127.0.0.1:0", None);
    let rd_uri = format!("coap://{rd}");
    let (_first, first_addr) =
        start_registered(&rd_uri, "dock", &dir.join("s1"), &["--no-cameras"]);
    wait_for_names(rd, &["dock"]);
    // The second on another address of this host (the directory owns a name by address).
    let state = dir.join("s2");
    let mut second = Proc::spawn(
        COAPCAM,
        &[
            "serve",
            "--bind",
            "127.0.0.2:0",
            "--state-dir",
            state.to_str().expect("UTF-8 path"),
            "--duration",
            "150",
            "--no-cameras",
            "--register",
            &rd_uri,
            "--rd-ep",
            "dock",
        ],
    );
    let said = second.stderr_line(LIMIT, |l| l.contains("4.03").then(|| l.to_owned()));
    assert!(
        said.contains("\"dock\" may be taken by another server") && said.contains("--rd-ep NAME"),
        "{said}"
    );
    let listed = endpoints(rd, &["ep=dock"]);
    assert_eq!(listed.len(), 1, "{listed:?}");
    assert_eq!(listed[0].addr, Some(first_addr), "{listed:?}");
    // It goes on trying (after 1, 2, 4 s ...) but warns once (issue 51, item 13: it
    // warned at every retry).
    thread::sleep(Duration::from_secs(4));
    let stopped = second.interrupt();
    let warned = stopped
        .stderr
        .matches("registering with the directory failed")
        .count();
    assert_eq!(warned, 1, "{}", stopped.stderr);
}

/// Issue 51, item 13: at the default level (no `RUST_LOG`) the server said nothing when it
/// registered with the directory or removed its registration, and its log lines were of
/// another format than its own (`coapcam: serving on ...`). Now both are said, and every
/// line it writes begins with `coapcam: `.
#[test]
fn a_registration_is_said_at_the_default_level_in_the_commands_format() {
    let dir = TempDir::new("rd-said");
    let (_rd_proc, rd) = start_rd("127.0.0.1:0", None);
    let (mut server, _) = start_registered(
        &format!("coap://{rd}"),
        "said",
        &dir.join("s"),
        &["--no-cameras"],
    );
    let registered = server.stderr_line(LIMIT, |l| l.contains("registered").then(|| l.to_owned()));
    assert!(
        registered.starts_with("coapcam: registered "),
        "{registered}"
    );
    wait_for_names(rd, &["said"]);
    let stopped = server.interrupt();
    assert!(stopped.status.success(), "{}", stopped.stderr);
    assert!(
        stopped
            .stderr
            .lines()
            .any(|l| l.starts_with("coapcam: registration removed")),
        "{}",
        stopped.stderr
    );
    let other: Vec<&str> = stopped
        .stderr
        .lines()
        .filter(|l| !l.starts_with("coapcam: "))
        .collect();
    assert!(other.is_empty(), "lines of another format: {other:?}");
}

#[test]
fn simple_registration_fetches_the_endpoints_own_links() {
    let (_rd_proc, rd) = start_rd("127.0.0.1:0", None);
    runtime().block_on(async {
        // An endpoint with one resource; it asks from its own socket, and the directory
        // reads its /.well-known/core from that address.
        let router = Router::new();
        router.add(
            "/sensor",
            Resource::new()
                .get(handler(|_| async { coap::Response::new(Code::CONTENT) }))
                .attr("rt", "example.sensor"),
        );
        let (server, r) = simple_registration(router, rd, &["ep=simple", "lt=60"]).await;
        assert_eq!(
            r.code,
            Code::CHANGED,
            "{}",
            String::from_utf8_lossy(&r.payload)
        );
        let c = client();
        let mut lookup = Request::new(Code::GET, "/rd-lookup/res");
        lookup.options.push(OptionNumber::URI_QUERY, "ep=simple");
        lookup.timeout = Some(LIMIT);
        let r = c.send(rd, lookup).await.expect("resource lookup");
        let base = format!("coap://{}", server.local_addrs()[0]);
        assert_eq!(
            String::from_utf8_lossy(&r.payload),
            format!(r#"<{base}/sensor>;rt="example.sensor";anchor="{base}""#)
        );
        // Simple registration takes no base; a document in the POST is refused.
        let mut with_base = Request::new(Code::POST, "/.well-known/rd");
        with_base.options.push(OptionNumber::URI_QUERY, "ep=x");
        with_base
            .options
            .push(OptionNumber::URI_QUERY, "base=coap://[::1]");
        with_base.timeout = Some(LIMIT);
        let r = c.send(rd, with_base).await.expect("answered");
        assert_eq!(r.code, Code::BAD_REQUEST);
    });
}

/// A CoAP server of `router` on 127.0.0.1 and its simple registration (RFC 9176 §5.1)
/// with the directory `rd`, sent from the server's own socket with the query `items`.
async fn simple_registration(
    router: std::sync::Arc<Router>,
    rd: SocketAddr,
    items: &[&str],
) -> (Server, coap::Response) {
    let server = Server::bind(
        &[SocketAddr::from(([127, 0, 0, 1], 0))],
        ServerConfig::default(),
        router,
    )
    .expect("binding");
    let own = server
        .client_for(rd)
        .expect("a client on the server's socket");
    let mut simple = Request::new(Code::POST, "/.well-known/rd");
    for item in items {
        simple.options.push(OptionNumber::URI_QUERY, *item);
    }
    simple.timeout = Some(LIMIT);
    let r = own.send(rd, simple).await.expect("simple registration");
    (server, r)
}

/// A link-format document of `len` bytes that counts the bytes read of it.
struct CountedLinks {
    len: usize,
    read: std::sync::Arc<std::sync::atomic::AtomicUsize>,
}

impl coap::BlockSource for CountedLinks {
    fn len(&self) -> usize {
        self.len
    }

    fn read(&self, range: std::ops::Range<usize>) -> Option<bytes::Bytes> {
        (self.read).fetch_add(range.len(), std::sync::atomic::Ordering::Relaxed);
        // `</r0000000>,` over and over.
        let link = b"</r0000000>,";
        let text: Vec<u8> = range.map(|i| link[i % link.len()]).collect();
        Some(text.into())
    }

    fn held(&self) -> usize {
        0
    }
}

#[test]
fn simple_registration_reads_no_more_of_the_endpoints_links_than_a_registration_may_hold() {
    let (_rd_proc, rd) = start_rd("127.0.0.1:0", None);
    runtime().block_on(async {
        // An endpoint whose /.well-known/core has 4 MiB; a registration's document may
        // have 32 KiB.
        let read = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let router = Router::new();
        let counted = read.clone();
        router.set_around(std::sync::Arc::new(move |_: &coap::IncomingRequest| {
            let read = counted.clone();
            Box::new(move |r: &mut coap::Response| {
                if r.code == Code::CONTENT {
                    let links = CountedLinks { len: 4 << 20, read };
                    *r = coap::Response::new(Code::CONTENT).with_source(links);
                }
            })
        }));
        let (_server, r) = simple_registration(router, rd, &["ep=large"]).await;
        assert_eq!(
            r.code,
            Code::REQUEST_ENTITY_TOO_LARGE,
            "{}",
            String::from_utf8_lossy(&r.payload)
        );
        // Before: the directory fetched all 4 MiB (and then refused the document).
        let read = read.load(std::sync::atomic::Ordering::Relaxed);
        assert!(
            read <= 64 << 10,
            "{read} bytes of the endpoint's links read"
        );
    });
}

/// Whether the directories and clients of both peers are installed (as [`available`]).
fn rd_peers(test: &str) -> bool {
    if !available(test, &[Peer::Libcoap, Peer::Aiocoap]) {
        return false;
    }
    let Some(why) = peers::missing_on_path(&["aiocoap-rd", "coap-rd-notls"]) else {
        return true;
    };
    assert!(
        !std::env::var("CI").is_ok_and(|v| v == "true" || v == "1"),
        "{test}: {why}; scripts/test.sh installs aiocoap and libcoap3-bin"
    );
    eprintln!("\n!!! SKIPPED interop test {test}: {why}\n");
    false
}

/// Runs a peer's client to its end and returns what it printed.
fn peer_get(program: &str, args: &[&str]) -> String {
    let f = Proc::run(program, args, LIMIT).expect_success(program);
    f.stdout_text()
}

/// As [`peer_get`], but a failure (the directory not answering yet: a Python one takes a
/// while to start) is an empty answer, for polling.
fn peer_poll(program: &str, args: &[&str]) -> String {
    let f = Proc::run(program, args, LIMIT);
    if f.status.success() {
        f.stdout_text()
    } else {
        String::new()
    }
}

#[test]
fn aiocoap_and_libcoap_clients_look_up_coapcams_directory() {
    if !rd_peers("aiocoap_and_libcoap_clients_look_up_coapcams_directory") {
        return;
    }
    let dir = TempDir::new("rd-peer-clients");
    let (_rd_proc, rd) = start_rd("127.0.0.1:0", None);
    let rd_uri = format!("coap://{rd}");
    let (_a, a_addr) = start_registered(&rd_uri, "station-a", &dir.join("a"), &["--no-cameras"]);
    let (_b, _) = start_registered(&rd_uri, "station-b", &dir.join("b"), &[]);
    wait_for_names(rd, &["station-a", "station-b"]);
    // Discovery of the directory's interfaces.
    let wkc = peer_get(
        LIBCOAP_CLIENT,
        &[
            "-m",
            "get",
            "-B",
            "10",
            &format!("{rd_uri}/.well-known/core?rt=core.rd*"),
        ],
    );
    for rt in ["core.rd\"", "core.rd-lookup-ep", "core.rd-lookup-res"] {
        assert!(wkc.contains(rt), "{wkc}");
    }
    for (program, extra) in [
        (LIBCOAP_CLIENT, &["-m", "get", "-B", "10"][..]),
        (AIOCOAP_CLIENT, &[][..]),
    ] {
        let mut args = extra.to_vec();
        let eps = format!("{rd_uri}/rd-lookup/ep?et=coapcam.station");
        args.push(&eps);
        let out = peer_get(program, &args);
        assert!(
            out.contains("ep=station-a") && out.contains("ep=station-b"),
            "{program}: {out}"
        );
        let mut args = extra.to_vec();
        let res = format!("{rd_uri}/rd-lookup/res?rt=rgbd.color");
        args.push(&res);
        let out = peer_get(program, &args);
        assert!(
            out.contains("/cams/840412060746/color>"),
            "{program}: {out}"
        );
        assert!(!out.contains(&a_addr.to_string()), "{program}: {out}");
        let mut args = extra.to_vec();
        let page = format!("{rd_uri}/rd-lookup/ep?page=1&count=1");
        args.push(&page);
        let out = peer_get(program, &args);
        assert_eq!(
            out.matches("rt=\"core.rd-ep\"").count(),
            1,
            "{program}: {out}"
        );
    }
}

#[test]
fn coapcams_server_registers_with_aiocoaps_and_libcoaps_directories() {
    if !rd_peers("coapcams_server_registers_with_aiocoaps_and_libcoaps_directories") {
        return;
    }
    let dir = TempDir::new("rd-peer-directories");
    let aio_port = crate::support::free_port();
    let mut aiocoap_rd = Proc::spawn("aiocoap-rd", &["--bind", &format!("127.0.0.1:{aio_port}")]);
    let lc_port = crate::support::free_port();
    let lc_port_text = lc_port.to_string();
    let mut libcoap_rd = Proc::spawn("coap-rd-notls", &["-A", "127.0.0.1", "-p", &lc_port_text]);
    let aio = format!("coap://127.0.0.1:{aio_port}");
    let lc = format!("coap://127.0.0.1:{lc_port}");
    // aiocoap-rd: found through discovery (its registration resource is
    // /resourcedirectory/), renewed, removed at shutdown.
    let (mut s1, s1_addr) =
        start_registered(&aio, "coapcam-aio", &dir.join("a"), &["--rd-lifetime", "4"]);
    let deadline = Instant::now() + SETTLE;
    let eps = format!("{aio}/endpoint-lookup/");
    let listed = loop {
        let out = peer_poll(AIOCOAP_CLIENT, &[&eps]);
        if out.contains("ep=\"coapcam-aio\"") {
            break out;
        }
        assert!(Instant::now() < deadline, "aiocoap-rd lists {out}");
        thread::sleep(Duration::from_millis(200));
    };
    assert!(
        listed.contains(&format!("base=\"coap://{s1_addr}\"")),
        "{listed}"
    );
    let res = peer_get(
        AIOCOAP_CLIENT,
        &[&format!(
            "{aio}/resource-lookup/?ep=coapcam-aio&rt=rgbd.color"
        )],
    );
    assert!(
        res.contains(&format!("<coap://{s1_addr}/cams/840412060746/color>")),
        "{res}"
    );
    // Past twice its 4 s lifetime, still registered (renewed; on a loaded machine a late
    // renewal that finds it expired registers it again, so this polls briefly).
    thread::sleep(Duration::from_secs(10));
    let deadline = Instant::now() + SETTLE;
    loop {
        let out = peer_get(AIOCOAP_CLIENT, &[&eps]);
        if out.contains("ep=\"coapcam-aio\"") {
            break;
        }
        assert!(Instant::now() < deadline, "not renewed: {out}");
        thread::sleep(Duration::from_millis(200));
    }
    let f = s1.interrupt();
    assert!(f.status.success(), "{}", f.stderr);
    let out = peer_get(AIOCOAP_CLIENT, &[&eps]);
    assert!(!out.contains("coapcam-aio"), "not removed: {out}");
    // libcoap's coap-rd (the 4.3.1 example: no lookup interface; registrations are
    // listed in its /.well-known/core and read at their location).
    let (mut s2, _) = start_registered(&lc, "coapcam-lc", &dir.join("b"), &["--no-cameras"]);
    let deadline = Instant::now() + SETTLE;
    let location = loop {
        let out = peer_poll(
            LIBCOAP_CLIENT,
            &["-m", "get", "-B", "10", &format!("{lc}/.well-known/core")],
        );
        if let Some(l) = coap::link_format::parse(out.trim())
            .unwrap_or_default()
            .into_iter()
            .find(|l| l.target.starts_with("/rd/"))
        {
            break l.target;
        }
        assert!(Instant::now() < deadline, "coap-rd lists {out}");
        thread::sleep(Duration::from_millis(200));
    };
    let links = peer_get(
        LIBCOAP_CLIENT,
        &["-m", "get", "-B", "10", &format!("{lc}{location}")],
    );
    assert!(links.contains("</coap-group>"), "{links}");
    // coap-rd 4.3.1 frees a registration twice on DELETE and dies (checked by hand
    // with its own coap-client too): the server is killed, not asked to remove it.
    s2.kill();
    assert!(libcoap_rd.is_running(), "coap-rd-notls died");
    libcoap_rd.kill();
    aiocoap_rd.kill();
}

#[test]
#[ignore = "multicast: run inside scripts/netns-run (scripts/test.sh does)"]
fn three_servers_of_a_group_are_found_through_the_directory_and_a_killed_one_is_named() {
    if std::env::var("COAPCAM_NETNS").ok().as_deref() != Some("1") {
        eprintln!(
            "SKIP three_servers_of_a_group_are_found_through_the_directory: only inside scripts/netns-run"
        );
        return;
    }
    let dir = TempDir::new("rd-group");
    let (_rd_proc, rd) = start_rd("127.0.0.20:5683", None);
    let rd_uri = format!("coap://{rd}");
    let mut servers: Vec<Proc> = [21u8, 22, 23]
        .iter()
        .map(|host| {
            let serial = format!("0000000000{host}");
            let scene = dir.join(&format!("scene-{host}.toml"));
            std::fs::write(&scene, crate::group::box_scene(&serial, [0.0, 0.0, 1.0]))
                .expect("writing the scene");
            let state = dir.join(&format!("state-{host}"));
            let mut p = Proc::spawn(
                COAPCAM,
                &[
                    "serve",
                    "--bind",
                    &format!("127.0.0.{host}:5683"),
                    "--state-dir",
                    state.to_str().expect("UTF-8 path"),
                    "--scene",
                    scene.to_str().expect("UTF-8 path"),
                    "--group",
                    "224.0.1.192",
                    "--register",
                    &rd_uri,
                    "--rd-ep",
                    &format!("station-{host}"),
                    "--rd-lifetime",
                    "8",
                    "--duration",
                    "150",
                ],
            );
            p.stderr_line(LIMIT, |l| {
                l.starts_with("coapcam: serving on ").then_some(())
            });
            p
        })
        .collect();
    // A server in the same group that the directory does not list (anyone on the link can
    // join a group): a measurement through the directory leaves its answer out.
    let stranger_scene = dir.join("scene-24.toml");
    std::fs::write(
        &stranger_scene,
        crate::group::box_scene("000000000024", [0.3, 0.0, 1.0]),
    )
    .expect("writing the scene");
    let (_stranger, _) = crate::support::serve_at(
        "127.0.0.24:5683",
        &dir.join("state-24"),
        &[
            "--scene",
            stranger_scene.to_str().expect("UTF-8 path"),
            "--group",
            "224.0.1.192",
        ],
    );
    wait_for_names(rd, &["station-21", "station-22", "station-23"]);
    let f = Proc::run(
        COAPCAM,
        &[
            "discover",
            "--rd",
            &rd_uri,
            "--query",
            "grp=224.0.1.192:5683",
            "--json",
        ],
        LIMIT,
    )
    .expect_success("discover --rd");
    let mut bases: Vec<String> = f
        .json_lines()
        .iter()
        .filter_map(|l| l["base"].as_str().map(str::to_owned))
        .collect();
    bases.sort();
    assert_eq!(
        bases,
        [
            "coap://127.0.0.21",
            "coap://127.0.0.22",
            "coap://127.0.0.23"
        ]
    );
    // A group joined at run time (POST /coap-group) is registered again with it.
    Proc::run(
        COAPCAM,
        &[
            "post",
            "coap://127.0.0.21/coap-group",
            "--content-format",
            "256",
            "--payload",
            r#"{"a": "224.0.1.193"}"#,
        ],
        LIMIT,
    )
    .expect_success("joining a group at run time");
    let deadline = Instant::now() + SETTLE;
    while endpoints(rd, &["grp=224.0.1.193:5683"]).len() != 1 {
        assert!(
            Instant::now() < deadline,
            "the new group was not registered"
        );
        thread::sleep(Duration::from_millis(100));
    }
    assert_eq!(endpoints(rd, &["grp=224.0.1.193:5683"])[0].ep, "station-21");
    // A server of the group the directory does not list: its answer is named and left out.
    // The directory also lists a member that is up but never answers the group, so the
    // measurement waits its whole --wait and the stranger's answer surely comes in it
    // (with only answering members it ends at their last answer, whenever the stranger's
    // comes).
    Proc::run(
        COAPCAM,
        &[
            "post",
            "coap://127.0.0.24/coap-group",
            "--content-format",
            "256",
            "--payload",
            r#"{"a": "224.0.1.193"}"#,
        ],
        LIMIT,
    )
    .expect_success("the stranger joining a group at run time");
    let rt = runtime();
    let _silent = rt.block_on(async {
        let server = Server::bind(
            &[SocketAddr::from(([127, 0, 0, 25], 5683))],
            ServerConfig::default(),
            Router::new(),
        )
        .expect("binding the silent member");
        let own = server.client_for(rd).expect("a client on its socket");
        let mut register = Request::new(Code::POST, "/rd");
        for q in ["ep=silent", "lt=8", "grp=224.0.1.193:5683"] {
            register.options.push(OptionNumber::URI_QUERY, q);
        }
        register.timeout = Some(LIMIT);
        let r = own.send(rd, register).await.expect("registering");
        assert_eq!(
            r.code,
            Code::CREATED,
            "{}",
            String::from_utf8_lossy(&r.payload)
        );
        server
    });
    let f = Proc::run(
        COAPCAM,
        &[
            "measure",
            "--group",
            "224.0.1.193",
            "--rd",
            &rd_uri,
            "--wait",
            "3",
            "--json",
        ],
        LIMIT,
    );
    assert_eq!(f.status.code(), Some(6), "{}", f.stderr);
    for said in [
        "127.0.0.24:5683 answered the group 224.0.1.193:5683 but the directory does not list it: left out",
        "silent (coap://127.0.0.25), a member of the group the directory lists, did not answer",
    ] {
        assert!(f.stderr.contains(said), "{}", f.stderr);
    }
    assert_eq!(f.json()["servers"], serde_json::json!(["127.0.0.21:5683"]));
    // One is killed: it cannot remove its registration, and the directory still lists it.
    servers[2].kill();
    let started = Instant::now();
    let f = Proc::run(
        COAPCAM,
        &[
            "measure",
            "--group",
            "224.0.1.192",
            "--rd",
            &rd_uri,
            "--wait",
            "60",
            "--json",
        ],
        Duration::from_secs(110),
    );
    let took = started.elapsed();
    eprintln!("measure --group --rd with one of three members killed took {took:?} (--wait 60)");
    assert_eq!(f.status.code(), Some(6), "{}", f.stderr);
    assert!(
        f.stderr.contains("station-23 (coap://127.0.0.23), a member of the group the directory lists, did not answer"),
        "{}",
        f.stderr
    );
    let m = f.json();
    assert_eq!(m["parcel"], "measured", "{m}");
    let mut answered: Vec<&str> = m["servers"]
        .as_array()
        .expect("servers")
        .iter()
        .filter_map(|s| s.as_str())
        .collect();
    answered.sort_unstable();
    answered.dedup();
    assert_eq!(answered, ["127.0.0.21:5683", "127.0.0.22:5683"], "{m}");
    // After its lifetime the killed one is gone; the others renew theirs.
    wait_for_names(rd, &["station-21", "station-22"]);
}
