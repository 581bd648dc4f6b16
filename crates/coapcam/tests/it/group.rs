//! A multicast grab (issue "camera resource server", RFC 7390): three `coapcam serve` on
//! 127.0.0.2, .3 and .4 in the group 224.0.1.187; one POST /cams/pointclouds to the group
//! gets every server's whole merged cloud, each completed block-wise by unicast from the
//! server's own address. Runs only inside `scripts/netns-run` (a private namespace), which
//! `scripts/test.sh` uses; `#[ignore]`d elsewhere.

use std::net::SocketAddr;
use std::time::Duration;

use coap::{Code, EndpointConfig, Request};
use coap_net::Client;

use crate::cams::{Server, TempDir, serve_at};

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
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let answers = runtime.block_on(async {
        // Bound to 127.0.0.1, not 0.0.0.0: on lo the kernel would otherwise send each
        // unicast follow-up from the address it is sent to (127.0.0.N is local too), and
        // the servers keep the stored cloud for the address that asked.
        let client = Client::bind(
            SocketAddr::from(([127, 0, 0, 1], 0)),
            EndpointConfig::default(),
        )
        .expect("client socket");
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
