//! `serve --config FILE` and `serve --print-config` (issue 47, item 1): the keys are
//! serve's flags; a bad key or value exits 2 naming it and its line; flags override keys;
//! the printed configuration reads back as the same text, and a station starts from it.

use std::path::Path;
use std::time::Duration;

use crate::support::{COAPCAM, LIMIT, Proc, TempDir};

const STATION_MD: &str = include_str!("../../../../docs/station.md");

/// `coapcam serve ARGS`, run to its end.
fn serve(args: &[&str]) -> crate::support::Finished {
    let mut all = vec!["serve"];
    all.extend_from_slice(args);
    Proc::run(COAPCAM, &all, LIMIT)
}

fn path(p: &Path) -> &str {
    p.to_str().expect("UTF-8 path")
}

#[test]
fn a_typo_in_a_key_exits_2_naming_the_key_and_its_line() {
    let dir = TempDir::new("config-typo");
    let file = dir.join("station.toml");
    std::fs::write(
        &file,
        "# a station\nstation-name = \"dock-1\"\n\nauto-mesure = true\n",
    )
    .expect("writing the file");
    let done = serve(&["--config", path(&file)]).expect_status(2, "a typo'd key");
    assert!(
        done.stderr
            .contains("station.toml:4: unknown key `auto-mesure`"),
        "{}",
        done.stderr
    );
    // A table is no flag either.
    std::fs::write(&file, "station-name = \"a\"\n[broker]\nhost = \"b\"\n").expect("writing");
    let done = serve(&["--config", path(&file)]).expect_status(2, "a table");
    assert!(
        done.stderr.contains("station.toml:2: unknown key `broker`"),
        "{}",
        done.stderr
    );
}

#[test]
fn a_bad_value_exits_2_naming_the_key_and_its_line() {
    let dir = TempDir::new("config-value");
    let file = dir.join("station.toml");
    let cases = [
        (
            "bind = [\"127.0.0.1:0\"]\ngrab-memory = 0\n",
            2,
            "`grab-memory`",
        ),
        ("bind = \"127.0.0.1:99999\"\n", 1, "`bind`"),
        (
            "\n\nauto-measure = \"yes\"\n",
            3,
            "`auto-measure` is true or false",
        ),
        (
            "station-name = [\"a\", \"b\"]\n",
            1,
            "`station-name` takes one value",
        ),
        ("mqtt = \"tcp://broker\"\n", 1, "`mqtt`"),
    ];
    for (text, line, what) in cases {
        std::fs::write(&file, text).expect("writing the file");
        let done = serve(&["--config", path(&file)]).expect_status(2, text);
        let want = format!("station.toml:{line}: ");
        assert!(
            done.stderr.contains(&want) && done.stderr.contains(what),
            "{text:?}: want {want}{what}: {}",
            done.stderr
        );
    }
    // Not TOML: toml's own message, with the line.
    std::fs::write(&file, "station-name = \"a\"\nbind = \n").expect("writing the file");
    let done = serve(&["--config", path(&file)]).expect_status(2, "not TOML");
    assert!(done.stderr.contains("line 2"), "{}", done.stderr);
    // The rules between flags hold for keys as for flags, and name the keys at fault.
    std::fs::write(&file, "station-name = \"a\"\nwritable = true\n").expect("writing the file");
    let done = serve(&["--config", path(&file)]).expect_status(2, "writable without static");
    assert!(
        done.stderr.contains("station.toml:2: `writable`")
            && done.stderr.contains("--static")
            && !done.stderr.contains("`station-name`"),
        "{}",
        done.stderr
    );
    // A key in conflict with a flag given.
    std::fs::write(&file, "scene = \"lane.toml\"\n").expect("writing the file");
    let done = serve(&["--config", path(&file), "--no-cameras"]).expect_status(2, "a conflict");
    assert!(
        done.stderr.contains("station.toml:1: `scene`"),
        "{}",
        done.stderr
    );
    // A missing file.
    serve(&["--config", path(&dir.join("none.toml"))]).expect_status(2, "no file");
}

