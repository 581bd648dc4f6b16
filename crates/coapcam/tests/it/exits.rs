//! The exit statuses of README.md's table, and what commands print when the answer is
//! not a plain success: an error response, no answer, nothing on the table, a closed
//! standard output; and the units a measurement is reported in.

use std::io::Write as _;
use std::net::UdpSocket;
use std::process::{Command, Stdio};

use crate::support::{self, COAPCAM, Finished, LIMIT, Proc, SN, TempDir, serve, serve_with};

fn coapcam(args: &[&str]) -> Finished {
    Proc::run(COAPCAM, args, LIMIT)
}

fn status(f: &Finished) -> Option<i32> {
    f.status.code()
}

#[test]
fn an_error_response_exits_3_in_every_command() {
    let state = TempDir::new("exits-refused");
    let (_server, addr) = serve(state.path());
    let uri = format!("coap://{addr}");
    let unknown = "999999999999";
    let out = state.path().join("x.png");
    let out = out.to_str().expect("UTF-8 path");
    for args in [
        vec![
            "grab", "color", "--server", &uri, "--camera", unknown, "-o", out,
        ],
        vec!["measure", "--server", &uri, "--camera", unknown],
        vec!["get", &format!("{uri}/cams/{unknown}/color-settings")],
        vec![
            "monitor", "depth", "--server", &uri, "--camera", unknown, "--count", "1",
        ],
    ] {
        let f = coapcam(&args);
        assert_eq!(status(&f), Some(3), "{args:?}: {}", f.stderr);
        // monitor prints each failed result on standard output.
        let said = format!("{}{}", f.stderr, f.stdout_text());
        assert!(said.contains("4.04"), "{args:?}: {said}");
    }
    // A usage error is clap's 2, distinct from every answer of a server.
    let f = coapcam(&["measure", "--server", &uri, "--no-such-flag"]);
    assert_eq!(status(&f), Some(2), "{}", f.stderr);
}

#[test]
fn an_observation_the_server_refuses_exits_3() {
    let state = TempDir::new("exits-observe");
    let (_server, addr) = serve(state.path());
    // Discovery is not observable: the answer carries no Observe option.
    let f = coapcam(&[
        "get",
        &format!("coap://{addr}/.well-known/core"),
        "--observe",
        "2",
    ]);
    assert_eq!(status(&f), Some(3), "{}", f.stderr);
    assert!(f.stderr.contains("does not let"), "{}", f.stderr);
}

#[test]
fn no_answer_in_time_exits_4() {
    // A port nobody answers on: bound here and never read.
    let silent = UdpSocket::bind("127.0.0.1:0").expect("a socket");
    let addr = silent.local_addr().expect("its address");
    let f = coapcam(&[
        "get",
        &format!("coap://{addr}/x"),
        "--timeout",
        "1",
        "--ack-timeout-ms",
        "100",
    ]);
    assert_eq!(status(&f), Some(4), "{}", f.stderr);
    assert!(f.stderr.contains("timed out"), "{}", f.stderr);
}

#[test]
fn nothing_listening_at_the_address_exits_4_at_once_naming_it() {
    let free = UdpSocket::bind("127.0.0.1:0")
        .and_then(|s| s.local_addr())
        .expect("a free port");
    for args in [
        vec!["get".to_owned(), format!("coap://{free}/x")],
        vec![
            "measure".to_owned(),
            "--server".to_owned(),
            format!("coap://{free}"),
        ],
    ] {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let f = coapcam(&args);
        assert_eq!(status(&f), Some(4), "{args:?}: {}", f.stderr);
        assert!(f.stderr.contains("nothing listens"), "{}", f.stderr);
        assert!(f.stderr.contains(&free.to_string()), "{}", f.stderr);
    }
}

#[test]
fn a_closed_standard_output_ends_quietly() {
    let state = TempDir::new("exits-pipe");
    let (_server, addr) = serve(state.path());
    let mut child = Command::new(COAPCAM)
        .args(["discover", &format!("coap://{addr}")])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("coapcam discover");
    // The reader goes away before anything is written (`| head -0`).
    drop(child.stdout.take());
    let out = child.wait_with_output().expect("its end");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
}

