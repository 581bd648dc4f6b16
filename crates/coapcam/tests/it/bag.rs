//! `coapcam serve --bag FILE`: librealsense recordings (the rgbd crate's fixtures,
//! written by `tools/record_bags.py`) served as cameras; a POST grab of depth returns
//! the recorded pixels.

use std::path::PathBuf;

use coap::Code;
use serde::Deserialize;

use crate::support::{TempDir, client, runtime, send, serve_at};

#[derive(Deserialize)]
struct Expected {
    serial: String,
    depth_scale: f32,
    frames: Frames,
}

#[derive(Deserialize)]
struct Frames {
    depth: Vec<Frame>,
}

#[derive(Deserialize)]
struct Frame {
    fnv1a64: String,
}

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../rgbd/tests/fixtures/bag")
        .join(name)
}

fn fnv1a64(bytes: &[u8]) -> String {
    let h = bytes.iter().fold(0xcbf2_9ce4_8422_2325_u64, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    });
    format!("{h:016x}")
}

const DEPTH_1280: &str = r#"{"format": "Z16", "fps": 30, "width": 1280, "height": 720}"#;

#[test]
fn serve_bag_grabs_the_recorded_depth_frames_in_order() {
    for file in ["d415.bag", "d415.db3"] {
        let expected: Expected = serde_json::from_slice(
            &std::fs::read(fixture(&format!("{file}.expected.json"))).expect("expected JSON"),
        )
        .expect("expected JSON parses");
        let state = TempDir::new(&format!("bag-{file}"));
        let recording = fixture(file).to_string_lossy().into_owned();
        let (_server, addr) = serve_at("127.0.0.1:0", state.path(), &["--bag", &recording]);
        let sn = &expected.serial;
        runtime().block_on(async {
            let c = client();
            let depth = format!("/cams/{sn}/depth");
            for (i, frame) in expected.frames.depth.iter().enumerate() {
                let r = send(&c, addr, Code::POST, &depth, b"", None).await;
                assert_eq!(r.code, Code::CONTENT, "{file}: POST {depth}");
                let p = &r.payload;
                assert_eq!(p[0], 2, "depth packet");
                assert_eq!(&p[1..5], &[0x02, 0x80, 0x01, 0xe0], "640x480");
                assert_eq!(&p[10..14], &expected.depth_scale.to_be_bytes());
                assert_eq!(fnv1a64(&p[14..]), frame.fnv1a64, "{file}: depth frame {i}");
            }
            let r = send(
                &c,
                addr,
                Code::PUT,
                &format!("/cams/{sn}/depth-settings"),
                DEPTH_1280.as_bytes(),
                None,
            )
            .await;
            assert_eq!(r.code, Code::BAD_REQUEST, "{file}: another resolution");
            let why = String::from_utf8_lossy(&r.payload);
            assert!(why.contains("640x480"), "{why}");
        });
    }
}
