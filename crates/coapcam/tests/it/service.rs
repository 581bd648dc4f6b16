//! contrib/coapcam.service, the systemd unit docs/service.md installs: its ExecStart is
//! `coapcam serve --config` of contrib/station.toml, run here as systemd would run it
//! (with the unit's environment, the file without `realsense`, as no camera is here, and
//! on a free loopback port), and its KillSignal stops that server cleanly within
//! TimeoutStopSec.

use std::process::Command;
use std::time::Duration;

use crate::support::{COAPCAM, Proc, TempDir};

const UNIT: &str = include_str!("../../../../contrib/coapcam.service");
const SERVICE_MD: &str = include_str!("../../../../docs/service.md");
const STATION: &str = include_str!("../../../../contrib/station.toml");

/// The values of `key` in `section` of the unit, in order.
fn values(section: &str, key: &str) -> Vec<String> {
    let mut current = "";
    let mut out = Vec::new();
    for line in UNIT.lines().map(str::trim) {
        if line.starts_with('[') && line.ends_with(']') {
            current = line;
        } else if current == format!("[{section}]")
            && let Some((k, v)) = line.split_once('=')
            && k.trim() == key
        {
            out.push(v.trim().to_owned());
        }
    }
    out
}

#[test]
fn the_unit_file_starts_a_server_that_stops_cleanly() {
    let exec = values("Service", "ExecStart");
    assert_eq!(exec.len(), 1, "one ExecStart: {exec:?}");
    let words: Vec<&str> = exec[0].split_whitespace().collect();
    assert!(
        words[0].starts_with('/') && words[0].ends_with("/coapcam"),
        "{words:?}"
    );
    assert_eq!(
        words[1..],
        ["serve", "--config", "/etc/coapcam/station.toml"],
        "the station's settings are in its file"
    );
    let state = values("Service", "StateDirectory");
    assert_eq!(state, ["coapcam"]);
    assert!(
        STATION.lines().any(|l| l == "realsense = true"),
        "the service serves real cameras: {STATION}"
    );
    assert!(
        STATION
            .lines()
            .any(|l| l == "state-dir = \"/var/lib/coapcam\""),
        "StateDirectory's: {STATION}"
    );
    // The unit's file without real cameras; its state directory and a loopback port
    // given as flags, which override the file's keys.
    let dir = TempDir::new("service");
    let file = dir.join("station.toml");
    let station: String = STATION
        .lines()
        .filter(|l| *l != "realsense = true")
        .map(|l| format!("{l}\n"))
        .collect();
    std::fs::write(&file, station).expect("writing the station's file");
    let state_dir = dir.join("state");
    let args = [
        "serve",
        "--config",
        file.to_str().expect("UTF-8 path"),
        "--state-dir",
        state_dir.to_str().expect("UTF-8 path"),
        "--bind",
        "127.0.0.1:0",
    ];
    let env: Vec<(String, String)> = values("Service", "Environment")
        .iter()
        .map(|e| {
            let (k, v) = e.split_once('=').expect("Environment=KEY=VALUE");
            (k.to_owned(), v.to_owned())
        })
        .collect();
    let env: Vec<(&str, &str)> = env.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect();
    let mut server = Proc::spawn_with_env(COAPCAM, &args, &env);
    server.stderr_line(Duration::from_secs(30), |l| {
        l.contains("serving on 127.0.0.1:").then_some(())
    });
    let signal = values("Service", "KillSignal");
    assert_eq!(signal, ["SIGTERM"]);
    let stop: f64 = values("Service", "TimeoutStopSec")[0]
        .parse()
        .expect("TimeoutStopSec in seconds");
    let pid = server.pid().to_string();
    let sent = Command::new("kill").args(["-s", "TERM", &pid]).status();
    assert!(sent.is_ok_and(|s| s.success()), "kill -s TERM {pid}");
    let finished = server
        .wait(Duration::from_secs_f64(stop))
        .unwrap_or_else(|| panic!("still running {stop} s (TimeoutStopSec) after SIGTERM"));
    assert_eq!(finished.status.code(), Some(0), "{}", finished.stderr);
    // The log says so (issue 51, item 13: it said nothing on a clean stop).
    assert!(
        finished
            .stderr
            .contains("coapcam: stopped cleanly (SIGTERM)"),
        "{}",
        finished.stderr
    );
    // Restart=on-failure restarts it after a failure, not after this clean stop.
    assert_eq!(values("Service", "Restart"), ["on-failure"]);
}

/// Issue 51, item 6: the unit lets the server hold the files its limits allow (every HTTP
/// connection and line reader is one), above systemd's default soft limit of 1,024; and
/// docs/service.md's station file, which measures automatically with real cameras, keeps
/// them streaming as docs/station.md asks, and is a file `serve --config` takes.
#[test]
fn the_unit_allows_the_open_files_the_station_may_hold_and_the_example_file_streams() {
    let limit: usize = values("Service", "LimitNOFILE")
        .first()
        .and_then(|v| v.parse().ok())
        .expect("a LimitNOFILE number in [Service]");
    let held = coapcam::station::http::MAX_CONNECTIONS + coapcam::station::line::MAX_READERS;
    // Beside them: the sockets, the cameras, the log, MQTT, the webhooks.
    assert!(
        limit >= held + 256,
        "LimitNOFILE={limit} for {held} connections"
    );
    // Within it the HTTP side serves all its connections (with fewer files, fewer).
    let http = coapcam::station::http::limits::Bounds::within(
        Some(limit as u64),
        coapcam::station::http::MAX_CONNECTIONS,
        coapcam::station::http::CONNECTIONS_PER_CLIENT,
        1024,
    );
    assert_eq!(
        (http.connections, http.per_client),
        (
            coapcam::station::http::MAX_CONNECTIONS,
            coapcam::station::http::CONNECTIONS_PER_CLIENT
        ),
        "LimitNOFILE={limit}"
    );
    let example = SERVICE_MD
        .split("```toml")
        .nth(1)
        .and_then(|b| b.split("```").next())
        .expect("docs/service.md's station.toml");
    assert!(
        example.contains("auto-measure = true") && example.contains("realsense-streaming = true"),
        "{example}"
    );
    // A file serve takes.
    let dir = TempDir::new("service-example");
    let file = dir.join("station.toml");
    std::fs::write(&file, example).expect("writing the example");
    let file = file.to_str().expect("UTF-8 path");
    let done = Proc::run(
        COAPCAM,
        &["serve", "--config", file, "--print-config"],
        Duration::from_secs(60),
    );
    assert_eq!(done.status.code(), Some(0), "{}", done.stderr);
}
