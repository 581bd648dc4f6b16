//! Content negotiation of the grab resources: CBOR maps (decoded with ciborium and compared
//! field by field with the thesis packet of the same frame) and binary PLY point clouds;
//! an Accept a resource cannot produce answers 4.06; and `bench repr`, which sizes and times
//! every representation.

use ciborium::Value;
use coap::{Code, Response};

use crate::support::{COLOR_640, DEPTH_640, SN, TempDir, client, runtime, send, serve};

const CBOR: u16 = 60;
const PLY: u16 = 65100;
const PACKET: u16 = 42;

fn decode(response: &Response) -> Vec<(Value, Value)> {
    assert_eq!(response.code, Code::CONTENT, "{:?}", response.payload);
    assert_eq!(response.options.content_format().map(|c| c.0), Some(CBOR));
    match ciborium::from_reader::<Value, _>(&response.payload[..]) {
        Ok(Value::Map(entries)) => entries,
        other => panic!("not a CBOR map: {other:?}"),
    }
}

fn field<'a>(map: &'a [(Value, Value)], key: &str) -> &'a Value {
    map.iter()
        .find(|(k, _)| k.as_text() == Some(key))
        .map(|(_, v)| v)
        .unwrap_or_else(|| panic!("no key {key:?} in {map:?}"))
}

fn uint(map: &[(Value, Value)], key: &str) -> u64 {
    field(map, key)
        .as_integer()
        .and_then(|i| u64::try_from(i).ok())
        .unwrap_or_else(|| panic!("{key} is not an unsigned integer"))
}

fn float(map: &[(Value, Value)], key: &str) -> f64 {
    field(map, key)
        .as_float()
        .unwrap_or_else(|| panic!("{key} is not a float"))
}

fn text<'a>(map: &'a [(Value, Value)], key: &str) -> &'a str {
    field(map, key)
        .as_text()
        .unwrap_or_else(|| panic!("{key} is not text"))
}

fn bytes<'a>(map: &'a [(Value, Value)], key: &str) -> &'a [u8] {
    field(map, key)
        .as_bytes()
        .unwrap_or_else(|| panic!("{key} is not a byte string"))
}

fn be32(b: &[u8]) -> u32 {
    u32::from_be_bytes([b[0], b[1], b[2], b[3]])
}

/// Common checks of the CBOR fields shared with the packet: the header of `header` bytes
/// holds the timestamp (UNIX seconds) at `timestamp_at`.
fn same_frame_fields(map: &[(Value, Value)], packet: &[u8], header: usize, timestamp_at: usize) {
    assert_eq!(uint(map, "type"), u64::from(packet[0]));
    assert_eq!(text(map, "serial"), SN);
    assert!(uint(map, "frame") >= 1);
    let timestamp_s = be32(&packet[timestamp_at..timestamp_at + 4]);
    assert_eq!(uint(map, "timestamp"), u64::from(timestamp_s));
    assert_eq!(
        uint(map, "timestamp_us") / 1_000_000,
        u64::from(timestamp_s)
    );
    assert_eq!(bytes(map, "data"), &packet[header..]);
}

fn intrinsics(map: &[(Value, Value)], width: u64, height: u64) {
    let Value::Map(k) = field(map, "intrinsics") else {
        panic!("intrinsics is not a map");
    };
    assert_eq!((uint(k, "width"), uint(k, "height")), (width, height));
    for key in ["fx", "fy", "ppx", "ppy"] {
        assert!(float(k, key) > 0.0, "{key}");
    }
    assert!(!text(k, "model").is_empty());
    let coeffs = field(k, "coeffs").as_array().expect("coeffs array");
    assert_eq!(coeffs.len(), 5);
}

