//! Group communication (RFC 7390). `/coap-group` by unicast: memberships listed, created,
//! read, replaced and deleted, bad payloads refused without change. In a private network
//! namespace (`scripts/netns-run`, which `scripts/test.sh` uses; `#[ignore]`d elsewhere):
//! a multicast grab of three `coapcam serve` on 127.0.0.2, .3 and .4 in the group
//! 224.0.1.187, each answer completed block-wise by unicast from the server's own address;
//! and a membership created at run time by POST makes a server answer its group.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::time::Duration;

use coap::group::{GroupConfig, decode_list};
use coap::{Code, OptionNumber, Request, Response};
use coap_net::Client;

use crate::support::Proc;
use crate::support::{
    COAPCAM, LIMIT, Server, TempDir, client, runtime, send, serve_at, serve_with,
};

/// The membership list of `GET /coap-group`.
async fn list(c: &Client, addr: SocketAddr) -> BTreeMap<String, GroupConfig> {
    let r = send(c, addr, Code::GET, "/coap-group", b"", None).await;
    assert_eq!(r.code, Code::CONTENT);
    assert_eq!(r.options.content_format().map(|f| f.0), Some(256));
    decode_list(&r.payload).expect("an application/coap-group+json list")
}

fn membership(json: &str) -> GroupConfig {
    GroupConfig::from_json(json.as_bytes()).expect("a membership")
}

fn location(r: &Response) -> Vec<String> {
    r.options
        .values(OptionNumber::LOCATION_PATH)
        .map(|v| String::from_utf8_lossy(v).into_owned())
        .collect()
}

