//! The results log of a station (`/station/measurements`, docs/station.md) from the
//! client's side: the records a query selects, paged, and what one notification of
//! `/station/measurements/latest` holds.

use std::time::{Duration, Instant};

use coap::{ContentFormat, OptionNumber};

use super::timed::{Watch, WatchError};
use super::{CallError, CamClient};
use crate::api::paths::{EVENTS, LATEST, MEASUREMENTS as PATH};
use crate::api::record::{EventRecord, Record};
use crate::api::results::{ListQuery, MAX_LIST};

/// The results log could not be read or followed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ResultsError {
    /// A request failed (transparent: the causes the command's exit status looks for
    /// are the [`CallError`]'s sources, not itself).
    #[error(transparent)]
    Call(#[from] CallError),
    /// The observation failed (transparent, as `Call`).
    #[error(transparent)]
    Watch(#[from] WatchError),
    /// An answer is not records.
    #[error("the results log's answer is not the CBOR of records")]
    Decode(#[source] ciborium::de::Error<std::io::Error>),
    /// The server answered without registering the observation.
    #[error("the server did not accept the observation of {0}")]
    NotAccepted(&'static str),
    /// The server ended the observation.
    #[error("the server ended the observation of {0}")]
    Ended(&'static str),
}

/// Records from a CBOR body: a list, one record, or `null` (no record yet).
pub fn decode<T: serde::de::DeserializeOwned>(body: &[u8]) -> Result<T, ResultsError> {
    ciborium::from_reader(body).map_err(ResultsError::Decode)
}

/// Up to `limit` records newest first, as `q` selects (its `limit` ignored), asking page
/// after page of at most [`MAX_LIST`].
pub async fn list(
    client: &CamClient,
    q: &ListQuery,
    limit: usize,
) -> Result<Vec<Record>, ResultsError> {
    pages(client, PATH, q, limit, |r: &Record| r.id).await
}

/// Up to `limit` events (`/station/events`) newest first, as `q`'s `since` and `before`
/// select, asking page after page of at most [`MAX_LIST`]; none from a station that
/// answers 4.04 (one from before events).
pub async fn events(
    client: &CamClient,
    q: &ListQuery,
    limit: usize,
) -> Result<Vec<EventRecord>, ResultsError> {
    let q = ListQuery {
        since: q.since,
        before: q.before,
        ..ListQuery::default()
    };
    match pages(client, EVENTS, &q, limit, |e: &EventRecord| e.id).await {
        // A station from before events has no such resource: it has none.
        Err(e) if matches!(&e, ResultsError::Call(c) if c.code() == Some(coap::Code::NOT_FOUND)) => {
            Ok(Vec::new())
        }
        other => other,
    }
}

/// Up to `limit` items of the list at `path`, newest first, page after page.
async fn pages<T: serde::de::DeserializeOwned>(
    client: &CamClient,
    path: &str,
    q: &ListQuery,
    limit: usize,
    id: impl Fn(&T) -> u64,
) -> Result<Vec<T>, ResultsError> {
    let mut out: Vec<T> = Vec::new();
    let mut page = q.clone();
    while out.len() < limit {
        page.limit = (limit - out.len()).min(MAX_LIST);
        let response = client
            .get_query(path, &page.items(), Some(ContentFormat::CBOR))
            .await?;
        let records: Vec<T> = decode(&response.payload)?;
        let Some(last) = records.last() else { break };
        page.before = Some(id(last));
        let full = records.len() == page.limit;
        out.extend(records);
        if !full || page.before == Some(1) {
            break;
        }
    }
    Ok(out)
}

/// Follows the results log: observes its newest record and reports
/// each record added after the registration once, in id order, fetching those appended
/// between two notifications (an observer is told the newest state, not every one).
///
/// The first answer must come within `timeout`; `on_start` gets the id the following
/// starts after, `on_record` each record with the notification's size and the time since
/// the previous record, until it says to stop (true) or the observation ends (an error).
/// An error of `on_record` ends it as that error, untouched.
pub async fn follow<E: From<ResultsError>>(
    client: &CamClient,
    timeout: Duration,
    on_start: impl FnOnce(u64),
    mut on_record: impl FnMut(Record, usize, Duration) -> Result<bool, E>,
) -> Result<(), E> {
    let path = LATEST;
    let mut on_start = Some(on_start);
    let mut previous = Instant::now();
    let mut watch = Watch::start(client, path, Some(ContentFormat::CBOR), timeout)
        .await
        .map_err(ResultsError::from)?;
    // The newest id reported (at first: the newest when the observation began).
    let mut last: Option<u64> = None;
    let mut stop = false;
    loop {
        let next = watch.next().await.map_err(ResultsError::from)?;
        let response = super::check(&format!("GET {path}"), next).map_err(ResultsError::from)?;
        let observing = response.options.contains(OptionNumber::OBSERVE);
        let newest: Option<Record> = decode(&response.payload)?;
        let Some(from) = last else {
            let from = newest.as_ref().map_or(0, |r| r.id);
            if !observing {
                return Err(ResultsError::NotAccepted(path).into());
            }
            if let Some(started) = on_start.take() {
                started(from);
            }
            last = Some(from);
            previous = Instant::now();
            continue;
        };
        if let Some(newest) = newest.filter(|r| r.id > from) {
            let mut records = Vec::new();
            if newest.id > from + 1 {
                let missed = ListQuery {
                    since: Some(from),
                    before: Some(newest.id),
                    ..ListQuery::default()
                };
                let wanted = usize::try_from(newest.id - from - 1).unwrap_or(usize::MAX);
                let mut got = list(client, &missed, wanted).await?;
                got.reverse();
                records = got;
            }
            records.push(newest);
            for record in records {
                let elapsed = previous.elapsed();
                previous = Instant::now();
                last = Some(record.id);
                if on_record(record, response.payload.len(), elapsed)? {
                    stop = true;
                    break;
                }
            }
        }
        if !observing {
            return Err(ResultsError::Ended(path).into());
        }
        if stop {
            return Ok(());
        }
    }
}
