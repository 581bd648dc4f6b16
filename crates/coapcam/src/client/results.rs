//! The results log of a station (`/station/measurements`, docs/station.md) from the
//! client's side: the records a query selects, paged, and what one notification of
//! `/station/measurements/latest` holds.

use anyhow::Context as _;
use coap::ContentFormat;

use super::CamClient;
use crate::station::log::{ListQuery, MAX_LIST};
use crate::station::record::Record;

/// The list's path.
pub const PATH: &str = "/station/measurements";

/// The newest record's path (observable).
pub const LATEST: &str = "/station/measurements/latest";

/// The Uri-Query items of `q`.
pub fn query_items(q: &ListQuery) -> Vec<String> {
    let mut items = Vec::new();
    if let Some(since) = q.since {
        items.push(format!("since={since}"));
    }
    if let Some(before) = q.before {
        items.push(format!("before={before}"));
    }
    items.push(format!("limit={}", q.limit.clamp(1, MAX_LIST)));
    if let Some(code) = &q.code {
        items.push(format!("code={code}"));
    }
    items
}

/// Records from a CBOR body: a list, one record, or `null` (no record yet).
pub fn decode<T: serde::de::DeserializeOwned>(body: &[u8]) -> anyhow::Result<T> {
    ciborium::from_reader(body).context("the results log's answer is not the CBOR of records")
}

/// Up to `limit` records newest first, as `q` selects (its `limit` ignored), asking page
/// after page of at most [`MAX_LIST`].
pub async fn list(client: &CamClient, q: &ListQuery, limit: usize) -> anyhow::Result<Vec<Record>> {
    let mut out: Vec<Record> = Vec::new();
    let mut page = q.clone();
    while out.len() < limit {
        page.limit = (limit - out.len()).min(MAX_LIST);
        let response = client
            .get_query(PATH, &query_items(&page), Some(ContentFormat::CBOR))
            .await?;
        let records: Vec<Record> = decode(&response.payload)?;
        let Some(last) = records.last() else { break };
        page.before = Some(last.id);
        let full = records.len() == page.limit;
        out.extend(records);
        if !full || page.before == Some(1) {
            break;
        }
    }
    Ok(out)
}
