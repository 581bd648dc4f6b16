//! The PostgreSQL output (issue 47, item 4) against a real server: Debian's postgresql,
//! a cluster made per test by `initdb` in a scratch folder and served by `postgres` on a
//! free port of 127.0.0.1 (its socket in the same folder), stopped and started again
//! while the station records: on request, and by itself (`serve --auto-measure`). initdb and postgres refuse to run as root: as root the
//! test runs them as the user `nobody`. The server missing fails in CI (`CI=true`) and
//! skips loudly elsewhere.

use std::net::{TcpListener, TcpStream};
use std::os::unix::process::CommandExt as _;
use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, Instant};

use coapcam::process::peers;
use coapcam::station::log::ResultsLog;
use coapcam::station::postgres::CONSUMER;
use serde_json::Value;

use crate::lane::Lane;
use crate::support::{COAPCAM, LIMIT, Peer, Proc, TempDir, available, runtime, station};

/// The cluster's superuser (initdb -U), trusted on loopback.
const USER: &str = "coapcam";

/// A PostgreSQL server of its own: a cluster in a scratch folder, on one port throughout.
struct Server {
    bin: PathBuf,
    /// The folder of the cluster (`data`) and the server's socket.
    root: PathBuf,
    port: u16,
    /// The user and group the programs run as (`nobody` when the test runs as root).
    owner: Option<(u32, u32)>,
    process: Option<Proc>,
}

impl Server {
    /// A new cluster in `dir`, started.
    fn start(dir: &TempDir) -> Self {
        let bin = peers::postgres_bin().expect("checked by available()");
        let root = dir.join("pg");
        std::fs::create_dir_all(&root).expect("the cluster's folder");
        let owner = (id(&["-u"]) == 0).then(|| (id(&["-u", "nobody"]), id(&["-g", "nobody"])));
        if let Some((uid, gid)) = owner {
            std::os::unix::fs::chown(&root, Some(uid), Some(gid)).expect("chown to nobody");
        }
        let mut server = Self {
            bin,
            root,
            port: 0,
            owner,
            process: None,
        };
        let data = server.root.join("data");
        let mut initdb = server.command("initdb");
        initdb.args(["-D", &data.to_string_lossy(), "-U", USER, "--auth=trust"]);
        initdb.args(["-E", "UTF8", "--locale=C", "--no-sync"]);
        let mut p = Proc::spawn_command(initdb, "initdb");
        let f = p
            .wait(LIMIT)
            .unwrap_or_else(|| panic!("initdb took over {LIMIT:?}"));
        f.expect_success("initdb");
        for _ in 0..10 {
            server.port = free_tcp_port();
            if server.try_start() {
                return server;
            }
        }
        panic!("postgres did not start on any of 10 free ports");
    }

    /// `program` of the server's folder, run as the cluster's owner in its folder.
    fn command(&self, program: &str) -> Command {
        let mut command = Command::new(self.bin.join(program));
        command.current_dir(&self.root);
        if let Some((uid, gid)) = self.owner {
            command.uid(uid).gid(gid);
        }
        command
    }

