//! The JSON report of `bench transfer`: the configuration, the machine, the programs,
//! every run with the relay's counters, and every pair run, as serde types borrowing the
//! results. A time that is not a number (a run that never started) is `null`.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::thread;

use netem::Counters;
use serde::Serialize;

use super::config::{
    BLOCK_BYTES, Config, FAIR_SHARE, Link, PAIR_LINK, RATE_50_MBIT, RELAY_QUEUE_LIMIT,
};
use super::runs::{Cell, PairCell, PairRun, RunResult};
use super::servers::Programs;
use crate::stats::Spread;

/// The whole report.
#[derive(Serialize)]
pub(super) struct ReportJson<'a> {
    benchmark: &'static str,
    coapcam_version: &'static str,
    argv: Vec<String>,
    finished_unix_s: u64,
    timing: &'static str,
    check: &'static str,
    statistics: &'static str,
    block_bytes: u32,
    runs: u32,
    slow_runs: u32,
    cap_s: f64,
    seed: u64,
    machine: Machine,
    programs: ProgramsJson,
    links: Vec<LinkJson>,
    modes: Vec<ModeJson<'a>>,
    cells: Vec<CellJson<'a>>,
    pairs: PairsJson<'a>,
}

/// `uname -a`, or what /proc says.
#[derive(Serialize)]
struct Machine {
    uname: Option<String>,
    arch: &'static str,
    cpu: Option<String>,
    cpus: Option<usize>,
    loadavg_at_end: Option<String>,
}

impl Machine {
    fn now() -> Self {
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
        Self {
            uname,
            arch: std::env::consts::ARCH,
            cpu,
            cpus: thread::available_parallelism().map(usize::from).ok(),
            loadavg_at_end: load,
        }
    }
}

#[derive(Serialize)]
struct ProgramsJson {
    coapcam: String,
    libcoap_4_3_1_client: Option<String>,
    libcoap_4_3_5_client: Option<String>,
    quic_bench: Option<String>,
}

#[derive(Serialize)]
struct LinkJson {
    name: &'static str,
    description: &'static str,
    relay: bool,
    up: Option<DirectionJson>,
    down: Option<DirectionJson>,
    queue_limit_datagrams: Option<usize>,
    queue_bytes: Option<usize>,
}

#[derive(Serialize, Clone, Copy)]
struct DirectionJson {
    loss: f64,
    delay_ms: f64,
    jitter_ms: u32,
    rate_bytes_per_s: Option<u64>,
}

impl LinkJson {
    fn of(link: Link) -> Self {
        let shape = link.shape();
        let direction = shape.map(|(loss, delay, rate, _)| DirectionJson {
            loss,
            delay_ms: delay.as_secs_f64() * 1e3,
            jitter_ms: 0,
            rate_bytes_per_s: rate,
        });
        Self {
            name: link.name(),
            description: link.description(),
            relay: shape.is_some(),
            up: direction,
            down: direction,
            queue_limit_datagrams: shape.map(|_| RELAY_QUEUE_LIMIT),
            queue_bytes: shape.and_then(|s| s.3),
        }
    }
}

#[derive(Serialize)]
struct ModeJson<'a> {
    name: &'static str,
    description: &'static str,
    slow: bool,
    unavailable: Option<&'a str>,
}

/// One run; its time is `null` when it is not a number.
#[derive(Serialize)]
struct RunJson<'a> {
    time_s: Option<f64>,
    ok: bool,
    exit: Option<i32>,
    killed_at_cap: bool,
    bit_exact: Option<bool>,
    error: Option<&'a str>,
    relay: Option<&'a Counters>,
}

impl<'a> RunJson<'a> {
    fn of(r: &'a RunResult) -> Self {
        Self {
            time_s: finite(r.time_s),
            ok: r.ok,
            exit: r.exit,
            killed_at_cap: r.killed_at_cap,
            bit_exact: r.bit_exact,
            error: r.error.as_deref(),
            relay: r.relay.as_ref(),
        }
    }
}

#[derive(Serialize)]
struct CellJson<'a> {
    link: &'static str,
    bytes: u64,
    mode: &'static str,
    unavailable: Option<&'a str>,
    runs: usize,
    ok: usize,
    all_bit_exact: bool,
    median_s: Option<f64>,
    min_s: Option<f64>,
    p95_s: Option<f64>,
    max_s: Option<f64>,
    times_s: Vec<Option<f64>>,
    ok_flags: Vec<bool>,
    results: Vec<RunJson<'a>>,
}

impl<'a> CellJson<'a> {
    fn of(c: &'a Cell) -> Self {
        let stats = c.stats();
        let pick = |f: fn(Spread) -> f64| stats.map(f);
        Self {
            link: c.link.name(),
            bytes: c.size,
            mode: c.mode.name(),
            unavailable: c.skipped.as_deref(),
            runs: c.runs.len(),
            ok: c.ok_count(),
            all_bit_exact: !c.runs.is_empty() && c.runs.iter().all(|r| r.bit_exact == Some(true)),
            median_s: pick(|s| s.median),
            min_s: pick(|s| s.min),
            p95_s: c.p95(),
            max_s: pick(|s| s.max),
            times_s: c.runs.iter().map(|r| finite(r.time_s)).collect(),
            ok_flags: c.runs.iter().map(|r| r.ok).collect(),
            results: c.runs.iter().map(RunJson::of).collect(),
        }
    }
}

#[derive(Serialize)]
struct PairsJson<'a> {
    runs: u32,
    link: &'static str,
    rate_bytes_per_s: u64,
    what: &'static str,
    shares: &'static str,
    holds_at_smaller_share: f64,
    utilisation: &'static str,
    statistics: &'static str,
    cells: Vec<PairCellJson<'a>>,
}

