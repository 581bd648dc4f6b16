//! MQTT to the warehouse (`serve --mqtt mqtt://HOST[:PORT][/PREFIX]`): every record of the
//! results log, as JSON with its id, published with QoS 1 to `PREFIX/<station>/measurements`
//! in the log's order, and the station's state on `PREFIX/<station>/status` (`online` when
//! connected, `offline` as the last will and on a clean stop; both retained), and after each
//! record the log's head (`{"id":ID,"hash":HASH}`, that record's) on `PREFIX/<station>/head`,
//! retained, QoS 1: a copy of the chain's newest hash outside the station.
//!
//! Nothing is lost while the broker is away: the publisher reads the log from a durable
//! per-consumer cursor ([`CONSUMER`]) that moves only past records the broker
//! acknowledged (PUBACK), so a record waits in the log until then and is delivered at least
//! once, with its id for the consumer to drop repeats.
//!
//! [`Delivery`] is the bookkeeping without IO (which record is in flight, which PUBACK
//! acknowledges which, how far the cursor may move); [`Publisher`] drives it with a
//! rumqttc connection. Each connection is a fresh clean session: what was unacknowledged
//! when a connection was lost is sent again, from the cursor, on the next one, and the
//! client library keeps nothing of its own across connections.
//!
//! Troubles are said once, not at each reconnection: a broker that closes the connection
//! soon after accepting it, again and again (3 times within 5 s each: another client has
//! the station's id), and a broker that acknowledges nothing for 20 s (the publisher then
//! connects again).

use std::collections::VecDeque;
use std::fmt;
use std::future::Future;
use std::pin::Pin;
use std::str::FromStr;
use std::time::Duration;

use rumqttc::{
    AsyncClient, ConnectionError, Event, EventLoop, LastWill, MqttOptions, Outgoing, Packet, QoS,
};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;
use tokio::time::{Instant, sleep_until};

use super::follow::{self, Feed, Next, Output, OutputId, Sink, Start};
use super::log::ResultsLog;
use crate::api::record::{Head, Record};

/// The cursor name in the results log of the MQTT publisher its flag gives (of one with an
/// `id` of its own: `mqtt/ID`).
pub const CONSUMER: &str = "mqtt";
/// The broker port when the URI names none (MQTT over TCP, IANA).
pub const DEFAULT_PORT: u16 = 1883;
/// The topic prefix when the URI names none.
pub const DEFAULT_PREFIX: &str = "coapcam";
/// The retained payload of the status topic while the station is connected.
pub const ONLINE: &str = "online";
/// The retained payload of the status topic after the station left (the last will, or
/// published on a clean stop).
pub const OFFLINE: &str = "offline";

/// Records in flight (published, not yet acknowledged) at once.
const WINDOW: usize = 16;
/// The first wait before reconnecting; doubled per failed attempt up to [`BACKOFF_MAX`],
/// and back to this after a connection was made.
const BACKOFF_FIRST: Duration = Duration::from_millis(250);
/// The longest wait between connection attempts.
const BACKOFF_MAX: Duration = Duration::from_secs(5);
/// The MQTT keep-alive: a broker that answers nothing for about this long is taken as
/// gone (and a station that sends nothing for 1.5 times it is taken as gone by the broker,
/// which then publishes the last will).
const KEEP_ALIVE: Duration = Duration::from_secs(15);
/// The largest message published; a record is far smaller (no pictures).
const MAX_PACKET: usize = 1 << 20;
/// How long a clean stop waits for the broker to acknowledge `offline`.
const STOP_WAIT: Duration = Duration::from_secs(2);
/// The longest the broker may leave the messages in flight unacknowledged (no PUBACK
/// for the oldest); then the publisher says so and connects again, sending them again
/// from the cursor.
const ACK_TIMEOUT: Duration = Duration::from_secs(20);
/// A connection the broker closes within this long of accepting it counts as kicked: a
/// broker closes a client's connection when another client connects with the same id.
const KICKED_WITHIN: Duration = Duration::from_secs(5);
/// Connections kicked in a row (each accepted at the first attempt, so the broker did not
/// restart meanwhile) before the publisher reports another client with its id.
const KICKS: u32 = 3;

/// Where to publish: the broker and the topic prefix of
/// `mqtt://[USER[:PASSWORD]@]HOST[:PORT][/PREFIX]`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Target {
    /// The broker's host name or address (an IPv6 address in brackets).
    pub host: String,
    /// The broker's port.
    pub port: u16,
    /// The first topic levels, without a trailing `/`.
    pub prefix: String,
    /// The user name and password the URI gives, sent in CONNECT.
    pub credentials: Option<Credentials>,
}

