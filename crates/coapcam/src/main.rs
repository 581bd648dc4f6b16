//! `coapcam`: RGB-D cameras as CoAP resources, and parcel measurement.

#![forbid(unsafe_code)]

use std::process::ExitCode;

use clap::Parser;

/// RGB-D cameras (Intel RealSense D400 and a synthetic D415) as CoAP resources.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Cli {}

fn main() -> ExitCode {
    let _cli = Cli::parse();
    ExitCode::SUCCESS
}
