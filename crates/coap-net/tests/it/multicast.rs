//! RFC 7390 group communication over real sockets, inside a private network namespace
//! (`scripts/netns-run`, which `scripts/test.sh` uses): several servers on their own
//! unicast addresses in one group; a multicast request collects every answer, each from
//! the server's unicast address; error answers to multicast requests are suppressed.

use std::net::{IpAddr, SocketAddr, SocketAddrV6};

use coap::{Code, EndpointConfig, Request, Response};
use coap_net::socket::groups;
use coap_net::{Client, Resource, Router, Server, ServerConfig, handler};

/// Whether the test runs inside `scripts/netns-run`; elsewhere multicast could leave
/// through a real interface. The tests are `#[ignore]`d in the ordinary run, and this
/// guards a `--ignored` run outside the namespace.
fn in_namespace(test: &str) -> bool {
    let ok = std::env::var("COAPCAM_NETNS").is_ok_and(|v| v == "1");
    if !ok {
        eprintln!(
            "SKIP {test}: multicast tests run only inside scripts/netns-run (scripts/test.sh does that)"
        );
    }
    ok
}

/// A group server on `bind` once that address is free: servers dropped just before
/// release their sockets when their threads end, a moment later.
async fn group_server_when_free(bind: SocketAddr, name: &'static str, fail: bool) -> Server {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    loop {
        match try_group_server(bind, name, fail) {
            Ok(s) => return s,
            Err(e) if std::time::Instant::now() < deadline => {
                assert_eq!(e.kind(), std::io::ErrorKind::AddrInUse, "bind {bind}: {e}");
                tokio::time::sleep(std::time::Duration::from_millis(50)).await;
            }
            Err(e) => panic!("bind {bind}: {e}"),
        }
    }
}

fn group_server(bind: SocketAddr, name: &'static str, fail: bool) -> Server {
    try_group_server(bind, name, fail).unwrap_or_else(|e| panic!("bind {bind}: {e}"))
}

fn try_group_server(bind: SocketAddr, name: &'static str, fail: bool) -> std::io::Result<Server> {
    let router = Router::new();
    router.add(
        "/who",
        Resource::new().get(handler(move |_| async move {
            if fail {
                Response::diagnostic(Code::NOT_FOUND, "not here")
            } else {
                Response::new(Code::CONTENT).with_payload(name)
            }
        })),
    );
    let config = ServerConfig {
        endpoint: EndpointConfig {
            leisure: std::time::Duration::from_millis(50),
            ..EndpointConfig::default()
        },
        ..ServerConfig::default()
    };
    Server::bind(&[bind], config, router)
}

