//! MQTT to a real broker: Debian's mosquitto, started per test on a free loopback port
//! with a configuration file of the test's own, and read by a subscriber of the test's own
//! (rumqttc) and by `mosquitto_sub`. The broker missing fails in CI (`CI=true`) and skips
//! loudly elsewhere.

use std::collections::BTreeMap;
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use coapcam::station::mqtt::{Config, Outbox, Publisher};
use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};
use tokio::sync::{mpsc, watch};

use crate::support::{MOSQUITTO_SUB, Peer, Proc, TempDir, available, mosquitto_broker, runtime};

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
                    "listener {port} 127.0.0.1\nallow_anonymous true\npersistence {persistent}\n\
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

/// The records (id to JSON) and the cursor of a [`MemoryLog`].
#[derive(Default)]
struct Kept(BTreeMap<u64, Vec<u8>>, u64);

/// Records kept in memory, as the results log keeps them, for the publisher's tests.
#[derive(Clone, Default)]
struct MemoryLog {
    inner: Arc<Mutex<Kept>>,
    newest: Arc<Mutex<Option<watch::Sender<u64>>>>,
}

impl MemoryLog {
    fn append(&self, json: serde_json::Value) -> u64 {
        let mut inner = self.inner.lock().unwrap();
        let id = inner.0.keys().next_back().copied().unwrap_or(0) + 1;
        let mut json = json;
        json["id"] = id.into();
        inner.0.insert(id, serde_json::to_vec(&json).unwrap());
        drop(inner);
        if let Some(tx) = &*self.newest.lock().unwrap() {
            tx.send_replace(id);
        }
        id
    }

    fn cursor(&self) -> u64 {
        self.inner.lock().unwrap().1
    }
}

impl Outbox for MemoryLog {
    type Error = String;

    fn after(&self, id: u64, limit: usize) -> Result<Vec<(u64, Vec<u8>)>, String> {
        let inner = self.inner.lock().unwrap();
        Ok(inner
            .0
            .range(id + 1..)
            .take(limit)
            .map(|(k, v)| (*k, v.clone()))
            .collect())
    }

    fn cursor(&self, _consumer: &str) -> Result<u64, String> {
        Ok(self.inner.lock().unwrap().1)
    }

    fn set_cursor(&self, _consumer: &str, id: u64) -> Result<(), String> {
        self.inner.lock().unwrap().1 = id;
        Ok(())
    }

    fn subscribe(&self) -> watch::Receiver<u64> {
        let newest = self.inner.lock().unwrap().0.keys().next_back().copied();
        let mut tx = self.newest.lock().unwrap();
        let tx = tx.get_or_insert_with(|| watch::channel(newest.unwrap_or(0)).0);
        tx.subscribe()
    }
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
    let log = MemoryLog::default();
    // Two recorded before the publisher starts, three after.
    log.append(serde_json::json!({"n": 1}));
    log.append(serde_json::json!({"n": 2}));
    runtime().block_on(async {
        let mut sub = Subscriber::start(broker.port, "test-sub", "lane/#", false).await;
        let publisher = Publisher::start(config(&broker, "dock-1"), log.clone()).expect("start");
        let status = sub.next_on("lane/dock-1/status").await;
        assert_eq!(status.text(), "online");
        for n in 3..=5 {
            log.append(serde_json::json!({ "n": n }));
        }
        for id in 1..=5u64 {
            let m = sub.next_on("lane/dock-1/measurements").await;
            assert!(!m.retain, "measurements are not retained");
            let json = m.json();
            assert_eq!(json["id"], id, "{json}");
            assert_eq!(json["n"], id, "{json}");
        }
        assert_eq!(retained(broker.port, "lane/dock-1/status"), "online");
        let deadline = Instant::now() + LIMIT;
        while log.cursor() != 5 {
            assert!(
                Instant::now() < deadline,
                "the cursor stays at {}",
                log.cursor()
            );
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        publisher.stop().await;
        let offline = sub.next_on("lane/dock-1/status").await;
        assert_eq!(offline.text(), "offline");
    });
    assert_eq!(retained(broker.port, "lane/dock-1/status"), "offline");
}

#[test]
fn records_made_while_the_broker_is_down_arrive_after_it_is_back() {
    if !available("mqtt broker restarts", &[Peer::Mosquitto]) {
        return;
    }
    let dir = TempDir::new("mqtt-restarts");
    let mut broker = Broker::start(&dir, true);
    let log = MemoryLog::default();
    runtime().block_on(async {
        let mut sub =
            Subscriber::start(broker.port, "test-durable", "lane/+/measurements", true).await;
        let publisher = Publisher::start(config(&broker, "dock-2"), log.clone()).expect("start");
        let mut repeats = 0;
        for cycle in 0..20u64 {
            broker.stop();
            let id = log.append(serde_json::json!({ "cycle": cycle }));
            tokio::time::sleep(Duration::from_millis(100)).await;
            broker.restart();
            // At least once: a repeat of an earlier record may come first.
            loop {
                let json = sub.next().await.json();
                let got_id = json["id"].as_u64().expect("an id");
                assert!(got_id <= id, "cycle {cycle}: {json} before record {id}");
                if got_id == id {
                    break;
                }
                repeats += 1;
            }
        }
        eprintln!("20 broker restarts: every record arrived in order, {repeats} repeats");
        publisher.stop().await;
    });
}
