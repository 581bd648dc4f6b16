//! The JSON report of `bench transfer`: the configuration, the machine, the programs,
//! every run with the relay's counters, and every pair run. A benchmark's report is an
//! edge that writes arbitrary JSON, so it is built as `serde_json` values.

use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::thread;

use super::config::{
    BLOCK_BYTES, Config, FAIR_SHARE, Link, Mode, PAIR_LINK, RATE_50_MBIT, RELAY_QUEUE_LIMIT,
};
use super::runs::{Cell, PairCell, PairRun, RunResult};
use super::servers::Programs;
use crate::stats::Spread;

/// `uname -a`, or what /proc says.
fn machine() -> serde_json::Value {
    let uname = Command::new("uname")
        .arg("-a")
        .stderr(Stdio::null())
        .output()
        .ok()
        .filter(|o| o.status.success())
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_owned());
    let cpu = std::fs::read_to_string("/proc/cpuinfo").ok().and_then(|t| {
        t.lines()
            .find(|l| l.starts_with("model name"))
            .and_then(|l| l.split_once(':'))
            .map(|(_, v)| v.trim().to_owned())
    });
    let load = std::fs::read_to_string("/proc/loadavg")
        .ok()
        .map(|t| t.trim().to_owned());
    serde_json::json!({
        "uname": uname,
        "arch": std::env::consts::ARCH,
        "cpu": cpu,
        "cpus": thread::available_parallelism().map(usize::from).ok(),
        "loadavg_at_end": load,
    })
}

pub(super) fn report_json(
    args: &Config,
    links: &[Link],
    modes: &[Mode],
    cells: &[Cell],
    pair_cells: &[PairCell],
    programs: &Programs,
) -> serde_json::Value {
    let unix_s = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let program = |p: &Result<PathBuf, String>| match p {
        Ok(p) => serde_json::json!(p.display().to_string()),
        Err(_) => serde_json::Value::Null,
    };
    let pair = |p: &Result<(PathBuf, PathBuf), String>| program(&p.clone().map(|(c, _)| c));
    serde_json::json!({
        "benchmark": "coapcam bench transfer",
        "coapcam_version": env!("CARGO_PKG_VERSION"),
        "argv": std::env::args().collect::<Vec<_>>(),
        "finished_unix_s": unix_s,
        "timing": "wall time of the client's whole process, from its start to its exit as \
                   seen by polling every 1 ms; servers started before and are not timed; \
                   QUIC's time includes its handshake",
        "check": "every output compared byte for byte with the body; a run is ok when the \
                  client exited 0 within the cap and its output is bit-exact",
        "statistics": "median, min and max over the successful runs; the median of an even \
                       count is the mean of the middle two",
        "block_bytes": BLOCK_BYTES,
        "runs": args.runs,
        "slow_runs": args.slow_runs,
        "cap_s": args.cap.as_secs_f64(),
        "seed": args.seed,
        "machine": machine(),
        "programs": {
            "coapcam": programs.coapcam.display().to_string(),
            "libcoap_4_3_1_client": pair(&programs.libcoap431),
            "libcoap_4_3_5_client": pair(&programs.libcoap435),
            "quic_bench": program(&programs.quic),
        },
        "links": links.iter().map(|&l| link_json(l)).collect::<Vec<_>>(),
        "modes": modes.iter().map(|&m| serde_json::json!({
            "name": m.name(),
            "description": m.description(),
            "slow": m.slow(),
            "unavailable": programs.missing(m),
        })).collect::<Vec<_>>(),
        "cells": cells.iter().map(Cell::json).collect::<Vec<_>>(),
        "pairs": {
            "runs": args.pairs,
            "link": PAIR_LINK.name(),
            "rate_bytes_per_s": RATE_50_MBIT,
            "what": "two clients of one mode started together through one relay of the \
                     link to one server, per size and fast mode; none when --pairs is 0 \
                     or the link is not among --links",
            "shares": "each client address's payload bytes delivered by the relay \
                       (server to client) when the first client ended, over the sum of \
                       both; the relay knows clients by address, not by process, so a run \
                       gives its smaller and larger share",
            "holds_at_smaller_share": FAIR_SHARE,
            "utilisation": "2 x bytes over the later client's time, over the link's rate",
            "statistics": "median, min and max over the successful runs (both clients ok)",
            "cells": pair_cells.iter().map(PairCell::json).collect::<Vec<_>>(),
        },
    })
}

