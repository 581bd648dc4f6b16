//! `bench transfer`: the researcher's instrument. Whole-body GETs of seeded random bodies
//! through emulated links (the `netem` crate, in this process), with our client's three
//! transfer modes, libcoap 4.3.1 (RFC 7959), libcoap 4.3.5 (RFC 9177 Q-Block2 NON) and
//! QUIC (`quic-bench`: quinn with BBR) as the modern-transport reference. Every client and
//! server is a child process ([`crate::process`]), so every mode is timed the same way:
//! the client process's wall time, start to exit. Every body is compared bit-exact with
//! the original. Pair runs start two clients of one mode at once through one 50 Mbit/s
//! relay and report how the link's bytes were shared between them.
//!
//! - `config.rs`: what to run (`Config`), the links and the modes;
//! - `body.rs`: the seeded bodies and how an output differs from one;
//! - `relay.rs`: a `netem` relay on a thread of its own;
//! - `servers.rs`: the servers of every mode, holding every body, and the client commands;
//! - `runs.rs`: timed, checked runs and what a cell's runs say together;
//! - `table.rs`, `json.rs`, `plot.rs`: the report as Markdown, JSON and a PNG plot.

mod body;
mod config;
mod json;
mod plot;
mod relay;
mod runs;
mod servers;
mod table;

use std::path::PathBuf;

use anyhow::{Context as _, bail};
use image::RgbImage;

pub use config::{Config, Link, MAX_BODY, Mode, UnknownName};

use body::{Body, mix};
use config::{PAIR_LINK, PAIR_SEED, unique};
use relay::Relay;
use runs::{Cell, Client, PairCell, run_pair, time_client};
use servers::{Programs, Servers, client_command};

/// A scratch directory, removed on drop.
struct WorkDir(PathBuf);

impl Drop for WorkDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// What the benchmark found: every cell's runs and every pair run.
pub struct Report {
    /// The configuration, each size, link and mode once.
    config: Config,
    bodies: Vec<Body>,
    programs: Programs,
    cells: Vec<Cell>,
    pair_cells: Vec<PairCell>,
}

