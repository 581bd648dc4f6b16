//! Round trips remembered per server host between processes, as TCP's metrics cache
//! keeps them per destination address: each CLI process starts with a new endpoint that knows no round
//! trip, so a lost first CON waits ACK_TIMEOUT (2-3 s) where the path's estimate would
//! have retransmitted it after about 120 ms (20 ms links). A process that has measured a
//! server's round trip writes it into a small file; the next one to that server starts
//! from it ([`coap_net::Client::remember_rtt`]), until it measures its own.
//!
//! The file is `$XDG_CACHE_HOME/coapcam/rtt.json` (`~/.cache/coapcam/rtt.json` without
//! it): a JSON object from the server's IP address to its smoothed round trip, its
//! variation and when it was written (Unix seconds). The key is the address without the
//! port, as TCP's is: servers (and relays) on other ports of one host share the path.
//! A wrong estimate costs little: one too short sends the first CON once more than
//! needed (its timeout is at least the estimate plus 100 ms), one too long waits at
//! most what the estimate says instead of 2-3 s. At most [`MAX_ENTRIES`] servers are
//! kept (the least recently written go first); an entry older than [`MAX_AGE`] is
//! ignored, and so is a file that cannot be read or parsed (a warning in the debug log;
//! the next write replaces it). Writes go to a temporary file renamed over the old one,
//! so concurrent processes never read half a file (the last writer's entries win).
//! `COAPCAM_RTT_CACHE=off` turns it off (neither read nor written).

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use coap_net::Client;
use serde::{Deserialize, Serialize};

/// Hosts remembered at most.
pub const MAX_ENTRIES: usize = 64;

/// How long an entry is trusted: a round trip an hour old may describe another network.
pub const MAX_AGE: Duration = Duration::from_secs(3600);

/// The environment variable that turns the cache off (`off`, `0` or `no`).
pub const ENV: &str = "COAPCAM_RTT_CACHE";

/// One server's remembered round trip.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Entry {
    /// The smoothed round trip, microseconds.
    pub srtt_us: u64,
    /// Its variation, microseconds.
    pub rttvar_us: u64,
    /// When it was written, seconds since the Unix epoch.
    pub written_unix_s: u64,
}

/// The cache's file, or `None` when it is turned off or there is no home directory.
pub fn default_path() -> Option<PathBuf> {
    if std::env::var(ENV).is_ok_and(|v| matches!(v.trim(), "off" | "0" | "no" | "false")) {
        return None;
    }
    let base = match std::env::var_os("XDG_CACHE_HOME").filter(|v| !v.is_empty()) {
        Some(dir) => PathBuf::from(dir),
        None => PathBuf::from(std::env::var_os("HOME").filter(|v| !v.is_empty())?).join(".cache"),
    };
    Some(base.join("coapcam").join("rtt.json"))
}

/// The file's key of `server`: its IP address.
fn key(server: SocketAddr) -> String {
    server.ip().to_string()
}

fn unix_now() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// Every entry of the file at `path`; empty when it is missing or unreadable.
pub fn load(path: &Path) -> BTreeMap<String, Entry> {
    let text = match std::fs::read(path) {
        Ok(text) => text,
        Err(e) => {
            if e.kind() != std::io::ErrorKind::NotFound {
                tracing::debug!(path = %path.display(), error = %e, "round-trip cache not read");
            }
            return BTreeMap::new();
        }
    };
    serde_json::from_slice(&text).unwrap_or_else(|e| {
        tracing::debug!(path = %path.display(), error = %e, "round-trip cache ignored");
        BTreeMap::new()
    })
}

/// The remembered round trip of `server` in the file at `path`, if fresh at `now_unix_s`.
pub fn lookup(path: &Path, server: SocketAddr, now_unix_s: u64) -> Option<Entry> {
    let entry = *load(path).get(&key(server))?;
    let age = now_unix_s.saturating_sub(entry.written_unix_s);
    (age <= MAX_AGE.as_secs() && entry.srtt_us > 0).then_some(entry)
}

