//! `coapcam measure`: grab point clouds (one camera, every camera of a server, or every
//! server of a multicast group), merge them and measure the largest parcel on the floor
//! (DESIGN.md §6).

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use clap::Args;
use coap_net::Uri;

use super::{DimensionArgs, TransmissionArgs};
use coapcam::client::CamClient;
use coapcam::client::measure::{Source, measure_once, prepare_cameras};
use coapcam::client::{annotate, codes};

/// Flags of `measure`.
#[derive(Debug, Args)]
pub(crate) struct MeasureArgs {
    /// The server, coap://host[:port] (not needed with --group).
    #[arg(long, value_name = "URI", required_unless_present = "group")]
    server: Option<String>,
    /// Measure with this camera only (12-digit serial).
    #[arg(long, value_name = "SN", conflicts_with_all = ["all", "group"])]
    camera: Option<String>,
    /// Measure with every camera of the server, merged (POST /cams/pointclouds); the
    /// default when neither --camera nor --group is given.
    #[arg(long)]
    all: bool,
    /// Ask every server of this multicast group (e.g. 224.0.1.187 or
    /// coap://[ff02::fd%eth0]:5683) and merge the clouds of all that answer.
    #[arg(long, value_name = "MCAST_ADDR", conflicts_with = "server")]
    group: Option<String>,
    /// With --group: stop waiting once this many servers have answered.
    #[arg(long, value_name = "N", requires = "group")]
    expect: Option<usize>,
    /// With --group: the local address to send from (e.g. 127.0.0.1 when the servers are
    /// on loopback addresses); by default the kernel chooses per destination.
    #[arg(long, value_name = "ADDR", requires = "group")]
    bind: Option<std::net::IpAddr>,
    /// With --group: how long to collect answers, in seconds.
    #[arg(
        long,
        value_name = "SECONDS",
        default_value_t = 3.0,
        requires = "group"
    )]
    wait: f64,
    /// First prepare the server's cameras as `demo` does (and the thesis's client
    /// expects): roi3d becomes the space above the floor within 1 m of the origin, so
    /// the floor is not sent, and the spatial filter runs; the rest of each camera's
    /// application-config stays. Not with --group.
    #[arg(long, conflicts_with = "group")]
    prepare: bool,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
    /// Also read the QR and Code 128 codes on the parcel from a new color image of each
    /// camera (`codes` in the JSON). With --prepare the color stream first becomes
    /// 1920x1080, where a code may be a third smaller than at 1280x720.
    #[arg(long)]
    codes: bool,
    /// Draw the measured box and its dimensions onto a new color image of the first
    /// camera and write it as PNG.
    #[arg(long, value_name = "FILE.png")]
    annotate: Option<PathBuf>,
    /// Give up on a request after this many seconds.
    #[arg(long, value_name = "SECONDS", default_value_t = 30.0)]
    timeout: f64,
    #[command(flatten)]
    dimension: DimensionArgs,
    #[command(flatten)]
    transmission: TransmissionArgs,
}

/// Runs `measure`. Returns whether a measurement came out.
pub(crate) async fn run(args: MeasureArgs) -> anyhow::Result<bool> {
    let timeout = Duration::try_from_secs_f64(args.timeout).context("--timeout")?;
    let config = args.transmission.endpoint_config();
    let (client, source) = match (&args.group, &args.server) {
        (Some(g), _) => {
            let group = group_address(g).await?;
            let wait = Duration::try_from_secs_f64(args.wait).context("--wait")?;
            let client = CamClient::for_group(group, args.bind, config, timeout)?;
            let expect = args.expect;
            (
                client,
                Source::Group {
                    group,
                    expect,
                    wait,
                },
            )
        }
        (None, Some(server)) => {
            let client = CamClient::connect(server, config, timeout).await?;
            if args.prepare {
                let serials = match &args.camera {
                    Some(sn) => vec![sn.clone()],
                    None => client.cameras().await?,
                };
                prepare_cameras(&client, &serials, 1.0, args.codes).await?;
            }
            let source = match &args.camera {
                Some(sn) => Source::Camera(sn.clone()),
                None => Source::All,
            };
            (client, source)
        }
        (None, None) => bail!("give --server URI or --group MCAST_ADDR"),
    };
    let m = measure_once(&client, &source, &args.dimension.config()).await?;
    let codes = if args.codes {
        let started = Instant::now();
        let codes = codes::read_cameras(&client, &m.grabbed.cameras).await?;
        Some((codes, started.elapsed()))
    } else {
        None
    };
    if args.json {
        let mut json = m.to_json();
        if let Some((codes, took)) = &codes {
            json["codes"] = codes.iter().map(codes::Seen::to_json).collect();
            json["codes_ms"] = ((took.as_secs_f64() * 1e4).round() / 10.0).into();
        }
        println!("{json}");
    } else {
        println!("{}", m.to_text());
        if let Some((codes, took)) = &codes {
            println!(
                "codes: {} (grabbed and read in {:.0} ms)",
                codes::describe(codes),
                took.as_secs_f64() * 1e3
            );
        }
    }
    if let Some(path) = &args.annotate {
        let (server, sn) = m
            .grabbed
            .cameras
            .first()
            .context("no camera to take the color image from")?;
        let one = CamClient::unicast(&client, *server);
        annotate::from_server(&one, sn, &m.dimensions, path).await?;
        eprintln!("coapcam: wrote {}", path.display());
    }
    Ok(true)
}

/// `224.0.1.187`, `[ff02::fd]`, or a full `coap://group:port` URI; port 5683 by default.
async fn group_address(text: &str) -> anyhow::Result<SocketAddr> {
    let uri = if text.starts_with("coap://") {
        text.to_owned()
    } else if text.contains(':') && !text.starts_with('[') {
        format!("coap://[{text}]")
    } else {
        format!("coap://{text}")
    };
    let addr = Uri::parse(&uri)?
        .resolve()
        .await
        .with_context(|| format!("resolving {text}"))?;
    if !addr.ip().is_multicast() {
        bail!("{} is not a multicast address", addr.ip());
    }
    Ok(addr)
}
