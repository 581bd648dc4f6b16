//! The client commands end to end against a real `coapcam serve`: `grab` in every stream
//! and file type (and the pictures of `--view`), `measure` on the default scene, `monitor`
//! (repeated grabs, failures, observation, Ctrl-C) and `demo`.

use std::path::Path;
use std::time::Duration;

use image::{DynamicImage, ImageFormat};

use crate::support::{COAPCAM, COLOR_640, DEPTH_640, SN, TempDir, serve};
use crate::support::{Finished, Proc};

/// Bound on one command (the servers stop by themselves after 120 s).
const LIMIT: Duration = Duration::from_secs(110);

/// The default scene's box, millimetres (docs/design.md §7, `Scene::default_single`).
const BOX_MM: [f64; 3] = [400.0, 300.0, 200.0];
/// How far a measured dimension may be from the box.
const TOLERANCE_MM: f64 = 5.0;

/// Runs `coapcam ARGS` to its end.
fn coapcam(args: &[&str]) -> Finished {
    Proc::run(COAPCAM, args, LIMIT)
}

fn ok(args: &[&str]) -> Finished {
    coapcam(args).expect_success(&format!("coapcam {}", args.join(" ")))
}

fn path(p: &Path) -> &str {
    p.to_str().expect("UTF-8 path")
}

fn decode(file: &Path, format: ImageFormat) -> DynamicImage {
    let bytes = std::fs::read(file).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
    image::load_from_memory_with_format(&bytes, format)
        .unwrap_or_else(|e| panic!("{} does not decode: {e}", file.display()))
}

/// The header lines of a binary PLY file and the bytes after `end_header`.
fn ply_parts(bytes: &[u8]) -> (Vec<String>, &[u8]) {
    let end = b"end_header\n";
    let at = bytes
        .windows(end.len())
        .position(|w| w == end)
        .expect("a PLY header ending in end_header");
    let header = String::from_utf8_lossy(&bytes[..at])
        .lines()
        .map(str::to_owned)
        .collect();
    (header, &bytes[at + end.len()..])
}

/// Points in a thesis point-cloud packet, checking its length.
fn cloud_packet_points(packet: &[u8]) -> usize {
    assert_eq!(packet.get(..2), Some(&[3u8, 12][..]), "point-cloud header");
    let n = u32::from_be_bytes([packet[4], packet[5], packet[6], packet[7]]) as usize;
    assert_eq!(packet.len(), 12 + 12 * n, "{n} points");
    n
}

/// A default server with 640x480 color and depth (quick grabs).
fn small_server(state: &TempDir) -> (crate::support::Server, String) {
    let (server, addr) = serve(state.path());
    let uri = format!("coap://{addr}");
    for (name, doc) in [("color-settings", COLOR_640), ("depth-settings", DEPTH_640)] {
        let resource = format!("{uri}/cams/{SN}/{name}");
        ok(&[
            "put",
            &resource,
            "--payload",
            doc,
            "--content-format",
            "json",
        ]);
    }
    (server, uri)
}