    /// Starts the server on its port; false if it exited (the port was taken meanwhile).
    fn try_start(&mut self) -> bool {
        let mut postgres = self.command("postgres");
        let port = self.port.to_string();
        let (data, socket) = (self.root.join("data"), self.root.to_string_lossy());
        postgres.args(["-D", &data.to_string_lossy(), "-p", &port, "-k", &socket]);
        postgres.args(["-c", "listen_addresses=127.0.0.1", "-c", "fsync=off"]);
        let mut p = Proc::spawn_command(postgres, "postgres");
        let deadline = Instant::now() + LIMIT;
        while Instant::now() < deadline {
            if !p.is_running() {
                let f = p.kill();
                eprintln!("postgres on port {port} exited: {}", f.stderr);
                return false;
            }
            if TcpStream::connect(("127.0.0.1", self.port)).is_ok() {
                self.process = Some(p);
                return true;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        panic!("postgres did not listen on port {port} within {LIMIT:?}");
    }

    /// Stops the server: SIGINT is its fast shutdown (clients cut off, the data
    /// written), SIGQUIT its immediate one (as a crash: recovered from the WAL at the
    /// next start).
    fn stop(&mut self, signal: &str) {
        let mut p = self.process.take().expect("the server runs");
        let pid = p.pid().to_string();
        let sent = Command::new("kill").args([signal, &pid]).status();
        assert!(sent.is_ok_and(|s| s.success()), "kill {signal} {pid}");
        if p.wait(LIMIT).is_none() {
            p.kill();
            panic!("postgres still ran {LIMIT:?} after {signal}");
        }
    }

    fn restart(&mut self) {
        assert!(
            self.try_start(),
            "postgres did not start again on port {}",
            self.port
        );
    }

    fn url(&self) -> String {
        format!("postgres://{USER}@127.0.0.1:{}/postgres", self.port)
    }
}

/// `id ARGS`' number.
fn id(args: &[&str]) -> u32 {
    let out = Command::new("id").args(args).output().expect("running id");
    String::from_utf8_lossy(&out.stdout)
        .trim()
        .parse()
        .unwrap_or_else(|e| panic!("id {args:?}: {e}"))
}

fn free_tcp_port() -> u16 {
    let l = TcpListener::bind("127.0.0.1:0").expect("binding 127.0.0.1:0");
    l.local_addr().expect("local address").port()
}

/// One measurement recorded by the station at `addr`.
fn measure(addr: std::net::SocketAddr) {
    let uri = format!("coap://{addr}/cams/dimensions");
    Proc::run(COAPCAM, &["post", &uri, "-o", "/dev/null"], LIMIT).expect_success("POST");
}

/// Runs `sql` on the server at `url` and returns its rows as text columns.
fn query(url: &str, sql: &str) -> Vec<Vec<Option<String>>> {
    try_query(url, sql).unwrap_or_else(|e| panic!("{sql}: {e}"))
}

/// [`query`], or why it could not be run (the server's message).
fn try_query(url: &str, sql: &str) -> Result<Vec<Vec<Option<String>>>, String> {
    runtime().block_on(async {
        let (client, connection) =
            tokio::time::timeout(LIMIT, tokio_postgres::connect(url, tokio_postgres::NoTls))
                .await
                .map_err(|_| format!("connecting took over {LIMIT:?}"))?
                // The server may still be recovering after an immediate shutdown.
                .map_err(|e| format!("connecting: {e}"))?;
        let connection = tokio::spawn(connection);
        let messages = tokio::time::timeout(LIMIT, client.simple_query(sql))
            .await
            .expect("an answer in time")
            .map_err(|e| match e.as_db_error() {
                Some(db) => db.to_string(),
                None => e.to_string(),
            });
        drop(client);
        let _ = tokio::time::timeout(LIMIT, connection).await;
        Ok(messages?
            .into_iter()
            .filter_map(|m| match m {
                tokio_postgres::SimpleQueryMessage::Row(row) => Some(
                    (0..row.len())
                        .map(|i| row.get(i).map(str::to_owned))
                        .collect(),
                ),
                _ => None,
            })
            .collect())
    })
}

/// The ids of `station`'s rows in the order they arrived; none while the output has not
/// made the table.
fn in_table(url: &str, station: &str) -> Vec<String> {
    let sql =
        format!("SELECT id FROM coapcam_records WHERE station = '{station}' ORDER BY arrival");
    try_query(url, &sql)
        .unwrap_or_default()
        .into_iter()
        .filter_map(|row| row.into_iter().next().flatten())
        .collect()
}

/// Waits (bounded) until the table holds `made` rows of `station`; their ids in arrival
/// order.
fn copied(url: &str, station: &str, made: usize) -> Vec<String> {
    let deadline = Instant::now() + LIMIT;
    let mut ids = in_table(url, station);
    while ids.len() < made && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(100));
        ids = in_table(url, station);
    }
    ids
}

