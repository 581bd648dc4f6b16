//! PostgreSQL (`serve --postgres URL`): every record of the results log copied into the
//! table [`TABLE`] of a PostgreSQL database, in id order, each once. The position is a
//! durable cursor in the log (consumer [`CONSUMER`]), moved past a record only once its
//! row is committed; a record sent again (its commit done, the cursor not yet moved when
//! the station stopped) is a row the table already has, keyed by `(station, id)`, and is
//! not inserted twice. While the server is down the records wait in the log;
//! [`follow::run`] retries with back-off (0.25 s, doubling to 5 s), connecting anew.
//!
//! A row holds the record's canonical bytes (`body`, the bytes its `hash` is taken over,
//! as the log stores them), so the table alone checks each record's hash; [`compare`]
//! checks the table against a log (`results verify FILE --postgres URL`).
//!
//! No TLS: the server is reached over plain TCP or a Unix socket.

use std::fmt;
use std::str::FromStr;
use std::time::Duration;

use tokio::task::JoinHandle;
use tokio_postgres::{Client, NoTls};

use super::follow::{self, Feed, Next, Output, OutputId, Sink, Start};
use super::log::ResultsLog;
use crate::api::record::Record;

/// The cursor name in the results log of the PostgreSQL output its flag gives (of one
/// with an `id` of its own: `postgres/ID`).
pub const CONSUMER: &str = "postgres";

/// The table the records go into.
pub const TABLE: &str = "coapcam_records";

/// How long connecting, or one statement, may take.
const TIMEOUT: Duration = Duration::from_secs(10);

/// The table, made when it is not there. `arrival` numbers the rows in the order they
/// were inserted (a station's rows arrive in id order); `time` is the record's time.
const SCHEMA: &str = "CREATE TABLE IF NOT EXISTS coapcam_records (
    station text NOT NULL,
    id bigint NOT NULL,
    time timestamptz NOT NULL,
    hash text NOT NULL,
    prev_hash text NOT NULL,
    body text NOT NULL,
    signature text,
    arrival bigint GENERATED ALWAYS AS IDENTITY,
    PRIMARY KEY (station, id)
)";

/// Rows read at a time by [`compare`].
const PAGE: i64 = 1000;

/// A PostgreSQL database: `postgres://[USER[:PASSWORD]@]HOST[:PORT]/DATABASE[?PARAMS]`
/// (or `postgresql://`), as libpq's connection URIs; a Unix socket's folder as the host
/// (`postgres://USER@%2Frun%2Fpostgresql/DB`) or `?host=/run/postgresql`.
#[derive(Clone)]
pub struct Target {
    config: tokio_postgres::Config,
    /// The URL with its password masked.
    shown: String,
}

impl FromStr for Target {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        let shown = masked(text);
        if !(text.starts_with("postgres://") || text.starts_with("postgresql://")) {
            return Err(format!(
                "{shown}: a PostgreSQL URL is postgres://[USER[:PASSWORD]@]HOST[:PORT]/DATABASE"
            ));
        }
        let query = text.split_once('?').map_or("", |(_, q)| q);
        if query
            .split('&')
            .any(|p| p.split('=').next() == Some("password"))
        {
            return Err(format!(
                "{shown}: give the password as postgres://USER:PASSWORD@HOST/DATABASE (there --print-config masks it), not as ?password="
            ));
        }
        let mut config: tokio_postgres::Config =
            text.parse().map_err(|e| format!("{shown}: {e}"))?;
        if config.get_connect_timeout().is_none() {
            config.connect_timeout(TIMEOUT);
        }
        Ok(Self { config, shown })
    }
}

impl fmt::Display for Target {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.shown)
    }
}

impl fmt::Debug for Target {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Target({})", self.shown)
    }
}

/// `url` with the password of its user part as `********`.
fn masked(url: &str) -> String {
    let Some((scheme, rest)) = url.split_once("://") else {
        return url.to_owned();
    };
    let end = rest.find(['/', '?']).unwrap_or(rest.len());
    match rest[..end].rsplit_once('@') {
        Some((userinfo, _)) => match userinfo.split_once(':') {
            Some((user, _)) => format!("{scheme}://{user}:********{}", &rest[userinfo.len()..]),
            None => url.to_owned(),
        },
        None => url.to_owned(),
    }
}