fn link_json(link: Link) -> serde_json::Value {
    let direction = link.shape().map(|(loss, delay, rate, _)| {
        serde_json::json!({
            "loss": loss, "delay_ms": delay.as_secs_f64() * 1e3, "jitter_ms": 0,
            "rate_bytes_per_s": rate,
        })
    });
    serde_json::json!({
        "name": link.name(),
        "description": link.description(),
        "relay": link.shape().is_some(),
        "up": direction,
        "down": direction,
        "queue_limit_datagrams": link.shape().map(|_| RELAY_QUEUE_LIMIT),
        "queue_bytes": link.shape().and_then(|s| s.3),
    })
}

impl RunResult {
    pub(super) fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "time_s": self.time_s.is_finite().then_some(self.time_s),
            "ok": self.ok,
            "exit": self.exit,
            "killed_at_cap": self.killed_at_cap,
            "bit_exact": self.bit_exact,
            "error": self.error,
            "relay": self.relay,
        })
    }
}

impl Cell {
    pub(super) fn json(&self) -> serde_json::Value {
        let stats = self.stats();
        let pick = |f: fn(Spread) -> f64| stats.map(f);
        let all_bit_exact =
            !self.runs.is_empty() && self.runs.iter().all(|r| r.bit_exact == Some(true));
        let times: Vec<Option<f64>> = self
            .runs
            .iter()
            .map(|r| r.time_s.is_finite().then_some(r.time_s))
            .collect();
        serde_json::json!({
            "link": self.link.name(),
            "bytes": self.size,
            "mode": self.mode.name(),
            "unavailable": self.skipped,
            "runs": self.runs.len(),
            "ok": self.ok_count(),
            "all_bit_exact": all_bit_exact,
            "median_s": pick(|s| s.median),
            "min_s": pick(|s| s.min),
            "max_s": pick(|s| s.max),
            "times_s": times,
            "ok_flags": self.runs.iter().map(|r| r.ok).collect::<Vec<_>>(),
            "results": self.runs.iter().map(RunResult::json).collect::<Vec<_>>(),
        })
    }
}

impl PairRun {
    pub(super) fn json(&self, size: u64) -> serde_json::Value {
        let finite = |x: f64| x.is_finite().then_some(x);
        let shares = self.shares();
        serde_json::json!({
            "ok": self.ok(),
            "clients": self.clients.iter().map(RunResult::json).collect::<Vec<_>>(),
            "delivered_at_first_end": self.delivered.iter().map(|(client, bytes)| {
                serde_json::json!({ "client": client.to_string(), "bytes": bytes })
            }).collect::<Vec<_>>(),
            "smaller_share": shares.map(|s| s.0),
            "larger_share": shares.map(|s| s.1),
            "holds": self.holds(),
            "later_s": finite(self.later_s()),
            "aggregate_bytes_per_s": finite(self.utilisation(size) * RATE_50_MBIT as f64),
            "utilisation": finite(self.utilisation(size)),
            "relay": self.relay,
        })
    }
}

impl PairCell {
    pub(super) fn json(&self) -> serde_json::Value {
        let shares = self.smaller_shares();
        let used = self.utilisation();
        serde_json::json!({
            "bytes": self.size,
            "mode": self.mode.name(),
            "unavailable": self.skipped,
            "runs": self.runs.len(),
            "ok": self.ok_runs().count(),
            "holding": self.holding(),
            "median_smaller_share": shares.map(|s| s.median),
            "min_smaller_share": shares.map(|s| s.min),
            "max_smaller_share": shares.map(|s| s.max),
            "median_utilisation": used.map(|s| s.median),
            "min_utilisation": used.map(|s| s.min),
            "max_utilisation": used.map(|s| s.max),
            "results": self.runs.iter().map(|r| r.json(self.size)).collect::<Vec<_>>(),
        })
    }
}
