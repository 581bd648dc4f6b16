//! The one follower of the results log: its records in id order from a position, read on
//! the blocking pool in batches, waking on each append. Every output is a [`Sink`] that
//! [`run`] drives through a `Follower` (private: no output reads the log another way):
//! the line output, the webhook, the MQTT publisher (a window of records in flight, the
//! cursor moved by acknowledgements, its connection's events) and the HTTP event stream
//! of each client (its keep-alives). [`run`] keeps a sink's durable cursor when it has
//! one and backs off while it fails.

use std::future::Future;
use std::path::Path;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::watch;
use tokio::time::{Instant, sleep_until};

use super::log::{LogError, ResultsLog};
use crate::api::record::Record;

/// The first wait after a sink failed; it doubles up to [`BACKOFF_MAX`].
const BACKOFF_MIN: Duration = Duration::from_millis(250);

/// The longest wait after a failure, and the wait after the log could not be read.
const BACKOFF_MAX: Duration = Duration::from_secs(5);

/// Records read from the log at a time by [`run`] for a sink with room for more.
const BATCH: usize = 64;

/// The records of a results log after a position, in id order.
struct Follower {
    log: ResultsLog,
    newest: watch::Receiver<u64>,
    after: u64,
}

impl Follower {
    /// From the record after `after` (0: from the first).
    fn new(log: ResultsLog, after: u64) -> Self {
        let newest = log.subscribe();
        Self { log, newest, after }
    }

    /// The id of the last record read (or sought): the next read starts after it.
    fn position(&self) -> u64 {
        self.after
    }

    /// Reads on from the record after `after`.
    fn seek(&mut self, after: u64) {
        self.after = after;
    }

    /// The newest record's id in the log (0 while there is none).
    fn newest(&self) -> u64 {
        *self.newest.borrow()
    }

    /// Up to `max` records after the position, read on the blocking pool; the position
    /// moves past them. Empty when there are none yet.
    async fn read(&mut self, max: usize) -> Result<Vec<Record>, LogError> {
        let (log, after) = (self.log.clone(), self.after);
        let path = log.path().to_path_buf();
        let batch = tokio::task::spawn_blocking(move || log.after(after, max))
            .await
            .map_err(|e| LogError::Failed {
                path,
                why: format!("reading the records after {after}: {e}"),
            })??;
        if let Some(last) = batch.last() {
            self.after = last.id;
        }
        Ok(batch)
    }

    /// Waits until the log holds a record after the position (at once when it does).
    /// False when the log is gone.
    async fn appended(&mut self) -> bool {
        loop {
            if *self.newest.borrow_and_update() > self.after {
                return true;
            }
            if self.newest.changed().await.is_err() {
                return false;
            }
        }
    }
}

/// Which output of its kind one is: the `id` a configuration file's `[[output]]` gives it,
/// or none (an output given by its flag, or a table without an `id` or with its kind's
/// name as one). It names the output's durable cursor in the log ([`OutputId::cursor`]),
/// so that two outputs of a kind each keep their own position.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct OutputId(Option<String>);

impl OutputId {
    /// The output `id` of kind `kind`: none when `id` is the kind's name.
    pub fn new(kind: &str, id: Option<&str>) -> Self {
        Self(id.filter(|id| *id != kind).map(str::to_owned))
    }

    /// Its id, when it has one of its own.
    pub fn id(&self) -> Option<&str> {
        self.0.as_deref()
    }

    /// The name of its durable cursor in the log: `KIND` (the cursor of the output its
    /// flag gives, as before there were lists), or `KIND/ID`.
    pub fn cursor(&self, kind: &str) -> String {
        match &self.0 {
            None => kind.to_owned(),
            Some(id) => format!("{kind}/{id}"),
        }
    }
}

/// Where a [`Sink`] starts.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Start {
    /// After its durable cursor of this name in the log, which [`run`] moves past each
    /// record it takes: it gets every record, across restarts and failures.
    Cursor(String),
    /// After the record with this id.
    After(u64),
    /// After the newest record at its start: the records appended from then on.
    Newest,
}

/// What a [`Sink`] says after it was handed a record or handled an event of its own.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Next {
    /// Go on: the record was taken (or, for a sink that rewinds with [`Next::After`], left
    /// to it).
    Go,
    /// The record was not taken, for this reason: [`run`] waits (longer while it keeps
    /// failing) and hands it again. (After an event, as [`Next::Go`].)
    Retry(String),
    /// Hand it the records after this id next.
    After(u64),
    /// It is done (its client left, it was stopped): [`run`] returns.
    End,
}