#[test]
fn grab_writes_every_stream_in_every_file_type() {
    let state = TempDir::new("client-grab");
    let (_server, uri) = small_server(&state);
    let dir = state.path();
    let grab = |stream: &str, file: &str, extra: &[&str]| {
        let out = dir.join(file);
        let mut args = vec!["grab", stream, "--server", &uri, "-o", path(&out)];
        args.extend_from_slice(extra);
        ok(&args);
        out
    };

    let png = decode(&grab("color", "color.png", &[]), ImageFormat::Png);
    assert!(
        matches!(png, DynamicImage::ImageRgb8(_)),
        "{:?}",
        png.color()
    );
    assert_eq!((png.width(), png.height()), (640, 480));
    let jpg = decode(&grab("color", "color.jpg", &[]), ImageFormat::Jpeg);
    assert_eq!((jpg.width(), jpg.height()), (640, 480));
    let packet = std::fs::read(grab("color", "color.bin", &[])).expect("color.bin");
    assert_eq!(packet.len(), 10 + 640 * 480 * 3);
    assert_eq!(
        packet[..6],
        [1, 2, 128, 1, 224, 3],
        "type, 640, 480, 3 bytes"
    );

    let depth = decode(&grab("depth", "depth.png", &[]), ImageFormat::Png);
    let DynamicImage::ImageLuma16(depth) = depth else {
        panic!("depth.png is not 16-bit grayscale: {:?}", depth.color());
    };
    assert_eq!(depth.dimensions(), (640, 480));
    // The box top is 0.8 m from the camera, the floor 1 m: raw units of 1 mm.
    let centre = depth.get_pixel(320, 240).0[0];
    assert!(
        (780..=820).contains(&centre),
        "depth at the centre {centre}"
    );
    let packet = std::fs::read(grab("depth", "depth.bin", &[])).expect("depth.bin");
    assert_eq!(packet.len(), 14 + 640 * 480 * 2);
    assert_eq!(packet[..6], [2, 2, 128, 1, 224, 2]);

    let ply = std::fs::read(grab("pointcloud", "cloud.ply", &[])).expect("cloud.ply");
    let (header, body) = ply_parts(&ply);
    assert_eq!(header[0], "ply");
    assert_eq!(header[1], "format binary_little_endian 1.0");
    let vertices: usize = header
        .iter()
        .find_map(|l| l.strip_prefix("element vertex "))
        .and_then(|n| n.trim().parse().ok())
        .unwrap_or_else(|| panic!("no vertex count in {header:?}"));
    let properties: Vec<&String> = header
        .iter()
        .filter(|l| l.starts_with("property "))
        .collect();
    assert_eq!(
        properties,
        ["property float x", "property float y", "property float z"]
    );
    assert!(vertices > 100_000, "{vertices} points");
    assert_eq!(body.len(), 12 * vertices, "the body holds every vertex");
    let decoded = geometry::decode_ply(&ply).expect("our PLY reader");
    assert_eq!(decoded.len(), vertices);
    let packet = std::fs::read(grab("pointcloud", "cloud.bin", &[])).expect("cloud.bin");
    let n = cloud_packet_points(&packet);
    assert!(n > 100_000, "{n} points");
    let merged = std::fs::read(grab("pointcloud", "all.bin", &["--all"])).expect("all.bin");
    // One camera: the merged cloud is a new frame of its cloud (the noise differs).
    let m = cloud_packet_points(&merged);
    assert!(m.abs_diff(n) < n / 50, "{m} points merged, {n} in one grab");
    // The compact clouds: the filtered depth with its geometry, and quantized millimetres.
    let dcl = std::fs::read(grab("pointcloud", "cloud.dcl", &[])).expect("cloud.dcl");
    let from_depth = coapcam::repr::clouds::cloud_from_depth_cloud(&dcl).expect("65103 decodes");
    assert_eq!(from_depth.serials, [SN]);
    let k = from_depth.cloud.points.len();
    assert!(
        k.abs_diff(n) < n / 50,
        "{k} points from .dcl, {n} in a packet"
    );
    assert!(
        dcl.len() * 8 < packet.len(),
        "{} B .dcl, {} B packet",
        dcl.len(),
        packet.len()
    );
    let qmm = std::fs::read(grab("pointcloud", "cloud.qmm", &[])).expect("cloud.qmm");
    let from_mm = coapcam::repr::clouds::cloud_from_mm(&qmm).expect("65104 decodes");
    assert!(from_mm.cloud.points.len().abs_diff(n) < n / 50);
    assert!(
        qmm.len() * 4 < packet.len(),
        "{} B .qmm, {} B packet",
        qmm.len(),
        packet.len()
    );

    // --view: the pictures a person looks at.
    let view = dir.join("color-view.png");
    grab("color", "c.bin", &["--view", path(&view)]);
    let v = decode(&view, ImageFormat::Png);
    assert_eq!((v.width(), v.height()), (640, 480));
    let view = dir.join("depth-view.png");
    grab("depth", "d.bin", &["--view", path(&view)]);
    let gray = decode(&view, ImageFormat::Png);
    assert_eq!((gray.width(), gray.height()), (640, 480));
    let colored = decode(&dir.join("depth-view-color.png"), ImageFormat::Png);
    assert_eq!((colored.width(), colored.height()), (640, 480));
    let gray = gray.to_luma8();
    // Near is bright: the box top is brighter than the floor beside it.
    assert!(
        gray.get_pixel(320, 240).0[0] > gray.get_pixel(20, 20).0[0],
        "box top not brighter than the floor"
    );
    let view = dir.join("cloud-view.png");
    grab("pointcloud", "p.ply", &["--view", path(&view)]);
    let top = decode(&view, ImageFormat::Png);
    assert!(top.width() > 0 && top.height() > 0);
}