/// Writes `entry` for `server` into the file at `path`, keeping at most [`MAX_ENTRIES`]
/// (the oldest written go) and dropping stale ones.
pub fn store(path: &Path, server: SocketAddr, entry: Entry) -> std::io::Result<()> {
    let mut all = load(path);
    all.retain(|_, e| entry.written_unix_s.saturating_sub(e.written_unix_s) <= MAX_AGE.as_secs());
    all.insert(key(server), entry);
    while all.len() > MAX_ENTRIES {
        let oldest = all
            .iter()
            .min_by_key(|(_, e)| e.written_unix_s)
            .map(|(k, _)| k.clone());
        match oldest {
            Some(k) => all.remove(&k),
            None => break,
        };
    }
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    let tmp = path.with_extension(format!("json.{}.tmp", std::process::id()));
    let text = serde_json::to_vec_pretty(&all).map_err(std::io::Error::other)?;
    std::fs::write(&tmp, text)?;
    std::fs::rename(&tmp, path).inspect_err(|_| {
        let _ = std::fs::remove_file(&tmp);
    })
}

/// Starts `client`'s path to `server` from the remembered round trip, if the cache is on
/// and holds a fresh one.
pub fn seed(client: &Client, server: SocketAddr) {
    let Some(path) = default_path() else { return };
    if let Some(entry) = lookup(&path, server, unix_now()) {
        let _ = client.remember_rtt(server, Duration::from_micros(entry.srtt_us));
    }
}

/// Remembers what `client` measured of its path to `server`, if the cache is on and
/// there is an estimate; a failure to write is only logged (debug).
pub async fn save(client: &Client, server: SocketAddr) {
    let Some(path) = default_path() else { return };
    let Ok(Some(stats)) = client.path_stats(server).await else {
        return;
    };
    let Some(srtt) = stats.srtt else { return };
    let entry = Entry {
        srtt_us: srtt.as_micros() as u64,
        rttvar_us: stats.rttvar.as_micros() as u64,
        written_unix_s: unix_now(),
    };
    if let Err(e) = store(&path, server, entry) {
        tracing::debug!(path = %path.display(), error = %e, "round-trip cache not written");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("coapcam-rtt-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    fn entry(srtt_ms: u64, at: u64) -> Entry {
        Entry {
            srtt_us: srtt_ms * 1000,
            rttvar_us: 1000,
            written_unix_s: at,
        }
    }

    #[test]
    fn remembers_per_host_and_forgets_stale_ones() {
        let d = dir("per-server");
        let path = d.join("coapcam").join("rtt.json");
        let (a, b): (SocketAddr, SocketAddr) = (
            "127.0.0.1:5683".parse().unwrap(),
            "[::1]:5684".parse().unwrap(),
        );
        let a_other_port: SocketAddr = "127.0.0.1:6000".parse().unwrap();
        assert_eq!(lookup(&path, a, 1000), None, "no file yet");
        store(&path, a, entry(21, 1000)).unwrap();
        store(&path, b, entry(55, 1001)).unwrap();
        assert_eq!(lookup(&path, a, 1000), Some(entry(21, 1000)));
        assert_eq!(
            lookup(&path, a_other_port, 1000),
            Some(entry(21, 1000)),
            "per host"
        );
        assert_eq!(lookup(&path, b, 1002).map(|e| e.srtt_us), Some(55_000));
        // An hour and a second later it is stale.
        assert_eq!(lookup(&path, a, 1000 + 3601), None);
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn keeps_the_newest_64_and_ignores_a_broken_file() {
        let d = dir("bounded");
        std::fs::create_dir_all(&d).unwrap();
        let path = d.join("rtt.json");
        std::fs::write(&path, b"{ not json").unwrap();
        let a: SocketAddr = "10.0.0.1:5683".parse().unwrap();
        assert_eq!(lookup(&path, a, 10), None);
        for host in 0..70u8 {
            let server = SocketAddr::from(([10, 0, 0, host], 5683));
            store(&path, server, entry(20, 100 + u64::from(host))).unwrap();
        }
        let all = load(&path);
        assert_eq!(all.len(), MAX_ENTRIES);
        assert!(!all.contains_key("10.0.0.0"), "the oldest went first");
        assert!(all.contains_key("10.0.0.69"));
        let _ = std::fs::remove_dir_all(&d);
    }
}