/// The flag of the PostgreSQL output (`serve --postgres`).
#[derive(Debug, Clone, Default, clap::Args)]
#[group(skip)]
pub struct Args {
    /// Copy every record of the results log into the table coapcam_records of this
    /// PostgreSQL database (made if missing; plain TCP or a Unix socket, no TLS), in id
    /// order, each once: a row per record keyed by (station, id), with its hash,
    /// prev_hash and canonical bytes. The position is kept in the log (cursor
    /// `postgres`): nothing is lost while the server is down or the station restarts
    /// (retrying 0.25 s, doubling to 5 s), and a record sent again is not a second row.
    /// A new log's whole history is copied first. `results verify LOG --postgres URL`
    /// compares the table with the log.
    #[arg(long, value_name = "postgres://[USER:PASSWORD@]HOST[:PORT]/DATABASE")]
    postgres: Option<Target>,
}

impl Args {
    /// Whether `--postgres` is given.
    pub(super) fn configured(&self) -> bool {
        self.postgres.is_some()
    }

    /// The output `--postgres` asks for, as output `id` (its cursor's name).
    pub(super) async fn start(
        &self,
        feed: &Feed<'_>,
        id: &OutputId,
    ) -> Result<Option<Box<dyn Output>>, std::convert::Infallible> {
        Ok(self.postgres.clone().map(|target| {
            Box::new(Postgres::start(
                target,
                feed.log.clone(),
                id.cursor(CONSUMER),
            )) as Box<dyn Output>
        }))
    }
}

/// The running output: its task follows the log until dropped.
#[derive(Debug)]
pub struct Postgres {
    task: JoinHandle<()>,
    target: Target,
}

impl Output for Postgres {
    fn describe(&self) -> String {
        format!("PostgreSQL table {TABLE} at {}", self.target)
    }
}

impl Drop for Postgres {
    fn drop(&mut self) {
        self.task.abort();
    }
}

impl Postgres {
    /// Copies `log`'s records into `target`'s table from the cursor named `cursor`
    /// ([`CONSUMER`] for the output of `--postgres`).
    pub fn start(target: Target, log: ResultsLog, cursor: String) -> Self {
        let copier = Copier {
            target: target.clone(),
            client: None,
            cursor,
        };
        Self {
            task: tokio::spawn(follow::run(log, copier)),
            target,
        }
    }
}

/// The output as a [`Sink`]: one connection, made again after any failure.
struct Copier {
    target: Target,
    client: Option<Client>,
    /// Its durable cursor's name.
    cursor: String,
}

impl Sink for Copier {
    type Event = std::convert::Infallible;

    fn name(&self) -> String {
        format!(
            "{}: {}",
            super::output_name("postgres", &self.cursor),
            self.target
        )
    }

    fn start(&self) -> Start {
        Start::Cursor(self.cursor.clone())
    }

    async fn deliver(&mut self, record: &Record) -> Next {
        match self.insert(record).await {
            Ok(()) => Next::Go,
            Err(why) => {
                self.client = None;
                Next::Retry(why)
            }
        }
    }

    async fn handle(&mut self, event: Self::Event) -> Next {
        match event {}
    }
}

