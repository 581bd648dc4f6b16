//! The software identity (issue 48, item 1): the checksum of the legally relevant sources
//! that `coapcam --version` prints and every record carries, computed by the same function
//! the build script runs.

use std::io::{Read as _, Write as _};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::time::Duration;

use coapcam::identity::{self, sources};

use crate::support::{COAPCAM, LIMIT, Proc, TempDir, station_with_http};

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Copies the legally relevant sources and a CLI source of the workspace into `dir`.
fn copy_tree(dir: &Path) {
    let root = workspace();
    let mut files = sources::legal_sources(&root).expect("the sources");
    files.push("crates/coapcam/src/cli/results.rs".to_owned());
    for file in files {
        let to = dir.join(&file);
        std::fs::create_dir_all(to.parent().expect("a folder")).expect("mkdir");
        std::fs::copy(root.join(&file), &to).expect("copy");
    }
}

/// Replaces the first line of `path` that contains `old` with one where it is `new`.
fn change_line(path: &Path, old: &str, new: &str) {
    let text = std::fs::read_to_string(path).expect("read");
    let at = text
        .find(old)
        .unwrap_or_else(|| panic!("{old} in {}", path.display()));
    let mut changed = text;
    changed.replace_range(at..at + old.len(), new);
    std::fs::write(path, changed).expect("write");
}

#[test]
fn a_geometry_line_changes_the_checksum_and_a_cli_string_does_not() {
    let (built, files) = sources::legal_checksum(&workspace()).expect("checksum");
    assert_eq!(
        built,
        identity::SOFTWARE_SHA256,
        "the build's checksum is of these sources"
    );
    for part in [
        "crates/geometry/src/",
        "crates/rgbd/src/filter/",
        "crates/coapcam/src/report/",
    ] {
        assert!(files.iter().any(|f| f.starts_with(part)), "{part} counts");
    }
    assert!(
        !files.iter().any(|f| f.contains("/cli/")),
        "the CLI does not count"
    );

    let dir = TempDir::new("identity");
    copy_tree(dir.path());
    let (copied, _) = sources::legal_checksum(dir.path()).expect("checksum");
    assert_eq!(copied, built, "a copy of the same sources");

    change_line(
        &dir.join("crates/coapcam/src/cli/results.rs"),
        "the chain verifies",
        "the chain holds",
    );
    let (cli_changed, _) = sources::legal_checksum(dir.path()).expect("checksum");
    assert_eq!(cli_changed, built, "a CLI string is not legally relevant");

    change_line(
        &dir.join("crates/geometry/src/dimension.rs"),
        "pub ",
        "pub  ",
    );
    let (geometry_changed, _) = sources::legal_checksum(dir.path()).expect("checksum");
    assert_ne!(geometry_changed, built, "one line of geometry changed");

    std::fs::write(dir.join("crates/geometry/src/parcels/extra.rs"), "").expect("write");
    let (added, _) = sources::legal_checksum(dir.path()).expect("checksum");
    assert_ne!(added, geometry_changed, "a new geometry file counts");
}

/// Issue 48: what decides a measured or a refused number on the server counts (the
/// cloud of a grab, the no-depth regions, the merge and the table measured from it, the
/// frames' times); how the answer is sent (`edge.rs`) does not.
#[test]
fn the_servers_measuring_files_count_and_its_transport_does_not() {
    let root = workspace();
    let (built, _) = sources::legal_checksum(&root).expect("checksum");
    let dir = TempDir::new("identity-server");
    copy_tree(dir.path());
    let transport = "crates/coapcam/src/server/cams/edge.rs";
    std::fs::copy(root.join(transport), dir.join(transport)).expect("copy");
    change_line(&dir.join(transport), "pub(super) ", "pub(super)  ");
    let (sent, _) = sources::legal_checksum(dir.path()).expect("checksum");
    assert_eq!(sent, built, "{transport} is not legally relevant");
    for file in [
        "crates/coapcam/src/repr/no_depth.rs",
        "crates/coapcam/src/repr/clouds.rs",
        "crates/coapcam/src/server/cams/grab.rs",
        "crates/coapcam/src/server/cams/merge.rs",
        "crates/coapcam/src/timesync.rs",
    ] {
        let before = sources::legal_checksum(dir.path()).expect("checksum").0;
        change_line(&dir.join(file), "fn ", "fn  ");
        let (changed, _) = sources::legal_checksum(dir.path()).expect("checksum");
        assert_ne!(changed, before, "a line of {file} changed");
    }
}

