//! `coapcam bench transfer` as a process, on a tiny configuration: our window and
//! stop-and-wait clients against `coapcam serve`, on loopback and through its in-process
//! 20 ms relay. What is checked is the report (every run bit-exact, the counts, the relay
//! counters, the table and the plot's size), never a wall-clock time.

use std::time::Duration;

use crate::support::{COAPCAM, Proc, TempDir};

/// Ample for 4 runs of 20,000 bytes (the 20 ms stop-and-wait one is 20 round trips).
const LIMIT: Duration = Duration::from_secs(120);

#[test]
fn bench_transfer_reports_bit_exact_runs_as_table_json_and_plot() {
    let dir = TempDir::new("bench-transfer");
    let json = dir.join("bench.json");
    let plot = dir.join("bench.png");
    let args = [
        "bench",
        "transfer",
        "--sizes",
        "20000",
        "--links",
        "loopback,20ms",
        "--modes",
        "window,stop-and-wait",
        "--runs",
        "1",
        "--seed",
        "3",
        "--json",
        json.to_str().expect("UTF-8 path"),
        "--plot",
        plot.to_str().expect("UTF-8 path"),
    ];
    let finished = Proc::run(COAPCAM, &args, LIMIT).expect_success("coapcam bench transfer");

    // The table: a header with both modes and their ratio, one row per link.
    let table = finished.stdout_text();
    let header = table
        .lines()
        .find(|l| l.starts_with("| link"))
        .unwrap_or_else(|| panic!("no table header in {table}"));
    for column in ["window", "stop-and-wait", "stop-and-wait / window"] {
        assert!(header.contains(column), "{header}");
    }
    for link in ["| loopback ", "| 20ms "] {
        let row = table
            .lines()
            .find(|l| l.starts_with(link))
            .unwrap_or_else(|| panic!("no row {link} in {table}"));
        assert_eq!(row.matches(" 1/1 ").count(), 2, "{row}");
        assert_eq!(row.matches(" p95 ").count(), 2, "{row}");
        // One run per cell is too few for a ratio (15 at least).
        let ratio = row.trim_end().trim_end_matches('|').rsplit('|').next();
        assert_eq!(ratio.map(str::trim), Some("-"), "{row}");
    }

    let report: serde_json::Value = serde_json::from_slice(
        &std::fs::read(&json).unwrap_or_else(|e| panic!("reading {}: {e}", json.display())),
    )
    .expect("the report is JSON");
    assert_eq!(report["seed"], 3);
    assert_eq!(report["runs"], 1);
    assert!(
        report["timing"]
            .as_str()
            .is_some_and(|t| t.contains("whole process"))
    );
    let links: Vec<&str> = report["links"]
        .as_array()
        .expect("links")
        .iter()
        .filter_map(|l| l["name"].as_str())
        .collect();
    assert_eq!(links, ["loopback", "20ms"]);
    let cells = report["cells"].as_array().expect("cells");
    assert_eq!(cells.len(), 4, "{report:#}");
    for cell in cells {
        assert_eq!(cell["bytes"], 20000, "{cell:#}");
        assert_eq!(cell["runs"], 1, "{cell:#}");
        assert_eq!(cell["ok"], 1, "{cell:#}");
        assert_eq!(cell["all_bit_exact"], true, "{cell:#}");
        assert!(cell["unavailable"].is_null(), "{cell:#}");
        assert!(
            cell["median_s"].as_f64().is_some_and(|t| t > 0.0),
            "{cell:#}"
        );
        assert_eq!(cell["p95_s"], cell["max_s"], "one run: {cell:#}");
        let run = &cell["results"][0];
        assert_eq!(run["ok"], true, "{cell:#}");
        assert_eq!(run["bit_exact"], true, "{cell:#}");
        assert_eq!(run["exit"], 0, "{cell:#}");
        // Through the relay, every datagram went both ways and none was lost.
        if cell["link"] == "20ms" {
            let relay = &run["relay"];
            assert!(
                relay["up"]["forwarded"].as_u64().is_some_and(|n| n > 0),
                "{relay}"
            );
            assert!(
                relay["down"]["forwarded"].as_u64().is_some_and(|n| n > 0),
                "{relay}"
            );
            assert_eq!(relay["up"]["dropped"], 0, "{relay}");
        } else {
            assert!(run["relay"].is_null(), "{cell:#}");
        }
    }
    let modes: Vec<&str> = cells.iter().filter_map(|c| c["mode"].as_str()).collect();
    assert_eq!(
        modes,
        ["window", "stop-and-wait", "window", "stop-and-wait"]
    );

    // The plot: one 600x450 panel for the one size and the 300-pixel legend.
    let png = image::open(&plot).unwrap_or_else(|e| panic!("decoding {}: {e}", plot.display()));
    assert_eq!((png.width(), png.height()), (900, 450));
}