/// A user name and password for the broker; the password is never shown (not by `Debug`
/// either), so that it stays out of logs.
#[derive(Clone, PartialEq, Eq)]
pub struct Credentials {
    /// The user name.
    pub user: String,
    /// The password (may be empty).
    pub password: String,
}

impl fmt::Debug for Credentials {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:<password>", self.user)
    }
}

/// Why an `mqtt://` URI or a station name cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum TargetError {
    /// Not `mqtt://...`.
    #[error("{0:?} is not an mqtt:// URI (mqtt://HOST[:PORT][/PREFIX])")]
    Scheme(String),
    /// No host before the port or prefix.
    #[error("{0:?} names no broker host")]
    NoHost(String),
    /// The port is not a number from 1 to 65535.
    #[error("{0:?}: the port is not a number from 1 to 65535")]
    Port(String),
    /// The user or password is not percent-encoded UTF-8.
    #[error("the user or password of the MQTT URI is not percent-encoded UTF-8")]
    Credentials,
    /// The prefix or the station name cannot be part of a topic name.
    #[error(
        "{0:?} cannot be part of an MQTT topic name (no +, #, NUL, empty levels, or a / in the station name)"
    )]
    Topic(String),
}

/// The publisher could not start: the station's name cannot be a level of its topics.
#[derive(Debug, thiserror::Error)]
#[error("the station's name as an MQTT topic level (--station-name)")]
pub struct StationNameError(#[source] pub TargetError);

impl FromStr for Target {
    type Err = TargetError;

    fn from_str(uri: &str) -> Result<Self, Self::Err> {
        let rest = uri
            .strip_prefix("mqtt://")
            .ok_or_else(|| TargetError::Scheme(uri.into()))?;
        let (authority, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        let (credentials, authority) = match authority.rsplit_once('@') {
            Some((userinfo, hostport)) => {
                let (user, password) = userinfo.split_once(':').unwrap_or((userinfo, ""));
                let decode = |part: &str| {
                    coap_net::uri::percent_decode(part).ok_or(TargetError::Credentials)
                };
                let credentials = Credentials {
                    user: decode(user)?,
                    password: decode(password)?,
                };
                (Some(credentials), hostport)
            }
            None => (None, authority),
        };
        let (host, port) = if let Some(v6) = authority.strip_prefix('[') {
            let (addr, after) = v6
                .split_once(']')
                .ok_or_else(|| TargetError::NoHost(uri.into()))?;
            (format!("[{addr}]"), after.strip_prefix(':'))
        } else {
            match authority.rsplit_once(':') {
                Some((h, p)) => (h.to_owned(), Some(p)),
                None => (authority.to_owned(), None),
            }
        };
        if host.is_empty() || host == "[]" {
            return Err(TargetError::NoHost(uri.into()));
        }
        let port = match port {
            None => DEFAULT_PORT,
            Some(p) => match p.parse::<u16>() {
                Ok(p) if p > 0 => p,
                _ => return Err(TargetError::Port(uri.into())),
            },
        };
        let prefix = prefix.trim_end_matches('/');
        let prefix = if prefix.is_empty() {
            DEFAULT_PREFIX.to_owned()
        } else {
            check_topic(prefix, true)?;
            prefix.to_owned()
        };
        Ok(Self {
            host,
            port,
            prefix,
            credentials,
        })
    }
}

impl fmt::Display for Target {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let user = match &self.credentials {
            Some(c) => format!("{}@", c.user),
            None => String::new(),
        };
        write!(
            f,
            "mqtt://{user}{}:{}/{}",
            self.host, self.port, self.prefix
        )
    }
}

/// Refuses what cannot be topic levels (MQTT 3.1.1 §4.7): wildcards, NUL, empty levels,
/// and a `/` unless `levels`.
fn check_topic(text: &str, levels: bool) -> Result<(), TargetError> {
    let bad = text.is_empty()
        || text.contains(['+', '#', '\0'])
        || (!levels && text.contains('/'))
        || text.split('/').any(str::is_empty);
    if bad {
        return Err(TargetError::Topic(text.into()));
    }
    Ok(())
}

/// The topics of one station under a [`Target`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Topics {
    /// `PREFIX/<station>/measurements`: each record, JSON, QoS 1.
    pub measurements: String,
    /// `PREFIX/<station>/status`: `online` or `offline`, retained, QoS 1.
    pub status: String,
    /// `PREFIX/<station>/head`: the id and hash of the newest record published,
    /// retained, QoS 1.
    pub head: String,
}

impl Topics {
    /// The topics of `station` (a single topic level) under `target`.
    pub fn new(target: &Target, station: &str) -> Result<Self, TargetError> {
        check_topic(station, false)?;
        let base = format!("{}/{station}", target.prefix);
        Ok(Self {
            measurements: format!("{base}/measurements"),
            status: format!("{base}/status"),
            head: format!("{base}/head"),
        })
    }
}