impl Copier {
    /// Inserts `record`'s row unless the table has it; a row of the same `(station, id)`
    /// with another hash is refused (the records wait until someone resolves it).
    async fn insert(&mut self, record: &Record) -> Result<(), String> {
        let client = match &mut self.client {
            Some(client) if !client.is_closed() => client,
            slot => slot.insert(connect(&self.target).await?),
        };
        let id = i64::try_from(record.id).map_err(|_| format!("record id {}", record.id))?;
        let body = String::from_utf8(record.stored_body())
            .map_err(|e| format!("record {}: {e}", record.id))?;
        let inserted = timed(client.execute(
            "INSERT INTO coapcam_records (station, id, time, hash, prev_hash, body, signature)
             VALUES ($1, $2, to_timestamp($3::bigint / 1000.0), $4, $5, $6, $7)
             ON CONFLICT (station, id) DO NOTHING",
            &[
                &record.station,
                &id,
                &record.time.unix_ms,
                &record.hash,
                &record.prev_hash,
                &body,
                &record.signature,
            ],
        ))
        .await
        .map_err(|e| format!("inserting record {}: {e}", record.id))?;
        if inserted == 1 {
            return Ok(());
        }
        let row = timed(client.query_opt(
            "SELECT hash FROM coapcam_records WHERE station = $1 AND id = $2",
            &[&record.station, &id],
        ))
        .await
        .map_err(|e| format!("reading record {}: {e}", record.id))?;
        match row.map(|r| r.get::<_, String>(0)) {
            Some(hash) if hash == record.hash => {
                tracing::debug!("postgres: record {} was there already", record.id);
                Ok(())
            }
            Some(hash) => Err(format!(
                "the table already holds record {} of station {} with another hash ({hash})",
                record.id, record.station
            )),
            None => Err(format!(
                "record {} was neither inserted nor found",
                record.id
            )),
        }
    }
}

/// `future` within [`TIMEOUT`].
async fn timed<T>(
    future: impl Future<Output = Result<T, tokio_postgres::Error>>,
) -> Result<T, String> {
    match tokio::time::timeout(TIMEOUT, future).await {
        Ok(result) => result.map_err(|e| said(&e)),
        Err(_) => Err(format!("no answer within {TIMEOUT:?}")),
    }
}

/// `e` with its causes (the server's message, the socket's error), which its `Display`
/// leaves out.
fn said(e: &tokio_postgres::Error) -> String {
    let mut text = e.to_string();
    let mut cause = std::error::Error::source(e);
    while let Some(c) = cause {
        text.push_str(&format!(": {c}"));
        cause = c.source();
    }
    text
}

/// A connection to `target`, its table made if missing.
async fn connect(target: &Target) -> Result<Client, String> {
    let (client, connection) = timed(target.config.connect(NoTls))
        .await
        .map_err(|e| format!("connecting: {e}"))?;
    tokio::spawn(async move {
        if let Err(e) = connection.await {
            tracing::debug!("postgres: connection: {e}");
        }
    });
    timed(client.batch_execute(SCHEMA))
        .await
        .map_err(|e| format!("making the table {TABLE}: {e}"))?;
    Ok(client)
}

/// What [`compare`] found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TableReport {
    /// The station whose rows were compared.
    pub station: String,
    /// The rows that matched the log's records before the first difference (all of
    /// them when there is none).
    pub rows: u64,
    /// The first difference: the record's id and what differs.
    pub first_difference: Option<(u64, String)>,
}

/// The table could not be compared: the database did not answer, or refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum CompareError {
    /// No connection.
    #[error("connecting to {target}: {why}")]
    Connect {
        /// The target, as it is shown (without a password).
        target: String,
        /// The client's words, with their causes, or the timeout.
        why: String,
    },
    /// The table could not be read.
    #[error("reading {TABLE} at {target}: {why}")]
    Read {
        /// The target, as it is shown.
        target: String,
        /// The server's words, with their causes, or the timeout.
        why: String,
    },
}