#[test]
fn bench_transfer_pairs_two_bit_exact_clients_through_one_relay() {
    let dir = TempDir::new("bench-transfer-pairs");
    let json = dir.join("bench.json");
    let args = [
        "bench",
        "transfer",
        "--sizes",
        "30000",
        "--links",
        "20ms-2%-50mbit",
        "--modes",
        "window",
        "--runs",
        "1",
        "--pairs",
        "1",
        "--seed",
        "3",
        "--json",
        json.to_str().expect("UTF-8 path"),
    ];
    let finished = Proc::run(COAPCAM, &args, LIMIT).expect_success("coapcam bench transfer");

    // The second table, after the main one: one row for the one (size, mode).
    let table = finished.stdout_text();
    let heading = table
        .find("Two transfers at once through 20ms-2%-50mbit")
        .unwrap_or_else(|| panic!("no pair table in {table}"));
    assert!(table[..heading].contains("| link "), "{table}");
    let row = table[heading..]
        .lines()
        .find(|l| l.starts_with("| 30000 "))
        .unwrap_or_else(|| panic!("no pair row in {table}"));
    assert!(row.contains(" window "), "{row}");
    assert!(row.ends_with(" 1/1 |"), "{row}");

    let report: serde_json::Value = serde_json::from_slice(
        &std::fs::read(&json).unwrap_or_else(|e| panic!("reading {}: {e}", json.display())),
    )
    .expect("the report is JSON");
    // The single run is there as usual.
    assert_eq!(
        report["cells"].as_array().map(Vec::len),
        Some(1),
        "{report:#}"
    );
    let pairs = &report["pairs"];
    assert_eq!(pairs["runs"], 1, "{pairs:#}");
    assert_eq!(pairs["link"], "20ms-2%-50mbit", "{pairs:#}");
    let cells = pairs["cells"].as_array().expect("pair cells");
    assert_eq!(cells.len(), 1, "{pairs:#}");
    let cell = &cells[0];
    assert_eq!(
        (&cell["bytes"], &cell["mode"]),
        (&30000.into(), &"window".into())
    );
    assert_eq!(
        (&cell["runs"], &cell["ok"]),
        (&1.into(), &1.into()),
        "{cell:#}"
    );
    let run = &cell["results"][0];
    assert_eq!(run["ok"], true, "{run:#}");
    let clients = run["clients"].as_array().expect("clients");
    assert_eq!(clients.len(), 2, "{run:#}");
    for client in clients {
        assert_eq!(client["ok"], true, "{run:#}");
        assert_eq!(client["bit_exact"], true, "{run:#}");
        assert_eq!(client["exit"], 0, "{run:#}");
    }
    // What the relay had delivered when the first client ended: to one or both client
    // addresses (a client that started late may have had nothing yet), all of it.
    let delivered = run["delivered_at_first_end"].as_array().expect("delivered");
    assert!((1..=2).contains(&delivered.len()), "{run:#}");
    assert!(
        delivered
            .iter()
            .all(|d| d["bytes"].as_u64().is_some_and(|n| n > 0)),
        "{run:#}"
    );
    let smaller = run["smaller_share"].as_f64().expect("smaller share");
    let larger = run["larger_share"].as_f64().expect("larger share");
    assert!(
        (0.0..=0.5).contains(&smaller) && smaller <= larger,
        "{run:#}"
    );
    assert!((smaller + larger - 1.0).abs() < 1e-9, "{run:#}");
    assert!(
        run["utilisation"].as_f64().is_some_and(|u| u > 0.0),
        "{run:#}"
    );
    assert!(
        run["relay"]["down"]["forwarded"]
            .as_u64()
            .is_some_and(|n| n > 0),
        "{run:#}"
    );
    assert_eq!(run["relay"]["clients"], 2, "{run:#}");
}

#[test]
fn bench_transfer_refuses_bad_flags() {
    for bad in [
        &["--runs", "0"][..],
        &["--sizes", "0"],
        &["--links", "moon"],
        &["--modes", "carrier-pigeon"],
        &["--cap", "0"],
    ] {
        let mut args = vec!["bench", "transfer"];
        args.extend_from_slice(bad);
        let finished = Proc::run(COAPCAM, &args, LIMIT);
        assert_eq!(
            finished.status.code(),
            Some(2),
            "{bad:?}: {}",
            finished.stderr
        );
    }
}
