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

/// Frames written by hand and put on the wire of `mc1`, so that they arrive on `mc0` (the
/// other end of the namespace's veth pair) from a network interface, whatever their
/// source address says.
mod wire {
    use std::net::{Ipv4Addr, Ipv6Addr, SocketAddr};

    use nix::sys::socket::{AddressFamily, MsgFlags, SockFlag, SockType, sendto, socket};

    /// The internet checksum of `parts` (RFC 1071).
    fn checksum(parts: &[&[u8]]) -> u16 {
        let mut bytes: Vec<u8> = parts.concat();
        if bytes.len() % 2 == 1 {
            bytes.push(0);
        }
        let mut sum: u32 = bytes
            .chunks(2)
            .map(|w| u32::from(u16::from_be_bytes([w[0], w[1]])))
            .sum();
        while sum > 0xffff {
            sum = (sum & 0xffff) + (sum >> 16);
        }
        !(sum as u16)
    }

    fn udp(sport: u16, dport: u16, payload: &[u8]) -> Vec<u8> {
        let len = u16::try_from(8 + payload.len()).expect("a small datagram");
        let mut udp = Vec::new();
        for field in [sport, dport, len, 0] {
            udp.extend_from_slice(&field.to_be_bytes());
        }
        udp.extend_from_slice(payload);
        udp
    }

    fn mac(interface: &str) -> Vec<u8> {
        let text = std::fs::read_to_string(format!("/sys/class/net/{interface}/address"))
            .expect("the interface's MAC address");
        text.trim()
            .split(':')
            .map(|h| u8::from_str_radix(h, 16).expect("a MAC address"))
            .collect()
    }

    /// An Ethernet frame for `mc0` from `mc1` carrying `packet` of `ethertype`.
    fn ethernet(ethertype: u16, packet: &[u8]) -> Vec<u8> {
        [
            &mac("mc0")[..],
            &mac("mc1")[..],
            &ethertype.to_be_bytes(),
            packet,
        ]
        .concat()
    }

    /// UDP `payload` from `from` to `to` in an IPv6 (or, for IPv4 addresses, IPv4) frame.
    pub(super) fn frame(from: SocketAddr, to: SocketAddr, payload: &[u8]) -> Vec<u8> {
        let mut udp = udp(from.port(), to.port(), payload);
        match (from, to) {
            (SocketAddr::V6(f), SocketAddr::V6(t)) => {
                let len = u32::try_from(udp.len()).expect("length");
                let pseudo = [
                    &f.ip().octets()[..],
                    &t.ip().octets(),
                    &len.to_be_bytes(),
                    &[0, 0, 0, 17],
                ]
                .concat();
                let sum = match checksum(&[&pseudo, &udp]) {
                    0 => 0xffff,
                    s => s,
                };
                udp[6..8].copy_from_slice(&sum.to_be_bytes());
                let mut ip = vec![0x60, 0, 0, 0];
                ip.extend_from_slice(&(len as u16).to_be_bytes());
                ip.extend_from_slice(&[17, 64]);
                ip.extend_from_slice(&f.ip().octets());
                ip.extend_from_slice(&t.ip().octets());
                ethernet(0x86dd, &[ip, udp].concat())
            }
            (SocketAddr::V4(f), SocketAddr::V4(t)) => {
                let len = u16::try_from(20 + udp.len()).expect("length");
                let mut ip = vec![0x45, 0];
                ip.extend_from_slice(&len.to_be_bytes());
                ip.extend_from_slice(&[0, 1, 0, 0, 64, 17, 0, 0]);
                ip.extend_from_slice(&f.ip().octets());
                ip.extend_from_slice(&t.ip().octets());
                let sum = checksum(&[&ip]);
                ip[10..12].copy_from_slice(&sum.to_be_bytes());
                ethernet(0x0800, &[ip, udp].concat())
            }
            _ => panic!("{from} and {to} are of different families"),
        }
    }