#[test]
fn cbor_maps_carry_the_packet_fields_of_the_same_frame() {
    let state = TempDir::new("formats-cbor");
    let (_server, addr) = serve(state.path());
    runtime().block_on(async {
        let c = client();
        for (name, doc) in [("color-settings", COLOR_640), ("depth-settings", DEPTH_640)] {
            let path = format!("/cams/{SN}/{name}");
            let r = send(&c, addr, Code::PUT, &path, doc.as_bytes(), None).await;
            assert_eq!(r.code, Code::CHANGED, "{name}");
        }
        // Color: a CBOR grab, then the same frame as the thesis packet.
        let color = format!("/cams/{SN}/color");
        let grabbed = send(&c, addr, Code::POST, &color, b"", Some(CBOR)).await;
        let map = decode(&grabbed);
        let packet = send(&c, addr, Code::GET, &color, b"", Some(PACKET)).await;
        assert_eq!(packet.payload.len(), 921_610);
        same_frame_fields(&map, &packet.payload, 10, 6);
        assert_eq!((uint(&map, "width"), uint(&map, "height")), (640, 480));
        assert_eq!(uint(&map, "pixel_size"), 3);
        assert_eq!(text(&map, "format"), "BGR8");
        intrinsics(&map, 640, 480);
        // One ETag per representation; GET with Accept 60 is the stored grab again.
        assert_ne!(grabbed.options.etag(), packet.options.etag());
        let again = send(&c, addr, Code::GET, &color, b"", Some(CBOR)).await;
        assert_eq!(again.payload, grabbed.payload);
        assert_eq!(again.options.etag(), grabbed.options.etag());

        let depth = format!("/cams/{SN}/depth");
        let map = decode(&send(&c, addr, Code::POST, &depth, b"", Some(CBOR)).await);
        let packet = send(&c, addr, Code::GET, &depth, b"", Some(PACKET)).await;
        assert_eq!(packet.payload.len(), 14 + 640 * 480 * 2);
        same_frame_fields(&map, &packet.payload, 14, 6);
        assert_eq!(uint(&map, "pixel_size"), 2);
        let scale = f32::from_be_bytes([
            packet.payload[10],
            packet.payload[11],
            packet.payload[12],
            packet.payload[13],
        ]);
        assert_eq!(float(&map, "depth_scale") as f32, scale);
        intrinsics(&map, 640, 480);

        let cloud = format!("/cams/{SN}/pointcloud");
        let map = decode(&send(&c, addr, Code::POST, &cloud, b"", Some(CBOR)).await);
        let packet = send(&c, addr, Code::GET, &cloud, b"", Some(PACKET)).await;
        let n = be32(&packet.payload[4..8]);
        assert!(n > 0);
        assert_eq!(uint(&map, "points"), u64::from(n));
        assert_eq!(uint(&map, "point_size"), 12);
        same_frame_fields(&map, &packet.payload, 12, 8);

        let all = send(&c, addr, Code::POST, "/cams/pointclouds", b"", Some(CBOR)).await;
        let map = decode(&all);
        assert_eq!(uint(&map, "type"), 3);
        let serials = field(&map, "serials").as_array().expect("serials array");
        assert_eq!(serials, &[Value::Text(SN.to_string())]);
        assert_eq!(bytes(&map, "data").len() as u64, 12 * uint(&map, "points"));
        assert!(uint(&map, "points") > 0);
    });
}

