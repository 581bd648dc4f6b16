//! The OPC UA output (`serve --opcua`) against a client we did not write: PyPI's asyncua,
//! driven by `tests/peers/opcua_client.py`, browses the station, reads its identity, its
//! cameras and the latest result with its photo, calls MeasureNow and gets the event of the record it made, and reads
//! the log's records by id (GetResultById) and by id and time (GetResultsSince). asyncua
//! missing fails in CI (`CI=true`) and skips loudly elsewhere.

use std::time::Duration;

use coap::Code;
use coapcam::api::record::sha256_hex;

use crate::support::{
    COAPCAM, Peer, Proc, Station, TempDir, available, client, measure, runtime, script, send,
    station,
};

/// Longest wait for the client script, and for each of its steps.
const LIMIT: Duration = Duration::from_secs(60);

#[test]
fn asyncua_browses_reads_the_latest_result_calls_measure_now_and_gets_its_event() {
    if !available("serve --opcua with asyncua", &[Peer::Asyncua]) {
        return;
    }
    let dir = TempDir::new("opcua");
    let Station {
        process: _server,
        coap,
        opcua,
        ..
    } = station(
        dir.path(),
        &[
            "--opcua",
            "opc.tcp://127.0.0.1:0",
            "--station-name",
            "dock-ua",
        ],
    );
    let opcua = opcua.expect("the OPC UA server's address (its line at the start)");
    // Record 1, made before the client connects: the latest result it reads.
    let first = runtime().block_on(measure(&client(), coap));
    let first = *first
        .reported()
        .expect("the default scene's parcel is measured");
    let url = format!("opc.tcp://{opcua}/");
    let seconds = LIMIT.as_secs().to_string();
    let out = Proc::run(
        "python3",
        &[&script("opcua_client.py"), &url, &seconds],
        LIMIT * 2,
    )
    .expect_success("opcua_client.py");
    let steps = out.json_lines();
    let step = |name: &str| -> Vec<&serde_json::Value> {
        steps.iter().filter_map(|s| s.get(name)).collect()
    };

    let browse = step("browse")[0];
    let has = |list: &serde_json::Value, name: &str| {
        list.as_array()
            .is_some_and(|l| l.iter().any(|n| n.as_str() == Some(name)))
    };
    for name in ["Server", "Station"] {
        assert!(has(&browse["Objects"], name), "{name}: {browse}");
    }
    for name in ["Identity", "Cameras", "LatestResult", "MeasureNow"] {
        assert!(has(&browse["Station"], name), "{name}: {browse}");
    }
    for name in [
        "RecordId",
        "Time",
        "LengthMm",
        "WidthMm",
        "HeightMm",
        "DivisionMm",
        "Shape",
        "Codes",
        "Status",
        "Trigger",
        "Photo",
    ] {
        assert!(has(&browse["LatestResult"], name), "{name}: {browse}");
    }
    assert_eq!(step("display_name")[0], "dock-ua");

    let identity = step("identity")[0];
    assert_eq!(identity["StationName"], "dock-ua", "{identity}");
    assert_eq!(identity["SoftwareName"], "coapcam", "{identity}");
    assert_eq!(
        identity["SoftwareVersion"],
        env!("CARGO_PKG_VERSION"),
        "{identity}"
    );
    assert_eq!(
        identity["SoftwareSha256"].as_str().map(str::len),
        Some(64),
        "{identity}"
    );

    // The cameras, as the camera server has them: the default scene's one camera.
    let cameras = step("cameras")[0]
        .as_object()
        .expect("the cameras by serial");
    assert_eq!(cameras.len(), 1, "{cameras:?}");
    let (serial, camera) = cameras.iter().next().expect("a camera");
    assert_eq!(camera["Serial"], serial.as_str(), "{camera}");
    assert!(
        camera["Model"]
            .as_str()
            .is_some_and(|m| m.starts_with("Intel RealSense")),
        "{camera}"
    );
    assert!(camera["Calibrated"].is_boolean(), "{camera}");
    let c = client();
    for (stream, field) in [("color", "Color"), ("depth", "Depth")] {
        let path = format!("/cams/{serial}/{stream}-settings");
        let got = runtime().block_on(send(&c, coap, Code::GET, &path, &[], Some(50)));
        let settings: serde_json::Value =
            serde_json::from_slice(&got.payload).expect("the settings' JSON");
        for name in ["format", "width", "height", "fps"] {
            let mut key = format!("{field}{name}");
            key[field.len()..=field.len()].make_ascii_uppercase();
            assert_eq!(camera[&key], settings[name], "{key}: {camera} {settings}");
        }
    }
    // A record's photo as the log keeps it (CoAP's /station/measurements/N/photo).
    let photo_of = |id: u64| {
        let path = format!("/station/measurements/{id}/photo");
        let got = runtime().block_on(send(&c, coap, Code::GET, &path, &[], None));
        assert_eq!(got.code, Code::CONTENT, "{path}");
        serde_json::json!({
            "bytes": got.payload.len(),
            "sha256": sha256_hex(&got.payload),
            "head": "ffd8",
        })
    };
    let photos = step("photo");
    assert_eq!(photos[0], &photo_of(1), "record 1's photo");
    assert_eq!(photos[1], &photo_of(2), "record 2's photo");
    eprintln!(
        "the latest result's photo over OPC UA: {} bytes",
        photos[1]["bytes"]
    );

    let latest = step("latest");
    let before = latest[0];
    assert_eq!(before["RecordId"], 1, "{before}");
    assert_eq!(before["Status"], "measured", "{before}");
    assert_eq!(before["Trigger"], "request", "{before}");
    assert_eq!(before["Shape"], "cuboid", "{before}");
    assert_eq!(before["LengthMm"], first.length_mm, "{before}");
    assert_eq!(before["WidthMm"], first.width_mm, "{before}");
    assert_eq!(before["HeightMm"], first.height_mm, "{before}");
    assert_eq!(before["DivisionMm"].as_f64(), first.division_mm, "{before}");
    assert_eq!(before["Codes"], serde_json::json!(["PKG-0001"]), "{before}");
    assert!(before["Time"].as_f64().is_some(), "{before}");

    let called = step("measure_now")[0];
    assert_eq!(called["record_id"], 2, "{called}");
    assert_eq!(called["outcome"], "recorded", "{called}");

    // Record 1 was there before the subscription: the one event is record 2's.
    let events = step("event");
    assert_eq!(events.len(), 1, "{events:?}");
    let event = events[0];
    let message = event["message"].as_str().expect("a message");
    assert!(message.starts_with("record 2: "), "{event}");
    assert_eq!(event["source_name"], "dock-ua", "{event}");
    assert_eq!(event["event_type"], "NewResultEventType", "{event}");
    let after = latest[1];
    // The event carries the record: the same as the latest result read after it.
    let fields = &event["fields"];
    assert_eq!(fields["RecordId"], 2, "{event}");
    for name in ["LengthMm", "WidthMm", "HeightMm", "Status", "Codes"] {
        assert_eq!(fields[name], after[name], "{name}: {event} {after}");
    }
    assert_eq!(after["RecordId"], 2, "{after}");
    assert_eq!(after["Trigger"], "request", "{after}");
    assert_eq!(after["Time"], event["time_unix_ms"], "{after} {event}");
    // Results by id, read from the log: record 1 as the latest result showed it first,
    // record 2 as after MeasureNow; an id the log does not hold is BadNotFound.
    let by_id = step("result_by_id")[0];
    assert_eq!(&by_id["1"], before, "{by_id}");
    assert_eq!(&by_id["2"], after, "{by_id}");
    assert_eq!(step("result_by_id_missing")[0], "BadNotFound");
    // Results by id and time: oldest first, at most MaxResults, after AfterId, at Since
    // or later; each array's entry is the record's.
    let since = step("results_since")[0];
    let ids = |name: &str| since[name]["RecordIds"].clone();
    assert_eq!(ids("all"), serde_json::json!([1, 2]), "{since}");
    assert_eq!(ids("first_only"), serde_json::json!([1]), "{since}");
    assert_eq!(ids("after_1"), serde_json::json!([2]), "{since}");
    assert_eq!(ids("since_the_second"), serde_json::json!([2]), "{since}");
    assert_eq!(ids("after_the_last"), serde_json::json!([]), "{since}");
    for (i, record) in [before, after].into_iter().enumerate() {
        let all = &since["all"];
        assert_eq!(all["Times"][i], record["Time"], "{since}");
        for name in ["LengthMm", "WidthMm", "HeightMm", "Status"] {
            assert_eq!(all[name][i], record[name], "{name}: {since}");
        }
    }
    let delay = event["arrived_unix_ms"].as_f64().expect("arrived")
        - event["time_unix_ms"].as_f64().expect("time");
    eprintln!("record to the asyncua client's event: {delay:.0} ms");
}