    /// Sends `frame` out of `mc1` through a packet socket.
    pub(super) fn inject(frame: &[u8]) {
        let mc1 = nix::ifaddrs::getifaddrs()
            .expect("interfaces")
            .filter(|i| i.interface_name == "mc1")
            .find_map(|i| i.address.and_then(|a| a.as_link_addr().copied()))
            .expect("mc1's link address");
        let fd = socket(
            AddressFamily::Packet,
            SockType::Raw,
            SockFlag::empty(),
            None,
        )
        .expect("a packet socket (root)");
        let sent = sendto(
            std::os::fd::AsRawFd::as_raw_fd(&fd),
            frame,
            &mc1,
            MsgFlags::empty(),
        )
        .expect("sending on mc1");
        assert_eq!(sent, frame.len());
    }

    /// `fd00::2`, on `mc0`.
    pub(super) const SERVER_V6: Ipv6Addr = Ipv6Addr::new(0xfd00, 0, 0, 0, 0, 0, 0, 2);
    /// `::ffff:127.0.0.1`.
    pub(super) const MAPPED_LOOPBACK: Ipv6Addr = Ipv4Addr::LOCALHOST.to_ipv6_mapped();
}

/// Sets the IPv4 sysctl `name` of `mc0` to `value`, returning the old value.
fn mc0_sysctl(name: &str, value: &str) -> String {
    let path = format!("/proc/sys/net/ipv4/conf/mc0/{name}");
    let old = std::fs::read_to_string(&path).expect("reading a sysctl");
    std::fs::write(&path, value).expect("writing a sysctl");
    old.trim().to_owned()
}

