//! `serve --config FILE` and `serve --print-config` (issue 47, item 1): the keys are
//! serve's flags; a bad key or value exits 2 naming it and its line; flags override keys;
//! the printed configuration reads back as the same text, and a station starts from it.

use std::path::Path;
use std::time::Duration;

use std::io::{BufRead as _, BufReader};
use std::net::TcpStream;

use crate::support::{COAPCAM, LIMIT, Proc, TempDir, client, measure, runtime, station};

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
fn the_examples_of_the_docs_are_valid_files() {
    let section = STATION_MD
        .split("## A configuration file")
        .nth(1)
        .and_then(|s| s.split("\n## ").next())
        .expect("docs/station.md's section");
    let examples: Vec<&str> = section
        .split("```toml\n")
        .skip(1)
        .filter_map(|s| s.split("```").next())
        .collect();
    assert_eq!(examples.len(), 2, "the file and the outputs as a list");
    let dir = TempDir::new("config-docs");
    let file = dir.join("station.toml");
    for example in examples {
        std::fs::write(&file, example).expect("writing the file");
        let printed = serve(&["--config", path(&file), "--print-config"])
            .expect_success("the docs' example")
            .stdout_text();
        // Every key of the example is in effect; the [[output]] tables are printed as
        // they are written, in their order.
        let mut tables = false;
        for line in example.lines().filter(|l| !l.starts_with('#')) {
            let line = line.split(" # ").next().unwrap_or(line).trim_end();
            tables |= line == "[[output]]";
            if line.is_empty() {
                continue;
            }
            let key = line.split(" = ").next().expect("key = value");
            assert!(
                printed.lines().any(|l| if tables {
                    l == line
                } else {
                    l.starts_with(&format!("{key} = "))
                }),
                "{line} not in\n{printed}"
            );
        }
        assert_eq!(
            printed.matches("[[output]]\n").count(),
            example.matches("[[output]]\n").count(),
            "{printed}"
        );
    }
}

#[test]
fn an_output_table_and_its_kinds_flag_are_two_outputs_each_getting_every_record() {
    let dir = TempDir::new("config-outputs");
    let file = dir.join("station.toml");
    std::fs::write(
        &file,
        "[[output]]\nkind = \"line\"\nid = \"second\"\nline-output = \"tcp://127.0.0.1:0\"\n",
    )
    .expect("writing the file");
    let s = station(
        &dir.join("state"),
        &[
            "--config",
            path(&file),
            "--line-output",
            "tcp://127.0.0.1:0",
        ],
    );
    assert_eq!(s.lines.len(), 2, "two line outputs: {:?}", s.lines);
    // A measurement takes far longer than the server takes to accept the readers.
    let mut readers: Vec<BufReader<TcpStream>> = s
        .lines
        .iter()
        .map(|addr| {
            let stream = TcpStream::connect(addr).expect("connecting to a line output");
            stream.set_read_timeout(Some(LIMIT)).expect("a timeout");
            BufReader::new(stream)
        })
        .collect();
    let client = client();
    for id in 1..=2 {
        runtime().block_on(measure(&client, s.coap));
        for reader in &mut readers {
            let mut line = String::new();
            reader.read_line(&mut line).expect("a line");
            assert!(line.starts_with(&format!("{id},")), "record {id}: {line:?}");
        }
    }
}

#[test]
fn output_tables_print_and_read_back_and_bad_ones_exit_2_naming_the_line() {
    let dir = TempDir::new("config-output-tables");
    let file = dir.join("station.toml");
    std::fs::write(
        &file,
        "station-name = \"dock-1\"\n\n[[output]]\nkind = \"line\"\nid = \"left\"\nline-output = \"tcp://127.0.0.1:4001\"\n\n\
         [[output]]\nid = \"wms\"\nkind = \"webhook\"\nwebhook = \"http://u:s3cret@127.0.0.1:9/x\"\n\n\
         [[output]]\nkind = \"webhook\"\nwebhook = \"http://127.0.0.1:9/y\"\n",
    )
    .expect("writing the file");
    let first = serve(&["--config", path(&file), "--print-config"]).expect_success("print");
    let text = first.stdout_text();
    let tables: Vec<&str> = text.split("\n[[output]]\n").skip(1).collect();
    assert_eq!(
        tables,
        [
            "kind = \"line\"\nid = \"left\"\nline-output = \"tcp://127.0.0.1:4001\"\n",
            "kind = \"webhook\"\nid = \"wms\"\nwebhook = \"http://u:********@127.0.0.1:9/x\"\n",
            "kind = \"webhook\"\nwebhook = \"http://127.0.0.1:9/y\"\n",
        ],
        "{text}"
    );
    assert!(first.stderr.contains("`wms`"), "{}", first.stderr);
    let printed = dir.join("printed.toml");
    std::fs::write(&printed, &text).expect("writing the file");
    let again = serve(&["--config", path(&printed), "--print-config"]).expect_success("again");
    assert_eq!(again.stdout_text(), text, "print → file → print");

    let table = "[[output]]\nkind = \"line\"\nline-output = \"tcp://127.0.0.1:0\"\n";
    let cases = [
        (
            format!("{table}\n{table}"),
            5,
            "a second output of kind \"line\" named `line`",
        ),
        (
            format!("{table}\n{table}id = \"line\"\n"),
            8,
            "a second output of kind \"line\" named `line`",
        ),
        (
            "\n[[output]]\nkind = \"lines\"\n".into(),
            3,
            "\"mqtt\", \"line\", \"webhook\"",
        ),
        ("[[output]]\nid = \"x\"\n".into(), 1, "`kind` is missing"),
        (
            format!("{table}broker = 3\n"),
            4,
            "unknown key `broker` for kind \"line\"",
        ),
        (
            "[[output]]\nkind = \"line\"\n\nline-output = \"udp://h:1\"\n".into(),
            4,
            "`line-output`",
        ),
        (
            "[[output]]\nkind = \"webhook\"\n".into(),
            1,
            "needs `webhook`",
        ),
        ("output = 3\n".into(), 1, "[[output]]"),
    ];
    for (text, line, what) in cases {
        std::fs::write(&file, &text).expect("writing the file");
        let done = serve(&["--config", path(&file)]).expect_status(2, &text);
        let want = format!("station.toml:{line}: ");
        assert!(
            done.stderr.contains(&want) && done.stderr.contains(what),
            "{text:?}: want {want}{what}: {}",
            done.stderr
        );
    }
    // A flag and a table without an id: two outputs of one name, which would share a
    // cursor.
    std::fs::write(&file, table).expect("writing the file");
    let done = serve(&[
        "--config",
        path(&file),
        "--line-output",
        "tcp://127.0.0.1:0",
    ])
    .expect_status(2, "a flag and a table of one name");
    assert!(
        done.stderr
            .contains("two outputs of kind \"line\" are named `line`"),
        "{}",
        done.stderr
    );
}
