//! The runs of `bench transfer`: a client process (or two at once) timed from its start
//! to its exit, its output checked against the body, and what the runs of one table cell
//! (or one pair row) say together.

use std::cmp::Reverse;
use std::fs::File;
use std::net::SocketAddr;
use std::path::Path;
use std::process::{Command, ExitStatus, Stdio};
use std::time::Duration;

use anyhow::Context as _;
use netem::{Counters, LinkConfig};

use super::body::{Body, difference};
use super::config::{FAIR_SHARE, Link, Mode, RATE_50_MBIT};
use super::relay::Relay;
use super::servers::{Programs, Target, client_command};
use crate::process::{Proc, tail, wait_all_capped};
use crate::stats::Spread;

/// One run's result.
#[derive(Debug, Clone)]
pub(super) struct RunResult {
    /// Client process wall time, seconds (until it was killed, for a run past the cap).
    pub(super) time_s: f64,
    pub(super) ok: bool,
    /// The exit code; `None` when killed at the cap or by a signal, or not started.
    pub(super) exit: Option<i32>,
    pub(super) killed_at_cap: bool,
    /// Whether the output equals the body; `None` if the client failed before that
    /// mattered (or it wrote nothing).
    pub(super) bit_exact: Option<bool>,
    pub(super) error: Option<String>,
    pub(super) relay: Option<Counters>,
}

impl RunResult {
    pub(super) fn failed(error: String) -> Self {
        Self {
            time_s: f64::NAN,
            ok: false,
            exit: None,
            killed_at_cap: false,
            bit_exact: None,
            error: Some(error),
            relay: None,
        }
    }
}

/// A client to run: its command, the file it writes the body into and the log of its
/// standard error.
pub(super) struct Client<'a> {
    pub(super) cmd: Command,
    pub(super) out: &'a Path,
    pub(super) log: &'a Path,
}

/// Runs one client and checks its output.
pub(super) fn time_client(
    client: Client<'_>,
    name: &str,
    cap: Duration,
    body: &[u8],
) -> anyhow::Result<RunResult> {
    time_clients(vec![client], name, cap, body, || {})?
        .pop()
        .context("a client without a result")
}

/// Starts `clients` one right after the other, waits for all of them (each timed from its
/// own start) and checks each one's output against `body`; one result per client, in
/// order. `on_first_end` is called once, as soon as the first of them is seen to end (its
/// exit, or its kill at the cap). A client that cannot start fails the run of every one
/// (those started are killed).
pub(super) fn time_clients(
    clients: Vec<Client<'_>>,
    name: &str,
    cap: Duration,
    body: &[u8],
    on_first_end: impl FnOnce(),
) -> anyhow::Result<Vec<RunResult>> {
    let count = clients.len();
    let mut procs = Vec::with_capacity(count);
    let mut files = Vec::with_capacity(count);
    for (i, Client { mut cmd, out, log }) in clients.into_iter().enumerate() {
        let _ = std::fs::remove_file(out);
        let stderr = File::create(log).with_context(|| format!("creating {}", log.display()))?;
        cmd.stdout(Stdio::null()).stderr(stderr);
        match Proc::spawn(cmd, name) {
            Ok(proc) => procs.push(proc),
            Err(e) => {
                let why = crate::error_text(&e);
                let result = |j| {
                    if j == i {
                        RunResult::failed(why.clone())
                    } else {
                        RunResult::failed(format!("another client of the run failed: {why}"))
                    }
                };
                return Ok((0..count).map(result).collect());
            }
        }
        files.push((out, log));
    }
    let ended = wait_all_capped(&mut procs, cap, on_first_end)?;
    drop(procs);
    Ok(ended
        .into_iter()
        .zip(files)
        .map(|((status, elapsed), (out, log))| client_result(status, elapsed, cap, out, log, body))
        .collect())
}

