//! MQTT to a real broker: Debian's mosquitto, started per test on a free loopback port
//! with a configuration file of the test's own, and read by a subscriber of the test's own
//! (rumqttc) and by `mosquitto_sub`. The broker missing fails in CI (`CI=true`) and skips
//! loudly elsewhere.

use std::io::{BufRead as _, BufReader};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use coap::Code;
use coapcam::api::record::{NewRecord, Trigger, UtcTime};
use coapcam::report::{Billing, Measurement, Seen, Table};
use coapcam::station::log::ResultsLog;
use coapcam::station::mqtt::{CONSUMER, Config, Publisher};
use coapcam::vision::codes::{Code as Label, CodeKind};
use geometry::{Dimensions, ParcelFit};
use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};
use tokio::sync::{mpsc, watch};

use crate::support::{
    MOSQUITTO_SUB, Peer, Proc, Station, TempDir, available, client, mosquitto_broker, runtime,
    send, station,
};

/// Longest wait for a message that should come.
const LIMIT: Duration = Duration::from_secs(30);

/// A mosquitto broker on 127.0.0.1, stopped and started again on the same port.
struct Broker {
    port: u16,
    config: PathBuf,
    process: Option<Proc>,
}

impl Broker {
    /// Starts a broker; `persistent` keeps its sessions (and the messages queued for a
    /// subscriber's persistent session) across a stop and a start, in `dir`.
    fn start(dir: &TempDir, persistent: bool) -> Self {
        Self::start_with(dir, persistent, "allow_anonymous true\n")
    }

    /// A broker that takes only the user `dock` with the password `s@cret:1` (a password
    /// file made by `mosquitto_passwd`).
    fn start_with_password(dir: &TempDir) -> Self {
        let passwords = dir.join("passwords");
        let made = std::process::Command::new("mosquitto_passwd")
            .args(["-b", "-c", &passwords.to_string_lossy(), "dock", "s@cret:1"])
            .status()
            .expect("running mosquitto_passwd (Debian's mosquitto package has it)");
        assert!(made.success(), "mosquitto_passwd failed");
        let _ = std::process::Command::new("chmod")
            .args(["0644", &passwords.to_string_lossy()])
            .status();
        let extra = format!(
            "allow_anonymous false\npassword_file {}\n",
            passwords.display()
        );
        Self::start_with(dir, false, &extra)
    }

    fn start_with(dir: &TempDir, persistent: bool, access: &str) -> Self {
        for _ in 0..10 {
            let port = free_tcp_port();
            let data = dir.join("broker-data");
            std::fs::create_dir_all(&data).expect("broker data directory");
            // mosquitto started as root runs as the user mosquitto.
            let _ = std::process::Command::new("chmod")
                .args(["0777", &data.to_string_lossy()])
                .status();
            let config = dir.join(&format!("mosquitto-{port}.conf"));
            std::fs::write(
                &config,
                format!(
                    "listener {port} 127.0.0.1\n{access}persistence {persistent}\n\
                     persistence_location {}/\nlog_dest stderr\nlog_type error\nlog_type warning\n",
                    data.display()
                ),
            )
            .expect("writing the broker's configuration");
            let mut broker = Self {
                port,
                config,
                process: None,
            };
            if broker.try_start() {
                return broker;
            }
        }
        panic!("mosquitto did not start on any of 10 free ports");
    }

    /// Starts the broker on its port; false if it exited (the port was taken meanwhile).
    fn try_start(&mut self) -> bool {
        let program = mosquitto_broker().expect("checked by available()");
        let mut p = Proc::spawn(
            &program.to_string_lossy(),
            &["-c", &self.config.to_string_lossy()],
        );
        let deadline = Instant::now() + LIMIT;
        while Instant::now() < deadline {
            if !p.is_running() {
                return false;
            }
            if TcpStream::connect(self.addr()).is_ok() {
                self.process = Some(p);
                return true;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        panic!(
            "mosquitto did not listen on {} within {LIMIT:?}",
            self.addr()
        );
    }

    fn addr(&self) -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], self.port))
    }

    fn uri(&self, prefix: &str) -> String {
        format!("mqtt://127.0.0.1:{}/{prefix}", self.port)
    }

    /// Stops the broker cleanly (SIGTERM: a persistent one saves its sessions).
    fn stop(&mut self) {
        let mut p = self.process.take().expect("the broker runs");
        let f = p.interrupt();
        assert!(
            !f.stderr.contains("rror"),
            "mosquitto reported: {}",
            f.stderr
        );
    }

    /// Starts it again on the same port.
    fn restart(&mut self) {
        assert!(
            self.try_start(),
            "mosquitto did not start again on {}",
            self.port
        );
    }
}

