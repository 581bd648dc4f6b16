//! The results log's query (`/station/measurements?since=..`, docs/station.md): the one
//! type, its Uri-Query items and their reading, for the client that asks and every front
//! end (CoAP, HTTP) of the log that answers.

use super::record::UtcTime;

/// The most records one list returns.
pub const MAX_LIST: usize = 1000;

/// Which records a list of the results log returns, newest first.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ListQuery {
    /// Only records with a larger id.
    pub since: Option<u64>,
    /// Only records with a smaller id (paging back: the smallest id of the last page).
    pub before: Option<u64>,
    /// At most this many (1 to [`MAX_LIST`]).
    pub limit: usize,
    /// Only records with a code of exactly this text.
    pub code: Option<String>,
    /// Only records measured at this time or later.
    pub from: Option<UtcTime>,
    /// Only records measured before this time.
    pub to: Option<UtcTime>,
}

impl Default for ListQuery {
    fn default() -> Self {
        Self {
            since: None,
            before: None,
            limit: 50,
            code: None,
            from: None,
            to: None,
        }
    }
}

impl ListQuery {
    /// The Uri-Query items that ask for this query (what [`ListQuery::parse`] reads).
    pub fn items(&self) -> Vec<String> {
        let mut items = Vec::new();
        if let Some(since) = self.since {
            items.push(format!("since={since}"));
        }
        if let Some(before) = self.before {
            items.push(format!("before={before}"));
        }
        items.push(format!("limit={}", self.limit.clamp(1, MAX_LIST)));
        if let Some(code) = &self.code {
            items.push(format!("code={code}"));
        }
        if let Some(from) = self.from {
            items.push(format!("from={from}"));
        }
        if let Some(to) = self.to {
            items.push(format!("to={to}"));
        }
        items
    }

    /// The records `items` (a request's Uri-Query) select; why not, for a bad item.
    /// `path` names the resource in the refusal of an unknown item.
    pub fn parse<S: AsRef<str>>(
        items: impl IntoIterator<Item = S>,
        path: &str,
    ) -> Result<Self, String> {
        let mut q = Self::default();
        let mut seen: Vec<String> = Vec::new();
        for item in items {
            let item = item.as_ref();
            let (key, value) = item.split_once('=').unwrap_or((item, ""));
            if seen.iter().any(|k| k == key) {
                return Err(format!("{key} is given twice"));
            }
            seen.push(key.to_owned());
            let id = |what: &str| {
                value
                    .parse::<u64>()
                    .map_err(|_| format!("{key}={value}: {what} is a record id, a whole number"))
            };
            match key {
                "since" => q.since = Some(id("since")?),
                "before" => q.before = Some(id("before")?),
                "limit" => {
                    q.limit = match value.parse::<usize>() {
                        Ok(n @ 1..=MAX_LIST) => n,
                        _ => {
                            return Err(format!(
                                "limit={value}: the most records to give, from 1 to {MAX_LIST}"
                            ));
                        }
                    };
                }
                "code" if !value.is_empty() => q.code = Some(value.to_owned()),
                "from" => {
                    q.from = Some(UtcTime::parse(value).map_err(|e| format!("from={value}: {e}"))?)
                }
                "to" => q.to = Some(UtcTime::parse(value).map_err(|e| format!("to={value}: {e}"))?),
                "code" => return Err("code= needs the code's text".into()),
                _ => {
                    return Err(format!(
                        "unknown query item {key}: {path} takes since=ID, before=ID, limit=N (1-{MAX_LIST}, default {}), code=TEXT, from=TIME and to=TIME",
                        Self::default().limit
                    ));
                }
            }
        }
        Ok(q)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_query_selects_and_refuses_with_the_reason() {
        assert_eq!(
            ListQuery::parse([""; 0], "/station/measurements"),
            Ok(ListQuery::default())
        );
        let q = ListQuery::parse(
            ["since=3", "limit=2", "code=PKG-1", "before=9"],
            "/station/measurements",
        )
        .expect("valid");
        assert_eq!(
            q,
            ListQuery {
                since: Some(3),
                before: Some(9),
                limit: 2,
                code: Some("PKG-1".into()),
                ..ListQuery::default()
            }
        );
        for bad in [
            "since=-1",
            "since=x",
            "limit=0",
            "limit=1001",
            "code=",
            "colour=red",
            "before=",
            "from=yesterday",
            "to=2026-11-27",
        ] {
            let why = ListQuery::parse([bad], "/station/measurements").expect_err(bad);
            let key = bad.split('=').next().unwrap_or(bad);
            assert!(why.contains(key), "{why}");
        }
        assert!(ListQuery::parse(["limit=1", "limit=2"], "/station/measurements").is_err());
    }

    #[test]
    fn the_items_of_a_query_read_back_as_the_query() {
        let q = ListQuery {
            since: Some(3),
            before: Some(90),
            limit: 20,
            code: Some("PKG-1".into()),
            from: Some(UtcTime::parse("2026-11-27T10:00:00Z").expect("time")),
            to: Some(UtcTime::parse("2026-11-28T10:00:00Z").expect("time")),
        };
        assert_eq!(ListQuery::parse(q.items(), "/x"), Ok(q));
        let over = ListQuery {
            limit: MAX_LIST + 1,
            ..ListQuery::default()
        };
        assert_eq!(
            ListQuery::parse(over.items(), "/x").map(|q| q.limit),
            Ok(MAX_LIST)
        );
    }
}