/// What a message in flight carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Carried {
    /// The station's status.
    Status,
    /// The record with this id.
    Record(u64),
    /// The head after the record with this id.
    Head(u64),
}

#[derive(Debug)]
struct Flight {
    carried: Carried,
    /// The packet id the client gave it, once it was written.
    pkid: Option<u16>,
    acked: bool,
}

/// The delivery bookkeeping of one publisher, without IO: which messages are in flight on
/// the current connection, in the order they were handed to the client, and how far the
/// durable cursor may move. MQTT 3.1.1 §4.6 has a broker acknowledge QoS 1 messages in the
/// order it received them; the bookkeeping pairs acknowledgements by packet id all the
/// same, and moves the cursor only over an unbroken run of acknowledged records.
#[derive(Debug)]
pub struct Delivery {
    window: usize,
    cursor: u64,
    sent_up_to: u64,
    connected: bool,
    flights: VecDeque<Flight>,
}

impl Delivery {
    /// Bookkeeping that starts after `cursor` (every id up to it delivered), with at most
    /// `window` records in flight.
    pub fn new(cursor: u64, window: usize) -> Self {
        Self {
            window: window.max(1),
            cursor,
            sent_up_to: cursor,
            connected: false,
            flights: VecDeque::new(),
        }
    }

    /// Every id up to this one was acknowledged.
    pub fn cursor(&self) -> u64 {
        self.cursor
    }

    /// The newest id handed to the client on this connection (the cursor when none).
    pub fn sent_up_to(&self) -> u64 {
        self.sent_up_to
    }

    /// A connection was made (a new clean session): nothing is in flight.
    pub fn connected(&mut self) {
        self.connected = true;
        self.flights.clear();
        self.sent_up_to = self.cursor;
    }

    /// The connection was lost: what was not acknowledged will be sent again from the
    /// cursor on the next one.
    pub fn disconnected(&mut self) {
        self.connected = false;
        self.flights.clear();
        self.sent_up_to = self.cursor;
    }

    /// How many more records may be handed to the client now.
    pub fn room(&self) -> usize {
        if !self.connected {
            return 0;
        }
        let records = self
            .flights
            .iter()
            .filter(|f| matches!(f.carried, Carried::Record(_)))
            .count();
        self.window.saturating_sub(records)
    }

    /// A message is handed to the client (records in id order).
    pub fn sending(&mut self, carried: Carried) {
        if let Carried::Record(id) = carried {
            self.sent_up_to = self.sent_up_to.max(id);
        }
        self.flights.push_back(Flight {
            carried,
            pkid: None,
            acked: false,
        });
    }

    /// The client wrote a QoS 1 publish with this packet id: the oldest message without
    /// one (the client writes in the order it was handed them).
    pub fn written(&mut self, pkid: u16) {
        if let Some(f) = self.flights.iter_mut().find(|f| f.pkid.is_none()) {
            f.pkid = Some(pkid);
        }
    }

    /// Whether a message in flight waits for its acknowledgement.
    pub fn waiting(&self) -> bool {
        self.flights.iter().any(|f| !f.acked)
    }

    /// Whether a status message waits for its acknowledgement.
    pub fn status_in_flight(&self) -> bool {
        self.flights
            .iter()
            .any(|f| f.carried == Carried::Status && !f.acked)
    }

    /// The broker acknowledged packet `pkid`. Returns what it acknowledged, and the new
    /// cursor when it moved.
    pub fn acked(&mut self, pkid: u16) -> (Option<Carried>, Option<u64>) {
        let Some(f) = self
            .flights
            .iter_mut()
            .find(|f| f.pkid == Some(pkid) && !f.acked)
        else {
            return (None, None);
        };
        f.acked = true;
        let carried = f.carried;
        let before = self.cursor;
        while self.flights.front().is_some_and(|f| f.acked) {
            if let Some(Flight {
                carried: Carried::Record(id),
                ..
            }) = self.flights.pop_front()
            {
                self.cursor = self.cursor.max(id);
            }
        }
        (
            Some(carried),
            (self.cursor != before).then_some(self.cursor),
        )
    }
}

/// The flag of the MQTT output (`serve --mqtt`).
#[derive(Debug, Clone, Default, clap::Args)]
#[group(skip)]
pub struct Args {
    /// Publish every record of the results log to an MQTT broker, as JSON with QoS 1, on
    /// `PREFIX/<station-name>/measurements` (PREFIX default coapcam, port default 1883),
    /// and `online` / `offline` (retained; offline also as the last will) on
    /// `PREFIX/<station-name>/status`. While the broker is away the records wait in the
    /// log and follow in order once it is back: each is delivered at least once, with its
    /// id. USER:PASSWORD@ logs in to the broker (percent-encoded; never printed).
    #[arg(long, value_name = "mqtt://[USER:PASSWORD@]HOST[:PORT][/PREFIX]")]
    mqtt: Option<Target>,
}

