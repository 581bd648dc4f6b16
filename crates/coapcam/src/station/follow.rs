//! The one follower of the results log: its records in id order from a position, read on
//! the blocking pool in batches, waking on each append. Every output reads the log
//! through it: the [`Sink`]s (the line output, the webhook) through [`run`], which also
//! keeps a sink's durable cursor and backs off while it fails; the MQTT publisher (its
//! window of unacknowledged records) and the HTTP event stream (one per client) through
//! a [`Follower`] of their own.

use std::future::Future;
use std::time::Duration;

use tokio::sync::watch;

use super::log::{LogError, ResultsLog};
use crate::api::record::Record;

/// The first wait after a sink failed; it doubles up to [`BACKOFF_MAX`].
const BACKOFF_MIN: Duration = Duration::from_millis(250);

/// The longest wait after a failure, and the wait after the log could not be read.
const BACKOFF_MAX: Duration = Duration::from_secs(5);

/// Records read from the log at a time by [`run`].
const BATCH: usize = 64;

/// The records of a results log after a position, in id order.
pub struct Follower {
    log: ResultsLog,
    newest: watch::Receiver<u64>,
    after: u64,
}

impl Follower {
    /// From the record after `after` (0: from the first).
    pub fn new(log: ResultsLog, after: u64) -> Self {
        let newest = log.subscribe();
        Self { log, newest, after }
    }

    /// The id of the last record read (or sought): the next read starts after it.
    pub fn position(&self) -> u64 {
        self.after
    }

    /// Reads on from the record after `after`.
    pub fn seek(&mut self, after: u64) {
        self.after = after;
    }

    /// The newest record's id in the log (0 while there is none).
    pub fn newest(&self) -> u64 {
        *self.newest.borrow()
    }

    /// Up to `max` records after the position, read on the blocking pool; the position
    /// moves past them. Empty when there are none yet.
    pub async fn read(&mut self, max: usize) -> Result<Vec<Record>, LogError> {
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
    pub async fn appended(&mut self) -> bool {
        loop {
            if *self.newest.borrow_and_update() > self.after {
                return true;
            }
            if self.newest.changed().await.is_err() {
                return false;
            }
        }
    }

    /// Waits for the next append, whatever the position. False when the log is gone.
    pub async fn changed(&mut self) -> bool {
        self.newest.changed().await.is_ok()
    }
}

/// An output that takes the records one by one, in id order, and that [`run`] drives.
/// A new output is a file with a `Sink` and one line that starts [`run`] with it
/// (`Station::start`).
pub trait Sink: Send + 'static {
    /// Who it is, for the log's messages (`webhook: http://...`).
    fn name(&self) -> String;

    /// Its durable cursor in the log (it then gets every record after it, across
    /// restarts and failures), or `None`: it gets the records appended from its start,
    /// and none twice.
    fn cursor(&self) -> Option<&'static str>;

    /// Hands `record` on; an error means it was not taken: [`run`] waits and hands it
    /// again.
    fn deliver(&mut self, record: &Record) -> impl Future<Output = Result<(), String>> + Send;
}

/// Follows `log` into `sink` for as long as the log is open: from its cursor (moved past
/// each record taken), or from the next record appended.
pub async fn run(log: ResultsLog, mut sink: impl Sink) {
    let name = sink.name();
    let start = match sink.cursor() {
        Some(consumer) => loop {
            let l = log.clone();
            match tokio::task::spawn_blocking(move || l.cursor(consumer)).await {
                Ok(Ok(cursor)) => break cursor,
                Ok(Err(e)) => tracing::warn!("{name}: reading its cursor: {e}"),
                Err(e) => tracing::warn!("{name}: reading its cursor: {e}"),
            }
            tokio::time::sleep(BACKOFF_MAX).await;
        },
        None => log.newest(),
    };
    let mut follower = Follower::new(log.clone(), start);
    let mut backoff = BACKOFF_MIN;
    let mut failing = false;
    while follower.appended().await {
        let records = match follower.read(BATCH).await {
            Ok(records) => records,
            Err(e) => {
                tracing::warn!("{name}: reading the results log: {e}");
                tokio::time::sleep(BACKOFF_MAX).await;
                continue;
            }
        };
        for record in &records {
            let taken = match sink.deliver(record).await {
                Ok(()) => match sink.cursor() {
                    Some(consumer) => {
                        let (l, id) = (log.clone(), record.id);
                        match tokio::task::spawn_blocking(move || l.set_cursor(consumer, id)).await
                        {
                            Ok(Ok(())) => Ok(()),
                            Ok(Err(e)) => Err(format!("moving the cursor: {e}")),
                            Err(e) => Err(format!("moving the cursor: {e}")),
                        }
                    }
                    None => Ok(()),
                },
                Err(e) => Err(e),
            };
            match taken {
                Ok(()) => {
                    if failing {
                        tracing::info!("{name} takes the records again");
                    }
                    failing = false;
                    backoff = BACKOFF_MIN;
                }
                Err(e) => {
                    if !failing {
                        tracing::warn!("{name}: {e}; retrying (the records wait in the log)");
                    }
                    failing = true;
                    follower.seek(record.id - 1);
                    tokio::time::sleep(backoff).await;
                    backoff = (backoff * 2).min(BACKOFF_MAX);
                    break;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use tokio::sync::mpsc;

    use super::*;
    use crate::ScratchDir;
    use crate::api::record::{NewRecord, Trigger, UtcTime};

    fn new(n: u64) -> NewRecord {
        NewRecord {
            time: UtcTime {
                unix_ms: 1_795_734_229_000 + i64::try_from(n).unwrap_or(0),
            },
            station: "lane-1".into(),
            trigger: Trigger::Request,
            measurement: crate::api::record::tests::measurement(300.0 + n as f64, "PKG"),
            cameras: Vec::new(),
            version: NewRecord::VERSION.into(),
            photo_jpeg: None,
            annotated_png: None,
        }
    }

    /// Takes every other hand-over only, and tells which it took.
    struct Flaky {
        durable: bool,
        tries: u32,
        took: mpsc::UnboundedSender<u64>,
    }

    impl Sink for Flaky {
        fn name(&self) -> String {
            "flaky".into()
        }

        fn cursor(&self) -> Option<&'static str> {
            self.durable.then_some("flaky")
        }

        async fn deliver(&mut self, record: &Record) -> Result<(), String> {
            self.tries += 1;
            if self.tries % 2 == 1 {
                return Err("not now".into());
            }
            let _ = self.took.send(record.id);
            Ok(())
        }
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