#[test]
fn nothing_on_the_table_is_a_result_with_exit_5() {
    let state = TempDir::new("exits-empty");
    let scene = support::empty_table(&state);
    let (_server, addr) = serve_with(state.path(), &["--scene", &scene]);
    let uri = format!("coap://{addr}");
    let f = coapcam(&["measure", "--server", &uri, "--prepare", "--json"]);
    assert_eq!(status(&f), Some(5), "{}", f.stderr);
    // --prepare changes the server's settings for every client, and says so.
    assert!(
        f.stderr.contains(&format!(
            "prepared camera(s) {SN} on the server, for every client"
        )),
        "{}",
        f.stderr
    );
    let m = f.json();
    assert_eq!(m["parcel"], "nothing", "{m}");
    assert_eq!(m["cameras"], serde_json::json!([SN]), "{m}");
    assert!(m["parcel_points"].as_u64().is_some(), "{m}");
    assert!(m.get("length_mm").is_none(), "{m}");
    let f = coapcam(&["measure", "--server", &uri]);
    assert_eq!(status(&f), Some(5), "{}", f.stderr);
    assert!(
        f.stdout_text().starts_with("nothing on the table"),
        "{}",
        f.stdout_text()
    );
    // Setting up on an empty table is no result: the results log (and so MQTT, the line
    // output and the webhooks, which follow it) holds no record of either measurement.
    // What --prepare changed on the server is there: events, which the listing shows
    // (issue 48, item 2).
    let f = coapcam(&["results", "--server", &uri]);
    assert_eq!(status(&f), Some(0), "{}", f.stderr);
    let text = f.stdout_text();
    assert!(!text.is_empty(), "{text}");
    let event = format!(" PUT /cams/{SN}/application-config by coap://");
    assert!(text.lines().all(|l| l.contains(&event)), "{text}");
    let f = coapcam(&["results", "--server", &uri, "--json"]);
    assert_eq!(status(&f), Some(0), "{}", f.stderr);
    assert!(
        f.json_lines().iter().all(|l| l.get("event").is_some()),
        "{}",
        f.stdout_text()
    );
    // Issue 51, item 13: with --json (JSON Lines) and --csv standard output holds no
    // record and no header line more; that there are none is said on standard error
    // (before: nothing at all with --json). A code selects measurements alone.
    let f = coapcam(&["results", "--server", &uri, "--json", "--code", "PKG-1"]);
    assert_eq!(status(&f), Some(0), "{}", f.stderr);
    assert_eq!(f.stdout_text(), "", "JSON Lines of no record");
    assert_eq!(f.stderr.trim(), "coapcam: no records", "{}", f.stderr);
    let f = coapcam(&["results", "--server", &uri, "--csv"]);
    assert_eq!(f.stdout_text().lines().count(), 1, "{}", f.stdout_text());
    assert_eq!(f.stderr.trim(), "coapcam: no records", "{}", f.stderr);
}

/// A camera 1.65 m over a black box (reflectivity 0.01) that returns no depth at all.
fn black_box(state: &TempDir) -> String {
    let path = state.path().join("black.toml");
    let mut f = std::fs::File::create(&path).expect("a scene file");
    writeln!(
        f,
        "[[camera]]\nserial = \"{SN}\"\nposition = [0.0, 0.0, 1.65]\nlook_at = [0.0, 0.0, 0.0]\ncalibrated = true\n\n[[box]]\nsize = [0.30, 0.20, 0.15]\ncenter = [0.05, 0.0]\nyaw_deg = 20.0\nreflectivity = 0.01"
    )
    .expect("writing the scene");
    path.to_str().expect("UTF-8 path").to_owned()
}