#[test]
fn grab_refuses_a_file_type_that_does_not_fit() {
    let state = TempDir::new("client-grab-refused");
    // Refused before any request: no server is needed (port 9 discards).
    let uri = "coap://127.0.0.1:9".to_owned();
    let files = state.path().join("files");
    std::fs::create_dir_all(&files).expect("a directory for the files");
    let out = |name: &str| path(&files.join(name)).to_owned();
    let cases: [(Vec<String>, &str); 6] = [
        (
            vec!["color".into(), "-o".into(), out("c.txt")],
            "extension must be",
        ),
        (
            vec!["depth".into(), "-o".into(), out("d.jpg")],
            "cannot be written as .jpg",
        ),
        (
            vec!["pointcloud".into(), "-o".into(), out("p.png")],
            "cannot be written as .png",
        ),
        (
            vec!["color".into(), "-o".into(), out("c.ply")],
            "cannot be written as .ply",
        ),
        (
            vec![
                "color".into(),
                "-o".into(),
                out("c.png"),
                "--view".into(),
                out("v.jpg"),
            ],
            "--view writes PNG",
        ),
        (
            vec!["depth".into(), "--all".into(), "-o".into(), out("d.png")],
            "--all is for point clouds",
        ),
    ];
    for (args, why) in &cases {
        let mut all = vec!["grab", "--server", &uri];
        all.extend(args.iter().map(String::as_str));
        let f = coapcam(&all);
        assert!(!f.status.success(), "{all:?} succeeded");
        assert!(f.stderr.contains(why), "{all:?}: {}", f.stderr);
    }
    let written: Vec<_> = std::fs::read_dir(&files)
        .expect("the directory")
        .filter_map(Result::ok)
        .map(|e| e.path())
        .collect();
    assert!(written.is_empty(), "files written: {written:?}");
}

/// Checks a `measure --json` object against the default scene.
fn assert_measures_the_box(m: &serde_json::Value) {
    for key in [
        "length_mm",
        "width_mm",
        "height_mm",
        "yaw_deg",
        "corners_m",
        "volume_l",
        "parcel_points",
        "cameras",
        "frames_unix_us",
    ] {
        assert!(m.get(key).is_some(), "{key} missing in {m}");
    }
    let got = ["length_mm", "width_mm", "height_mm"].map(|k| m[k].as_f64().expect(k));
    assert!(got[0] >= got[1], "length < width: {m}");
    for (g, want) in got.iter().zip(BOX_MM) {
        assert!((g - want).abs() <= TOLERANCE_MM, "{got:?} vs {BOX_MM:?}");
    }
    let corners = m["corners_m"].as_array().expect("corners");
    assert_eq!(corners.len(), 4);
    assert!(
        corners
            .iter()
            .all(|c| c.as_array().is_some_and(|xy| xy.len() == 2))
    );
    let yaw = m["yaw_deg"].as_f64().expect("yaw");
    assert!((yaw - 15.0).abs() < 2.0, "yaw {yaw}");
    let volume = m["volume_l"].as_f64().expect("volume");
    assert!((volume - 24.0).abs() < 1.0, "volume {volume} l");
    assert!(m["parcel_points"].as_u64().is_some_and(|p| p > 1000), "{m}");
    let stamps = m["frames_unix_us"].as_array().expect("timestamps");
    assert!(
        !stamps.is_empty()
            && stamps
                .iter()
                .all(|t| t.as_u64() > Some(1_600_000_000_000_000))
    );
}

