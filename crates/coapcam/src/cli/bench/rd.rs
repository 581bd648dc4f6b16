//! `coapcam bench rd`: prints what `coapcam::bench::rd` measured.

use clap::Args;

use super::super::{Exit, outln};
use coapcam::bench::rd::{self, Config};

/// Flags of `bench rd`.
#[derive(Debug, Args)]
pub(crate) struct RdArgs {
    /// Registrations to fill the directory with (each a one-camera station, about 900
    /// bytes of links); fewer when it is full first (its count at 128 MiB).
    #[arg(long, value_name = "N", default_value_t = 10_000)]
    registrations: usize,
    /// Lookups of each kind to time.
    #[arg(long, value_name = "N", default_value_t = 200)]
    lookups: usize,
    /// Registrations sent at once.
    #[arg(long, value_name = "N", default_value_t = 16)]
    concurrency: usize,
    /// Full lookups (every link of every registration, `/rd-lookup/res` without a query) after the
    /// timed ones, each from a client of its own, four at a time.
    #[arg(long, value_name = "N", default_value_t = 0)]
    full_lookups: usize,
    /// Print one JSON object instead of the table.
    #[arg(long)]
    json: bool,
}

/// Runs `bench rd`.
pub(crate) async fn run(args: RdArgs) -> anyhow::Result<Exit> {
    let exe = std::env::current_exe()?;
    let report = rd::run(&Config {
        exe,
        registrations: args.registrations,
        lookups: args.lookups,
        concurrency: args.concurrency,
        full_lookups: args.full_lookups,
    })
    .await?;
    if args.json {
        outln!("{}", serde_json::to_string(&report)?);
        return Ok(Exit::Success);
    }
    let per = (report.rss_filled_kib.saturating_sub(report.rss_idle_kib)) as f64 * 1024.0
        / report.registrations.max(1) as f64;
    outln!(
        "{} registrations in {:.1} s{}; resident memory {:.1} MiB idle, {:.1} MiB filled ({:.0} bytes per registration), peak {:.1} MiB; the directory counts them for {:.1} MiB ({:.0} bytes each)",
        report.registrations,
        report.fill_s,
        if report.full {
            ", then full (5.03)"
        } else {
            ""
        },
        report.rss_idle_kib as f64 / 1024.0,
        report.rss_filled_kib as f64 / 1024.0,
        per,
        report.rss_peak_kib as f64 / 1024.0,
        report.counted_kib as f64 / 1024.0,
        report.counted_kib as f64 * 1024.0 / report.registrations.max(1) as f64
    );
    outln!("| lookup | links | median ms | p95 ms | max ms | its work: median ms | p95 ms |");
    outln!("|---|---:|---:|---:|---:|---:|---:|");
    for row in &report.lookups {
        outln!(
            "| {} | {} | {:.2} | {:.2} | {:.2} | {:.3} | {:.3} |",
            row.lookup,
            row.links,
            row.median_ms,
            row.p95_ms,
            row.max_ms,
            row.work_median_ms,
            row.work_p95_ms
        );
    }
    if report.full_lookups > 0 {
        outln!(
            "{} full lookups of {:.1} MB each in {:.1} s: resident memory {:.1} MiB before them, {:.1} MiB after",
            report.full_lookups,
            report.full_lookup_bytes as f64 / 1e6,
            report.full_lookups_s,
            report.rss_looked_up_kib as f64 / 1024.0,
            report.rss_full_kib as f64 / 1024.0
        );
    }
    Ok(Exit::Success)
}