#[test]
fn an_address_off_the_machine_without_users_is_refused() {
    let refused = Proc::run(
        COAPCAM,
        &["serve", "--opcua", "opc.tcp://0.0.0.0:4840"],
        LIMIT,
    )
    .expect_status(2, "serve --opcua opc.tcp://0.0.0.0:4840");
    assert!(
        refused.stderr.contains("loopback") && refused.stderr.contains("--opcua-users"),
        "{}",
        refused.stderr
    );
}

#[test]
fn with_users_only_signed_and_encrypted_sessions_of_a_trusted_client_and_a_user_get_in() {
    if !available("serve --opcua --opcua-users with asyncua", &[Peer::Asyncua]) {
        return;
    }
    let dir = TempDir::new("opcua-secure");
    let users = dir.join("opcua-users");
    std::fs::write(&users, "# the PLC\nplc:s3cret\n").expect("writing the users");
    let client_dir = dir.join("client");
    std::fs::create_dir_all(&client_dir).expect("the client's folder");
    let Station {
        process: _server,
        opcua,
        ..
    } = station(
        &dir.join("state"),
        &[
            "--opcua",
            "opc.tcp://127.0.0.1:0",
            "--opcua-users",
            users.to_str().expect("UTF-8"),
        ],
    );
    let url = format!("opc.tcp://{}/", opcua.expect("the OPC UA server's address"));
    let seconds = LIMIT.as_secs().to_string();
    let attempt = |password: &str| {
        let out = Proc::run(
            "python3",
            &[
                &script("opcua_secure.py"),
                &url,
                &seconds,
                client_dir.to_str().expect("UTF-8"),
                "plc",
                password,
            ],
            LIMIT * 2,
        )
        .expect_success("opcua_secure.py");
        let lines = out.json_lines();
        let anonymous = lines.iter().find_map(|l| l.get("anonymous").cloned());
        let secure = lines.iter().find_map(|l| l.get("secure").cloned());
        (anonymous.expect("anonymous"), secure.expect("secure"))
    };
    // The client's certificate is unknown: refused, and left where an operator trusts it.
    let (anonymous, secure) = attempt("s3cret");
    assert!(
        anonymous.as_str().is_some_and(|a| a.starts_with("refused")),
        "{anonymous}"
    );
    assert_eq!(secure["in"], false, "{secure}");
    assert!(
        secure["why"]
            .as_str()
            .is_some_and(|w| w.contains("BadCertificateUntrusted")),
        "{secure}"
    );
    let pki = dir.join("state").join("opcua-pki");
    assert!(
        pki.join("own").join("cert.der").is_file(),
        "the station's certificate"
    );
    // Its key in a folder no one else may enter, and itself the owner's alone.
    let mode = |p: &std::path::Path| {
        use std::os::unix::fs::PermissionsExt as _;
        std::fs::metadata(p)
            .expect("its metadata")
            .permissions()
            .mode()
            & 0o777
    };
    let private = pki.join("private");
    assert_eq!(mode(&private), 0o700, "{}", private.display());
    assert_eq!(mode(&private.join("private.pem")), 0o600);
    let rejected: Vec<_> = std::fs::read_dir(pki.join("rejected"))
        .expect("the rejected certificates")
        .map(|e| e.expect("an entry").path())
        .collect();
    assert_eq!(rejected.len(), 1, "{rejected:?}");
    let name = rejected[0].file_name().expect("a file name");
    std::fs::rename(&rejected[0], pki.join("trusted").join(name)).expect("trusting it");
    // Trusted, with a wrong password: the user is refused.
    let (_, secure) = attempt("wrong");
    assert_eq!(secure["in"], false, "{secure}");
    assert!(
        secure["why"]
            .as_str()
            .is_some_and(|w| w.contains("BadIdentityTokenRejected")),
        "{secure}"
    );
    // Trusted, and the user's password: in, reading and measuring.
    let (anonymous, secure) = attempt("s3cret");
    assert!(
        anonymous.as_str().is_some_and(|a| a.starts_with("refused")),
        "{anonymous}"
    );
    assert_eq!(secure["in"], true, "{secure}");
    assert_eq!(secure["latest"], 0, "{secure}");
    assert_eq!(
        secure["measure_now"],
        serde_json::json!([1, "recorded"]),
        "{secure}"
    );
}