#[test]
fn measure_finds_the_default_scenes_box() {
    let state = TempDir::new("client-measure");
    let (_server, addr) = serve(state.path());
    let uri = format!("coap://{addr}");

    let m = ok(&["measure", "--server", &uri, "--json"]).json();
    assert_measures_the_box(&m);
    assert_eq!(m["cameras"], serde_json::json!([SN]));
    assert_eq!(m["warnings"], serde_json::json!([]), "a calibrated camera");

    let annotated = state.path().join("annotated.png");
    let m = ok(&[
        "measure",
        "--server",
        &uri,
        "--camera",
        SN,
        "--json",
        "--annotate",
        path(&annotated),
    ])
    .json();
    assert_measures_the_box(&m);
    assert_eq!(m["cameras"], serde_json::json!([SN]));
    let picture = decode(&annotated, ImageFormat::Png);
    assert!(picture.width() >= 640 && picture.height() >= 480);

    let text = ok(&["measure", "--server", &uri, "--codes"]).stdout_text();
    assert!(text.starts_with("length "), "{text}");
    assert!(text.contains(SN), "{text}");
    assert!(
        text.contains(&format!(
            "codes: qr \"PKG-0001\" ({SN}) (grabbed and read in "
        )),
        "{text}"
    );

    // --prepare cuts the floor out of what the camera sends: the same box from a
    // fraction of the points, and the camera's application-config says so afterwards.
    let whole = m["received_bytes"].as_u64().expect("bytes");
    let m = ok(&[
        "measure",
        "--server",
        &uri,
        "--prepare",
        "--codes",
        "--json",
    ])
    .json();
    assert_measures_the_box(&m);
    assert_eq!(
        m["codes"],
        serde_json::json!([{ "kind": "qr", "text": "PKG-0001", "cameras": [SN] }])
    );
    assert!(m["codes_ms"].as_f64().is_some(), "{m}");
    let cut = m["received_bytes"].as_u64().expect("bytes");
    assert!(
        cut * 3 < whole,
        "{cut} bytes with --prepare, {whole} without"
    );
    let config = ok(&["get", &format!("{uri}/cams/{SN}/application-config")]).json();
    let min_z = config["roi3d"]["min_z"].as_f64().expect("min_z");
    assert!((min_z - 0.005).abs() < 1e-6, "{config}");
    assert_ne!(
        config["postprocessing"]["spatial"],
        serde_json::json!(0),
        "{config}"
    );
    // --codes made the color stream 1920x1080 (the codes' resolution).
    let color = ok(&["get", &format!("{uri}/cams/{SN}/color-settings")]).json();
    assert_eq!(
        (&color["width"], &color["height"]),
        (&1920.into(), &1080.into())
    );

    let f = coapcam(&["measure", "--server", &uri, "--camera", "999999999999"]);
    assert!(!f.status.success());
    assert!(f.stderr.contains("4.04"), "{}", f.stderr);
}

#[test]
fn monitor_prints_each_result_and_the_statistics() {
    let state = TempDir::new("client-monitor");
    let (_server, uri) = small_server(&state);

    let f = ok(&[
        "monitor",
        "color",
        "--server",
        &uri,
        "--count",
        "3",
        "--interval",
        "0.05",
        "--accept",
        "42",
    ]);
    let text = f.stdout_text();
    let results: Vec<&str> = text.lines().filter(|l| l.starts_with('#')).collect();
    assert_eq!(results.len(), 3, "{text}");
    for (i, line) in results.iter().enumerate() {
        assert!(line.starts_with(&format!("#{}", i + 1)), "{line}");
        assert!(line.contains("921,610 B"), "{line}");
        assert!(line.contains(" ms"), "{line}");
    }
    assert!(text.contains("3 result(s), 0 failed"), "{text}");
    let header = text
        .lines()
        .find(|l| l.contains("median ms"))
        .unwrap_or_else(|| panic!("no statistics table: {text}"));
    for column in ["count", "min ms", "max ms", "mean ms", "sd ms", "cv"] {
        assert!(header.contains(column), "{header}");
    }

    let f = ok(&[
        "monitor",
        "pointcloud",
        "--server",
        &uri,
        "--count",
        "2",
        "--interval",
        "0",
        "--json",
    ]);
    let lines = f.json_lines();
    assert_eq!(lines.len(), 3, "two results and the statistics: {lines:?}");
    for (i, l) in lines[..2].iter().enumerate() {
        assert_eq!(l["n"], i + 1);
        assert_eq!(l["ok"], true);
        // The compact cloud of 640x480 depth; the packet would be 3.1 MB.
        assert!(
            l["received_bytes"]
                .as_u64()
                .is_some_and(|b| b > 10_000 && b < 500_000),
            "{l}"
        );
        assert!(l["time_ms"].as_f64().is_some_and(|t| t > 0.0), "{l}");
    }
    let stats = &lines[2]["statistics"];
    assert_eq!(stats["count"], 2);
    assert_eq!(stats["failed"], 0);
    let ns = |k: &str| {
        stats[k]
            .as_u64()
            .unwrap_or_else(|| panic!("{k} in {stats}"))
    };
    assert!(ns("min_ns") <= ns("median_ns") && ns("median_ns") <= ns("max_ns"));
    assert!(ns("min_ns") <= ns("mean_ns") && ns("mean_ns") <= ns("max_ns"));
    let times: Vec<f64> = lines[..2]
        .iter()
        .map(|l| l["time_ms"].as_f64().expect("time"))
        .collect();
    // Two samples: the population deviation is half their difference.
    let sd_ms = (times[0] - times[1]).abs() / 2.0;
    assert!(
        (ns("sd_ns") as f64 / 1e6 - sd_ms).abs() < 0.01,
        "{stats} {times:?}"
    );

    // A measurement per result: the dimensions on each line.
    let f = ok(&[
        "monitor", "measure", "--server", &uri, "--count", "1", "--json",
    ]);
    let lines = f.json_lines();
    assert_eq!(lines.len(), 2, "{lines:?}");
    assert_measures_the_box(&lines[0]);
    assert_eq!(lines[1]["statistics"]["count"], 1);
}

