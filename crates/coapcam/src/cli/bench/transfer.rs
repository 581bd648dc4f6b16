//! `coapcam bench transfer`: its flags, and the report of `coapcam::bench::transfer`
//! printed (the Markdown tables) and written (`--json`, `--plot`).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context as _, bail};
use clap::Args;

use crate::cli::{Exit, outln};
use coapcam::bench::transfer::{self, Config, Link, MAX_BODY, Mode};
use coapcam::vision::picture;

/// Flags of `bench transfer`.
#[derive(Debug, Args)]
#[command(after_long_help = "\
Each cell of the table is one (link, size, mode): the client fetches a body of that size \
through that link RUNS times (SLOW_RUNS for the slow modes). Runs are interleaved: run 1 \
of every mode, then run 2, ..., so a change of the machine's load hits every mode alike. \
Run i of every mode goes through a fresh relay seeded alike (from --seed, the link, the \
size and i).

Timing: the client's whole process, from its start to its exit, as a user of each \
command waits for it (checked every millisecond). QUIC's time includes its handshake; \
CoAP needs none. Servers start before and are not timed.

Links (the emulator runs in this process, between the client and the server; every \
figure is for each direction):
  loopback          no relay: the client talks to the server directly
  20ms              10 ms each way (a 20 ms round trip)
  20ms-2%           20 ms round trip, 2 % loss each way
  20ms-2%-50mbit    20 ms, 2 %, 50 Mbit/s each way with a 64,000-byte drop-tail queue
  100ms-5%          50 ms each way, 5 % loss each way

Modes (1024-byte blocks for every CoAP mode):
  stop-and-wait     coapcam get --transfer stop-and-wait (RFC 7959), against coapcam serve
  window            coapcam get --transfer window (many blocks in flight), against coapcam serve
  q-block           coapcam get --transfer q-block (RFC 9177), against coapcam serve
  libcoap-4.3.1     coap-client-notls (Debian libcoap3-bin, RFC 7959 CON) against \
coap-server-notls -d, the body PUT first
  libcoap-4.3.5-qblock
                    libcoap 4.3.5's coap-client -L 5 -N (Q-Block2, NON) against its \
coap-server -L 5 -d, the body PUT first; found in $COAPCAM_LIBCOAP435 or \
~/.cache/coapcam-peers/libcoap-4.3.5/build (../shared/peers/build-libcoap.sh builds it)
  quic              quic-bench get (quinn with BBR, one stream) against quic-bench serve; \
found in $COAPCAM_QUIC_BENCH or next to this executable (cargo build --release -p quic-bench)
The slow modes are stop-and-wait and both libcoap modes. A mode whose programs are \
missing is reported as unavailable, loudly, and shown so in the table.

Bodies are random bytes from --seed, one file per size. libcoap's servers get theirs by \
a PUT on loopback before anything is timed, checked by a GET. A run succeeds when the \
client exits with status 0 within --cap and its output equals the body byte for byte; a \
client that exits 0 with a short file fails the run.

Two transfers at once (--pairs N, when 20ms-2%-50mbit is among --links): for each size \
and each fast mode, N runs of two clients of that mode started together through one relay \
of that link to one server, to see whether they share the 50 Mbit/s fairly. Both clients \
are timed and checked like any run. When the first of them ends, the relay's count of the \
payload bytes it has delivered to each client so far gives the shares: each client's bytes \
over the sum of both (the relay knows the clients by address, not by process, so a run \
reports its smaller and its larger share). A pair run holds when its smaller share is at \
least 35 %. Its link utilisation is both bodies (2 x size) over the later client's time, \
as a fraction of 50 Mbit/s. The slow modes are not paired; --pairs 0 runs none.