#[test]
#[ignore = "off-host: run inside scripts/netns-run (scripts/test.sh does)"]
fn offhost_a_forged_loopback_source_configures_nothing() {
    use std::net::{Ipv4Addr, Ipv6Addr, SocketAddrV4, SocketAddrV6};

    use coap_net::Client;

    let test = "offhost_a_forged_loopback_source_configures_nothing";
    if !in_namespace(test) {
        return;
    }
    let dir = TempDir::new("forged-loopback");
    let psk = dir.join("psk.txt");
    std::fs::write(&psk, "alice secret-of-alice configure\n").expect("writing identities");
    let psk = psk.to_str().expect("UTF-8 path");
    // The default bind's two wildcards, and one with identities configured.
    let servers = [
        serve_at("[::]:0", &dir.join("v6"), &[]),
        serve_at("[::]:0", &dir.join("v6-psk"), &["--psk-file", psk]),
        serve_at("0.0.0.0:0", &dir.join("v4"), &[]),
    ];
    // IPv4 frames from 127.0.0.1 are martians unless the interface allows them; some
    // hosts do (route_localnet, e.g. for a NodePort on 127.0.0.1). Here mc0 does.
    let localnet = mc0_sysctl("route_localnet", "1");
    let accept_local = mc0_sysctl("accept_local", "1");

    let app = format!("/cams/{}/application-config", support::SN);
    let pointcloud = format!("/cams/{}/pointcloud", support::SN);
    let rt = support::runtime();
    for (n, (_server, addr)) in servers.iter().enumerate() {
        let port = addr.port();
        let (here, client_bind, forged, target): (SocketAddr, SocketAddr, SocketAddr, SocketAddr) =
            if addr.is_ipv6() {
                (
                    (Ipv6Addr::LOCALHOST, port).into(),
                    (Ipv6Addr::LOCALHOST, 0).into(),
                    SocketAddrV6::new(wire::MAPPED_LOOPBACK, 40_000 + n as u16, 0, 0).into(),
                    SocketAddrV6::new(wire::SERVER_V6, port, 0, 0).into(),
                )
            } else {
                (
                    (Ipv4Addr::LOCALHOST, port).into(),
                    (Ipv4Addr::LOCALHOST, 0).into(),
                    SocketAddrV4::new(Ipv4Addr::LOCALHOST, 40_000 + n as u16).into(),
                    SocketAddrV4::new(Ipv4Addr::LOCALHOST, port).into(),
                )
            };
        let group = if addr.is_ipv6() {
            format!(r#"{{"a": "[ff05::71:9]:{port}"}}"#)
        } else {
            format!(r#"{{"a": "239.255.71.9:{port}"}}"#)
        };
        let client = Client::bind(client_bind, coap::EndpointConfig::default()).expect("client");
        let read =
            |path: &str| rt.block_on(support::send(&client, here, Code::GET, path, b"", None));
        let before = read(&app).payload;
        let groups_before = read("/coap-group").payload;
        let changed = String::from_utf8_lossy(&before).replace("\"icp\": 0", "\"icp\": 1");
        assert_ne!(changed.as_bytes(), &before[..], "a real change");

        // From "this machine" as far as the source address goes, arriving on mc0.
        let forged_requests: [(Code, &str, &[u8], Option<u32>); 3] = [
            (Code::PUT, &app, changed.as_bytes(), Some(50)),
            (Code::DELETE, &pointcloud, b"", None),
            (Code::POST, "/coap-group", group.as_bytes(), Some(256)),
        ];
        for (i, (method, path, payload, format)) in forged_requests.into_iter().enumerate() {
            let mut msg = Message::empty(Type::Con, 0x4000 + i as u16);
            msg.code = method;
            msg.token = Token::new(&[7, i as u8]).unwrap_or_default();
            msg.options.set_path(path);
            if let Some(f) = format {
                msg.options.set_uint(OptionNumber::CONTENT_FORMAT, f);
            }
            msg.payload = bytes::Bytes::copy_from_slice(payload);
            // Twice, as a CON might be retransmitted.
            for _ in 0..2 {
                wire::inject(&wire::frame(forged, target, &msg.encode()));
            }
        }

        // The same path carries frames to the server: one from fd00::7 (an address of
        // this machine, but on mc0, not loopback) is a stranger's and draws the Echo
        // challenge, which comes back to a socket bound there.
        if addr.is_ipv6() {
            let stranger = UdpSocket::bind("[fd00::7]:0").expect("bind fd00::7");
            stranger
                .set_read_timeout(Some(Duration::from_secs(5)))
                .expect("timeout");
            let from = stranger.local_addr().expect("address");
            wire::inject(&wire::frame(from, target, &get(&app, 9).encode()));
            let mut buf = [0u8; 1500];
            let (len, _) = stranger.recv_from(&mut buf).expect("an answer on fd00::7");
            let answer = Message::decode(&buf[..len]).expect("a CoAP answer");
            assert_eq!(answer.code, Code::UNAUTHORIZED, "a stranger is challenged");
        }
        // The server works through its datagrams in order; a grace period lets the
        // handlers of anything let through finish.
        std::thread::sleep(Duration::from_millis(500));
        assert_eq!(
            read(&app).payload,
            before,
            "server {n}: the configuration changed"
        );
        let links = String::from_utf8_lossy(&read("/.well-known/core").payload).into_owned();
        assert!(
            links.contains(&format!("<{pointcloud}>")),
            "server {n}: the point cloud resource is gone: {links}"
        );
        assert_eq!(
            read("/coap-group").payload,
            groups_before,
            "server {n}: a group was joined"
        );
        // This machine still may, over loopback.
        let put = rt.block_on(async {
            let mut put = coap::Request::new(Code::PUT, &app).with_payload(changed.clone());
            put.options.set_uint(OptionNumber::CONTENT_FORMAT, 50);
            put.timeout = Some(LIMIT);
            client.send(here, put).await.expect("PUT")
        });
        assert_eq!(put.code, Code::CHANGED, "server {n}: a local PUT");
    }
    mc0_sysctl("route_localnet", &localnet);
    mc0_sysctl("accept_local", &accept_local);
}

/// One HTTP/1.1 request from a socket bound to `from` (an address of this namespace
/// that is not loopback, when the test says so) to `to`; the status code and the body.
fn http_from(from: std::net::IpAddr, to: SocketAddr, method: &str, path: &str) -> (u16, String) {
    use std::io::{Read as _, Write as _};
    use std::net::TcpStream;

    use nix::sys::socket::{
        AddressFamily, SockFlag, SockType, SockaddrStorage, bind, connect, socket,
    };

    let family = if to.is_ipv6() {
        AddressFamily::Inet6
    } else {
        AddressFamily::Inet
    };
    let fd = socket(family, SockType::Stream, SockFlag::SOCK_CLOEXEC, None).expect("socket");
    bind(
        std::os::fd::AsRawFd::as_raw_fd(&fd),
        &SockaddrStorage::from(SocketAddr::new(from, 0)),
    )
    .expect("binding the client's address");
    connect(
        std::os::fd::AsRawFd::as_raw_fd(&fd),
        &SockaddrStorage::from(to),
    )
    .expect("connecting");
    let mut stream = TcpStream::from(fd);
    stream.set_read_timeout(Some(LIMIT)).expect("timeout");
    write!(
        stream,
        "{method} {path} HTTP/1.1\r\nHost: {to}\r\nConnection: close\r\nContent-Length: 0\r\n\r\n"
    )
    .expect("sending");
    let mut raw = String::new();
    stream.read_to_string(&mut raw).expect("reading the answer");
    let status = raw
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("not an HTTP answer: {raw:?}"));
    let body = raw
        .split_once("\r\n\r\n")
        .map_or("", |(_, b)| b)
        .to_string();
    (status, body)
}

#[test]
#[ignore = "off-host: run inside scripts/netns-run (scripts/test.sh does)"]
fn offhost_http_reads_for_everyone_and_measures_only_for_this_machine() {
    let test = "offhost_http_reads_for_everyone_and_measures_only_for_this_machine";
    if !in_namespace(test) {
        return;
    }
    let dir = TempDir::new("offhost-http");
    let port = std::net::TcpListener::bind("[::]:0")
        .and_then(|l| l.local_addr())
        .expect("a free TCP port")
        .port();
    let http = format!("[::]:{port}");
    let (_server, _coap) = serve_at("[::1]:0", &dir.join("state"), &["--http", &http]);
    let local = SocketAddr::from((std::net::Ipv6Addr::LOCALHOST, port));
    let remote: SocketAddr = format!("[fd00::2]:{port}").parse().expect("address");
    let stranger: std::net::IpAddr = "fd00::3".parse().expect("address");
    let deadline = Instant::now() + LIMIT;
    while std::net::TcpStream::connect(local).is_err() {
        assert!(Instant::now() < deadline, "no HTTP server on {local}");
        std::thread::sleep(Duration::from_millis(50));
    }
    // A stranger reads, and is refused a measurement with a JSON error.
    let (status, body) = http_from(stranger, remote, "GET", "/api/measurements");
    assert_eq!(status, 200, "{body}");
    let (status, body) = http_from(stranger, remote, "POST", "/api/measure");
    assert_eq!(status, 403, "{body}");
    let error: serde_json::Value = serde_json::from_str(&body).expect("a JSON error");
    assert!(
        error["error"]
            .as_str()
            .is_some_and(|e| e.contains("own machine")),
        "{body}"
    );
    let (_, body) = http_from(stranger, remote, "GET", "/api/measurements");
    assert_eq!(body.trim(), "[]", "the stranger's POST recorded nothing");
    // This machine measures, over loopback.
    let (status, body) = http_from(
        std::net::Ipv6Addr::LOCALHOST.into(),
        local,
        "POST",
        "/api/measure",
    );
    assert_eq!(status, 201, "{body}");
}

#[test]
#[ignore = "off-host: run inside scripts/netns-run (scripts/test.sh does)"]
fn offhost_the_proxy_reaches_the_stations_own_server_only() {
    let test = "offhost_the_proxy_reaches_the_stations_own_server_only";
    if !in_namespace(test) {
        return;
    }
    use std::sync::atomic::Ordering;
    // Another server of the station's machine, on loopback only, and a host of the LAN.
    let inside = crate::http::CoapStub::on("127.0.0.1:0", b"loopback only".to_vec());
    let lan = crate::http::CoapStub::on("[fd00::4]:0", b"another host".to_vec());
    let dir = TempDir::new("offhost-proxy");
    let port = std::net::TcpListener::bind("[::]:0")
        .and_then(|l| l.local_addr())
        .expect("a free TCP port")
        .port();
    let http = format!("[::]:{port}");
    let (_server, coap) = serve_at("[fd00::2]:0", &dir.join("state"), &["--http", &http]);
    let remote: SocketAddr = format!("[fd00::2]:{port}").parse().expect("address");
    let stranger: std::net::IpAddr = "fd00::3".parse().expect("address");
    let deadline = Instant::now() + LIMIT;
    while std::net::TcpStream::connect(remote).is_err() {
        assert!(Instant::now() < deadline, "no HTTP server on {remote}");
        std::thread::sleep(Duration::from_millis(50));
    }
    // The station's own server, through the proxy, from another host.
    let (status, body) = http_from(
        stranger,
        remote,
        "GET",
        &format!("/hc/coap://{coap}/.well-known/core"),
    );
    assert_eq!(status, 200, "{body}");
    let other = inside.addr.port();
    for target in [
        format!("coap://127.0.0.1:{other}/x"),
        format!("coap://localhost:{other}/x"),
        format!("coap://127.1:{other}/x"),
        format!("coap%3A%2F%2F127.0.0.1%3A{other}%2Fx"),
        format!("coap://[::ffff:127.0.0.1]:{other}/x"),
        format!("coap://{}/x", lan.addr),
        format!("coap://[fd00::5]:{}/x", coap.port()),
        "coap://[ff02::fd%25mc0]:5683/x".to_owned(),
    ] {
        for method in ["GET", "HEAD"] {
            let (status, body) = http_from(stranger, remote, method, &format!("/hc/{target}"));
            assert_eq!(status, 403, "{method} {target}: {body}");
        }
    }
    assert_eq!(
        inside.requests.load(Ordering::Relaxed),
        0,
        "the loopback server was reached"
    );
    assert_eq!(
        lan.requests.load(Ordering::Relaxed),
        0,
        "the LAN host was reached"
    );
}

/// The directory's endpoints of `query`, asked from `client`.
fn rd_endpoints(
    client: &coap_net::Client,
    rd: SocketAddr,
    query: &[&str],
) -> Vec<coap_rd::registrant::Endpoint> {
    let query: Vec<String> = query.iter().map(|q| (*q).to_owned()).collect();
    support::runtime().block_on(async {
        coap_rd::registrant::lookup_endpoints(client, rd, &query, LIMIT)
            .await
            .unwrap_or_else(|e| panic!("endpoint lookup at {rd}: {e:#}"))
    })
}

#[test]
#[ignore = "off-host: run inside scripts/netns-run (scripts/test.sh does)"]
fn offhost_forged_directory_updates_and_removals_leave_the_station_at_its_own_base() {
    let test = "offhost_forged_directory_updates_and_removals_leave_the_station_at_its_own_base";
    if !in_namespace(test) {
        return;
    }
    let dir = TempDir::new("rd-forged");
    let mut rd_proc = Proc::spawn(
        COAPCAM,
        &[
            "rd",
            "--bind",
            "[fd00::2]:0",
            "--no-state",
            "--duration",
            "120",
        ],
    );
    let rd: SocketAddr = rd_proc.stderr_line(LIMIT, |l| {
        l.strip_prefix("coapcam: resource directory on ")
            .and_then(|a| a.trim().parse().ok())
    });
    // The station registers from its server socket on fd00::3; the directory's CoAP
    // layer has verified that address, as in the issue.
    let (_station, station) = serve_at(
        "[fd00::3]:0",
        &dir.join("station"),
        &[
            "--no-cameras",
            "--register",
            &format!("coap://{rd}"),
            "--rd-ep",
            "victim",
            "--rd-lifetime",
            "60",
        ],
    );
    let own_base = format!("coap://{station}");
    let looker = coap_net::Client::bind(
        "[fd00::5]:0".parse().expect("an address"),
        coap::EndpointConfig::default(),
    )
    .expect("a client on fd00::5");
    let deadline = Instant::now() + LIMIT;
    let location = loop {
        if let Some(e) = rd_endpoints(&looker, rd, &["ep=victim"]).first() {
            break e.link.target.clone();
        }
        assert!(Instant::now() < deadline, "the station never registered");
        std::thread::sleep(Duration::from_millis(100));
    };
    // The location is a random 64-bit number, not /rd/1.
    let number: u64 = location
        .strip_prefix("/rd/")
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("location {location}"));
    assert!(number > u64::from(u32::MAX), "{location}");

    // Forged from the station's address and port: a NON update that moves the base
    // and stretches the lifetime, a registration of its name elsewhere, registrations
    // that would fill its quota, and a DELETE (each twice).
    let attacker = "coap://[fd00::66]";
    let non = |method: Code, path: &str, query: &[String], payload: &[u8], mid: u16| {
        let mut msg = Message::empty(Type::Non, mid);
        msg.code = method;
        msg.token = Token::new(&mid.to_be_bytes()).unwrap_or_default();
        msg.options.set_path(path);
        for q in query {
            msg.options.push(OptionNumber::URI_QUERY, q.as_bytes());
        }
        msg.payload = bytes::Bytes::copy_from_slice(payload);
        msg
    };
    let mut forged = vec![
        non(
            Code::POST,
            &location,
            &[format!("base={attacker}"), "lt=100000".to_owned()],
            b"",
            0x5000,
        ),
        non(
            Code::POST,
            "/rd",
            &[
                "ep=victim".to_owned(),
                format!("base={attacker}"),
                "et=coapcam.station".to_owned(),
                "lt=4294967295".to_owned(),
            ],
            b"</cams>",
            0x5001,
        ),
    ];
    for i in 0..64u16 {
        forged.push(non(
            Code::POST,
            "/rd",
            &[format!("ep=squat-{i}"), "lt=4294967295".to_owned()],
            b"",
            0x5100 + i,
        ));
    }
    forged.push(non(Code::DELETE, &location, &[], b"", 0x5200));
    let target = rd;
    for msg in &forged {
        for _ in 0..2 {
            wire::inject(&wire::frame(station, target, &msg.encode()));
        }
    }
    std::thread::sleep(Duration::from_millis(500));
    let listed = rd_endpoints(&looker, rd, &[]);
    assert_eq!(listed.len(), 1, "{listed:?}");
    assert_eq!(listed[0].ep, "victim");
    assert_eq!(listed[0].base, own_base, "{listed:?}");
    assert_eq!(listed[0].link.target, location);

    // A lookup from an address the CoAP layer has verified (as the station's is) but
    // without the directory's own fresh Echo value: a small 4.01, at most three times
    // the request, whoever sent it. With the value, the answer.
    let socket = UdpSocket::bind("[fd00::6]:0").expect("bind fd00::6");
    let lookup = |mid: u16, echo: Option<&[u8]>| {
        let mut msg = get("/rd-lookup/res", mid);
        if let Some(e) = echo {
            msg.options.set(OptionNumber::ECHO, e);
        }
        msg
    };
    let answer = |replies: &[Vec<u8>]| Message::decode(&replies[0]).expect("a CoAP reply");
    // The CoAP layer's challenge, then its Echo value back: the address is verified.
    let first = answer(&exchange(&socket, rd, &lookup(1, None)));
    assert_eq!(first.code, Code::UNAUTHORIZED);
    let layer_echo = first
        .options
        .first(OptionNumber::ECHO)
        .expect("Echo")
        .to_vec();
    let _ = exchange(&socket, rd, &lookup(2, Some(&layer_echo)));
    let request = lookup(3, None);
    let replies = exchange(&socket, rd, &request);
    let (sent, got) = (
        request.encode().len(),
        replies.iter().map(Vec::len).sum::<usize>(),
    );
    eprintln!(
        "a lookup from a verified address without a fresh Echo: {sent} B sent, {got} B back ({:.2}x)",
        got as f64 / sent as f64
    );
    assert!(got <= 3 * sent, "{got} B back for a {sent}-byte lookup");
    let challenge = answer(&replies);
    assert_eq!(challenge.code, Code::UNAUTHORIZED);
    let rd_echo = challenge
        .options
        .first(OptionNumber::ECHO)
        .expect("Echo")
        .to_vec();
    let full = answer(&exchange(&socket, rd, &lookup(4, Some(&rd_echo))));
    assert_eq!(full.code, Code::CONTENT);
    assert!(
        String::from_utf8_lossy(&full.payload).contains(&own_base),
        "{full:?}"
    );
    rd_proc.kill();
}