/// A parcel from which no pixel returns depth is neither "nothing on the table" nor the
/// few flying pixels along its edges measured as a parcel (372 x 171 x 61 mm for this
/// 300 x 200 x 150 box, before): the camera's server sees the hole in the floor before
/// the floor cut zeroes the floor, and the answer is a refusal (10) with that reason,
/// whether the client measures the clouds or the server does, prepared or not.
#[test]
fn a_parcel_that_returns_no_depth_is_refused_with_exit_10_not_nothing_there() {
    let state = TempDir::new("exits-no-depth");
    let scene = black_box(&state);
    let (_server, addr) = serve_with(state.path(), &["--scene", &scene]);
    let uri = format!("coap://{addr}");
    let no_depth = |args: &[&str]| {
        let f = coapcam(args);
        assert_eq!(status(&f), Some(10), "{args:?}: {}", f.stderr);
        let m = f.json();
        assert_eq!(m["parcel"], "refused", "{args:?}: {m}");
        assert!(
            m["reason"]
                .as_str()
                .is_some_and(|r| r.contains("no depth from part of the table")),
            "{args:?}: {m}"
        );
        let first = &m["parcels"][0];
        assert_eq!(first["parcel"], "refused", "{m}");
        assert!(first.get("length_mm").is_none(), "{m}");
        // Its footprint (where the rays meet the floor) holds the box's centre.
        let corners = first["corners_m"].as_array().expect("corners");
        let xs: Vec<f64> = corners.iter().map(|c| c[0].as_f64().expect("x")).collect();
        let ys: Vec<f64> = corners.iter().map(|c| c[1].as_f64().expect("y")).collect();
        let within = |v: &[f64], at: f64| {
            v.iter().copied().fold(f64::INFINITY, f64::min) < at
                && v.iter().copied().fold(f64::NEG_INFINITY, f64::max) > at
        };
        assert!(within(&xs, 0.05) && within(&ys, 0.0), "{m}");
    };
    // Unprepared first: the floor is sent, and the wall pixels the floor cut drops.
    no_depth(&["measure", "--server", &uri, "--clouds", "--json"]);
    no_depth(&[
        "measure",
        "--server",
        &uri,
        "--prepare",
        "--clouds",
        "--json",
    ]);
    no_depth(&["measure", "--server", &uri, "--edge", "--json"]);
    // --annotate draws what was refused: its footprint in magenta on the camera's
    // picture, with the reason in the legend (issue 51, item 11; nothing was written).
    let picture = state.path().join("refused.png");
    let picture_arg = picture.to_str().expect("UTF-8 path");
    let f = coapcam(&["measure", "--server", &uri, "--annotate", picture_arg]);
    assert_eq!(status(&f), Some(10), "{}", f.stderr);
    assert!(
        f.stderr.contains("the refused parcel and why"),
        "{}",
        f.stderr
    );
    let image = image::open(&picture)
        .expect("the annotated picture")
        .to_rgb8();
    let magenta = image.pixels().filter(|p| p.0 == [255, 0, 255]).count();
    // Four edges of the footprint, a line of the legend: hundreds of pixels.
    assert!(magenta > 500, "{magenta} magenta pixels");
}

#[test]
fn the_volumetric_divisor_and_the_scale_division_are_the_integrators() {
    let state = TempDir::new("exits-units");
    let (_server, addr) = serve(state.path());
    let uri = format!("coap://{addr}");
    let m = coapcam(&[
        "measure",
        "--server",
        &uri,
        "--json",
        "--volumetric-divisor",
        "6000",
        "--round-up-mm",
        "5",
    ])
    .json();
    let dims: Vec<f64> = ["length_mm", "width_mm", "height_mm"]
        .iter()
        .map(|k| m[*k].as_f64().unwrap_or_else(|| panic!("{k} in {m}")))
        .collect();
    for d in &dims {
        assert_eq!(d % 5.0, 0.0, "{d} is not a multiple of 5 mm: {m}");
    }
    let weight = dims.iter().product::<f64>() / 1000.0 / 6000.0;
    let reported = m["volumetric_weight_kg"].as_f64().expect("weight");
    assert!(
        (reported - weight).abs() < 0.001,
        "{reported} vs {weight}: {m}"
    );
    assert_eq!(m["volumetric_divisor_cm3_per_kg"], 6000.0, "{m}");
    assert_eq!(m["division_mm"], 5.0, "{m}");
    // The default divisor is 5000, and the dimensions are rounded to the default 5 mm
    // division, which the top level names (issue 51, item 4: it said null and gave them
    // to 0.1 mm, while `parcels` had them rounded).
    let m = coapcam(&["measure", "--server", &uri, "--json"]).json();
    assert_eq!(m["volumetric_divisor_cm3_per_kg"], 5000.0, "{m}");
    support::billed_numbers(&m);
    let f = coapcam(&["measure", "--server", &uri, "--volumetric-divisor", "0"]);
    assert_eq!(status(&f), Some(2), "{}", f.stderr);
}