/// An output of the results log, which [`run`] hands the records one by one, in id order.
/// A new output is a file with a `Sink`, its flags and an [`Output`], and its name in the
/// list of `outputs.rs`.
pub trait Sink: Send + 'static {
    /// An event of its own (a broker's packet, a keep-alive's time), between records.
    type Event: Send;

    /// Who it is, for the log's messages (`webhook: http://...`).
    fn name(&self) -> String;

    /// Where it starts.
    fn start(&self) -> Start;

    /// How many records it takes now: 0 while it cannot (a publisher not connected, its
    /// window full), until one of its events says otherwise.
    fn room(&self) -> usize {
        BATCH
    }

    /// Hands `record` on.
    fn deliver(&mut self, record: &Record) -> impl Future<Output = Next> + Send;

    /// Waits for its next event; cancel-safe (it may be dropped for an append and asked
    /// again). None by default.
    fn event(&mut self) -> impl Future<Output = Self::Event> + Send {
        std::future::pending()
    }

    /// Handles an event [`Sink::event`] returned.
    fn handle(&mut self, event: Self::Event) -> impl Future<Output = Next> + Send;
}

/// A started output, kept while the station runs.
pub trait Output: Send {
    /// What it does, said once when the station starts (`line output on ADDR`).
    fn describe(&self) -> String;

    /// Ends it within a bounded time; by default it ends when dropped.
    fn stop(self: Box<Self>) -> Pin<Box<dyn Future<Output = ()> + Send>> {
        Box::pin(async {})
    }
}

/// Measures with every camera now and records it, as a client's request does: the new
/// record's id, `None` when the table was empty (nothing recorded), or why it failed.
pub type MeasureNow = Arc<
    dyn Fn() -> Pin<Box<dyn Future<Output = Result<Option<u64>, String>> + Send>> + Send + Sync,
>;

/// The cameras connected now, as the camera server knows them (OPC UA's `Cameras`).
pub type Cameras = Arc<dyn Fn() -> Vec<CameraView> + Send + Sync>;

/// A connected camera as an output shows it: what `GET /api/cameras` says of it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CameraView {
    /// Its serial.
    pub serial: String,
    /// Its product name.
    pub model: String,
    /// Whether it has a 3d-transformation other than the identity.
    pub calibrated: bool,
    /// Its color stream's settings.
    pub color: StreamView,
    /// Its depth stream's settings.
    pub depth: StreamView,
}

/// A stream's settings: its format's name, frame rate and resolution.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StreamView {
    /// `RGB8`, `Z16`, ...
    pub format: &'static str,
    /// Frames a second.
    pub fps: u32,
    /// Pixels.
    pub width: u32,
    /// Pixels.
    pub height: u32,
}

/// What an output starts from: the results log, the station's name, its state directory,
/// how to measure now and its cameras.
pub(super) struct Feed<'a> {
    pub(super) log: &'a ResultsLog,
    pub(super) station: &'a str,
    /// Read by the OPC UA output only (feature `opcua`).
    #[cfg_attr(not(feature = "opcua"), allow(dead_code))]
    pub(super) state_dir: &'a Path,
    /// Read by the OPC UA output only (feature `opcua`).
    #[cfg_attr(not(feature = "opcua"), allow(dead_code))]
    pub(super) measure: Option<MeasureNow>,
    /// Read by the OPC UA output only (feature `opcua`).
    #[cfg_attr(not(feature = "opcua"), allow(dead_code))]
    pub(super) cameras: Cameras,
}

/// Follows `log` into `sink` until the sink is done or the log is gone: from its
/// [`Start`], handing it records while it has room, its events between them.
pub async fn run<S: Sink>(log: ResultsLog, mut sink: S) {
    let name = sink.name();
    let (start, consumer) = match sink.start() {
        Start::Cursor(consumer) => loop {
            let l = log.clone();
            let c = consumer.clone();
            match tokio::task::spawn_blocking(move || l.cursor(&c)).await {
                Ok(Ok(cursor)) => break (cursor, Some(consumer)),
                Ok(Err(e)) => tracing::warn!("{name}: reading its cursor: {e}"),
                Err(e) => tracing::warn!("{name}: reading its cursor: {e}"),
            }
            tokio::time::sleep(BACKOFF_MAX).await;
        },
        Start::After(id) => (id, None),
        Start::Newest => (log.newest(), None),
    };
    let mut run = Run {
        name,
        log: log.clone(),
        consumer,
        follower: Follower::new(log, start),
        backoff: BACKOFF_MIN,
        failing: false,
        said_waiting: 0,
        paused: None,
    };
    loop {
        if run.paused.is_none() && !run.hand_over(&mut sink).await {
            return;
        }
        let next = tokio::select! {
            appended = run.follower.appended(), if run.paused.is_none() && sink.room() > 0 => {
                if appended { continue } else { return }
            }
            () = sleep_until(run.paused.unwrap_or_else(Instant::now)), if run.paused.is_some() => {
                run.paused = None;
                continue;
            }
            event = sink.event() => sink.handle(event).await,
        };
        match next {
            Next::Go | Next::Retry(_) => {}
            Next::After(id) => run.follower.seek(id),
            Next::End => return,
        }
    }
}