#[test]
fn version_prints_the_version_and_the_checksum() {
    let out =
        Proc::run(COAPCAM, &["--version"], Duration::from_secs(30)).expect_success("--version");
    assert_eq!(
        out.stdout_text().trim(),
        format!(
            "coapcam {} (legally relevant software SHA-256 {})",
            identity::VERSION,
            identity::SOFTWARE_SHA256
        )
    );
}

/// The JSON body of `GET path` over HTTP/1.1, with its status.
pub(crate) fn http_json(addr: SocketAddr, path: &str) -> (u16, serde_json::Value) {
    let mut stream = TcpStream::connect(addr).expect("connecting");
    stream.set_read_timeout(Some(LIMIT)).expect("timeout");
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .expect("asking");
    let mut raw = Vec::new();
    stream.read_to_end(&mut raw).expect("reading");
    let text = String::from_utf8_lossy(&raw);
    let status = text.get(9..12).and_then(|s| s.parse().ok()).unwrap_or(0);
    let (head, body) = text.split_once("\r\n\r\n").expect("a whole answer");
    assert!(!head.to_ascii_lowercase().contains("chunked"), "{head}");
    (
        status,
        serde_json::from_str(body).unwrap_or(serde_json::Value::Null),
    )
}

/// The JSON body of `coapcam get coap://ADDR/PATH`.
pub(crate) fn coap_json(addr: SocketAddr, path: &str) -> serde_json::Value {
    let uri = format!("coap://{addr}{path}");
    Proc::run(COAPCAM, &["get", &uri], LIMIT)
        .expect_success("get")
        .json()
}

#[test]
fn the_station_names_its_software_over_http_and_coap() {
    let state = TempDir::new("identity-station");
    let (_server, coap, http) = station_with_http(state.path(), &["--station-name", "dock-9"]);
    let (status, station) = http_json(http, "/api/station");
    assert_eq!(status, 200, "{station}");
    assert_eq!(
        station["software_sha256"],
        identity::SOFTWARE_SHA256,
        "{station}"
    );
    assert_eq!(station["version"], identity::VERSION);
    let over_http = station;
    let station = coap_json(coap, "/station");
    assert_eq!(station["station"], "dock-9", "{station}");
    assert_eq!(
        station["software_sha256"],
        identity::SOFTWARE_SHA256,
        "{station}"
    );
    assert_eq!(station["version"], identity::VERSION);
    // The event counter and the parameters in force, shown on demand (issue 48, item 2).
    assert_eq!(
        (&station["events"], &over_http["events"]),
        (&0.into(), &0.into())
    );
    let parameters = station["parameters_sha256"].clone();
    assert_eq!(parameters.as_str().map(str::len), Some(64), "{station}");
    assert_eq!(over_http["parameters_sha256"], parameters);
    let doc = format!(
        "coap://{coap}/cams/{}/application-config",
        crate::support::SN
    );
    Proc::run(COAPCAM, &["delete", &doc], LIMIT).expect_success("delete");
    let station = coap_json(coap, "/station");
    assert_eq!(station["events"], 1, "{station}");
    let event = &coap_json(coap, "/station/events")[0];
    assert_eq!(
        event["event"]["parameters_sha256"],
        station["parameters_sha256"]
    );
    assert_eq!(http_json(http, "/api/station").1["events"], 1);
}

/// Issue 48, item 4: the station publishes its log's head (the newest id and hash) over
/// HTTP and CoAP, before the first record and after each.
#[test]
fn the_station_publishes_its_head_over_http_and_coap() {
    let state = TempDir::new("identity-head");
    let (_server, coap, http) = station_with_http(state.path(), &[]);
    let genesis = serde_json::json!({"id": 0, "hash": coapcam::api::record::GENESIS});
    assert_eq!(http_json(http, "/api/log/head"), (200, genesis.clone()));
    assert_eq!(coap_json(coap, "/station/head"), genesis);
    let server = format!("coap://{coap}");
    Proc::run(COAPCAM, &["measure", "--server", &server], LIMIT).expect_success("measure");
    let (status, record) = http_json(http, "/api/measurements/1");
    assert_eq!(status, 200, "{record}");
    let head = serde_json::json!({"id": 1, "hash": record["hash"]});
    assert_eq!(http_json(http, "/api/log/head"), (200, head.clone()));
    assert_eq!(coap_json(coap, "/station/head"), head);
}