impl Args {
    /// Whether `--mqtt` is given.
    pub(super) fn configured(&self) -> bool {
        self.mqtt.is_some()
    }

    /// With `--mqtt`: refuses a station name that cannot be one topic level.
    pub(super) fn check_station(&self, station: &str) -> Result<(), TargetError> {
        match &self.mqtt {
            Some(target) => Topics::new(target, station).map(drop),
            None => Ok(()),
        }
    }

    /// The publisher `--mqtt` asks for, as output `id`.
    pub(super) async fn start(
        &self,
        feed: &Feed<'_>,
        id: &OutputId,
    ) -> Result<Option<Box<dyn Output>>, StationNameError> {
        let Some(target) = &self.mqtt else {
            return Ok(None);
        };
        let config = Config {
            target: target.clone(),
            station: feed.station.to_owned(),
        };
        let publisher =
            Publisher::start_as(config, feed.log.clone(), id).map_err(StationNameError)?;
        Ok(Some(Box::new(publisher)))
    }
}

/// How the publisher connects.
#[derive(Debug, Clone)]
pub struct Config {
    /// The broker and the prefix.
    pub target: Target,
    /// The station's name: its topic level and its MQTT client id (`coapcam-<station>`).
    pub station: String,
}

/// A running MQTT publisher; [`Publisher::stop`] ends it cleanly (status `offline`,
/// then DISCONNECT).
pub struct Publisher {
    stop: watch::Sender<bool>,
    task: JoinHandle<()>,
    /// The broker, as said when the station starts.
    target: Target,
}

impl Publisher {
    /// Starts publishing the records of `log` with `config` (connecting in the
    /// background, and again whenever the connection is lost). Fails only on a station
    /// name that cannot be a topic level.
    pub fn start(config: Config, log: ResultsLog) -> Result<Self, TargetError> {
        Self::start_as(config, log, &OutputId::default())
    }

    /// As [`Publisher::start`], as output `id`: with an id of its own, its cursor is
    /// `mqtt/ID` and its client id `coapcam-<station>-ID`, so that two publishers of a
    /// station neither share a position nor take turns on one broker.
    pub fn start_as(config: Config, log: ResultsLog, id: &OutputId) -> Result<Self, TargetError> {
        let topics = Topics::new(&config.target, &config.station)?;
        let client_id = match id.id() {
            Some(id) => format!("coapcam-{}-{id}", config.station),
            None => format!("coapcam-{}", config.station),
        };
        let mut options =
            MqttOptions::new(client_id, config.target.host.clone(), config.target.port);
        if let Some(c) = &config.target.credentials {
            options.set_credentials(c.user.clone(), c.password.clone());
        }
        options
            .set_keep_alive(KEEP_ALIVE)
            .set_clean_session(true)
            .set_max_packet_size(MAX_PACKET, MAX_PACKET)
            // The client's own window is one more than ours: the status message.
            .set_inflight(u16::try_from(WINDOW + 1).unwrap_or(u16::MAX))
            .set_last_will(LastWill::new(
                topics.status.clone(),
                OFFLINE,
                QoS::AtLeastOnce,
                true,
            ));
        let (stop, stopped) = watch::channel(false);
        let target = config.target.clone();
        let cursor = id.cursor(CONSUMER);
        let task = tokio::spawn(run(options, topics, config.target, log, cursor, stopped));
        Ok(Self { stop, task, target })
    }

    /// Stops: publishes `offline` (retained) and disconnects when connected, within
    /// about two seconds.
    pub async fn stop(self) {
        let _ = self.stop.send(true);
        if let Err(e) = self.task.await {
            tracing::warn!(error = %e, "the MQTT publisher ended abnormally");
        }
    }
}

impl Output for Publisher {
    fn describe(&self) -> String {
        format!("publishing to {}", self.target)
    }

    fn stop(self: Box<Self>) -> Pin<Box<dyn Future<Output = ()> + Send>> {
        Box::pin(Self::stop(*self))
    }
}

/// How one connection ended.
enum End {
    /// Lost, or never made: reconnect after the back-off.
    Lost(String),
    /// The broker acknowledged nothing for [`ACK_TIMEOUT`] (this says what waited):
    /// reconnect after the back-off.
    Unacknowledged(String),
}

/// What the publisher has said of its broker, so that each trouble is said once and not
/// at every reconnection.
#[derive(Debug, Default)]
struct Said {
    /// That the connection is lost; until a connection lasts [`KICKED_WITHIN`].
    lost: bool,
    /// Connections kicked in a row ([`KICKED_WITHIN`]).
    kicks: u32,
    /// That another client has the station's client id; until a connection lasts.
    collision: bool,
    /// That the broker acknowledges nothing; until it acknowledges a message.
    silent: bool,
}