fn free_tcp_port() -> u16 {
    let l = TcpListener::bind("127.0.0.1:0").expect("binding 127.0.0.1:0");
    l.local_addr().expect("local address").port()
}

/// A message as a subscriber got it.
#[derive(Debug, Clone)]
struct Message {
    topic: String,
    payload: Vec<u8>,
    retain: bool,
    /// When it arrived, ms since the UNIX epoch.
    arrived_unix_ms: i64,
}

impl Message {
    fn text(&self) -> &str {
        std::str::from_utf8(&self.payload).expect("UTF-8 payload")
    }

    fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.payload)
            .unwrap_or_else(|e| panic!("{}: {e}: {}", self.topic, self.text()))
    }
}

/// A subscriber of the test's own (QoS 1), reconnecting whenever the broker comes back.
/// A `persistent` one keeps its session at the broker (clean session off), so that what is
/// published while it is away waits for it.
struct Subscriber {
    messages: mpsc::UnboundedReceiver<Message>,
    task: tokio::task::JoinHandle<()>,
}

impl Subscriber {
    /// Connects and subscribes to `filter`; returns once the broker granted it.
    async fn start(port: u16, id: &str, filter: &str, persistent: bool) -> Self {
        let mut options = MqttOptions::new(id, "127.0.0.1", port);
        options
            .set_clean_session(!persistent)
            .set_keep_alive(Duration::from_secs(5));
        let (client, mut eventloop) = AsyncClient::new(options, 16);
        let (tx, messages) = mpsc::unbounded_channel();
        let (granted_tx, mut granted) = watch::channel(false);
        let filter = filter.to_owned();
        let task = tokio::spawn(async move {
            loop {
                match eventloop.poll().await {
                    Ok(Event::Incoming(Packet::ConnAck(ack))) => {
                        if !ack.session_present {
                            client
                                .subscribe(filter.clone(), QoS::AtLeastOnce)
                                .await
                                .expect("subscribing");
                        }
                    }
                    Ok(Event::Incoming(Packet::SubAck(_))) => {
                        let _ = granted_tx.send(true);
                    }
                    Ok(Event::Incoming(Packet::Publish(p))) => {
                        let _ = tx.send(Message {
                            topic: p.topic.clone(),
                            payload: p.payload.to_vec(),
                            retain: p.retain,
                            arrived_unix_ms: UtcTime::now().unix_ms,
                        });
                    }
                    Ok(_) => {}
                    Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
                }
            }
        });
        tokio::time::timeout(LIMIT, granted.wait_for(|g| *g))
            .await
            .expect("the broker granted the subscription in time")
            .expect("the subscriber runs");
        Self { messages, task }
    }

    async fn next(&mut self) -> Message {
        tokio::time::timeout(LIMIT, self.messages.recv())
            .await
            .unwrap_or_else(|_| panic!("no message within {LIMIT:?}"))
            .expect("the subscriber runs")
    }

    /// The next message on `topic` (others are skipped).
    async fn next_on(&mut self, topic: &str) -> Message {
        loop {
            let m = self.next().await;
            if m.topic == topic {
                return m;
            }
        }
    }
}