/// Compares the table at `target` with `records`, a log's measurements of `station`
/// (id and hash, in id order): the table must hold a row for each, with the same hash,
/// a body that hashes to it, arrived in id order, and no other row of the station.
///
/// # Errors
///
/// When the database cannot be reached or read (not a difference).
pub async fn compare(
    target: &Target,
    station: &str,
    records: &[(u64, String)],
) -> Result<TableReport, CompareError> {
    let (client, connection) =
        timed(target.config.connect(NoTls))
            .await
            .map_err(|why| CompareError::Connect {
                target: target.to_string(),
                why,
            })?;
    let connection = tokio::spawn(connection);
    let mut report = TableReport {
        station: station.to_owned(),
        rows: 0,
        first_difference: None,
    };
    let mut log = records.iter().peekable();
    let (mut after, mut last_arrival) = (0_i64, None::<(u64, i64)>);
    'pages: loop {
        let rows = timed(client.query(
            "SELECT id, hash, body, arrival FROM coapcam_records
             WHERE station = $1 AND id > $2 ORDER BY id LIMIT $3",
            &[&station, &after, &PAGE],
        ))
        .await
        .map_err(|why| CompareError::Read {
            target: target.to_string(),
            why,
        })?;
        let Some(last) = rows.last() else { break };
        after = last.get(0);
        for row in &rows {
            let id = u64::try_from(row.get::<_, i64>(0)).unwrap_or(0);
            let (hash, body, arrival): (String, String, i64) = (row.get(1), row.get(2), row.get(3));
            let why = match log.peek() {
                Some((logged, _)) if *logged < id => {
                    Some((*logged, format!("record {logged} is not in the table")))
                }
                Some((logged, logged_hash)) if *logged == id => {
                    if hash != *logged_hash {
                        Some((
                            id,
                            format!(
                                "record {id}: the table's hash {hash} is not the log's {logged_hash}"
                            ),
                        ))
                    } else if Record::hash_of(body.as_bytes()) != hash {
                        Some((
                            id,
                            format!(
                                "record {id}: the table's body does not hash to its hash (altered in the table)"
                            ),
                        ))
                    } else if let Some((before, _)) =
                        last_arrival.filter(|(_, earlier)| *earlier > arrival)
                    {
                        Some((
                            id,
                            format!("record {id} arrived in the table before record {before}"),
                        ))
                    } else {
                        None
                    }
                }
                _ => Some((
                    id,
                    format!(
                        "the table holds a record {id} of station {station} that the log does not have"
                    ),
                )),
            };
            if let Some(difference) = why {
                report.first_difference = Some(difference);
                break 'pages;
            }
            log.next();
            last_arrival = Some((id, arrival));
            report.rows += 1;
        }
    }
    if report.first_difference.is_none()
        && let Some((id, _)) = log.next()
    {
        let newest = records.last().map_or(*id, |(newest, _)| *newest);
        report.first_difference = Some((
            *id,
            format!(
                "the table ends before record {id} (the log goes on to {newest}): not copied yet, or lost"
            ),
        ));
    }
    drop(client);
    let _ = tokio::time::timeout(TIMEOUT, connection).await;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The `sql` blocks of docs/station.md's section on PostgreSQL, in its order.
    fn documented_sql() -> Vec<String> {
        let doc = include_str!("../../../../docs/station.md");
        let section = doc
            .split("\n## PostgreSQL\n")
            .nth(1)
            .and_then(|s| s.split("\n## ").next())
            .expect("docs/station.md has a section ## PostgreSQL");
        section
            .split("```sql\n")
            .skip(1)
            .filter_map(|b| b.split("```").next())
            .map(str::to_owned)
            .collect()
    }

    #[test]
    fn the_documented_table_is_the_one_made() {
        let words = |sql: &str| {
            sql.lines()
                .map(|l| l.split("--").next().unwrap_or_default())
                .collect::<Vec<_>>()
                .join(" ")
                .split_whitespace()
                .collect::<Vec<_>>()
                .join(" ")
        };
        let blocks = documented_sql();
        assert_eq!(words(&blocks[0]), words(SCHEMA));
    }

    #[test]
    fn urls_are_checked_and_shown_without_their_password() {
        let t: Target = "postgres://dock:s3cret@127.0.0.1:5433/plant"
            .parse()
            .unwrap();
        assert_eq!(
            t.to_string(),
            "postgres://dock:********@127.0.0.1:5433/plant"
        );
        assert_eq!(t.config.get_dbname(), Some("plant"));
        assert_eq!(t.config.get_ports(), [5433]);
        let t: Target = "postgresql://dock@%2Frun%2Fpostgresql/plant"
            .parse()
            .unwrap();
        assert_eq!(t.to_string(), "postgresql://dock@%2Frun%2Fpostgresql/plant");
        assert!(
            "mysql://h/db"
                .parse::<Target>()
                .unwrap_err()
                .contains("postgres://")
        );
        let e = "postgres://dock@h/db?password=x"
            .parse::<Target>()
            .unwrap_err();
        assert!(e.contains("USER:PASSWORD@"), "{e}");
        assert_eq!(masked("postgres://h/db?a=b:c@d"), "postgres://h/db?a=b:c@d");
    }
}