/// Reads the delivery cursor, then publishes from it as a [`Sink`] of the log.
async fn run(
    options: MqttOptions,
    topics: Topics,
    target: Target,
    log: ResultsLog,
    consumer: String,
    mut stop: watch::Receiver<bool>,
) {
    let cursor = loop {
        let (l, c) = (log.clone(), consumer.clone());
        match tokio::task::spawn_blocking(move || l.cursor(&c).map_err(|e| e.to_string())).await {
            Ok(Ok(c)) => break c,
            Ok(Err(e)) => tracing::error!(error = %e, "MQTT: reading the delivery cursor failed"),
            Err(e) => tracing::error!(error = %e, "MQTT: reading the delivery cursor failed"),
        }
        if wait_or_stop(BACKOFF_MAX, &mut stop).await {
            return;
        }
    };
    let publishing = Publishing {
        options,
        topics,
        target,
        log: log.clone(),
        consumer,
        stop,
        delivery: Delivery::new(cursor, WINDOW),
        backoff: BACKOFF_FIRST,
        said: Said::default(),
        connection: None,
        reconnect_at: Instant::now(),
    };
    follow::run(log, publishing).await;
}

/// Polls the client's event loop, handing each event over, until the first error (the
/// connection is then gone: a new client and event loop make the next one).
async fn pump(mut eventloop: EventLoop, events: mpsc::Sender<Result<Event, ConnectionError>>) {
    loop {
        let event = eventloop.poll().await;
        let end = event.is_err();
        if events.send(event).await.is_err() || end {
            return;
        }
    }
}

/// Waits `pause`; true when stopping instead.
async fn wait_or_stop(pause: Duration, stop: &mut watch::Receiver<bool>) -> bool {
    if *stop.borrow() {
        return true;
    }
    tokio::select! {
        () = tokio::time::sleep(pause) => false,
        _ = stop.changed() => true,
    }
}

/// One connection: its client, the events of its event loop (polled by a task of its
/// own, ended with it), and when things happened on it.
struct Connection {
    client: AsyncClient,
    events: mpsc::Receiver<Result<Event, ConnectionError>>,
    pump: JoinHandle<()>,
    /// When the broker accepted the connection (CONNACK).
    connected_at: Option<Instant>,
    /// Since when the oldest message in flight waits for its PUBACK (since the last
    /// acknowledgement, or since it was handed over when nothing waited).
    waiting_since: Option<Instant>,
}

impl Drop for Connection {
    fn drop(&mut self) {
        self.pump.abort();
    }
}

/// The publisher as a [`Sink`] of the results log: it takes records while its window
/// has room on a connection, and its events are the connection's (CONNACK, the
/// PUBACKs that move the cursor, its loss), the time to connect again, the
/// acknowledgement that does not come, and the stop. After each event the follower
/// reads on from the newest record sent on this connection (the cursor after a new one).
struct Publishing {
    options: MqttOptions,
    topics: Topics,
    target: Target,
    log: ResultsLog,
    /// Its durable cursor's name.
    consumer: String,
    stop: watch::Receiver<bool>,
    delivery: Delivery,
    /// The wait before the next connection after this one is lost.
    backoff: Duration,
    said: Said,
    /// The connection; `None` until `reconnect_at`.
    connection: Option<Connection>,
    reconnect_at: Instant,
}

/// What the publisher waits for between records.
enum Wake {
    /// The time to connect (again).
    Connect,
    /// An event of the connection's event loop (`None`: the loop ended).
    Event(Option<Result<Event, ConnectionError>>),
    /// The oldest message in flight waited [`ACK_TIMEOUT`] for its PUBACK.
    Unacknowledged,
    /// [`Publisher::stop`].
    Stop,
}

impl Sink for Publishing {
    type Event = Wake;

    fn name(&self) -> String {
        super::output_name("MQTT", &self.consumer)
    }

    fn start(&self) -> Start {
        Start::After(self.delivery.cursor())
    }

    fn room(&self) -> usize {
        self.delivery.room()
    }

