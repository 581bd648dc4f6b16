//! The `coapcam` binary: the command enum and its dispatch. Each command's flags and
//! `run` are in `cli/`; what they do is the `coapcam` library's.

#![forbid(unsafe_code)]

mod cli;

use std::process::ExitCode;

use anyhow::Context as _;
use clap::{CommandFactory as _, FromArgMatches as _, Parser, Subcommand};
use cli::{Deferred, Exit, interruptible};

/// RGB-D cameras (Intel RealSense D400 and a synthetic D415) as CoAP resources.
#[derive(Debug, Parser)]
#[command(version = coapcam::identity::VERSION_LINE, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// GET a resource; the body goes to standard output or -o FILE. Exit status 0 only for
    /// a 2.xx response whose body arrived whole.
    Get(Deferred<cli::request::RequestArgs>),
    /// POST to a resource.
    Post(Deferred<cli::request::RequestArgs>),
    /// PUT a resource.
    Put(Deferred<cli::request::RequestArgs>),
    /// DELETE a resource.
    Delete(Deferred<cli::request::RequestArgs>),
    /// List a server's resources (/.well-known/core), or every server in a multicast group.
    Discover(Deferred<cli::request::DiscoverArgs>),
    /// Grab one new frame into a file (.png, .jpg, .ply, .rvl, .rvl.zst, .dcl, .qmm or
    /// .bin) or standard output (-o -), optionally with a picture for people (--view).
    Grab(Deferred<cli::grab::GrabArgs>),
    /// Measure the largest parcel below the cameras: length, width, height in millimetres.
    Measure(Deferred<cli::measure::MeasureArgs>),
    /// Calibrate cameras: write each one's 3d-transformation so its points are in the
    /// table's frame. By default from AprilTag (tag36h11) markers on the table, every
    /// camera in the origin marker's frame; --floor: level each on the floor it sees;
    /// --adjust: correct by hand.
    Calibrate(Deferred<cli::calibrate::CalibrateArgs>),
    /// Write a PDF of AprilTag markers to print for calibrate, at their true size (A4 or
    /// Letter, with a 100 mm bar to check the printer kept the scale).
    Markers(Deferred<cli::markers::MarkersArgs>),
    /// Repeat a grab or a measurement every --interval seconds, or observe a resource;
    /// print each result and the statistics of the transfer times (count, min, median,
    /// max, mean, standard deviation, coefficient of variation: the thesis's Table 4.x).
    Monitor(Deferred<cli::monitor::MonitorArgs>),
    /// The whole job on synthetic cameras: serve a two-camera scene in-process, discover,
    /// grab, measure, and write pictures, a cloud and the dimensions next to the scene's
    /// truth into ./coapcam-demo/.
    Demo(Deferred<cli::demo::DemoArgs>),
    /// Benchmarks: `bench accuracy` measures a built-in set of synthetic parcels end to
    /// end over CoAP and prints the errors.
    Bench(Deferred<cli::bench::BenchArgs>),
    /// Run the CoAP server.
    Serve(Box<Deferred<cli::serve::ServeArgs>>),
    /// Run a resource directory (RFC 9176): servers register their resources
    /// (`serve --register`), clients look them up (`discover --rd`, `measure --group
    /// --rd`).
    Rd(Deferred<cli::rd::RdArgs>),
    /// A station's results log: list its records (--server URI), or verify a log file's
    /// hash chain (`results verify FILE`, exit status 7 naming the first altered record).
    Results(Deferred<cli::results::ResultsArgs>),
    /// Relay UDP between clients and a server over an emulated link (loss, delay, jitter,
    /// rate limit), and print the counters when it ends.
    Netem(Deferred<cli::netem::NetemArgs>),
}

fn main() -> ExitCode {
    // `serve --config FILE`'s keys come in as flags here.
    let mut matches = cli::config::command_line(Cli::command());
    let cli = Cli::from_arg_matches_mut(&mut matches)
        .unwrap_or_else(|e| e.format(&mut Cli::command()).exit());
    if matches!(cli.command, Command::Serve(_)) {
        cli::serve::fix_malloc_threshold();
    }
    // Logs go to standard error: warnings and a few changes of state by default (a request
    // the server failed (5.xx), a failed grab, a directory registration, an MQTT
    // connection); RUST_LOG=info adds refused requests (4.xx), RUST_LOG=debug every
    // request the server answers.
    cli::log::init();
    match run(cli) {
        Ok(exit) => ExitCode::from(exit.code()),
        Err(e) => match cli::exit_status(&e) {
            Some(exit) => {
                eprintln!("coapcam: {}", cli::error_text(e.as_ref()));
                ExitCode::from(exit.code())
            }
            // Standard output's reader went away (`| head`): nothing more to say.
            None => ExitCode::SUCCESS,
        },
    }
}

/// Runs the command; how it ended is its exit status (README.md's table).
fn run(cli: Cli) -> anyhow::Result<Exit> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    match cli.command {
        Command::Get(Deferred(args)) => {
            return runtime.block_on(interruptible(cli::request::run(coap::Code::GET, args)));
        }
        Command::Post(Deferred(args)) => {
            return runtime.block_on(interruptible(cli::request::run(coap::Code::POST, args)));
        }
        Command::Put(Deferred(args)) => {
            return runtime.block_on(interruptible(cli::request::run(coap::Code::PUT, args)));
        }
        Command::Delete(Deferred(args)) => {
            return runtime.block_on(interruptible(cli::request::run(coap::Code::DELETE, args)));
        }
        Command::Discover(Deferred(args)) => {
            return runtime.block_on(interruptible(cli::request::discover(args)));
        }
        Command::Grab(Deferred(args)) => {
            return runtime.block_on(interruptible(cli::grab::run(args)));
        }
        Command::Measure(Deferred(args)) => {
            return runtime.block_on(interruptible(cli::measure::run(args)));
        }
        Command::Calibrate(Deferred(args)) => {
            return runtime.block_on(interruptible(cli::calibrate::run(args)));
        }
        Command::Markers(Deferred(args)) => return runtime.block_on(cli::markers::run(args)),
        Command::Bench(Deferred(args)) => return runtime.block_on(cli::bench::run(args)),
        Command::Monitor(Deferred(args)) => return runtime.block_on(cli::monitor::run(args)),
        Command::Demo(Deferred(args)) => {
            return runtime.block_on(interruptible(cli::demo::run(args)));
        }
        Command::Results(Deferred(args)) => {
            return runtime.block_on(interruptible(cli::results::run(args)));
        }
        Command::Serve(args) => {
            let Deferred(args) = *args;
            let served = runtime.block_on(cli::serve::run(args));
            // A grab still waiting for its camera in a blocking thread must not hold up
            // the exit after SIGINT or SIGTERM.
            runtime.shutdown_timeout(std::time::Duration::from_secs(1));
            served?;
        }
        Command::Rd(Deferred(args)) => runtime.block_on(cli::rd::run(args))?,
        Command::Netem(Deferred(args)) => {
            let json = args.json;
            let counters = runtime.block_on(cli::netem::run(args))?;
            cli::outln!("{}", cli::netem::report(&counters, json)?);
        }
    }
    Ok(Exit::Success)
}