/// What [`run`] keeps of one sink.
struct Run {
    name: String,
    log: ResultsLog,
    /// Its durable cursor's name, when [`run`] keeps one.
    consumer: Option<String>,
    follower: Follower,
    /// The next wait after a failure.
    backoff: Duration,
    /// Whether the last hand-over failed (said once until one works).
    failing: bool,
    /// The largest power of ten of records waiting said during this failure (0: none).
    said_waiting: u64,
    /// No records are handed over before this (after a failure).
    paused: Option<Instant>,
}

impl Run {
    /// While the sink fails, says how many records wait for it in the log (those after
    /// `delivered`) each time that number reaches a power of ten from 10 on.
    fn say_waiting(&mut self, delivered: u64) {
        let waiting = self.follower.newest().saturating_sub(delivered);
        let mut power = 1;
        while power <= waiting / 10 {
            power *= 10;
        }
        if power >= 10 && power > self.said_waiting {
            self.said_waiting = power;
            tracing::warn!("{}: {waiting} records wait in the log for it", self.name);
        }
    }

    /// Hands `sink` the records after the position while it has room; false when it is
    /// done.
    async fn hand_over<S: Sink>(&mut self, sink: &mut S) -> bool {
        while sink.room() > 0 && self.follower.newest() > self.follower.position() {
            let records = match self.follower.read(sink.room()).await {
                Ok(records) => records,
                Err(e) => {
                    tracing::warn!("{}: reading the results log: {e}", self.name);
                    self.paused = Some(Instant::now() + BACKOFF_MAX);
                    return true;
                }
            };
            if records.is_empty() {
                return true;
            }
            for record in &records {
                let next = match sink.deliver(record).await {
                    Next::Go => self.move_cursor(record.id).await,
                    other => other,
                };
                match next {
                    Next::Go => {
                        if self.failing {
                            tracing::info!("{} takes the records again", self.name);
                        }
                        self.failing = false;
                        self.said_waiting = 0;
                        self.backoff = BACKOFF_MIN;
                    }
                    Next::Retry(e) => {
                        if !self.failing {
                            tracing::warn!(
                                "{}: {e}; retrying (the records wait in the log)",
                                self.name
                            );
                        }
                        self.failing = true;
                        self.say_waiting(record.id - 1);
                        self.follower.seek(record.id - 1);
                        self.paused = Some(Instant::now() + self.backoff);
                        self.backoff = (self.backoff * 2).min(BACKOFF_MAX);
                        return true;
                    }
                    Next::After(id) => {
                        self.follower.seek(id);
                        break;
                    }
                    Next::End => return false,
                }
            }
        }
        true
    }

    /// Moves the durable cursor, when there is one, past record `id`.
    async fn move_cursor(&self, id: u64) -> Next {
        let Some(consumer) = self.consumer.clone() else {
            return Next::Go;
        };
        let log = self.log.clone();
        match tokio::task::spawn_blocking(move || log.set_cursor(&consumer, id)).await {
            Ok(Ok(())) => Next::Go,
            Ok(Err(e)) => Next::Retry(format!("moving the cursor: {e}")),
            Err(e) => Next::Retry(format!("moving the cursor: {e}")),
        }
    }
}

#[cfg(test)]
mod tests {
    use tokio::sync::mpsc;

    use super::*;
    use crate::ScratchDir;
    use crate::api::record::NewRecord;

    fn new(n: u64) -> NewRecord {
        crate::api::record::tests::numbered_record(n, "PKG")
    }

    /// Takes every other hand-over only, and tells which it took.
    struct Flaky {
        durable: bool,
        tries: u32,
        took: mpsc::UnboundedSender<u64>,
    }

    impl Sink for Flaky {
        type Event = std::convert::Infallible;

        fn name(&self) -> String {
            "flaky".into()
        }

        fn start(&self) -> Start {
            if self.durable {
                Start::Cursor("flaky".into())
            } else {
                Start::Newest
            }
        }