Output: the table on standard output, one row per (link, size), one column per mode: \
the median of the successful runs in seconds, [min-max] of them, their 95th percentile \
(nearest rank) and successful/runs, then ratios of medians (only where both cells have \
at least 15 successful runs; \"-\" otherwise), and every failed run with its reason under \
the table. After it, \
when pairs ran, the table of the pair runs, one row per (size, mode): the median smaller \
share [min-max], the runs that held, the median link utilisation [min-max] and \
successful/runs (successful: both clients), medians of the successful runs. Progress goes \
to standard error. --json writes every \
run (time, exit, bit-exactness, the relay's counters) and every pair run (both clients, \
the bytes delivered to each client address when the first ended, the shares, the \
utilisation); --plot draws the medians against the loss rate, one panel per size.

Exit status: 0 when the benchmark ran, failed runs included (they are results); 1 when \
it could not run (a body or output file could not be written, a relay could not bind).")]
pub(super) struct TransferArgs {
    /// Runs per cell of the fast modes (window, q-block, quic); ratios of medians are
    /// printed only for cells with at least 15 successful runs.
    #[arg(long, value_name = "N", default_value_t = 15,
          value_parser = clap::value_parser!(u32).range(1..))]
    runs: u32,
    /// Runs per cell of the slow modes (stop-and-wait, libcoap-4.3.1, libcoap-4.3.5-qblock).
    #[arg(long, value_name = "N", default_value_t = 1,
          value_parser = clap::value_parser!(u32).range(1..))]
    slow_runs: u32,
    /// Body sizes in bytes, comma-separated (921610 and 2764810 are a 640x480 and a
    /// 1280x720 RGB frame; 10032012 the thesis's largest body).
    #[arg(long, value_name = "BYTES,...", value_delimiter = ',',
          default_values = ["921610", "2764810"],
          value_parser = clap::value_parser!(u64).range(1..=MAX_BODY))]
    sizes: Vec<u64>,
    /// Links, comma-separated: loopback, 20ms, 20ms-2%, 20ms-2%-50mbit, 100ms-5% (see
    /// below).
    #[arg(long, value_name = "LINK,...", value_delimiter = ',', value_parser = parse_link,
          default_values = ["loopback", "20ms", "20ms-2%", "20ms-2%-50mbit", "100ms-5%"])]
    links: Vec<Link>,
    /// Modes, comma-separated: stop-and-wait, window, q-block, libcoap-4.3.1,
    /// libcoap-4.3.5-qblock, quic (see below); the table's columns in this order.
    #[arg(long, value_name = "MODE,...", value_delimiter = ',', value_parser = parse_mode,
          default_values = ["stop-and-wait", "window", "q-block", "libcoap-4.3.1",
                            "libcoap-4.3.5-qblock", "quic"])]
    modes: Vec<Mode>,
    /// Pair runs per size and fast mode: two clients at once through one 20ms-2%-50mbit
    /// relay (see below); 0 runs none, and none run when that link is not among --links.
    #[arg(long, value_name = "N", default_value_t = 3)]
    pairs: u32,
    /// Seconds a run may take; a client still running then is killed and the run failed.
    #[arg(long, value_name = "SECONDS", default_value = "120", value_parser = parse_cap)]
    cap: Duration,
    /// Seed of the bodies and of the relays' loss decisions.
    #[arg(long, value_name = "N", default_value_t = 1)]
    seed: u64,
    /// Also write every run, the links, the modes and the machine as JSON into FILE.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    /// Also draw the medians against the loss rate into FILE (PNG), one panel per size.
    #[arg(long, value_name = "FILE.png")]
    plot: Option<PathBuf>,
}

fn parse_cap(text: &str) -> Result<Duration, String> {
    crate::cli::values::positive_seconds(text)
}

fn parse_link(text: &str) -> Result<Link, String> {
    text.parse().map_err(|e| format!("{e}"))
}

fn parse_mode(text: &str) -> Result<Mode, String> {
    text.parse().map_err(|e| format!("{e}"))
}

/// Runs `bench transfer`.
pub(super) async fn run(args: TransferArgs) -> anyhow::Result<Exit> {
    // Fail before any work on an output file whose folder is missing.
    for path in [&args.json, &args.plot].into_iter().flatten() {
        let dir = path.parent().filter(|d| !d.as_os_str().is_empty());
        if dir.is_some_and(|d| !d.is_dir()) {
            bail!("cannot write {}: its folder does not exist", path.display());
        }
    }
    let config = Config {
        runs: args.runs,
        slow_runs: args.slow_runs,
        sizes: args.sizes,
        links: args.links,
        modes: args.modes,
        pairs: args.pairs,
        cap: args.cap,
        seed: args.seed,
    };
    let coapcam = std::env::current_exe().context("finding this executable")?;
    let report = tokio::task::spawn_blocking(move || {
        transfer::run(&config, coapcam, |line| eprintln!("{line}"))
    })
    .await
    .context("the benchmark's thread")??;
    outln!("{}", report.table());
    if let Some(pairs) = report.pair_table() {
        outln!("\n{pairs}");
    }
    if let Some(path) = &args.json {
        let text = report.json_text()?;
        std::fs::write(path, text + "\n").with_context(|| format!("writing {}", path.display()))?;
    }
    if let Some(path) = &args.plot {
        picture::save(&report.plot(), path)?;
    }
    Ok(Exit::Success)
}
