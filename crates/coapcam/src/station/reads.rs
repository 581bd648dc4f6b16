//! The results log's read API, written once for its front ends (the CoAP resources in
//! `resources.rs`, the HTTP API in `http/`, the OPC UA methods in `opcua.rs`): the list,
//! the newest record, one record, the records after one, a record's pictures, and the
//! wording of every refusal. A front end reads its request into these calls, maps a
//! [`Refusal`]'s [`Kind`] to its own code (4.00/400, 4.04/404, 5.00/500;
//! `BadNotFound`, `BadResourceUnavailable`) and writes the document in its own format.

use super::log::{LogError, ResultsLog};
use crate::api::record::{EventRecord, Head, Record, UtcTime};
use crate::api::results::ListQuery;

/// The largest record id: SQLite's ids are signed 64-bit, so an id past it is no record
/// (not a 5.00 with the database's refusal of the number).
const MAX_ID: u64 = i64::MAX as u64;

/// What kind of refusal: the code each front end gives it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Kind {
    /// The request is wrong (a bad id or query): 4.00, 400.
    BadRequest,
    /// No such record or picture: 4.04, 404.
    NotFound,
    /// The log could not be read: 5.00, 500.
    Failed,
}

/// Why a read of the results log gives no document, in the words both front ends send.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Refusal {
    /// Its code.
    pub(crate) kind: Kind,
    /// Its message.
    pub(crate) why: String,
}

impl Refusal {
    fn new(kind: Kind, why: String) -> Self {
        Self { kind, why }
    }

    fn failed(e: &LogError) -> Self {
        tracing::warn!("results log: {e}");
        Self::new(Kind::Failed, e.public_text())
    }
}

/// A record's picture.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Picture {
    /// The photo (JPEG).
    Photo,
    /// The annotated picture (PNG).
    Annotated,
}

impl Picture {
    /// Its name in a message.
    fn what(self) -> &'static str {
        match self {
            Self::Photo => "photo",
            Self::Annotated => "annotated picture",
        }
    }
}

/// The records `items` (a request's query) select, newest first; `path` names the
/// resource in the refusal of an unknown item.
pub(crate) async fn list<S: AsRef<str>>(
    log: &ResultsLog,
    items: impl IntoIterator<Item = S>,
    path: &str,
) -> Result<Vec<Record>, Refusal> {
    let query = ListQuery::parse(items, path).map_err(|why| Refusal::new(Kind::BadRequest, why))?;
    blocking(log, move |log| log.list(&query)).await
}

/// The events `items` (a request's query: `since`, `before`, `limit`) select, newest
/// first; `path` names the resource in a refusal.
pub(crate) async fn events<S: AsRef<str>>(
    log: &ResultsLog,
    items: impl IntoIterator<Item = S>,
    path: &str,
) -> Result<Vec<EventRecord>, Refusal> {
    let query = ListQuery::parse(items, path).map_err(|why| Refusal::new(Kind::BadRequest, why))?;
    if query.code.is_some() || query.from.is_some() || query.to.is_some() {
        return Err(Refusal::new(
            Kind::BadRequest,
            format!("{path} takes since=ID, before=ID and limit=N only"),
        ));
    }
    blocking(log, move |log| log.list_events(&query)).await
}

/// The newest record (`None` before the first).
pub(crate) async fn latest(log: &ResultsLog) -> Result<Option<Record>, Refusal> {
    blocking(log, ResultsLog::latest).await
}

/// The log's head: the newest record's id and hash.
pub(crate) async fn head(log: &ResultsLog) -> Result<Head, Refusal> {
    blocking(log, ResultsLog::head).await
}

/// The record of id `text`.
pub(crate) async fn one(log: &ResultsLog, text: &str) -> Result<Record, Refusal> {
    record(log, parse_id(text)?).await
}

/// The record of id `id`.
pub(crate) async fn record(log: &ResultsLog, id: u64) -> Result<Record, Refusal> {
    if id > MAX_ID {
        return Err(no_record(id));
    }
    blocking(log, move |log| log.get(id))
        .await?
        .ok_or_else(|| no_record(id))
}

/// At most `max` records after id `after` (measured at `since` or later, when given),
/// oldest first. Read by the OPC UA methods only (feature `opcua`).
#[cfg_attr(not(feature = "opcua"), allow(dead_code))]
pub(crate) async fn after(
    log: &ResultsLog,
    after: u64,
    since: Option<UtcTime>,
    max: usize,
) -> Result<Vec<Record>, Refusal> {
    if after >= MAX_ID {
        return Ok(Vec::new());
    }
    blocking(log, move |log| match since {
        Some(from) => log.after_from(after, from, max),
        None => log.after(after, max),
    })
    .await
}

