//! The results log of a station (`/station/measurements`, docs/station.md) from the
//! client's side: the records a query selects, paged, and what one notification of
//! `/station/measurements/latest` holds.

use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use coap::{ContentFormat, OptionNumber};

use super::CamClient;
use super::timed::Watch;
use crate::api::paths::{EVENTS, LATEST, MEASUREMENTS as PATH};
use crate::api::record::{EventRecord, Record};
use crate::api::results::{ListQuery, MAX_LIST};

/// Records from a CBOR body: a list, one record, or `null` (no record yet).
pub fn decode<T: serde::de::DeserializeOwned>(body: &[u8]) -> anyhow::Result<T> {
    ciborium::from_reader(body).context("the results log's answer is not the CBOR of records")
}

/// Up to `limit` records newest first, as `q` selects (its `limit` ignored), asking page
/// after page of at most [`MAX_LIST`].
pub async fn list(client: &CamClient, q: &ListQuery, limit: usize) -> anyhow::Result<Vec<Record>> {
    pages(client, PATH, q, limit, |r: &Record| r.id).await
}

/// Up to `limit` events (`/station/events`) newest first, as `q`'s `since` and `before`
/// select, asking page after page of at most [`MAX_LIST`]; none from a station that
/// answers 4.04 (one from before events).
pub async fn events(
    client: &CamClient,
    q: &ListQuery,
    limit: usize,
) -> anyhow::Result<Vec<EventRecord>> {
    let q = ListQuery {
        since: q.since,
        before: q.before,
        ..ListQuery::default()
    };
    match pages(client, EVENTS, &q, limit, |e: &EventRecord| e.id).await {
        // A station from before events has no such resource: it has none.
        Err(e)
            if e.chain().any(|c| {
                c.downcast_ref::<super::ErrorResponse>()
                    .is_some_and(|r| r.response.code == coap::Code::NOT_FOUND)
            }) =>
        {
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
) -> anyhow::Result<Vec<T>> {
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
pub async fn follow(
    client: &CamClient,
    timeout: Duration,
    on_start: impl FnOnce(u64),
    mut on_record: impl FnMut(Record, usize, Duration) -> anyhow::Result<bool>,
) -> anyhow::Result<()> {
    let path = LATEST;
    let mut on_start = Some(on_start);
    let mut previous = Instant::now();
    let mut watch = Watch::start(client, path, Some(ContentFormat::CBOR), timeout).await?;
    // The newest id reported (at first: the newest when the observation began).
    let mut last: Option<u64> = None;
    let mut stop = false;
    loop {
        let response = super::check(&format!("GET {path}"), watch.next().await?)?;
        let observing = response.options.contains(OptionNumber::OBSERVE);
        let newest: Option<Record> = decode(&response.payload)?;
        let Some(from) = last else {
            let from = newest.as_ref().map_or(0, |r| r.id);
            if !observing {
                bail!("the server did not accept the observation of {path}");
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
            bail!("the server ended the observation of {path}");
        }
        if stop {
            return Ok(());
        }
    }
}
