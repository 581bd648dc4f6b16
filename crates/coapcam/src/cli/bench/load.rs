//! `coapcam bench load`: its flags, and what `coapcam::bench::load`'s clients counted
//! printed as one JSON object; exits 1 when anything failed, mismatched or was lost.

use std::time::Duration;

use clap::Args;
use serde_json::json;

use crate::cli::{Exit, outln, values};
use coapcam::bench::load::{self, Config};
use coapcam::stats;

/// Flags of `bench load`.
#[derive(Debug, Args)]
pub(crate) struct LoadArgs {
    /// The server, e.g. coap://127.0.0.1:5683 (started with --static DIR --writable).
    #[arg(long, value_name = "URI", value_parser = values::coap_uri)]
    server: String,
    /// Concurrent clients, each with its own socket, a quarter in each role (at least 1).
    #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    clients: u32,
    /// How long the clients keep going, in seconds.
    #[arg(long, value_name = "SECONDS", default_value = "60", value_parser = values::positive_seconds)]
    duration: Duration,
    /// Pause of each client between two of its requests, in milliseconds.
    #[arg(long, default_value_t = 50)]
    pause_ms: u64,
    /// Per-request timeout, in seconds.
    #[arg(long, value_name = "SECONDS", default_value = "60", value_parser = values::positive_seconds)]
    timeout: Duration,
}

/// Runs `bench load`.
pub(crate) async fn run(args: LoadArgs) -> anyhow::Result<Exit> {
    let config = Config {
        server: args.server.clone(),
        clients: args.clients as usize,
        duration: args.duration,
        pause: Duration::from_millis(args.pause_ms),
        timeout: args.timeout,
    };
    let t = load::run(&config).await?;
    let ms = &t.discovery_ms;
    let pct = |p: f64| stats::percentile(ms, p).unwrap_or(f64::NAN);
    let report = json!({
        "clients": args.clients,
        "duration_s": args.duration.as_secs_f64(),
        "discovery": {
            "requests": ms.len(),
            "p50_ms": pct(0.5),
            "p99_ms": pct(0.99),
            "max_ms": pct(1.0),
            "mismatches": t.discovery_mismatches,
        },
        "uploads": {
            "transfers": t.uploads,
            "bytes": t.upload_bytes,
            "mismatches": t.upload_mismatches,
        },
        "grabs": {
            "depth": t.depth_grabs,
            "measurements": t.measurements,
            "busy_retried": t.busy,
            "undecodable": t.undecodable,
        },
        "observers": {
            "notifications": t.notifications,
            "behind_at_end": t.behind_at_end,
        },
        "failures": t.failures,
    });
    outln!("{}", serde_json::to_string_pretty(&report)?);
    Ok(if t.clean() {
        Exit::Success
    } else {
        Exit::Failure
    })
}
