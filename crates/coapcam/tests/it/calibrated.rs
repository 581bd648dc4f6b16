//! The station's calibration and configuration on the documented path (issue 35): no
//! false floor alarm after `measure --prepare`, `calibrate --floor` after it, documents
//! the server cannot use refused before they are saved, DELETE back to the defaults, and
//! no dimensions from an uncalibrated station.

use std::path::Path;
use std::time::Duration;

use crate::support::{COAPCAM, Finished, Proc, SN, TempDir, serve, serve_with};

/// Bound on one command (the servers stop by themselves after 120 s).
const LIMIT: Duration = Duration::from_secs(110);

fn coapcam(args: &[&str]) -> Finished {
    Proc::run(COAPCAM, args, LIMIT)
}

fn ok(args: &[&str]) -> Finished {
    coapcam(args).expect_success(&format!("coapcam {}", args.join(" ")))
}

fn path(p: &Path) -> &str {
    p.to_str().expect("UTF-8 path")
}

fn warnings(m: &serde_json::Value) -> String {
    m["warnings"].to_string()
}

/// `measure --prepare` cuts the floor out of the clouds; the floor check looks at the
/// cameras' whole views, so the next measurements, at the edge or from the clouds, do
/// not warn. A camera whose floor really is off (raised 300 mm) is still warned about.
#[test]
fn measure_after_prepare_gives_no_floor_alarm_but_a_raised_floor_warns() {
    let state = TempDir::new("calibrated-prepare");
    let (_server, addr) = serve(state.path());
    let uri = format!("coap://{addr}");
    let prepared = ok(&["measure", "--server", &uri, "--prepare", "--json"]).json();
    assert_eq!(prepared["warnings"], serde_json::json!([]), "{prepared}");
    for how in ["--edge", "--clouds"] {
        let m = ok(&["measure", "--server", &uri, how, "--json"]).json();
        assert_eq!(m["parcel"], "measured", "{how}: {m}");
        assert_eq!(m["warnings"], serde_json::json!([]), "{how}: {m}");
    }
    let doc = format!("{uri}/cams/{SN}/3d-transformation");
    let mut t: serde_json::Value =
        serde_json::from_str(&ok(&["get", &doc]).stdout_text()).expect("JSON");
    t["post_translation_matrix"] = serde_json::json!([[0.0], [0.0], [0.3]]);
    ok(&["put", &doc, "--payload", &t.to_string()]);
    // The floor, 300 mm up, is one object reaching beyond the view: refused (exit
    // status 10), with the warning that says why.
    let f = coapcam(&["measure", "--server", &uri, "--json"]);
    assert_eq!(f.status.code(), Some(10), "{}", f.stderr);
    let m = f.json();
    assert_eq!(m["parcel"], "refused", "{m}");
    let w = warnings(&m);
    assert!(
        w.contains(&format!(
            "camera {SN}: the floor is not near z = 0: the lowest points lie at 300 mm"
        )),
        "{m}"
    );
}

/// After `measure --prepare` the clouds hold the parcel's lid but no floor:
/// `calibrate --floor` levels the camera on the whole depth image instead, says so, and
/// finds the true height (1 m), not the lid's.
#[test]
fn calibrate_floor_after_prepare_levels_on_the_floor_not_the_lid() {
    let state = TempDir::new("calibrated-floor");
    let (_server, addr) = serve(state.path());
    let uri = format!("coap://{addr}");
    ok(&["measure", "--server", &uri, "--prepare"]);
    let f = ok(&["calibrate", "--server", &uri, "--floor", "--json"]);
    let report = f.json();
    let height = report["height_mm"].as_f64().expect("height");
    assert!((height - 1000.0).abs() < 5.0, "{report}");
    assert!(
        f.stderr.contains("roi3d") && f.stderr.contains("whole depth image"),
        "{}",
        f.stderr
    );
    let m = ok(&["measure", "--server", &uri, "--json"]).json();
    for (key, truth) in [
        ("length_mm", 400.0),
        ("width_mm", 300.0),
        ("height_mm", 200.0),
    ] {
        let got = m[key].as_f64().expect("a dimension");
        assert!((got - truth).abs() <= 5.0, "{key} {got}: {m}");
    }
    assert_eq!(m["warnings"], serde_json::json!([]), "{m}");
}