#[test]
fn monitor_counts_failures_without_stopping() {
    let state = TempDir::new("client-monitor-fail");
    let (_server, addr) = serve(state.path());
    let uri = format!("coap://{addr}");
    let f = coapcam(&[
        "monitor",
        "depth",
        "--server",
        &uri,
        "--camera",
        "999999999999",
        "--count",
        "2",
        "--interval",
        "0.01",
    ]);
    // Nothing succeeded: the exit status of the last failure (3: an error response),
    // after every result and the statistics.
    assert_eq!(f.status.code(), Some(3), "{}", f.stderr);
    let text = f.stdout_text();
    let failed: Vec<&str> = text
        .lines()
        .filter(|l| l.contains("failed after"))
        .collect();
    assert_eq!(failed.len(), 2, "{text}");
    assert!(failed[0].contains("4.04"), "{text}");
    assert!(text.contains("0 result(s), 2 failed"), "{text}");
}

#[test]
fn monitor_observes_each_grab_and_stops_on_ctrl_c() {
    let state = TempDir::new("client-monitor-observe");
    let (_server, uri) = small_server(&state);
    let depth = format!("{uri}/cams/{SN}/depth");
    // The observation starts from the latest frame.
    ok(&["post", &depth, "-o", path(&state.path().join("first.bin"))]);
    let mut watcher = Proc::spawn(
        COAPCAM,
        &["monitor", "depth", "--observe", "--server", &uri, "--json"],
    );
    let size = |l: &str| {
        let v: serde_json::Value = serde_json::from_str(l).ok()?;
        v["received_bytes"].as_u64()
    };
    // Each notification arrives whole (it is sent block-wise).
    assert_eq!(watcher.stdout_line(LIMIT, size), 14 + 640 * 480 * 2);
    for _ in 0..2 {
        ok(&["post", &depth, "-o", path(&state.path().join("next.bin"))]);
        assert_eq!(watcher.stdout_line(LIMIT, size), 14 + 640 * 480 * 2);
    }
    let last = watcher.interrupt_json();
    assert_eq!(last["statistics"]["count"], 3, "{last}");
    assert_eq!(last["statistics"]["failed"], 0, "{last}");
}

#[test]
fn demo_writes_its_files_and_the_table() {
    let dir = TempDir::new("client-demo");
    let out = dir.path().join("demo");
    let f = ok(&["demo", "--dir", path(&out)]);
    let text = f.stdout_text();
    for (name, format) in [
        ("color.jpg", ImageFormat::Jpeg),
        ("depth.png", ImageFormat::Png),
        ("annotated.png", ImageFormat::Png),
    ] {
        let picture = decode(&out.join(name), format);
        assert!(picture.width() >= 640, "{name}");
    }
    let depth = decode(&out.join("depth.png"), ImageFormat::Png);
    assert!(
        matches!(depth, DynamicImage::ImageLuma16(_)),
        "depth.png holds raw 16-bit units"
    );
    let ply = std::fs::read(out.join("cloud.ply")).expect("cloud.ply");
    let cloud = geometry::decode_ply(&ply).expect("cloud.ply decodes");
    assert!(cloud.len() > 1000, "{} points", cloud.len());
    for row in ["length mm", "width mm", "height mm", "yaw deg"] {
        let line = text
            .lines()
            .find(|l| l.starts_with(row))
            .unwrap_or_else(|| panic!("no {row} row: {text}"));
        let error: f64 = line
            .split_whitespace()
            .last()
            .and_then(|e| e.parse().ok())
            .unwrap_or_else(|| panic!("no error column: {line}"));
        let tolerance = if row == "yaw deg" { 2.0 } else { TOLERANCE_MM };
        assert!(error.abs() <= tolerance, "{line}");
    }
    assert!(
        text.contains("measured") && text.contains("scene"),
        "{text}"
    );
    assert!(
        text.contains(
            "codes: qr \"PKG-0001\" (840412060746, 840412060757); on the scene's parcels: qr \"PKG-0001\""
        ),
        "{text}"
    );
    // Everything the demo leaves in its folder is named in the README's paragraph on
    // it (issue 51, item 13: the server's state/ folder was not).
    let readme = include_str!("../../../../README.md");
    let mut unnamed = Vec::new();
    for entry in std::fs::read_dir(&out).expect("the demo's folder") {
        let name = entry.expect("an entry").file_name();
        let name = name.to_str().expect("UTF-8 name");
        let named = if out.join(name).is_dir() {
            readme.contains(&format!("`./coapcam-demo/{name}/`"))
        } else {
            readme.contains(&format!("`{name}`"))
        };
        if !named {
            unnamed.push(name.to_owned());
        }
    }
    assert!(
        unnamed.is_empty(),
        "the demo writes {unnamed:?}, which README.md does not name"
    );
}