    async fn deliver(&mut self, record: &Record) -> Next {
        let id = record.id;
        let json = match serde_json::to_vec(record) {
            Ok(json) => json,
            Err(e) => return Next::Retry(format!("record {id} as JSON: {e}")),
        };
        if json.len() + self.topics.measurements.len() + 16 > MAX_PACKET {
            return Next::Retry(format!(
                "record {id} is {} bytes as JSON, more than an MQTT message of the station may hold ({MAX_PACKET})",
                json.len()
            ));
        }
        let published = match &self.connection {
            Some(c) => c
                .client
                .publish(&self.topics.measurements, QoS::AtLeastOnce, false, json)
                .await
                .map_err(|e| e.to_string()),
            None => Err("no connection".into()),
        };
        if let Err(e) = published {
            self.lose(End::Lost(e));
            return Next::After(self.delivery.sent_up_to());
        }
        self.handed(Carried::Record(id));
        // The head after it, retained: the newest hash a consumer holds.
        let head = serde_json::to_vec(&Head {
            id,
            hash: record.hash.clone(),
        })
        .unwrap_or_default();
        let published = match &self.connection {
            Some(c) => c
                .client
                .publish(&self.topics.head, QoS::AtLeastOnce, true, head)
                .await
                .map_err(|e| e.to_string()),
            None => Err("no connection".into()),
        };
        match published {
            Ok(()) => {
                self.handed(Carried::Head(id));
                Next::Go
            }
            Err(e) => {
                self.lose(End::Lost(e));
                Next::After(self.delivery.sent_up_to())
            }
        }
    }

    async fn event(&mut self) -> Wake {
        let stop = &mut self.stop;
        match &mut self.connection {
            None => tokio::select! {
                () = sleep_until(self.reconnect_at) => Wake::Connect,
                _ = stop.changed() => Wake::Stop,
            },
            Some(c) => {
                let unacknowledged = c.waiting_since.map(|at| at + ACK_TIMEOUT);
                tokio::select! {
                    event = c.events.recv() => Wake::Event(event),
                    () = sleep_until(unacknowledged.unwrap_or_else(Instant::now)), if unacknowledged.is_some() => {
                        Wake::Unacknowledged
                    }
                    _ = stop.changed() => Wake::Stop,
                }
            }
        }
    }

    async fn handle(&mut self, wake: Wake) -> Next {
        match wake {
            Wake::Connect => self.connect(),
            Wake::Event(Some(Ok(event))) => self.on_event(event).await,
            Wake::Event(Some(Err(e))) => self.lose(End::Lost(e.to_string())),
            Wake::Event(None) => self.lose(End::Lost("the client's event loop ended".into())),
            Wake::Unacknowledged => {
                let what = self.waiting_text();
                self.lose(End::Unacknowledged(what));
            }
            Wake::Stop => {
                self.stop().await;
                return Next::End;
            }
        }
        Next::After(self.delivery.sent_up_to())
    }
}

impl Publishing {
    /// A new client and its event loop, which connects.
    fn connect(&mut self) {
        let (client, eventloop) = AsyncClient::new(self.options.clone(), WINDOW + 4);
        let (events_tx, events) = mpsc::channel(64);
        self.connection = Some(Connection {
            client,
            events,
            pump: tokio::spawn(pump(eventloop, events_tx)),
            connected_at: None,
            waiting_since: None,
        });
    }

    async fn on_event(&mut self, event: Event) {
        match event {
            Event::Incoming(Packet::ConnAck(_)) => {
                if self.said.collision {
                    tracing::debug!(topic = %self.topics.status, "MQTT: connected, publishing from record {}", self.delivery.cursor() + 1);
                } else {
                    tracing::info!(topic = %self.topics.status, "MQTT: connected, publishing from record {}", self.delivery.cursor() + 1);
                }
                self.backoff = BACKOFF_FIRST;
                if let Some(c) = &mut self.connection {
                    c.connected_at = Some(Instant::now());
                }
                self.delivery.connected();
                if let Err(e) = self.publish_status(ONLINE).await {
                    self.lose(End::Lost(e));
                }
            }
            Event::Outgoing(Outgoing::Publish(pkid)) => self.delivery.written(pkid),
            Event::Incoming(Packet::PubAck(ack)) => {
                let (carried, cursor) = self.delivery.acked(ack.pkid);
                if carried.is_some() {
                    self.said.silent = false;
                    let waiting = self.delivery.waiting();
                    if let Some(c) = &mut self.connection {
                        c.waiting_since = waiting.then(Instant::now);
                    }
                }
                if let Some(cursor) = cursor {
                    self.save_cursor(cursor).await;
                }
            }
            _ => {}
        }
    }