/// The record of id `text` and its `picture`.
pub(crate) async fn picture(
    log: &ResultsLog,
    text: &str,
    picture: Picture,
) -> Result<(Record, Vec<u8>), Refusal> {
    let id = parse_id(text)?;
    let found = blocking(log, move |log| {
        let Some(record) = log.get(id)? else {
            return Ok(None);
        };
        let data = match picture {
            Picture::Photo => log.photo(id)?,
            Picture::Annotated => log.annotated(id)?,
        };
        Ok(Some((record, data)))
    })
    .await?;
    let (record, data) = found.ok_or_else(|| no_record(id))?;
    let sha = match picture {
        Picture::Photo => &record.photo_sha256,
        Picture::Annotated => &record.annotated_sha256,
    };
    let what = picture.what();
    match data {
        Some(data) => Ok((record, data)),
        None if sha.is_some() => Err(Refusal::new(
            Kind::NotFound,
            format!(
                "record {id}'s {what} was pruned by the retention (its SHA-256 stays in the record)"
            ),
        )),
        None => Err(Refusal::new(
            Kind::NotFound,
            format!("record {id} has no {what}"),
        )),
    }
}

/// A record id: a whole number from 1.
fn parse_id(text: &str) -> Result<u64, Refusal> {
    match text.parse::<u64>() {
        Ok(id) if id > MAX_ID => Err(no_record(id)),
        Ok(id) if id > 0 => Ok(id),
        _ => Err(Refusal::new(
            Kind::BadRequest,
            format!("{text} is not a record id (a whole number from 1)"),
        )),
    }
}

fn no_record(id: u64) -> Refusal {
    Refusal::new(Kind::NotFound, format!("no record {id} in the results log"))
}

/// Runs `f` on the log off the executor.
async fn blocking<T: Send + 'static>(
    log: &ResultsLog,
    f: impl FnOnce(&ResultsLog) -> Result<T, LogError> + Send + 'static,
) -> Result<T, Refusal> {
    let log = log.clone();
    let path = log.path().to_owned();
    let read = match tokio::task::spawn_blocking(move || f(&log)).await {
        Ok(result) => result,
        Err(e) => Err(LogError::Failed {
            path,
            why: format!("the reading task failed: {e}"),
        }),
    };
    read.map_err(|e| Refusal::failed(&e))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ScratchDir;

    #[tokio::test]
    async fn refusals_say_which_record_and_why() {
        let dir = ScratchDir::new("reads");
        let log = ResultsLog::open(&dir.path().join("log.db")).expect("log");
        let refused = |r: Result<Record, Refusal>| r.expect_err("a refusal");
        let bad = refused(one(&log, "0").await);
        assert_eq!(bad.kind, Kind::BadRequest);
        assert_eq!(bad.why, "0 is not a record id (a whole number from 1)");
        let missing = refused(one(&log, "7").await);
        assert_eq!(missing.kind, Kind::NotFound);
        assert_eq!(missing.why, "no record 7 in the results log");
        let query = list(&log, ["sincce=3"], "/x").await.expect_err("a refusal");
        assert_eq!(query.kind, Kind::BadRequest);
        assert_eq!(latest(&log).await, Ok(None));
        assert_eq!(list(&log, Vec::<String>::new(), "/x").await, Ok(Vec::new()));
    }

    /// The reads the OPC UA methods make by number: an id past SQLite's is no record and
    /// nothing follows it, not the log's failure (5.00, `BadResourceUnavailable`).
    #[tokio::test]
    async fn records_by_number_and_after_one() {
        let dir = ScratchDir::new("reads-after");
        let log = ResultsLog::open(&dir.path().join("log.db")).expect("log");
        for n in 0..3 {
            log.append(crate::api::record::tests::numbered_record(n * 1000, "PKG"))
                .expect("append");
        }
        let ids = |records: Vec<Record>| records.iter().map(|r| r.id).collect::<Vec<_>>();
        assert_eq!(record(&log, 2).await.map(|r| r.id), Ok(2));
        assert_eq!(
            record(&log, 0).await.expect_err("none").kind,
            Kind::NotFound
        );
        let past = record(&log, u64::MAX).await.expect_err("none");
        assert_eq!(past.kind, Kind::NotFound, "{}", past.why);
        assert_eq!(
            past.why,
            format!("no record {} in the results log", u64::MAX)
        );
        assert_eq!(after(&log, 0, None, 10).await.map(ids), Ok(vec![1, 2, 3]));
        assert_eq!(after(&log, 1, None, 1).await.map(ids), Ok(vec![2]));
        let second = Some(UtcTime {
            unix_ms: 1_795_734_230_000,
        });
        assert_eq!(after(&log, 0, second, 10).await.map(ids), Ok(vec![2, 3]));
        assert_eq!(
            after(&log, u64::MAX, None, 10).await.map(ids),
            Ok(Vec::new())
        );
    }
}