/// The SQL of docs/station.md's section on PostgreSQL: the table, the hash check, and
/// the two questions (today's parcels, a code's records) in one block.
fn documented_queries() -> Vec<&'static str> {
    let doc = include_str!("../../../../docs/station.md");
    let section = doc
        .split("\n## PostgreSQL\n")
        .nth(1)
        .and_then(|s| s.split("\n## ").next())
        .expect("docs/station.md's section on PostgreSQL");
    let blocks: Vec<&str> = section
        .split("```sql\n")
        .skip(1)
        .filter_map(|b| b.split("```").next())
        .collect();
    assert_eq!(blocks.len(), 3, "the table, the hash check, two questions");
    blocks
}

/// `coapcam results verify LOG --postgres URL --json`: its exit status and document.
fn verify(log: &str, url: &str) -> (Option<i32>, Value) {
    let f = Proc::run(
        COAPCAM,
        &["results", "verify", log, "--postgres", url, "--json"],
        LIMIT,
    );
    let doc = serde_json::from_str(f.stdout_text().trim())
        .unwrap_or_else(|e| panic!("{e}: {}\n{}", f.stdout_text(), f.stderr));
    (f.status.code(), doc)
}

/// The station's records while the server is stopped and started 10 times (every other
/// time as a crash): each is in the table once, in id order, and `results verify
/// --postgres` agrees; a cursor moved back (a station that stopped before it saved its
/// cursor) sends records the table has and adds no row; a row deleted or altered fails
/// the check, naming the record.
#[test]
fn every_record_reaches_the_table_once_across_ten_restarts_and_verify_checks_it() {
    let test = "every_record_reaches_the_table_once_across_ten_restarts_and_verify_checks_it";
    if !available(test, &[Peer::Postgres]) {
        return;
    }
    let dir = TempDir::new("postgres");
    let mut server = Server::start(&dir);
    let url = server.url();
    let state = dir.join("state");
    let flags = ["--station-name", "dock-pg", "--postgres", &url];
    let s = station(&state, &flags);
    let (mut process, addr) = (s.process, s.coap);
    let log_path = state.join("results.sqlite");
    let log = log_path.to_string_lossy().into_owned();

    let copied = |made: usize| copied(&url, "dock-pg", made);
    let started = Instant::now();
    let mut made = 0;
    for restart in 0..10 {
        measure(addr);
        made += 1;
        // Copied while the server is up: the output is connected again after each
        // restart, and each stop cuts a connection it uses.
        assert_eq!(copied(made).len(), made, "rows before stop {}", restart + 1);
        server.stop(if restart % 2 == 0 { "-INT" } else { "-QUIT" });
        // Records made while the server is down wait in the log.
        for _ in 0..2 {
            measure(addr);
            made += 1;
        }
        server.restart();
    }
    measure(addr);
    made += 1;

    // Every record arrives (the output retries at most 5 s apart), once, in id order.
    let mut wanted: Vec<String> = (1..=made).map(|id| id.to_string()).collect();
    assert_eq!(copied(made), wanted, "the rows in the order they arrived");
    eprintln!(
        "postgres: {made} records made and copied across 10 restarts of the server in {:.1} s",
        started.elapsed().as_secs_f64()
    );
    let (status, doc) = verify(&log, &url);
    assert_eq!(status, Some(0), "{doc}");
    assert_eq!(doc["postgres"]["rows"], made, "{doc}");
    assert_eq!(doc["postgres"]["station"], "dock-pg", "{doc}");

    // The queries docs/station.md gives: every body hashes to its hash; today's parcels
    // per station (all of them, unless the day changed meanwhile); a code's records.
    let blocks = documented_queries();
    assert_eq!(
        query(&url, blocks[1]),
        Vec::<Vec<Option<String>>>::new(),
        "{}",
        blocks[1]
    );
    let (today, code) = blocks[2].split_once(";\n\n").expect("two queries");
    let yesterday = query(
        &url,
        "SELECT count(*) FROM coapcam_records WHERE time < date_trunc('day', now())",
    );
    if yesterday[0][0].as_deref() == Some("0") {
        let rows = query(&url, today);
        assert_eq!(rows.len(), 1, "{today}");
        assert_eq!(
            rows[0][..2],
            [Some("dock-pg".to_owned()), Some(made.to_string())]
        );
        let litres: f64 = rows[0][2]
            .as_deref()
            .and_then(|l| l.parse().ok())
            .expect("litres");
        assert!(litres > 0.0, "{rows:?}");
    }
    // No code is read without ?codes: none found, and the query runs.
    assert!(query(&url, code).is_empty(), "{code}");

    // The station stops with its cursor moved back, as if it had died between a commit
    // and the cursor's save: the records are sent again, and no row is added.
    let f = process.interrupt().expect_success("serve");
    let failures = f
        .stderr
        .matches("retrying (the records wait in the log)")
        .count();
    assert!(failures >= 10, "a failure said for each stop: {}", f.stderr);
    ResultsLog::open(&log_path)
        .and_then(|l| l.set_cursor(CONSUMER, 3))
        .expect("moving the cursor back");
    let arrivals = query(&url, "SELECT id, arrival FROM coapcam_records ORDER BY id");
    let s = station(&state, &flags);
    let (mut process, addr) = (s.process, s.coap);
    // A new record is copied after those sent again (the output goes in id order).
    measure(addr);
    made += 1;
    wanted.push(made.to_string());
    assert_eq!(
        copied(made),
        wanted,
        "rows after records 4 on were sent again"
    );
    let now = query(&url, "SELECT id, arrival FROM coapcam_records ORDER BY id");
    assert_eq!(
        now[..arrivals.len()],
        arrivals[..],
        "the rows sent again were kept as they were"
    );
    let (status, doc) = verify(&log, &url);
    assert_eq!(status, Some(0), "{doc}");
    assert_eq!(doc["postgres"]["rows"], made, "{doc}");
    process.interrupt().expect_success("serve");

    // A row altered in the table (its body, the hash left) fails the check.
    let original = query(&url, "SELECT body FROM coapcam_records WHERE id = 7");
    let original = original[0][0].clone().expect("record 7's body");
    query(
        &url,
        "UPDATE coapcam_records SET body = replace(body, '\"trigger\":\"request\"', '\"trigger\":\"auto\"') WHERE id = 7",
    );
    let (status, doc) = verify(&log, &url);
    assert_eq!(status, Some(7), "{doc}");
    assert_eq!(doc["postgres"]["first_difference"]["id"], 7, "{doc}");
    assert_eq!(doc["postgres"]["rows"], 6, "{doc}");
    let body = original.replace('\'', "''");
    query(
        &url,
        &format!("UPDATE coapcam_records SET body = '{body}' WHERE id = 7"),
    );
    assert_eq!(verify(&log, &url).0, Some(0), "record 7 put back");

    // A row deleted fails it, naming the record.
    query(&url, "DELETE FROM coapcam_records WHERE id = 12");
    let (status, doc) = verify(&log, &url);
    assert_eq!(status, Some(7), "{doc}");
    assert_eq!(doc["postgres"]["first_difference"]["id"], 12, "{doc}");
    let why = doc["postgres"]["first_difference"]["why"]
        .as_str()
        .unwrap_or_default();
    assert!(why.contains("record 12 is not in the table"), "{why}");

    server.stop("-INT");
}