#[test]
fn calibrate_floor_levels_a_tilted_camera_so_measure_is_within_5_mm() {
    let state = TempDir::new("client-calibrate");
    let scene = crate::support::tilted_uncalibrated_scene(state.path());
    let (_server, addr) = crate::support::serve_with(state.path(), &["--scene", path(&scene)]);
    let uri = format!("coap://{addr}");
    let doc = format!("{uri}/cams/{SN}/3d-transformation");
    let identity = ok(&["get", &doc]).stdout_text();

    // --dry-run fits and reports, and writes nothing.
    let dry = ok(&[
        "calibrate",
        "--server",
        &uri,
        "--floor",
        "--dry-run",
        "--json",
    ])
    .json();
    assert_eq!(dry["written"], false);
    assert_eq!(ok(&["get", &doc]).stdout_text(), identity);

    let report = ok(&["calibrate", "--server", &uri, "--floor", "--json"]).json();
    assert_eq!(report["camera"], SN);
    let height = report["height_mm"].as_f64().expect("height");
    let tilt = report["tilt_deg"].as_f64().expect("tilt");
    assert!((height - 1050.0).abs() < 10.0, "{report}");
    assert!((tilt - 28.5).abs() < 0.5, "{report}");

    crate::support::assert_box_within_5_mm(&ok(&["measure", "--server", &uri, "--json"]).json());

    // --adjust sets the post rotation and translation given, and keeps the rest.
    ok(&[
        "calibrate",
        "--server",
        &uri,
        "--camera",
        SN,
        "--adjust",
        "--yaw",
        "-10",
        "--dz",
        "0.002",
    ]);
    let after: serde_json::Value =
        serde_json::from_str(&ok(&["get", &doc]).stdout_text()).expect("JSON");
    // Column vectors, as the thesis writes them (Listing A.4).
    assert_eq!(
        after["post_rotation_matrix"],
        serde_json::json!([[0.0], [0.0], [-10.0]])
    );
    assert_eq!(
        after["post_translation_matrix"],
        serde_json::json!([[0.0], [0.0], [0.002]])
    );
    assert_eq!(
        after["translation_matrix"],
        report["3d-transformation"]["translation_matrix"]
    );
}