        async fn deliver(&mut self, record: &Record) -> Next {
            self.tries += 1;
            if self.tries % 2 == 1 {
                return Next::Retry("not now".into());
            }
            let _ = self.took.send(record.id);
            Next::Go
        }

        async fn handle(&mut self, event: Self::Event) -> Next {
            match event {}
        }
    }

    /// What the test tells a [`Windowed`] sink.
    enum Told {
        /// The oldest record in flight is acknowledged.
        Ack,
        /// The connection was lost and made again: what is in flight is sent again.
        Again,
    }

    /// A window of two records in flight, acknowledged by the test, as the MQTT
    /// publisher's: it says which it was handed, and which were acknowledged.
    struct Windowed {
        told: mpsc::UnboundedReceiver<Told>,
        in_flight: Vec<u64>,
        acked: u64,
        took: mpsc::UnboundedSender<u64>,
    }

    impl Sink for Windowed {
        type Event = Option<Told>;

        fn name(&self) -> String {
            "windowed".into()
        }

        fn start(&self) -> Start {
            Start::After(self.acked)
        }

        fn room(&self) -> usize {
            2 - self.in_flight.len()
        }

        async fn deliver(&mut self, record: &Record) -> Next {
            self.in_flight.push(record.id);
            let _ = self.took.send(record.id);
            Next::Go
        }

        async fn event(&mut self) -> Option<Told> {
            self.told.recv().await
        }

        async fn handle(&mut self, event: Option<Told>) -> Next {
            match event {
                Some(Told::Ack) => {
                    self.acked = self.in_flight.remove(0);
                    Next::Go
                }
                Some(Told::Again) => {
                    self.in_flight.clear();
                    Next::After(self.acked)
                }
                None => Next::End,
            }
        }
    }

    /// Refuses every record until told to take them.
    struct Refusing {
        take: Arc<std::sync::atomic::AtomicBool>,
    }

    impl Sink for Refusing {
        type Event = std::convert::Infallible;

        fn name(&self) -> String {
            "refusing".into()
        }

        fn start(&self) -> Start {
            Start::After(0)
        }

        async fn deliver(&mut self, _record: &Record) -> Next {
            if self.take.load(std::sync::atomic::Ordering::SeqCst) {
                Next::Go
            } else {
                Next::Retry("down".into())
            }
        }

        async fn handle(&mut self, event: Self::Event) -> Next {
            match event {}
        }
    }

    /// What the station's messages say, kept for a test.
    #[derive(Clone, Default)]
    struct Said(Arc<std::sync::Mutex<Vec<u8>>>);

