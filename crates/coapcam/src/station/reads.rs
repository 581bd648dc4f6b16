//! The results log's read API, written once for its two front ends (the CoAP resources in
//! `resources.rs`, the HTTP API in `http/`): the list, the newest record, one record, a
//! record's pictures, and the wording of every refusal. A front end reads its request into
//! these calls, maps a [`Refusal`]'s [`Kind`] to its own code (4.00/400, 4.04/404,
//! 5.00/500) and writes the document in its own format.

use super::log::{LogError, ResultsLog};
use crate::api::record::{EventRecord, Head, Record};
use crate::api::results::ListQuery;

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
    let id = parse_id(text)?;
    blocking(log, move |log| log.get(id))
        .await?
        .ok_or_else(|| no_record(id))
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
        // SQLite's ids are signed 64-bit: one past them is no record (it was a 500 with
        // the database's error).
        Ok(id) if id > i64::MAX as u64 => Err(no_record(id)),
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
}