/// Documents that would break every grab, or every measurement, are refused with 4.00
/// naming the field, and nothing is saved: grabs go on.
#[test]
fn documents_the_server_cannot_use_are_refused_naming_the_field() {
    let state = TempDir::new("calibrated-documents");
    let (_server, addr) = serve(state.path());
    let uri = format!("coap://{addr}");
    let app = format!("{uri}/cams/{SN}/application-config");
    let before = ok(&["get", &app]).stdout_text();
    let mut doc: serde_json::Value = serde_json::from_str(&before).expect("JSON");
    doc["roi2d"] = serde_json::json!({"px": 50000, "py": 0, "width": 99999, "height": 720});
    let f = coapcam(&["put", &app, "--payload", &doc.to_string()]);
    assert_eq!(f.status.code(), Some(3), "{}", f.stderr);
    assert!(
        f.stderr.contains("4.00") && f.stderr.contains("roi2d.px = 50000"),
        "{}",
        f.stderr
    );
    assert_eq!(ok(&["get", &app]).stdout_text(), before);

    let t = format!("{uri}/cams/{SN}/3d-transformation");
    let before = ok(&["get", &t]).stdout_text();
    let mut doc: serde_json::Value = serde_json::from_str(&before).expect("JSON");
    doc["scale_matrix"] = serde_json::json!([[1.0], [0.0], [1.0]]);
    let f = coapcam(&["put", &t, "--payload", &doc.to_string()]);
    assert_eq!(f.status.code(), Some(3), "{}", f.stderr);
    assert!(
        f.stderr.contains("4.00") && f.stderr.contains("scale_matrix"),
        "{}",
        f.stderr
    );
    assert_eq!(ok(&["get", &t]).stdout_text(), before);
    let out = state.path().join("c.png");
    ok(&["grab", "color", "--server", &uri, "-o", path(&out)]);
    assert!(
        !state
            .path()
            .join(SN)
            .join("3d-transformation.json")
            .exists()
    );
}

/// DELETE of a configuration document means the camera's defaults, at once in memory,
/// in the state directory and for the measurement at the edge: a prepared
/// application-config does not come back with a new POST or a restart, and a deleted
/// 3d-transformation is the camera's own again (the identity for a real camera, so the
/// station is uncalibrated again).
#[test]
fn delete_of_a_document_goes_back_to_the_defaults_everywhere() {
    let state = TempDir::new("calibrated-delete");
    let default_app = {
        let (_server, addr) = serve(state.path());
        let uri = format!("coap://{addr}");
        let app = format!("{uri}/cams/{SN}/application-config");
        let default_app = ok(&["get", &app]).stdout_text();
        ok(&["measure", "--server", &uri, "--prepare"]);
        assert_ne!(ok(&["get", &app]).stdout_text(), default_app);
        ok(&["delete", &app]);
        ok(&[
            "post",
            &format!("{uri}/cams/application-config"),
            "--payload",
            SN,
        ]);
        assert_eq!(ok(&["get", &app]).stdout_text(), default_app);
        default_app
    };
    // A restart on the same state directory serves the defaults too.
    let (_server, addr) = serve(state.path());
    let app = format!("coap://{addr}/cams/{SN}/application-config");
    assert_eq!(ok(&["get", &app]).stdout_text(), default_app);

    // A camera that starts uncalibrated, levelled, then its calibration deleted.
    let dir = TempDir::new("calibrated-delete-tilted");
    let scene = crate::support::tilted_uncalibrated_scene(dir.path());
    let (_server, addr) = serve_with(dir.path(), &["--scene", path(&scene)]);
    let uri = format!("coap://{addr}");
    ok(&["calibrate", "--server", &uri, "--floor"]);
    let saved = dir.path().join(SN).join("3d-transformation.json");
    assert!(
        saved.exists(),
        "calibrate saved the levelled transformation"
    );
    assert_eq!(
        ok(&["measure", "--server", &uri, "--json"]).json()["parcel"],
        "measured"
    );
    ok(&["delete", &format!("{uri}/cams/{SN}/3d-transformation")]);
    let f = coapcam(&["measure", "--server", &uri, "--json"]);
    assert_eq!(f.status.code(), Some(8), "{}", f.stderr);
    assert_eq!(f.json()["parcel"], "uncalibrated");
    assert!(!saved.exists(), "the saved calibration is gone");
}