#[test]
fn get_json_lists_every_option() {
    let dir = TempDir::new("exits-options");
    let (_server, addr) = support::our_server(dir.path(), true);
    let f = coapcam(&[
        "post",
        &format!("coap://{addr}/files"),
        "--payload",
        "hello",
        "--json",
    ]);
    let lines = f.json_lines();
    assert_eq!(lines.len(), 1, "{}", f.stdout_text());
    let r = &lines[0];
    assert_eq!(r["code"], "2.01", "{r}");
    let location = r["options"]["Location-Path"]
        .as_array()
        .unwrap_or_else(|| panic!("no Location-Path in {r}"));
    assert_eq!(location[0], "files", "{r}");
    assert!(
        r["size_bytes"].as_u64().is_some() && r["time_ms"].as_f64().is_some(),
        "{r}"
    );
}

#[test]
fn an_error_says_its_prefix_and_the_os_error_once() {
    let dir = TempDir::new("exits-once");
    let missing = dir.join("missing.toml");
    let f = coapcam(&[
        "serve",
        "--scene",
        missing.to_str().expect("UTF-8 path"),
        "--bind",
        "127.0.0.1:0",
    ]);
    assert_eq!(status(&f), Some(1), "{}", f.stderr);
    assert_eq!(f.stderr.matches("coapcam:").count(), 1, "{}", f.stderr);
    assert_eq!(f.stderr.matches("(os error 2)").count(), 1, "{}", f.stderr);
}

#[test]
fn a_second_server_on_a_busy_port_fails_at_once() {
    let dir = TempDir::new("exits-busy");
    let (_first, addr) = support::our_server(dir.path(), false);
    let f = coapcam(&[
        "serve",
        "--no-cameras",
        "--bind",
        &addr.to_string(),
        "--duration",
        "30",
    ]);
    assert_eq!(status(&f), Some(1), "{}", f.stderr);
    assert!(f.stderr.contains("in use"), "{}", f.stderr);
    assert!(!f.stderr.contains("serving on"), "{}", f.stderr);
}

/// Issue 51, item 13: with `--mqtt` the station's name is one topic level
/// (PREFIX/<station>/measurements, matched with `+`), so `dock/1` is a bad value: status
/// 2 before anything is served (it was 1, from the publisher). Without `--mqtt` the name
/// is only a record's text, and `dock/1` serves.
#[test]
fn a_station_name_that_cannot_be_a_topic_level_with_mqtt_is_a_usage_error() {
    let dir = TempDir::new("exits-station-name");
    let state = dir.path().to_str().expect("UTF-8");
    for name in ["dock/1", "dock+", "#"] {
        let f = coapcam(&[
            "serve",
            "--station-name",
            name,
            "--mqtt",
            "mqtt://127.0.0.1:1",
            "--state-dir",
            state,
            "--bind",
            "127.0.0.1:0",
            "--duration",
            "30",
        ]);
        assert_eq!(status(&f), Some(2), "{name}: {}", f.stderr);
        assert!(f.stderr.contains("--station-name"), "{}", f.stderr);
        assert!(!f.stderr.contains("serving on"), "{}", f.stderr);
    }
    let f = coapcam(&[
        "serve",
        "--station-name",
        "dock/1",
        "--state-dir",
        state,
        "--bind",
        "127.0.0.1:0",
        "--duration",
        "1",
    ]);
    assert_eq!(status(&f), Some(0), "{}", f.stderr);
}

#[test]
fn an_output_of_the_results_log_without_cameras_is_a_usage_error() {
    for output in [
        ["--mqtt", "mqtt://127.0.0.1:1"],
        ["--line-output", "tcp://127.0.0.1:0"],
        ["--webhook", "http://127.0.0.1:1/hook"],
    ] {
        let f = coapcam(&[
            "serve",
            "--no-cameras",
            output[0],
            output[1],
            "--bind",
            "127.0.0.1:0",
            "--duration",
            "30",
        ]);
        assert_eq!(status(&f), Some(2), "{output:?}: {}", f.stderr);
        assert!(!f.stderr.contains("serving on"), "{}", f.stderr);
    }
}