#[test]
fn calibrate_by_markers_places_a_tilted_camera_within_2_mm_and_measure_within_5_mm() {
    let state = TempDir::new("client-markers");
    let scene = crate::support::tilted_uncalibrated_scene(state.path());
    let (_server, addr) = crate::support::serve_with(state.path(), &["--scene", path(&scene)]);
    let uri = format!("coap://{addr}");
    let view = state.path().join("view.png");
    let report = ok(&[
        "calibrate",
        "--server",
        &uri,
        "--map",
        path(&scene),
        "--view",
        path(&view),
        "--json",
    ])
    .json();
    assert_eq!(report["camera"], SN);
    assert_eq!(report["markers"], serde_json::json!([0, 3]), "{report}");
    assert!(
        report["reprojection_px"].as_f64().expect("px") < 0.5,
        "{report}"
    );
    // The world is the origin marker's frame: the camera's true position, seen from it.
    let ([mx, my], yaw) = crate::support::ORIGIN_MARKER;
    let [cx, cy, cz] = crate::support::TILTED_CAMERA;
    let (sin, cos) = yaw.to_radians().sin_cos();
    let (dx, dy) = (cx - mx, cy - my);
    let truth = [cos * dx + sin * dy, -sin * dx + cos * dy, cz].map(|v| v * 1000.0);
    for (i, want) in truth.iter().enumerate() {
        let got = report["camera_mm"][i].as_f64().expect("position");
        assert!(
            (got - want).abs() < 2.0,
            "axis {i}: {got} mm, truth {want} mm"
        );
    }
    for suffix in ["", "-side", &format!("-{SN}")] {
        let file = state.path().join(format!("view{suffix}.png"));
        let image = decode(&file, ImageFormat::Png);
        assert!(image.width() > 100, "{}", file.display());
    }
    crate::support::assert_box_within_5_mm(&ok(&["measure", "--server", &uri, "--json"]).json());

    // Without a map, the origin marker alone (its size given) places the camera too.
    let single = ok(&[
        "calibrate",
        "--server",
        &uri,
        "--marker-size",
        "0.14",
        "--dry-run",
        "--json",
    ])
    .json();
    assert_eq!(single["markers"], serde_json::json!([0]), "{single}");
    assert_eq!(
        single["ignored_markers"],
        serde_json::json!([3]),
        "{single}"
    );
    assert_eq!(single["written"], false);
    for i in 0..3 {
        let got = single["camera_mm"][i].as_f64().expect("position");
        assert!((got - truth[i]).abs() < 5.0, "axis {i}: {got} mm");
    }
}

#[test]
fn calibrate_names_a_camera_that_sees_no_marker_and_writes_nothing() {
    let state = TempDir::new("client-no-marker");
    // Two cameras: one sees the marker, the other looks at bare floor far away.
    let scene = state.path().join("two.toml");
    std::fs::write(
        &scene,
        "[[camera]]\nserial = \"840412060746\"\nposition = [0.3, -0.3, 1.0]\nlook_at = [0.0, 0.0, 0.0]\ncalibrated = false\n\
         [[camera]]\nserial = \"840412060757\"\nposition = [3.0, 3.0, 1.0]\nlook_at = [3.5, 3.0, 0.0]\ncalibrated = false\n\
         [[marker]]\nfamily = \"tag36h11\"\nid = 0\nsize = 0.16\ncenter = [0.0, 0.0]\n",
    )
    .expect("writing the scene");
    let (_server, addr) = crate::support::serve_with(state.path(), &["--scene", path(&scene)]);
    let uri = format!("coap://{addr}");
    let doc = |sn: &str| ok(&["get", &format!("{uri}/cams/{sn}/3d-transformation")]).stdout_text();
    let before = [doc("840412060746"), doc("840412060757")];
    let f = coapcam(&["calibrate", "--server", &uri]);
    assert_eq!(f.status.code(), Some(1), "{}", f.stderr);
    assert!(
        f.stderr
            .contains("camera 840412060757: sees no marker of the map"),
        "{}",
        f.stderr
    );
    assert!(!f.stderr.contains("camera 840412060746:"), "{}", f.stderr);
    assert!(f.stderr.contains("nothing was written"), "{}", f.stderr);
    assert_eq!([doc("840412060746"), doc("840412060757")], before);
    // The camera that sees it, alone, is calibrated.
    ok(&["calibrate", "--server", &uri, "--camera", "840412060746"]);
    assert_ne!(doc("840412060746"), before[0]);
}

#[test]
fn bench_accuracy_calibrate_places_one_to_three_tilted_cameras_as_well_as_their_true_poses() {
    let f = ok(&[
        "bench",
        "accuracy",
        "--calibrate",
        "--scenes",
        "3",
        "--json",
    ]);
    let b = f.json();
    assert_eq!(b["failed"], 0, "{b}");
    let scenes = b["scenes"].as_array().expect("scenes");
    let cameras: Vec<usize> = scenes
        .iter()
        .map(|s| s["cameras"].as_u64().expect("cameras") as usize)
        .collect();
    assert_eq!(cameras, [1, 2, 3]);
    for s in scenes {
        for e in s["pose_errors_mm_deg"].as_array().expect("pose errors") {
            let (mm, deg) = (e[0].as_f64().expect("mm"), e[1].as_f64().expect("deg"));
            assert!(mm <= 2.0 && deg <= 0.2, "{s}");
        }
        // The calibration adds nothing the measurement can see: the dimensions are those
        // measured with the true poses, within a millimetre. (How far both are from the
        // truth is the measurement's accuracy, `bench accuracy`'s subject.)
        let (calibrated, true_poses) = (&s["measured"], &s["measured_with_true_poses"]);
        for i in 0..3 {
            let difference = calibrated[i].as_f64().expect("measured")
                - true_poses[i]
                    .as_f64()
                    .expect("measured with the true poses");
            assert!(difference.abs() <= 1.0, "{s}");
        }
    }
    assert_eq!(b["calibration"]["cameras"], 6, "{b}");
}