    /// The connection ended as `end` says: says so (once per trouble), and connects
    /// again after the back-off; what was not acknowledged is sent again from the cursor.
    fn lose(&mut self, end: End) {
        let Some(connection) = self.connection.take() else {
            return;
        };
        let lasted = connection.connected_at.map(|at| at.elapsed());
        drop(connection);
        self.delivery.disconnected();
        let client_id = self.options.client_id();
        let (said, target) = (&mut self.said, &self.target);
        if lasted.is_some_and(|d| d >= KICKED_WITHIN) {
            // A connection that lasted: troubles are news again.
            *said = Said {
                silent: said.silent,
                ..Said::default()
            };
        }
        match end {
            End::Unacknowledged(what) => {
                if said.silent {
                    tracing::debug!(broker = %target, "MQTT: still no acknowledgement ({what})");
                } else {
                    tracing::warn!(broker = %target, "MQTT: the broker acknowledged nothing (no PUBACK) for {} s while {what} waited: delivery stalls there, so the station connects again and sends from record {} on; the log keeps the measurements. A broker that takes QoS 1 messages without acknowledging them is overloaded or broken (said once, until it acknowledges one)", ACK_TIMEOUT.as_secs(), self.delivery.cursor() + 1);
                    said.silent = true;
                }
            }
            End::Lost(why) => {
                // Kicked: closed soon after it was accepted. A connection not made at all
                // (the broker restarting) breaks the run.
                said.kicks = match lasted {
                    Some(d) if d < KICKED_WITHIN => said.kicks + 1,
                    _ => 0,
                };
                if said.kicks >= KICKS && !said.collision {
                    tracing::warn!(broker = %target, "MQTT: the broker closed the station's connection {} times in a row within {} s of accepting it ({why}): most likely another client connects with the station's client id {client_id}. A broker closes the older connection when a client id connects again, so the two take turns and the station's status flaps between online and offline. Give the other client another id, or this station another name (serve --station-name; the id is coapcam-<name>). Said once; the station keeps reconnecting", said.kicks, KICKED_WITHIN.as_secs());
                    said.collision = true;
                    said.lost = true;
                } else if !said.lost {
                    tracing::warn!(broker = %target, "MQTT: no connection ({why}); retrying, the log keeps the measurements");
                    said.lost = true;
                } else {
                    tracing::debug!(broker = %target, "MQTT: no connection ({why})");
                }
            }
        }
        self.reconnect_at = Instant::now() + self.backoff;
        self.backoff = (self.backoff * 2).min(BACKOFF_MAX);
    }

    async fn publish_status(&mut self, status: &str) -> Result<(), String> {
        let Some(c) = &self.connection else {
            return Err("no connection".into());
        };
        c.client
            .publish(&self.topics.status, QoS::AtLeastOnce, true, status)
            .await
            .map_err(|e| e.to_string())?;
        self.handed(Carried::Status);
        Ok(())
    }

    /// `carried` was handed to the client: it waits for its PUBACK from now, unless an
    /// older one waits already.
    fn handed(&mut self, carried: Carried) {
        self.delivery.sending(carried);
        if let Some(c) = &mut self.connection {
            c.waiting_since.get_or_insert_with(Instant::now);
        }
    }

    /// What waits for an acknowledgement, in words.
    fn waiting_text(&self) -> String {
        let records = self.delivery.sent_up_to() - self.delivery.cursor();
        let status = if self.delivery.status_in_flight() {
            "the status message"
        } else {
            ""
        };
        match (records, status.is_empty()) {
            (0, _) => status.to_owned(),
            (n, true) => format!("{n} records from {} on", self.delivery.cursor() + 1),
            (n, false) => format!(
                "{status} and {n} records from {} on",
                self.delivery.cursor() + 1
            ),
        }
    }

    async fn save_cursor(&self, cursor: u64) {
        let (l, c) = (self.log.clone(), self.consumer.clone());
        let saved = tokio::task::spawn_blocking(move || {
            l.set_cursor(&c, cursor).map_err(|e| e.to_string())
        })
        .await;
        match saved {
            Ok(Ok(())) => {}
            // The next acknowledgement saves a newer one; a restart sends these again.
            Ok(Err(e)) => tracing::warn!(error = %e, "MQTT: saving the delivery cursor failed"),
            Err(e) => tracing::warn!(error = %e, "MQTT: saving the delivery cursor failed"),
        }
    }

    /// The next event of the connection's event loop (`None` without one).
    async fn next_event(&mut self) -> Option<Result<Event, ConnectionError>> {
        match &mut self.connection {
            Some(c) => c.events.recv().await,
            None => None,
        }
    }

