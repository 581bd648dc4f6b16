//! A multicast grab (issue "camera resource server", RFC 7390): three `coapcam serve` on
//! 127.0.0.2, .3 and .4 in the group 224.0.1.187; one POST /cams/pointclouds to the group
//! gets every server's whole merged cloud, each completed block-wise by unicast from the
//! server's own address. Runs only inside `scripts/netns-run` (a private namespace), which
//! `scripts/test.sh` uses; `#[ignore]`d elsewhere.

use std::io::{BufRead as _, BufReader};
use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use coap::{Code, EndpointConfig, Request};
use coap_net::Client;

struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
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
    let serial = format!("{host:012}");
    let scene_file = dir.join(format!("scene-{host}.toml"));
    std::fs::write(&scene_file, scene(&serial)).expect("writing the scene");
    let state = dir.join(format!("state-{host}"));
    let mut child = Command::new(env!("CARGO_BIN_EXE_coapcam"))
        .args([
            "serve",
            "--bind",
            &format!("127.0.0.{host}:5683"),
            "--group",
            "224.0.1.187",
        ])
        .args(["--duration", "120", "--scene"])
        .arg(&scene_file)
        .arg("--state-dir")
        .arg(&state)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("starting coapcam serve");
    let stderr = child.stderr.take().expect("stderr pipe");
    let server = Server(child);
    // The server prints its address once the socket is bound and the group joined; it
    // stops by itself after --duration, which bounds this read.
    let mut lines = BufReader::new(stderr).lines();
    let seen = lines
        .by_ref()
        .map_while(Result::ok)
        .any(|l| l.starts_with("coapcam: serving on "));
    assert!(seen, "coapcam serve on 127.0.0.{host} did not start");
    std::thread::spawn(move || lines.for_each(drop));
    server
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
    let dir = std::env::temp_dir().join(format!("coapcam-group-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let _servers: Vec<Server> = [2u8, 3, 4].iter().map(|h| start(*h, &dir)).collect();
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
    let _ = std::fs::remove_dir_all(&dir);
}