/// How long each parcel of [`AUTO_SCENE`] stands still: a measurement by itself (the
/// codes, a photo, the annotated picture) took 1.7 to 2.3 s in a debug build on a busy
/// 2-core machine, and one still running when its parcel is taken away is not recorded.
const STAND_S: f64 = 6.5;

/// From one parcel's arrival to the next's: it slides in for 0.5 s, stands
/// [`STAND_S`], and the table is empty for 0.5 s.
const PERIOD_S: f64 = 7.5;

/// The parcels the test needs: one stop of the server during each one's measurement and
/// one between.
const PARCELS: usize = 5;

/// The scene of [`auto_measured_records_reach_the_table_once_in_order_across_ten_restarts`]:
/// [`PARCELS`] parcels placed one after another, each labelled `PKG-000N`, and a spare
/// one 10 s after them, measured only when one of them was not (its measurement outran
/// its parcel).
fn auto_scene() -> String {
    let mut scene = crate::lane::ONE_CAMERA.to_owned();
    for n in 0..=PARCELS {
        let appear = 1.0 + n as f64 * PERIOD_S + if n == PARCELS { 10.0 } else { 0.0 };
        scene.push_str(&parcel_text(n, appear));
    }
    scene
}

/// The `n`-th parcel (from 0) of a scene, labelled `PKG-000N` (N = n + 1), arriving at
/// `appear` s: slid in for 0.5 s, standing [`STAND_S`], taken away.
fn parcel_text(n: usize, appear: f64) -> String {
    let size = [
        0.40 - 0.02 * n as f64,
        0.30 - 0.01 * n as f64,
        0.12 + 0.02 * n as f64,
    ];
    let from = if n.is_multiple_of(2) {
        [0.45, 0.0]
    } else {
        [0.0, -0.45]
    };
    format!(
        "[[box]]\nsize = {size:?}\ncenter = [0.0, 0.0]\nyaw_deg = {}\nappear_s = {appear}\n\
         from = {from:?}\nstill_s = {}\nremove_s = {}\n\
         label = {{ kind = \"qr\", text = \"PKG-{:04}\", size = 0.08 }}\n",
        -20.0 + 10.0 * n as f64,
        appear + 0.5,
        appear + 0.5 + STAND_S,
        n + 1,
    )
}

