//! `coapcam`: RGB-D cameras as CoAP resources, and parcel measurement.

#![forbid(unsafe_code)]

mod netem;

use std::process::ExitCode;

use anyhow::Context as _;
use clap::{Parser, Subcommand};

/// RGB-D cameras (Intel RealSense D400 and a synthetic D415) as CoAP resources.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Relay UDP between clients and a server over an emulated link (loss, delay, jitter,
    /// rate limit), and print the counters when it ends.
    Netem(netem::NetemArgs),
}

fn main() -> ExitCode {
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("coapcam: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    match cli.command {
        Command::Netem(args) => {
            let json = args.json;
            let counters = runtime.block_on(netem::run(args))?;
            println!("{}", netem::report(&counters, json)?);
        }
    }
    Ok(())
}