#[test]
fn point_clouds_as_ply_hold_the_points_of_the_packet() {
    let state = TempDir::new("formats-ply");
    let (_server, addr) = serve(state.path());
    runtime().block_on(async {
        let c = client();
        let path = format!("/cams/{SN}/depth-settings");
        let r = send(&c, addr, Code::PUT, &path, DEPTH_640.as_bytes(), None).await;
        assert_eq!(r.code, Code::CHANGED);
        let cloud = format!("/cams/{SN}/pointcloud");
        let ply = send(&c, addr, Code::POST, &cloud, b"", Some(PLY)).await;
        assert_eq!(ply.code, Code::CONTENT);
        assert_eq!(ply.options.content_format().map(|c| c.0), Some(PLY));
        let header =
            format!("ply\nformat binary_little_endian 1.0\ncomment coapcam camera {SN} frame ");
        assert!(ply.payload.starts_with(header.as_bytes()));
        let decoded = geometry::decode_ply(&ply.payload).expect("a valid PLY file");
        let packet = send(&c, addr, Code::GET, &cloud, b"", Some(PACKET)).await;
        assert_eq!(decoded.len(), be32(&packet.payload[4..8]) as usize);
        let from_packet: Vec<[u32; 3]> = packet.payload[12..]
            .chunks_exact(12)
            .map(|p| {
                let f = |i: usize| u32::from_le_bytes([p[i], p[i + 1], p[i + 2], p[i + 3]]);
                [f(0), f(4), f(8)]
            })
            .collect();
        let from_ply: Vec<[u32; 3]> = decoded
            .points
            .iter()
            .map(|p| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
            .collect();
        assert!(from_ply == from_packet, "PLY and packet points differ");
        // The latest frame as PLY is the same file.
        let latest = send(&c, addr, Code::GET, &cloud, b"", Some(PLY)).await;
        assert_eq!(latest.payload, ply.payload);

        let all = send(&c, addr, Code::POST, "/cams/pointclouds", b"", Some(PLY)).await;
        assert_eq!(all.code, Code::CONTENT);
        let merged = geometry::decode_ply(&all.payload).expect("a valid PLY file");
        assert!(!merged.is_empty());
    });
}

#[test]
fn an_accept_a_resource_cannot_produce_answers_4_06() {
    let state = TempDir::new("formats-406");
    let (_server, addr) = serve(state.path());
    runtime().block_on(async {
        let c = client();
        for (path, accept) in [
            (format!("/cams/{SN}/color"), PLY),
            (format!("/cams/{SN}/depth"), PLY),
            (format!("/cams/{SN}/depth"), 22),
            (format!("/cams/{SN}/pointcloud"), 22),
            ("/cams/pointclouds".to_string(), 23),
        ] {
            for method in [Code::POST, Code::GET] {
                if path == "/cams/pointclouds" && method == Code::GET {
                    continue;
                }
                let r = send(&c, addr, method, &path, b"", Some(accept)).await;
                assert_eq!(r.code, Code::NOT_ACCEPTABLE, "{method:?} {path} {accept}");
                assert!(!r.payload.is_empty(), "a diagnostic names the formats");
            }
        }
    });
}

/// `bench repr`: every representation of the demo scene's depth, color and merged cloud,
/// with its bytes; the compact depth forms are smaller than the packet.
#[test]
fn bench_repr_reports_every_representation() {
    let args = ["bench", "repr", "--runs", "1", "--json"];
    let finished = crate::support::Proc::run(
        crate::support::COAPCAM,
        &args,
        std::time::Duration::from_secs(120),
    )
    .expect_success("coapcam bench repr");
    let report: serde_json::Value =
        serde_json::from_str(&finished.stdout_text()).expect("the report is JSON");
    let rows = report["representations"]
        .as_array()
        .expect("representations");
    let bytes = |what: &str, cf: u64| {
        rows.iter()
            .find(|r| r["what"] == what && r["content_format"] == cf)
            .and_then(|r| r["bytes"].as_u64())
            .unwrap_or_else(|| panic!("no {what} in {cf}: {report:#}"))
    };
    for (what, formats) in [
        ("depth", &[42, 23, 65101, 65102, 60][..]),
        ("color", &[42, 23, 22, 60][..]),
        ("merged cloud", &[42, 65100, 60][..]),
    ] {
        for &cf in formats {
            assert!(bytes(what, cf) > 0);
        }
    }
    assert_eq!(bytes("depth", 42), 1_843_214, "a 1280x720 depth packet");
    assert!(bytes("depth", 65102) < bytes("depth", 65101));
    assert!(bytes("depth", 65101) < bytes("depth", 42) / 2);
    assert!(
        report["points"].as_u64().is_some_and(|n| n > 1000),
        "{report:#}"
    );
}