/// As a real camera starts: the 3d-transformation is the identity, so the "parcel"
/// would be measured in the camera's own frame (z forward, the floor about 1 m away).
/// No dimensions are given, at the edge or from the clouds: `"parcel": "uncalibrated"`
/// naming the camera, and exit status 8.
#[test]
fn measure_on_an_uncalibrated_camera_gives_no_dimensions_and_exits_8() {
    let state = TempDir::new("calibrated-uncalibrated");
    let scene = crate::support::tilted_uncalibrated_scene(state.path());
    let (_server, addr) = serve_with(state.path(), &["--scene", path(&scene)]);
    let uri = format!("coap://{addr}");
    for how in ["--edge", "--clouds"] {
        let f = coapcam(&["measure", "--server", &uri, how, "--json"]);
        assert_eq!(f.status.code(), Some(8), "{how}: {}", f.stderr);
        let m = f.json();
        assert_eq!(m["parcel"], "uncalibrated", "{how}: {m}");
        assert_eq!(m["uncalibrated"], serde_json::json!([SN]), "{how}: {m}");
        assert!(m.get("length_mm").is_none(), "{how}: {m}");
        assert!(
            warnings(&m).contains(&format!("camera {SN} is not calibrated")),
            "{how}: {m}"
        );
        assert!(
            f.stderr.contains("coapcam: warning: "),
            "{how}: {}",
            f.stderr
        );
    }
    let f = coapcam(&["measure", "--server", &uri]);
    assert_eq!(f.status.code(), Some(8), "{}", f.stderr);
    assert!(
        f.stdout_text().starts_with("not calibrated: no dimensions"),
        "{}",
        f.stdout_text()
    );
}

#[test]
fn monitor_measure_on_an_uncalibrated_camera_prints_no_dimensions() {
    let state = TempDir::new("calibrated-monitor-uncalibrated");
    let scene = crate::support::tilted_uncalibrated_scene(state.path());
    let (_server, addr) = serve_with(state.path(), &["--scene", path(&scene)]);
    let uri = format!("coap://{addr}");
    let args = [
        "monitor",
        "measure",
        "--server",
        &uri,
        "--count",
        "2",
        "--interval",
        "0",
    ];
    let f = coapcam(&[&args[..], &["--json"]].concat());
    assert_eq!(f.status.code(), Some(0), "{}", f.stderr);
    let lines: Vec<serde_json::Value> = f
        .stdout_text()
        .lines()
        .filter(|l| l.contains("\"parcel\""))
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 2, "{}", f.stdout_text());
    for line in &lines {
        // The measurement's fields are the line's.
        assert_eq!(line["parcel"], "uncalibrated", "{line}");
        assert_eq!(line["uncalibrated"], serde_json::json!([SN]), "{line}");
        assert!(line.get("length_mm").is_none(), "{line}");
    }
    let f = coapcam(&args);
    assert_eq!(f.status.code(), Some(0), "{}", f.stderr);
    let text = f.stdout_text();
    assert_eq!(
        text.matches(&format!("not calibrated ({SN}): no dimensions"))
            .count(),
        2,
        "{text}"
    );
    assert!(!text.contains(" mm, yaw "), "{text}");
}