/// How many of the station's log lines so far contain `what`.
fn said(lane: &Lane, what: &str) -> usize {
    lane.log().matches(what).count()
}

/// Waits (bounded) until the station has said `what` `n` times.
fn wait_said(lane: &Lane, what: &str, n: usize) {
    let deadline = Instant::now() + LIMIT;
    while said(lane, what) < n {
        assert!(
            Instant::now() < deadline,
            "the station did not say `{what}` {n} times within {LIMIT:?}:\n{}",
            lane.log()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

const MEASURING: &str = "auto-measure: a parcel stands still; measuring";
const RECORDED: &str = "auto-measure: recorded measurement ";
const RETRYING: &str = "retrying (the records wait in the log)";

/// The ids of the records the station said it made, in order.
fn recorded_ids(lane: &Lane) -> Vec<String> {
    lane.log()
        .lines()
        .filter_map(|l| l.split(RECORDED).nth(1)?.split(':').next())
        .map(str::to_owned)
        .collect()
}

/// `serve --auto-measure` on a scene of parcels placed one after another, while the
/// server is stopped and started 10 times, every other time as a crash: for each parcel,
/// once while it is measured (its record is made while the server is down and waits in
/// the log) and once after its row is in (the connection the output holds is cut). Every
/// record of the log is in the table once, in id order, and `results verify --postgres`
/// passes; the documented question for a code finds the record of the parcel that
/// carried it.
#[test]
fn auto_measured_records_reach_the_table_once_in_order_across_ten_restarts() {
    let test = "auto_measured_records_reach_the_table_once_in_order_across_ten_restarts";
    if !available(test, &[Peer::Postgres]) {
        return;
    }
    let started = Instant::now();
    let dir = TempDir::new("postgres-auto");
    let mut server = Server::start(&dir);
    let url = server.url();
    let mut lane = Lane::start_with(&dir, &auto_scene(), &["--postgres", &url]);
    let (mut stops, mut made_while_down) = (0, 0);
    for k in 1..=PARCELS {
        // The measurement of the k-th record has started: the first one after the
        // record before it.
        let before = lane
            .log()
            .split(RECORDED)
            .take(k - 1)
            .collect::<Vec<_>>()
            .join(RECORDED)
            .matches(MEASURING)
            .count();
        wait_said(&lane, MEASURING, before + 1);
        let [first, second] = if k % 2 == 1 {
            ["-INT", "-QUIT"]
        } else {
            ["-QUIT", "-INT"]
        };
        server.stop(first);
        stops += 1;
        let ahead = said(&lane, RECORDED) >= k;
        wait_said(&lane, RECORDED, k);
        if !ahead {
            // Made while the server was down: the output tries, fails and says so.
            made_while_down += 1;
            wait_said(&lane, RETRYING, made_while_down);
        }
        server.restart();
        // Records 1 to k, in order; the next one may have been made and copied since.
        let ids = copied(&url, "lane-1", k);
        let first: Vec<String> = (1..=k).map(|id| id.to_string()).collect();
        assert!(
            ids.get(..k) == Some(&first[..]),
            "after stop {stops}: the rows {ids:?}, the records {:?}\n{}",
            recorded_ids(&lane),
            lane.log()
        );
        server.stop(second);
        stops += 1;
        server.restart();
    }
    assert_eq!(stops, 10);
    let status = lane.interrupt();
    assert!(status.success(), "{status}\n{}", lane.log());
    eprintln!(
        "postgres: {PARCELS} records measured by the station itself and copied across {stops} \
         restarts of the server ({made_while_down} made while it was down) in {:.1} s",
        started.elapsed().as_secs_f64()
    );

    // The log's records are the ones the station said it made, and each is in the table
    // once, in id order.
    let log = ResultsLog::open(lane.results()).expect("the results log");
    let records = log.after(0, 100).expect("the log's records");
    let ids: Vec<String> = records.iter().map(|r| r.id.to_string()).collect();
    let wanted: Vec<String> = (1..=PARCELS).map(|id| id.to_string()).collect();
    assert_eq!(ids, wanted, "{}", lane.log());
    // (copied waits while the server recovers from the last stop.)
    assert_eq!(
        copied(&url, "lane-1", PARCELS),
        wanted,
        "the rows in the order they arrived"
    );
    let path = lane.results().to_string_lossy().into_owned();
    let (status, doc) = verify(&path, &url);
    assert_eq!(status, Some(0), "{doc}");
    assert_eq!(doc["postgres"]["rows"], PARCELS, "{doc}");
    assert_eq!(doc["postgres"]["station"], "lane-1", "{doc}");

    // docs/station.md's question for a code (PKG-0001) finds the records that read it.
    let blocks = documented_queries();
    let (_, code) = blocks[2].split_once(";\n\n").expect("two queries");
    let read: Vec<String> = records
        .iter()
        .filter(|r| {
            r.measurement
                .codes
                .iter()
                .flatten()
                .any(|c| c.code.text == "PKG-0001")
        })
        .map(|r| r.id.to_string())
        .collect();
    assert!(!read.is_empty(), "PKG-0001 read\n{}", lane.log());
    let found: Vec<String> = query(&url, code)
        .into_iter()
        .filter_map(|row| row.get(1).cloned().flatten())
        .collect();
    assert_eq!(found, read, "{code}");

    // The station starts again with its cursor moved back, as if it had died between a
    // commit and the cursor's save: records 3 to 5 are sent again and add no row, and
    // the next parcel's record follows them.
    log.set_cursor(CONSUMER, 2).expect("moving the cursor back");
    drop(log);
    let arrivals = query(&url, "SELECT id, arrival FROM coapcam_records ORDER BY id");
    drop(lane);
    let mut scene = crate::lane::ONE_CAMERA.to_owned();
    scene.push_str(&parcel_text(PARCELS, 1.0));
    let mut lane = Lane::start_with(&dir, &scene, &["--postgres", &url]);
    let mut wanted = wanted;
    wanted.push((PARCELS + 1).to_string());
    assert_eq!(
        copied(&url, "lane-1", PARCELS + 1),
        wanted,
        "rows after records 3 on were sent again\n{}",
        lane.log()
    );
    let now = query(&url, "SELECT id, arrival FROM coapcam_records ORDER BY id");
    assert_eq!(
        now[..arrivals.len()],
        arrivals[..],
        "the rows sent again were kept as they were"
    );
    let status = lane.interrupt();
    assert!(status.success(), "{status}\n{}", lane.log());
    let (status, doc) = verify(&path, &url);
    assert_eq!(status, Some(0), "{doc}");
    assert_eq!(doc["postgres"]["rows"], PARCELS + 1, "{doc}");
    eprintln!(
        "postgres: with the records sent again after the cursor moved back, {:.1} s",
        started.elapsed().as_secs_f64()
    );

    server.stop("-INT");
}