async fn collect(group: SocketAddr) -> Vec<(SocketAddr, String)> {
    let any: SocketAddr = if group.is_ipv4() {
        "0.0.0.0:0"
    } else {
        "[::]:0"
    }
    .parse()
    .unwrap_or_else(|_| unreachable!());
    let client = Client::bind(
        any,
        EndpointConfig {
            rng_seed: 3,
            ..EndpointConfig::default()
        },
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let mut req = Request::new(Code::GET, "/who");
    req.timeout = Some(std::time::Duration::from_millis(800));
    let answers = client
        .multicast(group, req)
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let mut out: Vec<(SocketAddr, String)> = answers
        .into_iter()
        .map(|(p, r)| (p, String::from_utf8_lossy(&r.payload).into_owned()))
        .collect();
    out.sort();
    out
}

#[tokio::test]
#[ignore = "multicast: run inside scripts/netns-run (scripts/test.sh does)"]
async fn rfc7390_ipv4_group_on_lo_answers_from_unicast_addresses() {
    if !in_namespace("rfc7390_ipv4_group_on_lo_answers_from_unicast_addresses") {
        return;
    }
    let port = 5683;
    let mut servers = Vec::new();
    for (i, name) in [(2u8, "two"), (3, "three"), (4, "four")] {
        let s = group_server(SocketAddr::from(([127, 0, 0, i], port)), name, false);
        s.join(IpAddr::V4(groups::ALL_COAP_V4), 0)
            .await
            .unwrap_or_else(|e| panic!("join: {e}"));
        servers.push(s);
    }
    // A member that answers 4.04, suppressed for a group request, bound to its unicast
    // address (a group socket of its own receives for it).
    let failing = group_server(SocketAddr::from(([127, 0, 0, 5], port)), "five", true);
    failing
        .join(IpAddr::V4(groups::ALL_COAP_V4), 0)
        .await
        .unwrap_or_else(|e| panic!("join: {e}"));
    let got = collect(SocketAddr::from((groups::ALL_COAP_V4, port))).await;
    let expected: Vec<(SocketAddr, String)> = [(2u8, "two"), (3, "three"), (4, "four")]
        .iter()
        .map(|(i, n)| (SocketAddr::from(([127, 0, 0, *i], port)), n.to_string()))
        .collect();
    assert_eq!(
        got, expected,
        "one answer per member, from its unicast address; the 4.04s are suppressed"
    );
    // After leaving, a member no longer answers.
    servers[0]
        .leave(IpAddr::V4(groups::ALL_COAP_V4), 0)
        .await
        .unwrap_or_else(|e| panic!("leave: {e}"));
    let got = collect(SocketAddr::from((groups::ALL_COAP_V4, port))).await;
    assert_eq!(got.len(), 2, "{got:?}");
    // A member bound to the wildcard address: its own socket receives the group's
    // datagrams and reads their destination, so its 4.04 is suppressed too. A unicast or
    // wildcard address is bound without address reuse (a second server must not share
    // it), so it has the port once the others are gone.
    drop((servers, failing));
    let wildcard =
        group_server_when_free(SocketAddr::from(([0, 0, 0, 0], port)), "wildcard", true).await;
    wildcard
        .join(IpAddr::V4(groups::ALL_COAP_V4), 0)
        .await
        .unwrap_or_else(|e| panic!("join: {e}"));
    let got = collect(SocketAddr::from((groups::ALL_COAP_V4, port))).await;
    assert!(
        got.is_empty(),
        "the wildcard member's 4.04 was not suppressed: {got:?}"
    );
}

#[tokio::test]
#[ignore = "multicast: run inside scripts/netns-run (scripts/test.sh does)"]
async fn rfc7390_ipv6_link_local_group_on_veth() {
    if !in_namespace("rfc7390_ipv6_link_local_group_on_veth") {
        return;
    }
    let ifindex: u32 = std::env::var("COAPCAM_MC6_IF")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("COAPCAM_MC6_IF"));
    let port = 5683;
    let mut servers = Vec::new();
    for (i, name) in [(2u16, "six-two"), (3, "six-three")] {
        let addr = SocketAddr::V6(SocketAddrV6::new(
            [0xfd00, 0, 0, 0, 0, 0, 0, i].into(),
            port,
            0,
            0,
        ));
        let s = group_server(addr, name, false);
        s.join(IpAddr::V6(groups::ALL_COAP_V6_LINK), ifindex)
            .await
            .unwrap_or_else(|e| panic!("join: {e}"));
        servers.push(s);
    }
    let group = SocketAddr::V6(SocketAddrV6::new(
        groups::ALL_COAP_V6_LINK,
        port,
        0,
        ifindex,
    ));
    let got = collect(group).await;
    let names: Vec<&str> = got.iter().map(|(_, n)| n.as_str()).collect();
    assert_eq!(names, ["six-two", "six-three"], "{got:?}");
    for (peer, _) in &got {
        assert!(
            matches!(peer.ip(), IpAddr::V6(a) if a.segments()[0] == 0xfd00),
            "answered from {peer}"
        );
    }
    // A wildcard-bound member that answers 4.04: it reads each datagram's destination,
    // so it knows the request was sent to the group and stays silent. It has the port
    // once the unicast members are gone (their addresses are bound without reuse).
    drop(servers);
    let failing =
        group_server_when_free(SocketAddr::from(([0u16; 8], port)), "wildcard", true).await;
    failing
        .join(IpAddr::V6(groups::ALL_COAP_V6_LINK), ifindex)
        .await
        .unwrap_or_else(|e| panic!("join: {e}"));
    let got = collect(group).await;
    assert!(
        got.is_empty(),
        "the wildcard member's 4.04 was not suppressed: {got:?}"
    );
}