/// Runs the benchmark (blocking: call it off an async runtime's threads). `coapcam` is
/// the program of our modes (this executable); `progress` gets a line per run and what
/// cannot run, loudly. Runs that fail are results; an error means the benchmark could
/// not run (a body could not be written, a relay could not bind).
pub fn run(
    config: &Config,
    coapcam: PathBuf,
    mut progress: impl FnMut(String),
) -> anyhow::Result<Report> {
    let config = Config {
        sizes: unique(&config.sizes),
        links: unique(&config.links),
        modes: unique(&config.modes),
        ..config.clone()
    };
    let (sizes, links, modes) = (&config.sizes, &config.links, &config.modes);
    if sizes.is_empty() || links.is_empty() || modes.is_empty() {
        bail!("--sizes, --links and --modes each need at least one value");
    }
    let work = WorkDir(
        std::env::temp_dir().join(format!("coapcam-bench-transfer-{}", std::process::id())),
    );
    let files = work.0.join("files");
    std::fs::create_dir_all(&files).with_context(|| format!("creating {}", files.display()))?;
    let bodies = sizes
        .iter()
        .map(|&size| Body::write(&files, size, config.seed))
        .collect::<anyhow::Result<Vec<_>>>()?;

    let programs = Programs::locate(coapcam);
    for &mode in modes {
        if let Some(why) = programs.missing(mode) {
            progress(format!(
                "\n!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!\n\
                 !!! bench transfer: mode {} is UNAVAILABLE: {why}\n\
                 !!! It is shown as unavailable in the table and the JSON.\n\
                 !!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!\n",
                mode.name()
            ));
        }
    }
    let available: Vec<Mode> = modes
        .iter()
        .copied()
        .filter(|&m| programs.missing(m).is_none())
        .collect();
    let servers = Servers::start(&programs, &available, &bodies, &work.0, &mut progress)?;

    let runs_of = |m: Mode| {
        if m.slow() {
            config.slow_runs
        } else {
            config.runs
        }
    };
    let skipped = |mode: Mode, size: u64| {
        programs.missing(mode).map(str::to_owned).or_else(|| {
            servers
                .target(mode, size)
                .err()
                .map(|e| format!("setup failed: {e}"))
        })
    };
    let mut cells: Vec<Cell> = Vec::new();
    for &link in links {
        for body in &bodies {
            for &mode in modes {
                cells.push(Cell {
                    link,
                    size: body.size,
                    mode,
                    skipped: skipped(mode, body.size),
                    runs: Vec::new(),
                });
            }
        }
    }
    let mut pair_cells: Vec<PairCell> = Vec::new();
    if config.pairs > 0 && links.contains(&PAIR_LINK) {
        for body in &bodies {
            for &mode in modes.iter().filter(|m| !m.slow()) {
                pair_cells.push(PairCell {
                    size: body.size,
                    mode,
                    skipped: skipped(mode, body.size),
                    runs: Vec::new(),
                });
            }
        }
    }
    let runnable = pair_cells.iter().filter(|c| c.skipped.is_none()).count() as u32;
    let total: u32 = cells
        .iter()
        .filter(|c| c.skipped.is_none())
        .map(|c| runs_of(c.mode))
        .sum::<u32>()
        + runnable * config.pairs;
    let out = work.0.join("out");
    let log = work.0.join("client.log");
    let mut done = 0u32;
    for (link_index, &link) in links.iter().enumerate() {
        for body in &bodies {
            let row: Vec<usize> = (0..cells.len())
                .filter(|&i| cells[i].link == link && cells[i].size == body.size)
                .collect();
            let most = modes.iter().map(|&m| runs_of(m)).max().unwrap_or(0);
            for run in 0..most {
                let seed = mix(
                    mix(config.seed, link_index as u64),
                    mix(body.size, u64::from(run)),
                );
                for &i in &row {
                    let cell = &cells[i];
                    if cell.skipped.is_some() || run >= runs_of(cell.mode) {
                        continue;
                    }
                    let mode = cell.mode;
                    let target = servers
                        .target(mode, body.size)
                        .map_err(|e| anyhow::anyhow!("{e}"))?
                        .clone();
                    let relay = match link.config(seed) {
                        Some(config) => Some(Relay::start(target.addr, config)?),
                        None => None,
                    };
                    let addr = relay.as_ref().map_or(target.addr, |r| r.addr);
                    let cmd = client_command(&programs, mode, addr, &target, &out, config.cap)?;
                    let client = Client {
                        cmd,
                        out: &out,
                        log: &log,
                    };
                    let mut result = time_client(client, mode.name(), config.cap, &body.bytes)?;
                    if let Some(relay) = relay {
                        result.relay = Some(relay.finish()?);
                    }
                    done += 1;
                    progress(format!(
                        "[{done}/{total}] {} {} B {} run {}/{}: {:.3} s {}",
                        link.name(),
                        body.size,
                        mode.name(),
                        run + 1,
                        runs_of(mode),
                        result.time_s,
                        result
                            .error
                            .as_deref()
                            .map_or_else(|| "ok".to_owned(), |e| format!("FAILED: {e}"))
                    ));
                    cells[i].runs.push(result);
                }
            }
        }
    }
    for body in &bodies {
        for run in 0..config.pairs {
            let seed = mix(mix(config.seed, PAIR_SEED), mix(body.size, u64::from(run)));
            let link = PAIR_LINK
                .config(seed)
                .context("the pair runs' link has a relay")?;
            for cell in &mut pair_cells {
                if cell.size != body.size || cell.skipped.is_some() {
                    continue;
                }
                let target = servers
                    .target(cell.mode, body.size)
                    .map_err(|e| anyhow::anyhow!("{e}"))?;
                let pair = run_pair(
                    &programs, cell.mode, target, link, body, config.cap, &work.0,
                )?;
                done += 1;
                progress(format!(
                    "[{done}/{total}] {} {} B {} pair run {}/{}: {}",
                    PAIR_LINK.name(),
                    body.size,
                    cell.mode.name(),
                    run + 1,
                    config.pairs,
                    pair.summary(body.size)
                ));
                cell.runs.push(pair);
            }
        }
    }
    drop(servers);
    Ok(Report {
        config,
        bodies,
        programs,
        cells,
        pair_cells,
    })
}

impl Report {
    /// The Markdown table, its heading and the failed runs under it.
    pub fn table(&self) -> String {
        let c = &self.config;
        table::table(c, &self.bodies, &self.cells)
    }

    /// The Markdown table of the pair runs, if any ran.
    pub fn pair_table(&self) -> Option<String> {
        (!self.pair_cells.is_empty()).then(|| table::pair_table(&self.config, &self.pair_cells))
    }

    /// Every run, the links, the modes, the programs and the machine, as pretty JSON.
    pub fn json_text(&self) -> anyhow::Result<String> {
        let report = json::report_json(&self.config, &self.cells, &self.pair_cells, &self.programs);
        serde_json::to_string_pretty(&report).context("encoding the JSON")
    }

    /// The medians against the loss rate, one panel per size.
    pub fn plot(&self) -> RgbImage {
        let c = &self.config;
        plot::plot(&c.sizes, &c.links, &c.modes, &self.cells)
    }
}