    impl std::io::Write for Said {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            self.0
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner)
                .extend_from_slice(buf);
            Ok(buf.len())
        }

        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    impl Said {
        fn lines(&self, containing: &str) -> Vec<String> {
            let text = self.0.lock().map(|b| b.clone()).unwrap_or_default();
            String::from_utf8_lossy(&text)
                .lines()
                .filter(|l| l.contains(containing))
                .map(str::to_owned)
                .collect()
        }
    }

    /// Waits (on the paused clock) until `said` has `n` lines with `containing`.
    async fn until_said(said: &Said, containing: &str, n: usize) -> Vec<String> {
        for _ in 0..1000 {
            let lines = said.lines(containing);
            if lines.len() >= n {
                return lines;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        panic!("never said {n} times {containing:?}: {:?}", said.lines(""));
    }

    #[tokio::test(start_paused = true)]
    async fn the_records_waiting_for_a_failing_sink_are_said_at_each_power_of_ten() {
        // With one subscriber alive in the process, tracing asks the thread that first
        // meets a callsite whether anyone wants it: another test's thread, with none, would
        // switch this test's messages off for good. A second one, never set as anyone's
        // default, makes tracing ask every subscriber alive instead.
        let _second = tracing::Dispatch::new(
            tracing_subscriber::fmt()
                .with_writer(std::io::sink)
                .finish(),
        );
        let said = Said::default();
        let writer = said.clone();
        let _default = tracing::subscriber::set_default(
            tracing_subscriber::fmt()
                .with_writer(move || writer.clone())
                .with_ansi(false)
                .finish(),
        );
        let dir = ScratchDir::new("follow-waiting");
        let log = ResultsLog::open(&dir.path().join("log.db")).expect("log");
        for n in 1..=25 {
            log.append(new(n)).expect("append");
        }
        let take = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let task = tokio::spawn(run(log.clone(), Refusing { take: take.clone() }));
        let lines = until_said(&said, "wait in the log for it", 1).await;
        assert!(lines[0].contains("refusing: 25 records wait"), "{lines:?}");
        // More records, not yet a hundred waiting: said once, however often it retries.
        for n in 26..=99 {
            log.append(new(n)).expect("append");
        }
        tokio::time::sleep(BACKOFF_MAX * 4).await;
        assert_eq!(said.lines("wait in the log for it").len(), 1, "{lines:?}");
        log.append(new(100)).expect("append");
        let lines = until_said(&said, "wait in the log for it", 2).await;
        assert!(lines[1].contains("refusing: 100 records wait"), "{lines:?}");
        // It takes them again.
        take.store(true, std::sync::atomic::Ordering::SeqCst);
        until_said(&said, "refusing takes the records again", 1).await;
        task.abort();
    }

    #[tokio::test]
    async fn a_sink_with_a_window_gets_records_as_its_events_make_room_and_again_after_a_rewind() {
        let dir = ScratchDir::new("follow-window");
        let log = ResultsLog::open(&dir.path().join("log.db")).expect("log");
        for n in 1..=5 {
            log.append(new(n)).expect("append");
        }
        let (took, mut rx) = mpsc::unbounded_channel();
        let (tell, told) = mpsc::unbounded_channel();
        let sink = Windowed {
            told,
            in_flight: Vec::new(),
            acked: 0,
            took,
        };
        let task = tokio::spawn(run(log.clone(), sink));
        assert_eq!(taken(&mut rx, 2).await, [1, 2], "the window's two");
        tokio::task::yield_now().await;
        assert!(rx.try_recv().is_err(), "a record beyond the window");
        tell.send(Told::Ack).expect("ack");
        assert_eq!(taken(&mut rx, 1).await, [3], "room for one after an ack");
        // 2 and 3 are in flight and lost: they come again, after 1.
        tell.send(Told::Again).expect("again");
        assert_eq!(taken(&mut rx, 2).await, [2, 3]);
        tell.send(Told::Ack).expect("ack");
        tell.send(Told::Ack).expect("ack");
        assert_eq!(taken(&mut rx, 2).await, [4, 5]);
        log.append(new(6)).expect("append");
        tell.send(Told::Ack).expect("ack");
        assert_eq!(
            taken(&mut rx, 1).await,
            [6],
            "an append after the window had room"
        );
        drop(tell);
        tokio::time::timeout(Duration::from_secs(30), task)
            .await
            .expect("run ends when the sink says End")
            .expect("the task");
    }

    async fn taken(rx: &mut mpsc::UnboundedReceiver<u64>, n: usize) -> Vec<u64> {
        let mut out = Vec::new();
        while out.len() < n {
            match tokio::time::timeout(Duration::from_secs(30), rx.recv()).await {
                Ok(Some(id)) => out.push(id),
                _ => break,
            }
        }
        out
    }

    #[tokio::test]
    async fn a_durable_sink_gets_every_record_once_in_order_through_its_failures() {
        let dir = ScratchDir::new("follow-durable");
        let log = ResultsLog::open(&dir.path().join("log.db")).expect("log");
        for n in 1..=2 {
            log.append(new(n)).expect("append");
        }
        let (took, mut rx) = mpsc::unbounded_channel();
        let sink = Flaky {
            durable: true,
            tries: 0,
            took,
        };
        let task = tokio::spawn(run(log.clone(), sink));
        assert_eq!(taken(&mut rx, 2).await, [1, 2]);
        for n in 3..=5 {
            log.append(new(n)).expect("append");
        }
        assert_eq!(taken(&mut rx, 3).await, [3, 4, 5]);
        let mut cursor = 0;
        for _ in 0..300 {
            cursor = log.cursor("flaky").expect("cursor");
            if cursor == 5 {
                break;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        assert_eq!(cursor, 5);
        task.abort();
        assert!(rx.try_recv().is_err(), "a record handed over twice");
    }

    #[tokio::test]
    async fn a_sink_without_a_cursor_gets_what_is_appended_after_its_start() {
        let dir = ScratchDir::new("follow-now");
        let log = ResultsLog::open(&dir.path().join("log.db")).expect("log");
        log.append(new(1)).expect("append");
        let (took, mut rx) = mpsc::unbounded_channel();
        let sink = Flaky {
            durable: false,
            tries: 0,
            took,
        };
        let task = tokio::spawn(run(log.clone(), sink));
        // On this one-thread runtime the task takes its start (the newest record) and
        // waits, before the test goes on.
        tokio::task::yield_now().await;
        log.append(new(2)).expect("append");
        log.append(new(3)).expect("append");
        assert_eq!(taken(&mut rx, 2).await, [2, 3]);
        task.abort();
    }
}