#[test]
fn print_config_round_trips_masks_passwords_and_flags_override_keys() {
    let dir = TempDir::new("config-print");
    let flags = [
        "--bind",
        "127.0.0.1:5999",
        "--bind",
        "[::1]:5999",
        "--station-name",
        "007",
        "--grab-memory",
        "512",
        "--clock-offset-ms",
        "-40",
        "--auto-measure",
        "--mqtt",
        "mqtt://dock:s3cret@127.0.0.1:1883/x",
        "--print-config",
    ];
    let first = serve(&flags).expect_success("print-config");
    let text = first.stdout_text();
    for line in [
        "bind = [\"127.0.0.1:5999\", \"[::1]:5999\"]",
        "station-name = \"007\"",
        "grab-memory = 512",
        "clock-offset-ms = -40",
        "auto-measure = true",
        "mqtt = \"mqtt://dock:********@127.0.0.1:1883/x\"",
        "# rd-lifetime = 120",
    ] {
        assert!(text.lines().any(|l| l == line), "no {line:?} in\n{text}");
    }
    assert!(!text.contains("s3cret"), "{text}");
    assert!(first.stderr.contains("mqtt"), "{}", first.stderr);
    let file = dir.join("station.toml");
    std::fs::write(&file, &text).expect("writing the file");
    let again = serve(&["--config", path(&file), "--print-config"]).expect_success("again");
    assert_eq!(again.stdout_text(), text, "print → file → print");
    // A flag given overrides its key; a list is replaced whole; other keys stay.
    let over = serve(&[
        "--config",
        path(&file),
        "--bind",
        "127.0.0.1:6000",
        "--station-name",
        "dock-2",
        "--print-config",
    ])
    .expect_success("overridden");
    let over = over.stdout_text();
    for line in [
        "bind = [\"127.0.0.1:6000\"]",
        "station-name = \"dock-2\"",
        "grab-memory = 512",
    ] {
        assert!(over.lines().any(|l| l == line), "no {line:?} in\n{over}");
    }
}

#[test]
fn a_station_started_from_a_file_serves() {
    let dir = TempDir::new("config-serve");
    let file = dir.join("station.toml");
    std::fs::write(
        &file,
        format!(
            "bind = [\"127.0.0.1:0\"]\nstate-dir = {:?}\nstation-name = \"from-file\"\nduration = 60\n",
            path(&dir.join("state"))
        ),
    )
    .expect("writing the file");
    let mut server = Proc::spawn(COAPCAM, &["serve", "--config", path(&file)]);
    let addr: std::net::SocketAddr = server.stderr_line(Duration::from_secs(30), |l| {
        l.strip_prefix("coapcam: serving on ")
            .and_then(|a| a.trim().parse().ok())
    });
    let uri = format!("coap://{addr}/station/measurements");
    let got = Proc::run(COAPCAM, &["get", &uri], LIMIT).expect_success("GET");
    // The station's name came from the file: an empty log answers, and a measurement
    // records it.
    let post = format!("coap://{addr}/cams/dimensions");
    Proc::run(COAPCAM, &["post", &post, "-o", "/dev/null"], LIMIT).expect_success("POST");
    let got_after = Proc::run(COAPCAM, &["get", &uri], LIMIT).expect_success("GET");
    assert!(
        got_after.stdout_text().contains("from-file"),
        "before: {}\nafter: {}",
        got.stdout_text(),
        got_after.stdout_text()
    );
    server.interrupt().expect_success("SIGINT");
}

#[test]
fn the_example_of_the_docs_is_a_valid_file() {
    let example = STATION_MD
        .split("## A configuration file")
        .nth(1)
        .and_then(|s| s.split("```toml\n").nth(1))
        .and_then(|s| s.split("```").next())
        .expect("docs/station.md's example file");
    let dir = TempDir::new("config-docs");
    let file = dir.join("station.toml");
    std::fs::write(&file, example).expect("writing the file");
    let printed = serve(&["--config", path(&file), "--print-config"])
        .expect_success("the docs' example")
        .stdout_text();
    // Every key of the example is in effect.
    for line in example.lines().filter(|l| !l.starts_with('#')) {
        let key = line.split(" = ").next().expect("key = value");
        assert!(
            printed.lines().any(|l| l.starts_with(&format!("{key} = "))),
            "{key} not in\n{printed}"
        );
    }
}