#[derive(Serialize)]
struct Delivered {
    client: String,
    bytes: u64,
}

#[derive(Serialize)]
struct PairRunJson<'a> {
    ok: bool,
    clients: Vec<RunJson<'a>>,
    delivered_at_first_end: Vec<Delivered>,
    smaller_share: Option<f64>,
    larger_share: Option<f64>,
    holds: bool,
    later_s: Option<f64>,
    aggregate_bytes_per_s: Option<f64>,
    utilisation: Option<f64>,
    relay: &'a Counters,
}

impl<'a> PairRunJson<'a> {
    fn of(r: &'a PairRun, size: u64) -> Self {
        let shares = r.shares();
        let delivered = |&(client, bytes): &(SocketAddr, u64)| Delivered {
            client: client.to_string(),
            bytes,
        };
        Self {
            ok: r.ok(),
            clients: r.clients.iter().map(RunJson::of).collect(),
            delivered_at_first_end: r.delivered.iter().map(delivered).collect(),
            smaller_share: shares.map(|s| s.0),
            larger_share: shares.map(|s| s.1),
            holds: r.holds(),
            later_s: finite(r.later_s()),
            aggregate_bytes_per_s: finite(r.utilisation(size) * RATE_50_MBIT as f64),
            utilisation: finite(r.utilisation(size)),
            relay: &r.relay,
        }
    }
}

#[derive(Serialize)]
struct PairCellJson<'a> {
    bytes: u64,
    mode: &'static str,
    unavailable: Option<&'a str>,
    runs: usize,
    ok: usize,
    holding: usize,
    median_smaller_share: Option<f64>,
    min_smaller_share: Option<f64>,
    max_smaller_share: Option<f64>,
    median_utilisation: Option<f64>,
    min_utilisation: Option<f64>,
    max_utilisation: Option<f64>,
    results: Vec<PairRunJson<'a>>,
}

impl<'a> PairCellJson<'a> {
    fn of(c: &'a PairCell) -> Self {
        let shares = c.smaller_shares();
        let used = c.utilisation();
        Self {
            bytes: c.size,
            mode: c.mode.name(),
            unavailable: c.skipped.as_deref(),
            runs: c.runs.len(),
            ok: c.ok_runs().count(),
            holding: c.holding(),
            median_smaller_share: shares.map(|s| s.median),
            min_smaller_share: shares.map(|s| s.min),
            max_smaller_share: shares.map(|s| s.max),
            median_utilisation: used.map(|s| s.median),
            min_utilisation: used.map(|s| s.min),
            max_utilisation: used.map(|s| s.max),
            results: c.runs.iter().map(|r| PairRunJson::of(r, c.size)).collect(),
        }
    }
}

/// `x` if it is a number.
fn finite(x: f64) -> Option<f64> {
    x.is_finite().then_some(x)
}

/// The report of `cells` and `pair_cells` run with `config` by `programs`.
pub(super) fn report_json<'a>(
    config: &Config,
    cells: &'a [Cell],
    pair_cells: &'a [PairCell],
    programs: &'a Programs,
) -> ReportJson<'a> {
    let unix_s = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let program = |p: &Result<PathBuf, String>| p.as_ref().ok().map(|p| p.display().to_string());
    let client = |p: &Result<(PathBuf, PathBuf), String>| {
        p.as_ref().ok().map(|(c, _)| c.display().to_string())
    };
    ReportJson {
        benchmark: "coapcam bench transfer",
        coapcam_version: env!("CARGO_PKG_VERSION"),
        argv: std::env::args().collect(),
        finished_unix_s: unix_s,
        timing: "wall time of the client's whole process, from its start to its exit as \
                 seen by polling every 1 ms; servers started before and are not timed; \
                 QUIC's time includes its handshake",
        check: "every output compared byte for byte with the body; a run is ok when the \
                client exited 0 within the cap and its output is bit-exact",
        statistics: "median, min and max over the successful runs; the median of an even \
                     count is the mean of the middle two",
        block_bytes: BLOCK_BYTES,
        runs: config.runs,
        slow_runs: config.slow_runs,
        cap_s: config.cap.as_secs_f64(),
        seed: config.seed,
        machine: Machine::now(),
        programs: ProgramsJson {
            coapcam: programs.coapcam.display().to_string(),
            libcoap_4_3_1_client: client(&programs.libcoap431),
            libcoap_4_3_5_client: client(&programs.libcoap435),
            quic_bench: program(&programs.quic),
        },
        links: config.links.iter().map(|&l| LinkJson::of(l)).collect(),
        modes: config
            .modes
            .iter()
            .map(|&m| ModeJson {
                name: m.name(),
                description: m.description(),
                slow: m.slow(),
                unavailable: programs.missing(m),
            })
            .collect(),
        cells: cells.iter().map(CellJson::of).collect(),
        pairs: PairsJson {
            runs: config.pairs,
            link: PAIR_LINK.name(),
            rate_bytes_per_s: RATE_50_MBIT,
            what: "two clients of one mode started together through one relay of the link \
                   to one server, per size and fast mode; none when --pairs is 0 or the link \
                   is not among --links",
            shares: "each client address's payload bytes delivered by the relay (server to \
                     client) when the first client ended, over the sum of both; the relay \
                     knows clients by address, not by process, so a run gives its smaller \
                     and larger share",
            holds_at_smaller_share: FAIR_SHARE,
            utilisation: "2 x bytes over the later client's time, over the link's rate",
            statistics: "median, min and max over the successful runs (both clients ok)",
            cells: pair_cells.iter().map(PairCellJson::of).collect(),
        },
    }
}