    /// Publishes `offline` and disconnects, when connected; waits at most [`STOP_WAIT`].
    async fn stop(&mut self) {
        if !self.delivery.connected {
            return;
        }
        let wait = async {
            self.publish_status(OFFLINE).await?;
            // The acknowledgements of records still in flight move the cursor too.
            loop {
                match self.next_event().await {
                    Some(Ok(Event::Outgoing(Outgoing::Publish(pkid)))) => {
                        self.delivery.written(pkid);
                    }
                    Some(Ok(Event::Incoming(Packet::PubAck(ack)))) => {
                        let (carried, cursor) = self.delivery.acked(ack.pkid);
                        if let Some(cursor) = cursor {
                            self.save_cursor(cursor).await;
                        }
                        if carried == Some(Carried::Status) && !self.delivery.status_in_flight() {
                            break;
                        }
                    }
                    Some(Ok(_)) => {}
                    Some(Err(e)) => return Err(e.to_string()),
                    None => return Err("the client's event loop ended".into()),
                }
            }
            let client = self.connection.as_ref().map(|c| c.client.clone());
            if let Some(client) = client {
                client.disconnect().await.map_err(|e| e.to_string())?;
            }
            // The DISCONNECT is written (and flushed) when its event comes.
            loop {
                match self.next_event().await {
                    Some(Ok(Event::Outgoing(Outgoing::Disconnect))) => return Ok(()),
                    Some(Ok(_)) => {}
                    Some(Err(e)) => return Err(e.to_string()),
                    None => return Err("the client's event loop ended".into()),
                }
            }
        };
        match tokio::time::timeout(STOP_WAIT, wait).await {
            Ok(Ok(())) => tracing::info!("MQTT: offline published, disconnected"),
            Ok(Err(e)) => {
                tracing::warn!(
                    "MQTT: stopping without a clean disconnect ({e}); the broker publishes the last will"
                )
            }
            Err(_) => tracing::warn!(
                "MQTT: the broker did not acknowledge offline within {STOP_WAIT:?}; it publishes the last will"
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn targets() {
        let t: Target = "mqtt://broker.local".parse().unwrap();
        assert_eq!(
            t,
            Target {
                host: "broker.local".into(),
                port: 1883,
                prefix: "coapcam".into(),
                credentials: None,
            }
        );
        let t: Target = "mqtt://dock:p%40ss:w@broker.local:1884/x".parse().unwrap();
        let c = t.credentials.clone().expect("credentials");
        assert_eq!((c.user.as_str(), c.password.as_str()), ("dock", "p@ss:w"));
        assert_eq!((t.host.as_str(), t.port), ("broker.local", 1884));
        assert_eq!(t.to_string(), "mqtt://dock@broker.local:1884/x");
        assert!(!format!("{t:?}").contains("p@ss"), "{t:?}");
        assert!("mqtt://u:%ff@h".parse::<Target>().is_err());
        let t: Target = "mqtt://10.0.0.2:1884/site/hall-3/".parse().unwrap();
        assert_eq!((t.port, t.prefix.as_str()), (1884, "site/hall-3"));
        let t: Target = "mqtt://[::1]:1885".parse().unwrap();
        assert_eq!((t.host.as_str(), t.port), ("[::1]", 1885));
        let t: Target = "mqtt://[fe80::1]/x".parse().unwrap();
        assert_eq!(
            (t.host.as_str(), t.port, t.prefix.as_str()),
            ("[fe80::1]", 1883, "x")
        );
        for bad in [
            "tcp://h",
            "mqtt://",
            "mqtt://:1883",
            "mqtt://h:0",
            "mqtt://h:x",
            "mqtt://h/a/+/b",
            "mqtt://h/a//b",
            "mqtt://h/#",
        ] {
            assert!(bad.parse::<Target>().is_err(), "{bad}");
        }
        let topics = Topics::new(&"mqtt://h/p".parse().unwrap(), "dock-1").unwrap();
        assert_eq!(topics.measurements, "p/dock-1/measurements");
        assert_eq!(topics.status, "p/dock-1/status");
        for bad in ["a/b", "", "a+", "#"] {
            assert!(Topics::new(&t, bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_cursor_moves_over_acknowledged_records_only() {
        let mut d = Delivery::new(4, 3);
        assert_eq!(d.room(), 0, "no room before a connection");
        d.connected();
        d.sending(Carried::Status);
        for id in [5, 6, 7] {
            d.sending(Carried::Record(id));
        }
        assert_eq!((d.room(), d.sent_up_to()), (0, 7));
        assert!(d.waiting());
        for pkid in 1..=4 {
            d.written(pkid);
        }
        // Record 6 (pkid 3) first: the cursor waits for the status and record 5.
        assert_eq!(d.acked(3), (Some(Carried::Record(6)), None));
        assert_eq!(d.acked(1), (Some(Carried::Status), None));
        assert_eq!(d.acked(2), (Some(Carried::Record(5)), Some(6)));
        assert_eq!(
            d.acked(2),
            (None, None),
            "a repeated PUBACK changes nothing"
        );
        assert_eq!(d.room(), 2);
        // Lost before 7 was acknowledged: the next connection starts after 6.
        d.disconnected();
        assert_eq!((d.cursor(), d.sent_up_to(), d.room()), (6, 6, 0));
        d.connected();
        assert_eq!(d.room(), 3);
        d.sending(Carried::Record(7));
        d.written(1);
        assert_eq!(d.acked(1), (Some(Carried::Record(7)), Some(7)));
        assert!(!d.waiting(), "all acknowledged");
    }
}