/// The result of a client that ended with `status` (`None`: killed at the cap) `elapsed`
/// after its start: its output in `out` compared with `body` (and removed), the reason of a
/// failure from its `log`.
pub(super) fn client_result(
    status: Option<ExitStatus>,
    elapsed: Duration,
    cap: Duration,
    out: &Path,
    log: &Path,
    body: &[u8],
) -> RunResult {
    let wrote = out.exists();
    let diff = wrote.then(|| difference(out, body)).flatten();
    let bit_exact = wrote.then_some(diff.is_none());
    let _ = std::fs::remove_file(out);
    let mut result = RunResult {
        time_s: elapsed.as_secs_f64(),
        ok: false,
        exit: status.and_then(|s| s.code()),
        killed_at_cap: status.is_none(),
        bit_exact,
        error: None,
        relay: None,
    };
    result.error = match status {
        None => Some(format!(
            "still running after the cap of {} s, killed",
            cap.as_secs_f64()
        )),
        Some(s) if !s.success() => Some(format!("exited with {s}: {}", tail(log))),
        Some(_) if !wrote => Some("exited with 0 but wrote no output".into()),
        Some(_) => diff.map(|d| format!("exited with 0 but the {d}")),
    };
    result.ok = result.error.is_none();
    result
}

/// One (link, size, mode) and its runs.
pub(super) struct Cell {
    pub(super) link: Link,
    pub(super) size: u64,
    pub(super) mode: Mode,
    /// Why it was not run (the mode is unavailable or its server did not start).
    pub(super) skipped: Option<String>,
    pub(super) runs: Vec<RunResult>,
}

impl Cell {
    pub(super) fn ok_times(&self) -> Vec<f64> {
        self.runs
            .iter()
            .filter(|r| r.ok)
            .map(|r| r.time_s)
            .collect()
    }

    /// Median, min and max of the successful runs.
    pub(super) fn stats(&self) -> Option<Spread> {
        Spread::of(&self.ok_times())
    }

    pub(super) fn ok_count(&self) -> usize {
        self.runs.iter().filter(|r| r.ok).count()
    }

    /// The 95th percentile (nearest rank) of the successful runs.
    pub(super) fn p95(&self) -> Option<f64> {
        crate::stats::percentile(&self.ok_times(), 0.95)
    }
}

/// One pair run: two clients of one mode at once through one relay of [`PAIR_LINK`].
pub(super) struct PairRun {
    /// Both clients, in the order they were started.
    pub(super) clients: Vec<RunResult>,
    /// The payload bytes the relay had delivered to each client address when the first
    /// client ended, the most first.
    pub(super) delivered: Vec<(SocketAddr, u64)>,
    pub(super) relay: Counters,
}

impl PairRun {
    /// Both clients succeeded.
    pub(super) fn ok(&self) -> bool {
        self.clients.iter().all(|c| c.ok)
    }

    /// The smaller and the larger client's share of the bytes delivered to both when the
    /// first ended; `None` if none was delivered.
    pub(super) fn shares(&self) -> Option<(f64, f64)> {
        let total: u64 = self.delivered.iter().map(|&(_, n)| n).sum();
        let most = self.delivered.first()?.1;
        // A client that had been delivered nothing yet is not in the count.
        let least = if self.delivered.len() < self.clients.len() {
            0
        } else {
            self.delivered.last()?.1
        };
        (total > 0).then(|| (least as f64 / total as f64, most as f64 / total as f64))
    }

    pub(super) fn holds(&self) -> bool {
        self.shares()
            .is_some_and(|(smaller, _)| smaller >= FAIR_SHARE)
    }

    /// The later client's time, seconds (NaN when the clients did not start).
    pub(super) fn later_s(&self) -> f64 {
        self.clients
            .iter()
            .map(|c| c.time_s)
            .fold(f64::NAN, f64::max)
    }

    /// Both bodies of `size` bytes over the later client's time, as a fraction of the
    /// link's rate.
    pub(super) fn utilisation(&self, size: u64) -> f64 {
        let bytes = (self.clients.len() as u64 * size) as f64;
        bytes / self.later_s() / RATE_50_MBIT as f64
    }

    /// The progress line's summary: both times, the shares, the utilisation and the
    /// failures.
    pub(super) fn summary(&self, size: u64) -> String {
        let times: Vec<String> = self
            .clients
            .iter()
            .map(|c| format!("{:.3} s", c.time_s))
            .collect();
        let shares = self.shares().map_or_else(
            || "no bytes delivered".to_owned(),
            |(smaller, larger)| {
                format!(
                    "shares {:.1} % and {:.1} %",
                    smaller * 100.0,
                    larger * 100.0
                )
            },
        );
        let errors: Vec<String> = self
            .clients
            .iter()
            .enumerate()
            .filter_map(|(i, c)| Some(format!("client {}: {}", i + 1, c.error.as_ref()?)))
            .collect();
        let outcome = if errors.is_empty() {
            "ok".to_owned()
        } else {
            format!("FAILED: {}", errors.join("; "))
        };
        format!(
            "{}, {shares}, link {:.0} %: {outcome}",
            times.join(" and "),
            self.utilisation(size) * 100.0
        )
    }
}