/// The lane set's first scenes, one of each case: boxes and the cylinder measured close
/// to their truth, the parcels side by side and the one partly out of view refused with
/// the reason, nothing silently wrong; the two parcels apart both measured.
#[test]
fn bench_accuracy_on_the_lane_set_measures_refuses_and_is_never_silently_wrong() {
    let cases = rgbd::lane::Case::ALL.len().to_string();
    let f = coapcam(&[
        "bench", "accuracy", "--set", "lane", "--scenes", &cases, "--json",
    ]);
    let b = f.json();
    let case = |name: &str| {
        b["cases"]
            .as_array()
            .expect("cases")
            .iter()
            .find(|c| c["case"] == name)
            .unwrap_or_else(|| panic!("no case {name}: {b}"))
            .clone()
    };
    assert_eq!(case("all")["silently_wrong"], 0, "{b}");
    assert!(f.status.success(), "{}", f.stderr);
    for name in ["clean", "large", "apart"] {
        let c = case(name);
        assert_eq!(c["measured"], c["parcels"], "{name}: {b}");
        for axis in ["length_mm", "width_mm", "height_mm"] {
            assert!(
                c[axis]["max"].as_f64().expect("max") <= 3.0,
                "{name} {axis}: {b}"
            );
        }
    }
    assert_eq!(case("apart")["measured"], 2, "{b}");
    assert!(
        case("cylinder")["length_mm"]["max"].as_f64().expect("max") <= 10.0,
        "{b}"
    );
    assert_eq!(case("touching")["measured"], 0, "{b}");
    // Nothing measured, no errors: null (JSON has no NaN).
    for axis in ["length_mm", "width_mm", "height_mm"] {
        for stat in ["mean_signed", "mae", "p95", "max"] {
            assert!(case("touching")[axis][stat].is_null(), "{axis} {stat}: {b}");
        }
    }
    assert_eq!(case("cut")["refused"], 1, "{b}");
    let scenes = b["scenes"].as_array().expect("scenes");
    let reason = |name: &str| {
        let s = scenes
            .iter()
            .find(|s| s["case"] == name)
            .expect("the case's scene");
        s["parcels"][0]["refused"].as_str().unwrap_or("").to_owned()
    };
    assert!(reason("touching").contains("side by side"), "{b}");
    assert!(reason("cut").contains("view"), "{b}");
}

/// The lane set's table prints "-" for the errors of a case whose every parcel was
/// refused, never NaN.
#[test]
fn bench_accuracy_prints_no_errors_for_a_case_with_nothing_measured() {
    let cases = rgbd::lane::Case::ALL.len().to_string();
    let f = coapcam(&[
        "bench", "accuracy", "--set", "lane", "--scenes", &cases, "--repeat", "2",
    ]);
    assert!(f.status.success(), "{}", f.stderr);
    let text = f.stdout_text();
    assert!(!text.contains("NaN"), "{text}");
    // The spread of a parcel refused both times is no number either.
    assert!(
        text.lines()
            .any(|l| l.ends_with("no number in any of 2 runs (refused or not found)")),
        "{text}"
    );
    let row = |name: &str| {
        text.lines()
            .find(|l| l.split_whitespace().next() == Some(name))
            .unwrap_or_else(|| panic!("no row {name}: {text}"))
            .to_owned()
    };
    // touching: 2 parcels, 0 measured, 2 refused; then "-" for each axis.
    for name in ["touching", "cut"] {
        let r = row(name);
        let axes: Vec<&str> = r.split('|').skip(1).map(str::trim).collect();
        assert_eq!(axes, ["-", "-", "-"], "{r}");
    }
    let clean = row("clean");
    assert!(
        clean.split('|').skip(1).all(|a| a.trim().contains('/')),
        "{clean}"
    );
}