#[test]
fn coap_group_memberships_are_listed_created_replaced_and_deleted() {
    let state = TempDir::new("group-crud");
    // Administratively scoped groups (RFC 2365): never routed beyond the site.
    let (_server, addr) = serve_with(state.path(), &["--no-cameras", "--group", "239.255.71.1"]);
    let port = addr.port();
    runtime().block_on(async {
        let c = client();
        let mut discover = Request::new(Code::GET, "/.well-known/core");
        discover
            .options
            .push(OptionNumber::URI_QUERY, b"rt=core.gp");
        discover.timeout = Some(LIMIT);
        let links = c.send(addr, discover).await.expect("discovery");
        let links = String::from_utf8_lossy(&links.payload).into_owned();
        assert!(links.starts_with("</coap-group>"), "{links}");
        assert!(links.contains("ct=256"), "{links}");

        let start = list(&c, addr).await;
        let first = membership(&format!(r#"{{"a": "239.255.71.1:{port}"}}"#));
        assert_eq!(start, BTreeMap::from([("1".to_string(), first.clone())]));

        let floor1 = format!(r#"{{"n": "floor1.example", "a": "239.255.71.2:{port}"}}"#);
        let created = send(&c, addr, Code::POST, "/coap-group", floor1.as_bytes(), None).await;
        assert_eq!(created.code, Code::CREATED);
        assert_eq!(location(&created), ["coap-group", "2"]);
        let read = send(&c, addr, Code::GET, "/coap-group/2", b"", None).await;
        assert_eq!(read.code, Code::CONTENT);
        assert_eq!(read.options.content_format().map(|f| f.0), Some(256));
        assert_eq!(
            GroupConfig::from_json(&read.payload).ok(),
            Some(membership(&floor1))
        );
        let both = list(&c, addr).await;
        assert_eq!(both.len(), 2);

        let wrong_port = if port == 5683 { 5684 } else { 5683 };
        let bad = [
            ("not json".to_string(), "JSON"),
            ("[1]".to_string(), "object"),
            (r#"{"n": "no-address"}"#.to_string(), "\"a\""),
            (format!(r#"{{"a": "10.1.2.3:{port}"}}"#), "multicast"),
            (format!(r#"{{"a": "239.255.71.3:{wrong_port}"}}"#), "port"),
            (format!(r#"{{"a": "[ff05::fd]:{port}"}}"#), "family"),
        ];
        for (payload, why) in &bad {
            for (method, path) in [(Code::POST, "/coap-group"), (Code::PUT, "/coap-group/2")] {
                let r = send(&c, addr, method, path, payload.as_bytes(), None).await;
                assert_eq!(r.code, Code::BAD_REQUEST, "{method:?} {payload}");
                let text = String::from_utf8_lossy(&r.payload);
                assert!(text.contains(why), "{method:?} {payload}: {text}");
                assert_eq!(
                    list(&c, addr).await,
                    both,
                    "{method:?} {payload} changed the list"
                );
            }
        }
        let mut plain = Request::new(Code::POST, "/coap-group").with_payload(floor1.clone());
        plain.options.set_uint(OptionNumber::CONTENT_FORMAT, 0);
        plain.timeout = Some(LIMIT);
        let r = c.send(addr, plain).await.expect("POST text/plain");
        assert_eq!(r.code, Code::UNSUPPORTED_CONTENT_FORMAT);
        assert_eq!(list(&c, addr).await, both);

        let floor2 = format!(r#"{{"n": "floor2.example", "a": "239.255.71.3:{port}"}}"#);
        let r = send(
            &c,
            addr,
            Code::PUT,
            "/coap-group/2",
            floor2.as_bytes(),
            None,
        )
        .await;
        assert_eq!(r.code, Code::CHANGED);
        assert_eq!(
            list(&c, addr).await,
            BTreeMap::from([
                ("1".to_string(), first.clone()),
                ("2".to_string(), membership(&floor2))
            ])
        );
        let r = send(
            &c,
            addr,
            Code::PUT,
            "/coap-group/9",
            floor2.as_bytes(),
            None,
        )
        .await;
        assert_eq!(r.code, Code::NOT_FOUND);

        for (method, path) in [
            (Code::PUT, "/coap-group"),
            (Code::DELETE, "/coap-group"),
            (Code::POST, "/coap-group/1"),
        ] {
            let r = send(&c, addr, method, path, floor2.as_bytes(), None).await;
            assert_eq!(r.code, Code::METHOD_NOT_ALLOWED, "{method:?} {path}");
        }

        let r = send(&c, addr, Code::DELETE, "/coap-group/2", b"", None).await;
        assert_eq!(r.code, Code::DELETED);
        let r = send(&c, addr, Code::GET, "/coap-group/2", b"", None).await;
        assert_eq!(r.code, Code::NOT_FOUND);
        let r = send(&c, addr, Code::DELETE, "/coap-group/2", b"", None).await;
        assert_eq!(r.code, Code::NOT_FOUND);
        assert_eq!(
            list(&c, addr).await,
            BTreeMap::from([("1".to_string(), first)])
        );
    });
}

fn scene(serial: &str) -> String {
    format!(
        r#"
seed = 5
[floor]
z = 0.0
color = [120, 120, 120]

[[camera]]
serial = "{serial}"
position = [0.0, 0.0, 1.0]
look_at = [0.0, 0.0, 0.0]
noise = "ideal"
calibrated = true

[[box]]
size = [0.40, 0.30, 0.20]
center = [0.0, 0.0]
yaw_deg = 15.0
color = [180, 140, 90]
"#
    )
}

fn start(host: u8, dir: &std::path::Path) -> Server {
    let scene_file = dir.join(format!("scene-{host}.toml"));
    std::fs::write(&scene_file, scene(&format!("{host:012}"))).expect("writing the scene");
    let scene_arg = scene_file.to_str().expect("UTF-8 path");
    let state = dir.join(format!("state-{host}"));
    let bind = format!("127.0.0.{host}:5683");
    let extra = ["--group", "224.0.1.187", "--scene", scene_arg];
    serve_at(&bind, &state, &extra).0
}

/// `GET /.well-known/core` sent to `group`: the servers that answered.
async fn discover(client: &Client, group: SocketAddr) -> Vec<SocketAddr> {
    let mut request = Request::new(Code::GET, "/.well-known/core");
    request.timeout = Some(Duration::from_secs(2));
    let answers = tokio::time::timeout(LIMIT, client.multicast(group, request))
        .await
        .expect("bounded")
        .expect("multicast request");
    answers.into_iter().map(|(peer, _)| peer).collect()
}

#[test]
#[ignore = "multicast: run inside scripts/netns-run (scripts/test.sh does)"]
fn a_membership_created_by_post_makes_the_server_answer_its_group() {
    if std::env::var("COAPCAM_NETNS").ok().as_deref() != Some("1") {
        eprintln!(
            "SKIP a_membership_created_by_post_makes_the_server_answer_its_group: only inside scripts/netns-run"
        );
        return;
    }
    let dir = TempDir::new("group-runtime");
    let (_server, addr) = serve_at("127.0.0.5:5683", dir.path(), &["--no-cameras"]);
    let group: SocketAddr = "224.0.1.190:5683".parse().expect("group");
    runtime().block_on(async {
        let unicast = client();
        // Bound to 127.0.0.1, as in the multicast grab below.
        let multicast = client();
        assert!(
            discover(&multicast, group).await.is_empty(),
            "an answer before the server joined"
        );
        let created = send(
            &unicast,
            addr,
            Code::POST,
            "/coap-group",
            br#"{"n": "cams.local", "a": "224.0.1.190"}"#,
            None,
        )
        .await;
        assert_eq!(created.code, Code::CREATED);
        assert_eq!(discover(&multicast, group).await, [addr]);
        let deleted = send(
            &unicast,
            addr,
            Code::DELETE,
            &format!("/{}", location(&created).join("/")),
            b"",
            None,
        )
        .await;
        assert_eq!(deleted.code, Code::DELETED);
        assert!(
            discover(&multicast, group).await.is_empty(),
            "an answer after the server left"
        );
    });
}

#[test]
#[ignore = "multicast: run inside scripts/netns-run (scripts/test.sh does)"]
fn multicast_grab_of_three_servers_in_one_group() {
    if std::env::var("COAPCAM_NETNS").ok().as_deref() != Some("1") {
        eprintln!(
            "SKIP multicast_grab_of_three_servers_in_one_group: only inside scripts/netns-run"
        );
        return;
    }
    let dir = TempDir::new("group");
    let _servers: Vec<Server> = [2u8, 3, 4].iter().map(|h| start(*h, dir.path())).collect();
    let runtime = runtime();
    let answers = runtime.block_on(async {
        // Bound to 127.0.0.1, not 0.0.0.0: on lo the kernel would otherwise send each
        // unicast follow-up from the address it is sent to (127.0.0.N is local too), and
        // the servers keep the stored cloud for the address that asked.
        let client = client();
        let mut request = Request::new(Code::POST, "/cams/pointclouds");
        request.timeout = Some(Duration::from_secs(3));
        tokio::time::timeout(
            Duration::from_secs(60),
            client.multicast("224.0.1.187:5683".parse().expect("group"), request),
        )
        .await
        .expect("bounded")
        .expect("multicast grab")
    });
    let mut peers: Vec<SocketAddr> = answers.iter().map(|(p, _)| *p).collect();
    peers.sort();
    let expected: Vec<SocketAddr> = [2u8, 3, 4]
        .iter()
        .map(|h| SocketAddr::from(([127, 0, 0, *h], 5683)))
        .collect();
    assert_eq!(
        peers, expected,
        "one answer per server, from its unicast address"
    );
    for (peer, r) in &answers {
        assert_eq!(r.code, Code::CONTENT, "{peer}");
        let n =
            u32::from_be_bytes([r.payload[4], r.payload[5], r.payload[6], r.payload[7]]) as usize;
        assert!(n > 100_000, "{peer}: {n} points");
        assert_eq!(
            r.payload.len(),
            12 + 12 * n,
            "{peer}: the whole cloud arrived"
        );
    }
}

/// A scene with one calibrated camera `serial` at `position`, looking at the box every
/// server of the multicast measurement sees.
pub(crate) fn box_scene(serial: &str, position: [f64; 3]) -> String {
    format!(
        r#"
seed = 11
[floor]
z = 0.0
color = [120, 120, 120]

[[camera]]
serial = "{serial}"
position = [{}, {}, {}]
look_at = [0.0, 0.0, 0.0]
noise = "d415"
calibrated = true

[[box]]
size = [0.40, 0.30, 0.20]
center = [0.0, 0.0]
yaw_deg = 15.0
color = [180, 140, 90]
"#,
        position[0], position[1], position[2]
    )
}

#[test]
#[ignore = "multicast: run inside scripts/netns-run (scripts/test.sh does)"]
fn multicast_measurement_merges_three_servers_cameras() {
    if std::env::var("COAPCAM_NETNS").ok().as_deref() != Some("1") {
        eprintln!(
            "SKIP multicast_measurement_merges_three_servers_cameras: only inside scripts/netns-run"
        );
        return;
    }
    let dir = TempDir::new("group-measure");
    // Above, and obliquely from two sides.
    let cameras = [
        (6u8, "000000000006", [0.0, 0.0, 1.0]),
        (7, "000000000007", [0.6, 0.2, 1.1]),
        (8, "000000000008", [-0.3, -0.6, 1.2]),
    ];
    let _servers: Vec<Server> = cameras
        .iter()
        .map(|(host, serial, position)| {
            let scene_file = dir.path().join(format!("scene-{host}.toml"));
            std::fs::write(&scene_file, box_scene(serial, *position)).expect("writing the scene");
            let scene_arg = scene_file.to_str().expect("UTF-8 path");
            let state = dir.path().join(format!("state-{host}"));
            let bind = format!("127.0.0.{host}:5683");
            serve_at(
                &bind,
                &state,
                &["--group", "224.0.1.188", "--scene", scene_arg],
            )
            .0
        })
        .collect();
    let f = Proc::run(
        COAPCAM,
        &[
            "measure",
            "--group",
            "224.0.1.188",
            "--expect",
            "3",
            "--wait",
            "30",
            "--json",
        ],
        Duration::from_secs(110),
    )
    .expect_success("coapcam measure --group");
    let m = f.json();
    let sorted = |key: &str| {
        let mut v: Vec<&str> = m[key]
            .as_array()
            .expect(key)
            .iter()
            .filter_map(|s| s.as_str())
            .collect();
        v.sort_unstable();
        v
    };
    assert_eq!(
        sorted("cameras"),
        ["000000000006", "000000000007", "000000000008"],
        "{m}"
    );
    assert_eq!(
        sorted("servers"),
        ["127.0.0.6:5683", "127.0.0.7:5683", "127.0.0.8:5683"],
        "{m}"
    );
    assert_eq!(m["frames_unix_us"].as_array().map(Vec::len), Some(3), "{m}");
    let got = ["length_mm", "width_mm", "height_mm"].map(|k| m[k].as_f64().expect(k));
    for (g, want) in got.iter().zip([400.0, 300.0, 200.0]) {
        assert!(
            (g - want).abs() <= 5.0,
            "{got:?} vs 400 x 300 x 200 mm: {m}"
        );
    }
}

/// Whether the test runs inside `scripts/netns-run`; says so when it does not.
fn in_namespace(test: &str) -> bool {
    let ok = std::env::var("COAPCAM_NETNS").ok().as_deref() == Some("1");
    if !ok {
        eprintln!("SKIP {test}: only inside scripts/netns-run");
    }
    ok
}

/// The servers named in `coapcam discover --json` lines.
fn servers_of(f: &crate::support::Finished) -> Vec<String> {
    let mut servers: Vec<String> = f
        .json_lines()
        .iter()
        .filter_map(|l| l["server"].as_str().map(str::to_owned))
        .collect();
    servers.sort();
    servers.dedup();
    servers
}

#[test]
#[ignore = "multicast: run inside scripts/netns-run (scripts/test.sh does)"]
fn discover_lists_every_server_of_a_group_whatever_address_the_kernel_sends_from() {
    if !in_namespace("discover_lists_every_server_of_a_group") {
        return;
    }
    let dir = TempDir::new("group-discover");
    // Three servers of the default scene: their discovery answers take several blocks,
    // which the client asks of each server by unicast, from the address the kernel picks
    // for it (not the one the group request left from).
    let _servers: Vec<Server> = [10u8, 11, 12]
        .iter()
        .map(|host| {
            let state = dir.path().join(format!("state-{host}"));
            serve_at(
                &format!("127.0.0.{host}:5683"),
                &state,
                &["--group", "224.0.1.189"],
            )
            .0
        })
        .collect();
    let want = ["127.0.0.10:5683", "127.0.0.11:5683", "127.0.0.12:5683"];
    for query in [None, Some("rt=rgbd*")] {
        let mut args = vec!["discover", "coap://224.0.1.189:5683", "--json"];
        if let Some(q) = query {
            args.extend(["--query", q]);
        }
        let f = Proc::run(COAPCAM, &args, LIMIT).expect_success("coapcam discover a group");
        assert_eq!(servers_of(&f), want, "{query:?}: {}", f.stdout_text());
    }
}

#[test]
#[ignore = "multicast: run inside scripts/netns-run (scripts/test.sh does)"]
fn measure_group_with_fewer_servers_than_expected_warns_and_exits_6() {
    if !in_namespace("measure_group_with_fewer_servers_than_expected") {
        return;
    }
    let dir = TempDir::new("group-fewer");
    let _servers: Vec<Server> = [(13u8, "000000000013"), (14, "000000000014")]
        .iter()
        .map(|(host, serial)| {
            let scene_file = dir.path().join(format!("scene-{host}.toml"));
            std::fs::write(&scene_file, box_scene(serial, [0.0, 0.0, 1.0]))
                .expect("writing the scene");
            let scene_arg = scene_file.to_str().expect("UTF-8 path");
            let state = dir.path().join(format!("state-{host}"));
            serve_at(
                &format!("127.0.0.{host}:5683"),
                &state,
                &["--group", "224.0.1.190", "--scene", scene_arg],
            )
            .0
        })
        .collect();
    let f = Proc::run(
        COAPCAM,
        &[
            "measure",
            "--group",
            "224.0.1.190",
            "--expect",
            "3",
            "--wait",
            "5",
            "--json",
        ],
        Duration::from_secs(110),
    );
    assert_eq!(f.status.code(), Some(6), "{}", f.stderr);
    assert!(
        f.stderr.contains("warning: 2 of the 3 expected servers"),
        "{}",
        f.stderr
    );
    let m = f.json();
    assert_eq!(m["warnings"].as_array().map(Vec::len), Some(1), "{m}");
    assert_eq!(m["parcel"], "measured", "{m}");
}

#[test]
#[ignore = "multicast: run inside scripts/netns-run (scripts/test.sh does)"]
fn a_group_nobody_answers_exits_4_for_discover_and_measure() {
    if !in_namespace("a_group_nobody_answers_exits_4") {
        return;
    }
    for args in [
        &["discover", "coap://224.0.1.191:5683", "--wait", "1"][..],
        &["measure", "--group", "224.0.1.191", "--wait", "1"],
    ] {
        let f = Proc::run(COAPCAM, args, LIMIT);
        assert_eq!(f.status.code(), Some(4), "{args:?}: {}", f.stderr);
        assert!(f.stderr.contains("no server"), "{args:?}: {}", f.stderr);
    }
}

/// The interfaces (by name) on which `/proc/net/<file>` lists `group`, its address as the
/// kernel prints it there.
fn joined_on(file: &str, group: &str) -> Vec<String> {
    let text = std::fs::read_to_string(format!("/proc/net/{file}")).expect("/proc/net");
    let mut names = Vec::new();
    let mut current = String::new();
    for line in text.lines() {
        let fields: Vec<&str> = line.split_whitespace().collect();
        match (file, fields.as_slice()) {
            // igmp: "Idx Device : Count Querier" then indented group lines.
            ("igmp", [_, dev, ":", ..]) => current = (*dev).to_string(),
            ("igmp", [g, ..]) if g.eq_ignore_ascii_case(group) => names.push(current.clone()),
            // igmp6: "index device group users flags timer".
            ("igmp6", [_, dev, g, ..]) if g.eq_ignore_ascii_case(group) => {
                names.push((*dev).to_string());
            }
            _ => {}
        }
    }
    names
}

#[test]
#[ignore = "multicast: run inside scripts/netns-run (scripts/test.sh does)"]
fn a_group_is_joined_only_on_the_interface_of_the_bound_address() {
    if !in_namespace("a_group_is_joined_only_on_the_interface_of_the_bound_address") {
        return;
    }
    let dir = TempDir::new("group-interface");
    // fd00::2 is on mc0, 127.0.0.5 on lo: each server listens to its group there only.
    let _v6 = serve_at(
        "[fd00::2]:5695",
        &dir.join("s6"),
        &["--no-cameras", "--group", "ff02::fd"],
    );
    let _v4 = serve_at(
        "127.0.0.5:5695",
        &dir.join("s4"),
        &["--no-cameras", "--group", "224.0.1.187"],
    );
    assert_eq!(
        joined_on("igmp6", "ff0200000000000000000000000000fd"),
        ["mc0"]
    );
    assert_eq!(joined_on("igmp", "BB0100E0"), ["lo"]);
}