/// The pair runs of one (size, mode).
pub(super) struct PairCell {
    pub(super) size: u64,
    pub(super) mode: Mode,
    /// Why it was not run (the mode is unavailable or its server did not start).
    pub(super) skipped: Option<String>,
    pub(super) runs: Vec<PairRun>,
}

impl PairCell {
    pub(super) fn ok_runs(&self) -> impl Iterator<Item = &PairRun> {
        self.runs.iter().filter(|r| r.ok())
    }

    /// Median, min and max of the smaller shares of the successful runs.
    pub(super) fn smaller_shares(&self) -> Option<Spread> {
        let shares: Vec<f64> = self
            .ok_runs()
            .map(|r| r.shares().map_or(0.0, |s| s.0))
            .collect();
        Spread::of(&shares)
    }

    /// Median, min and max of the link utilisation of the successful runs.
    pub(super) fn utilisation(&self) -> Option<Spread> {
        let used: Vec<f64> = self.ok_runs().map(|r| r.utilisation(self.size)).collect();
        Spread::of(&used)
    }

    /// The successful runs that held.
    pub(super) fn holding(&self) -> usize {
        self.ok_runs().filter(|r| r.holds()).count()
    }
}

/// Two clients of `mode` fetching `body` from `target` at once through one relay of
/// `config`; the relay's delivered bytes are read when the first client ends.
pub(super) fn run_pair(
    programs: &Programs,
    mode: Mode,
    target: &Target,
    config: LinkConfig,
    body: &Body,
    cap: Duration,
    work: &Path,
) -> anyhow::Result<PairRun> {
    let relay = Relay::start(target.addr, config)?;
    let outs = [work.join("out-1"), work.join("out-2")];
    let logs = [work.join("client-1.log"), work.join("client-2.log")];
    let mut clients = Vec::new();
    for (out, log) in outs.iter().zip(&logs) {
        let cmd = client_command(programs, mode, relay.addr, target, out, cap)?;
        clients.push(Client { cmd, out, log });
    }
    let mut delivered = Vec::new();
    let clients = time_clients(clients, mode.name(), cap, &body.bytes, || {
        delivered = relay.delivered.snapshot().into_iter().collect();
    })?;
    delivered.sort_unstable_by_key(|&(client, bytes)| (Reverse(bytes), client));
    Ok(PairRun {
        clients,
        delivered,
        relay: relay.finish()?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use netem::DirCounters;
    use std::net::Ipv4Addr;

    #[test]
    fn pair_shares_are_of_the_bytes_delivered_when_the_first_client_ended() {
        let ok = RunResult {
            time_s: 2.0,
            ok: true,
            exit: Some(0),
            killed_at_cap: false,
            bit_exact: Some(true),
            error: None,
            relay: None,
        };
        let addr = |port| SocketAddr::from((Ipv4Addr::LOCALHOST, port));
        let mut pair = PairRun {
            clients: vec![ok.clone(), RunResult { time_s: 2.5, ..ok }],
            delivered: vec![(addr(1), 600), (addr(2), 400)],
            relay: Counters {
                seed: 0,
                elapsed_ms: 2500,
                clients: 2,
                clients_refused: 0,
                up: DirCounters::default(),
                down: DirCounters::default(),
            },
        };
        assert_eq!(pair.shares(), Some((0.4, 0.6)));
        assert!(pair.holds() && pair.ok());
        assert_eq!(pair.later_s(), 2.5);
        // 2 x 6,250,000 bytes in 2.5 s: 80 % of 50 Mbit/s.
        assert!((pair.utilisation(6_250_000) - 0.8).abs() < 1e-12);
        pair.delivered = vec![(addr(1), 900), (addr(2), 100)];
        assert!(!pair.holds());
        // A client that had nothing yet.
        pair.delivered = vec![(addr(2), 500)];
        assert_eq!(pair.shares(), Some((0.0, 1.0)));
        pair.delivered.clear();
        assert_eq!(pair.shares(), None);
        assert!(!pair.holds());
    }
}