impl Drop for Subscriber {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// The retained message of `topic`, as `mosquitto_sub` reads it.
fn retained(port: u16, topic: &str) -> String {
    let f = Proc::run(
        MOSQUITTO_SUB,
        &[
            "-h",
            "127.0.0.1",
            "-p",
            &port.to_string(),
            "-t",
            topic,
            "-C",
            "1",
            "-W",
            "10",
            "--retained-only",
        ],
        LIMIT,
    );
    assert!(f.status.success(), "mosquitto_sub: {}", f.stderr);
    f.stdout_text().trim_end().to_owned()
}

/// A results log of the test's own, in `dir`.
fn open_log(dir: &TempDir) -> ResultsLog {
    ResultsLog::open(&dir.join("results.sqlite")).expect("opening the results log")
}

/// Records a measurement of `length_mm` (with code `code`, if any), as a measurement
/// path does; returns its id. Blocking: call it off the runtime's threads.
pub(crate) fn record(log: &ResultsLog, length_mm: f64, code: Option<&str>) -> u64 {
    record_billed(log, length_mm, code, &Billing::default())
}

/// [`record`] with the dimensions reported as `billing` says.
pub(crate) fn record_billed(
    log: &ResultsLog,
    length_mm: f64,
    code: Option<&str>,
    billing: &Billing,
) -> u64 {
    let dimensions = Dimensions {
        length_mm,
        width_mm: 300.0,
        height_mm: 200.0,
        yaw_deg: 0.0,
        corners_m: [[0.0, 0.0], [0.4, 0.0], [0.4, 0.3], [0.0, 0.3]],
        volume_l: length_mm * 0.06,
        points: 5000,
    };
    // As the station's measurement path makes it: the top level and `parcels`.
    let table = Table {
        fits: vec![ParcelFit::whole_box(dimensions)],
        largest_points: dimensions.points,
    };
    let mut measurement = Measurement::of_table(
        &table,
        billing,
        0.8,
        20_000,
        vec!["840412060746".into()],
        vec![1],
        Duration::from_millis(80),
    );
    if let Some(text) = code {
        let code = Label {
            kind: CodeKind::Qr,
            text: text.into(),
        };
        measurement.set_codes(
            Seen::gather([("840412060746".into(), vec![code])]),
            Duration::ZERO,
        );
    }
    log.append(NewRecord {
        time: log.now(),
        station: "dock".into(),
        trigger: Trigger::Request,
        measurement,
        cameras: Vec::new(),
        version: NewRecord::VERSION.into(),
        software_sha256: coapcam::identity::SOFTWARE_SHA256.into(),
        photo_jpeg: Some(vec![0xff; 2000]),
        annotated_png: None,
        parameters_sha256: None,
    })
    .expect("appending a record")
    .id
}

/// [`record`] on the blocking pool.
async fn record_async(log: &ResultsLog, length_mm: f64) -> u64 {
    let log = log.clone();
    tokio::task::spawn_blocking(move || record(&log, length_mm, None))
        .await
        .expect("recording")
}

fn config(broker: &Broker, station: &str) -> Config {
    Config {
        target: broker.uri("lane").parse().expect("mqtt URI"),
        station: station.into(),
    }
}

#[test]
fn records_arrive_in_order_as_json_with_ids_and_the_status_is_retained() {
    if !available("mqtt records", &[Peer::Mosquitto]) {
        return;
    }
    let dir = TempDir::new("mqtt-records");
    let broker = Broker::start(&dir, false);
    let log = open_log(&dir);
    // Two recorded before the publisher starts, three after.
    record(&log, 401.0, Some("PKG-1"));
    record(&log, 402.0, None);
    runtime().block_on(async {
        let mut sub = Subscriber::start(broker.port, "test-sub", "lane/#", false).await;
        let publisher = Publisher::start(config(&broker, "dock-1"), log.clone()).expect("start");
        let status = sub.next_on("lane/dock-1/status").await;
        assert_eq!(status.text(), "online");
        for n in 3..=5 {
            record_async(&log, 400.0 + f64::from(n)).await;
        }
        for id in 1..=5u64 {
            let m = sub.next_on("lane/dock-1/measurements").await;
            assert!(!m.retain, "measurements are not retained");
            let json = m.json();
            // The record as the log keeps it, without its pictures.
            let kept = log.get(id).expect("reading").expect("recorded");
            assert_eq!(json, serde_json::to_value(&kept).unwrap());
            assert_eq!(json["id"], id, "{json}");
            assert_eq!(
                json["measurement"]["unrounded_mm"][0],
                400.0 + id as f64,
                "{json}"
            );
            assert!(
                json.get("photo_jpeg").is_none() && json["has_photo"] == true,
                "{json}"
            );
        }
        assert_eq!(retained(broker.port, "lane/dock-1/status"), "online");
        let deadline = Instant::now() + LIMIT;
        while log.cursor(CONSUMER).expect("the cursor") != 5 {
            assert!(Instant::now() < deadline, "the cursor stays below 5");
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        // The head after the newest record, retained (issue 48, item 4).
        let head = retained(broker.port, "lane/dock-1/head");
        let head = coapcam::api::record::Head::parse(&head).expect("a head");
        let newest = log.get(5).expect("reading").expect("recorded");
        assert_eq!((head.id, head.hash), (5, newest.hash));
        publisher.stop().await;
        let offline = sub.next_on("lane/dock-1/status").await;
        assert_eq!(offline.text(), "offline");
    });
    assert_eq!(retained(broker.port, "lane/dock-1/status"), "offline");
}

#[test]
fn the_uris_user_and_password_log_in_to_a_broker_that_refuses_anonymous_clients() {
    if !available("mqtt credentials", &[Peer::Mosquitto]) {
        return;
    }
    let dir = TempDir::new("mqtt-credentials");
    let broker = Broker::start_with_password(&dir);
    let log = open_log(&dir);
    record(&log, 401.0, None);
    record(&log, 402.0, None);
    let uri = format!("mqtt://dock:s%40cret%3A1@127.0.0.1:{}/lane", broker.port);
    let target: coapcam::station::mqtt::Target = uri.parse().expect("mqtt URI");
    assert!(!target.to_string().contains("cret"), "{target}");
    runtime().block_on(async {
        let publisher = Publisher::start(
            Config {
                target,
                station: "dock-1".into(),
            },
            log.clone(),
        )
        .expect("start");
        // The cursor moves only past records the broker acknowledged.
        let deadline = Instant::now() + LIMIT;
        while log.cursor(CONSUMER).expect("the cursor") != 2 {
            assert!(
                Instant::now() < deadline,
                "the broker took no record: the login failed"
            );
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        publisher.stop().await;
    });
}

#[test]
fn bursts_recorded_while_the_broker_is_down_arrive_in_order_after_it_is_back() {
    if !available("mqtt bursts", &[Peer::Mosquitto]) {
        return;
    }
    let dir = TempDir::new("mqtt-bursts");
    let mut broker = Broker::start(&dir, true);
    let log = open_log(&dir);
    runtime().block_on(async {
        let mut sub =
            Subscriber::start(broker.port, "test-durable", "lane/+/measurements", true).await;
        let publisher = Publisher::start(config(&broker, "dock-2"), log.clone()).expect("start");
        let mut next = 1;
        let mut repeats = 0;
        for cycle in 0..3 {
            broker.stop();
            // More than the publisher keeps in flight at once.
            let mut last = 0;
            for n in 0..40 {
                last = record_async(&log, 400.0 + f64::from(cycle * 40 + n)).await;
            }
            broker.restart();
            while next <= last {
                let json = sub.next().await.json();
                let id = json["id"].as_u64().expect("an id");
                assert!(id <= next, "cycle {cycle}: record {id} before {next}");
                if id == next {
                    next += 1;
                } else {
                    repeats += 1;
                }
            }
        }
        eprintln!("3 bursts of 40 while the broker was down: all in order, {repeats} repeats");
        publisher.stop().await;
    });
}

/// `POST /cams/dimensions`: a measurement, which the server records.
async fn measure(client: &coap_net::Client, addr: SocketAddr) {
    let r = send(client, addr, Code::POST, "/cams/dimensions", b"", None).await;
    assert_eq!(
        r.code,
        Code::CONTENT,
        "{}",
        String::from_utf8_lossy(&r.payload)
    );
}

/// Milliseconds at `q` (0 to 1) of sorted `v`.
fn quantile(v: &[i64], q: f64) -> i64 {
    v[((v.len() - 1) as f64 * q).round() as usize]
}

#[test]
fn serve_publishes_every_measurement_and_its_line_and_the_broker_tells_when_it_dies() {
    if !available("serve --mqtt", &[Peer::Mosquitto]) {
        return;
    }
    // COAPCAM_MQTT_RUNS=50 measures the delay from the record to the subscriber over more.
    let runs: u64 = std::env::var("COAPCAM_MQTT_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    let dir = TempDir::new("serve-mqtt");
    let broker = Broker::start(&dir, false);
    let uri = broker.uri("lane");
    let Station {
        process: mut server,
        coap: addr,
        line,
        ..
    } = station(
        dir.path(),
        &[
            "--mqtt",
            &uri,
            "--station-name",
            "dock-e2e",
            "--line-output",
            "tcp://127.0.0.1:0",
        ],
    );
    let line = line.expect("the line output's address");
    runtime().block_on(async {
        let mut sub = Subscriber::start(broker.port, "test-e2e", "lane/#", false).await;
        assert_eq!(sub.next_on("lane/dock-e2e/status").await.text(), "online");
        // Two readers; a measurement takes far longer than the server takes to accept
        // them.
        let mut readers: Vec<BufReader<TcpStream>> = (0..2)
            .map(|_| {
                let s = TcpStream::connect(line).expect("connecting to the line output");
                s.set_read_timeout(Some(LIMIT)).unwrap();
                BufReader::new(s)
            })
            .collect();
        let client = client();
        let mut delays = Vec::new();
        for id in 1..=runs {
            measure(&client, addr).await;
            let m = sub.next_on("lane/dock-e2e/measurements").await;
            let json = m.json();
            assert_eq!(json["id"], id, "{json}");
            assert_eq!(json["station"], "dock-e2e", "{json}");
            assert_eq!(json["trigger"], "request", "{json}");
            assert_eq!(json["measurement"]["parcel"], "measured", "{json}");
            let time = UtcTime::parse(json["time"].as_str().expect("a time")).expect("RFC 3339");
            delays.push(m.arrived_unix_ms - time.unix_ms);
            let billed = crate::support::billed_numbers(&json["measurement"]);
            for reader in &mut readers {
                let mut text = String::new();
                reader.read_line(&mut text).expect("a line");
                let fields: Vec<&str> = text.trim_end_matches("\r\n").split(',').collect();
                assert!(text.ends_with("\r\n"), "{text:?}");
                assert_eq!(fields.len(), 7, "{text:?}");
                assert_eq!(fields[0], id.to_string(), "{text:?}");
                assert_eq!(fields[1], json["time"], "{text:?}");
                assert_eq!(fields[2..5], billed, "{text:?}");
            }
        }
        delays.sort_unstable();
        eprintln!(
            "record to MQTT subscriber over {runs}: median {} ms, p95 {} ms, max {} ms",
            quantile(&delays, 0.5),
            quantile(&delays, 0.95),
            delays[delays.len() - 1]
        );
        assert_eq!(retained(broker.port, "lane/dock-e2e/status"), "online");
        // Killed: no DISCONNECT, so the broker publishes the last will.
        server.kill();
        assert_eq!(sub.next_on("lane/dock-e2e/status").await.text(), "offline");
    });
    assert_eq!(retained(broker.port, "lane/dock-e2e/status"), "offline");
}

#[test]
fn a_measurement_made_while_the_broker_is_down_arrives_after_it_is_back_20_times() {
    if !available("serve --mqtt broker restarts", &[Peer::Mosquitto]) {
        return;
    }
    let dir = TempDir::new("serve-mqtt-restarts");
    let mut broker = Broker::start(&dir, true);
    let uri = broker.uri("lane");
    let Station {
        process: mut server,
        coap: addr,
        ..
    } = station(dir.path(), &["--mqtt", &uri, "--station-name", "dock-r"]);
    runtime().block_on(async {
        // Connected before the broker first stops: the station's first connection is not
        // made by the time it answers CoAP, and a broker stopped first leaves it to the
        // first restart (one "connected" line fewer, as a loaded run saw).
        let mut status =
            Subscriber::start(broker.port, "test-e2e-status", "lane/dock-r/status", false).await;
        assert_eq!(status.next().await.text(), "online");
        drop(status);
        let mut sub =
            Subscriber::start(broker.port, "test-e2e-durable", "lane/+/measurements", true).await;
        let client = client();
        let mut repeats = 0;
        for id in 1..=20u64 {
            broker.stop();
            measure(&client, addr).await;
            broker.restart();
            // At least once: a repeat of an earlier record may come first.
            loop {
                let json = sub.next().await.json();
                let got = json["id"].as_u64().expect("an id");
                assert!(got <= id, "{json} before record {id}");
                if got == id {
                    assert_eq!(json["station"], "dock-r", "{json}");
                    break;
                }
                repeats += 1;
            }
        }
        eprintln!(
            "20 broker restarts through serve: every measurement in order, {repeats} repeats"
        );
    });
    // A clean stop (SIGINT) publishes offline itself, as the last will would.
    let f = server.interrupt();
    assert!(f.status.success(), "serve: {}", f.stderr);
    assert_eq!(retained(broker.port, "lane/dock-r/status"), "offline");
    // At the default level each connection is said, the first and every one after the
    // broker came back, and the last disconnection (issue 51, item 13: a reconnection
    // was not).
    let said = |what: &str| {
        f.stderr
            .lines()
            .filter(|l| l.starts_with(&format!("coapcam: MQTT: {what}")))
            .count()
    };
    assert!(
        said("connected, publishing from record") >= 21,
        "{}",
        f.stderr
    );
    assert_eq!(said("offline published, disconnected"), 1, "{}", f.stderr);
}

#[test]
fn the_delivery_cursor_survives_a_restart_of_the_station() {
    if !available("mqtt cursor across restarts", &[Peer::Mosquitto]) {
        return;
    }
    let dir = TempDir::new("mqtt-cursor");
    let mut broker = Broker::start(&dir, true);
    runtime().block_on(async {
        let mut sub =
            Subscriber::start(broker.port, "test-cursor", "lane/+/measurements", true).await;
        // Recorded while the broker is away, and the station stops before it is back.
        broker.stop();
        let log = open_log(&dir);
        let publisher = Publisher::start(config(&broker, "dock-3"), log.clone()).expect("start");
        for n in 0..3 {
            record_async(&log, 400.0 + f64::from(n)).await;
        }
        publisher.stop().await;
        drop(log);
        broker.restart();
        // A new station on the same file: the three follow.
        let log = open_log(&dir);
        let publisher = Publisher::start(config(&broker, "dock-3"), log.clone()).expect("start");
        for id in 1..=3u64 {
            assert_eq!(sub.next().await.json()["id"], id);
        }
        let deadline = Instant::now() + LIMIT;
        while log.cursor(CONSUMER).expect("the cursor") != 3 {
            assert!(Instant::now() < deadline, "the cursor stays below 3");
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        publisher.stop().await;
        // And once more: what was acknowledged is not sent again.
        let publisher = Publisher::start(config(&broker, "dock-3"), log.clone()).expect("start");
        let id = record_async(&log, 410.0).await;
        assert_eq!(sub.next().await.json()["id"], id);
        publisher.stop().await;
    });
}

/// Issue 46: another MQTT client with the station's client id made its status flap every
/// second (the broker closes the older connection of an id) without a word. Now the
/// station says once what happens and what to do.
#[test]
fn another_client_with_the_stations_client_id_is_reported_once() {
    if !available("mqtt client-id collision", &[Peer::Mosquitto]) {
        return;
    }
    let dir = TempDir::new("mqtt-twin");
    let broker = Broker::start(&dir, false);
    let uri = broker.uri("lane");
    let mut server = station(dir.path(), &["--mqtt", &uri, "--station-name", "dock-twin"]).process;
    let said = "another client connects with the station's client id coapcam-dock-twin";
    runtime().block_on(async {
        // The twin: reconnects whenever the broker closes it, as the station does.
        let mut options = MqttOptions::new("coapcam-dock-twin", "127.0.0.1", broker.port);
        options.set_keep_alive(Duration::from_secs(5));
        let (_client, mut eventloop) = AsyncClient::new(options, 16);
        let twin = tokio::spawn(async move {
            loop {
                if eventloop.poll().await.is_err() {
                    tokio::time::sleep(Duration::from_millis(200)).await;
                }
            }
        });
        tokio::task::block_in_place(|| {
            server.stderr_line(Duration::from_secs(60), |l| l.contains(said).then_some(()));
            // The flapping goes on a while, said no more.
            std::thread::sleep(Duration::from_secs(5));
        });
        twin.abort();
    });
    let stderr = server.kill().stderr;
    let lines = |what: &str| stderr.lines().filter(|l| l.contains(what)).count();
    assert_eq!(lines(said), 1, "{stderr}");
    assert_eq!(lines("Give the other client another id"), 1, "{stderr}");
    assert!(lines("MQTT: no connection") <= 1, "{stderr}");
}

/// A broker of the test's own that accepts every connection (CONNACK) and answers
/// PINGREQ, but never acknowledges a message: counts the connections until dropped.
struct SilentBroker {
    addr: SocketAddr,
    connections: std::sync::Arc<std::sync::atomic::AtomicUsize>,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl SilentBroker {
    fn start() -> Self {
        use std::io::{Read as _, Write as _};
        use std::sync::atomic::Ordering;
        let listener = TcpListener::bind("127.0.0.1:0").expect("binding");
        listener.set_nonblocking(true).expect("non-blocking");
        let addr = listener.local_addr().expect("address");
        let connections = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let (count, stopped) = (connections.clone(), stop.clone());
        std::thread::spawn(move || {
            while !stopped.load(Ordering::Relaxed) {
                let Ok((mut s, _)) = listener.accept() else {
                    std::thread::sleep(Duration::from_millis(20));
                    continue;
                };
                count.fetch_add(1, Ordering::Relaxed);
                let stopped = stopped.clone();
                std::thread::spawn(move || {
                    let _ = s.set_nonblocking(false);
                    let _ = s.set_read_timeout(Some(Duration::from_millis(200)));
                    let mut buf = Vec::new();
                    let mut chunk = [0u8; 4096];
                    while !stopped.load(Ordering::Relaxed) {
                        match s.read(&mut chunk) {
                            Ok(0) => return,
                            Ok(n) => buf.extend_from_slice(&chunk[..n]),
                            Err(e)
                                if e.kind() == std::io::ErrorKind::WouldBlock
                                    || e.kind() == std::io::ErrorKind::TimedOut =>
                            {
                                continue;
                            }
                            Err(_) => return,
                        }
                        // Whole packets: a type byte, a variable-length remaining length.
                        loop {
                            let (mut len, mut shift, mut at) = (0usize, 0, 1);
                            while let Some(&b) = buf.get(at) {
                                len |= usize::from(b & 0x7f) << shift;
                                shift += 7;
                                at += 1;
                                if b & 0x80 == 0 {
                                    break;
                                }
                            }
                            if at == 1
                                || buf.get(at - 1).is_some_and(|b| b & 0x80 != 0)
                                || buf.len() < at + len
                            {
                                break;
                            }
                            let answer: &[u8] = match buf[0] >> 4 {
                                1 => &[0x20, 0x02, 0x00, 0x00],
                                12 => &[0xd0, 0x00],
                                _ => &[],
                            };
                            if s.write_all(answer).is_err() {
                                return;
                            }
                            buf.drain(..at + len);
                        }
                    }
                });
            }
        });
        Self {
            addr,
            connections,
            stop,
        }
    }

    fn connections(&self) -> usize {
        self.connections.load(std::sync::atomic::Ordering::Relaxed)
    }
}

impl Drop for SilentBroker {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
    }
}

/// Issue 46: a broker that accepts the connection and never acknowledges stalled delivery
/// without a word. Now the station says so after 20 s and connects again.
#[test]
fn a_broker_that_never_acknowledges_is_reported_and_connected_again() {
    let dir = TempDir::new("mqtt-silent");
    let broker = SilentBroker::start();
    let uri = format!("mqtt://{}/lane", broker.addr);
    let mut server = station(
        dir.path(),
        &["--mqtt", &uri, "--station-name", "dock-silent"],
    )
    .process;
    let said = server.stderr_line(Duration::from_secs(60), |l| {
        l.contains("acknowledged nothing (no PUBACK)")
            .then(|| l.to_owned())
    });
    assert!(said.contains("the status message"), "{said}");
    let deadline = Instant::now() + LIMIT;
    while broker.connections() < 2 {
        assert!(
            Instant::now() < deadline,
            "the station did not connect again"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}
