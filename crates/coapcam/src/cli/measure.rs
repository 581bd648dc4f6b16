//! `coapcam measure`: grab point clouds (one camera, every camera of a server, or every
//! server of a multicast group), merge them and measure the largest parcel on the floor
//! (DESIGN.md §6).

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use bytes::Bytes;
use clap::Args;
use coap::{Code, ContentFormat};
use coap_net::Uri;
use geometry::{DimensionConfig, Dimensions, PointCloud};

use crate::cbor;
use crate::client::{CamClient, Stream, check};
use crate::transmission::TransmissionArgs;

/// Divisor of the volumetric weight, cm³ per kg (the courier convention).
pub(crate) const VOLUMETRIC_DIVISOR_CM3_PER_KG: f64 = 5000.0;

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

/// Thresholds of the measurement.
#[derive(Debug, Clone, Args)]
pub(crate) struct DimensionArgs {
    /// Points lower than this above the floor are floor, in millimetres.
    #[arg(long, value_name = "MM", default_value_t = 10.0)]
    min_height_mm: f32,
    /// Points closer than this belong to one object, in millimetres.
    #[arg(long, value_name = "MM", default_value_t = 20.0)]
    cluster_mm: f32,
}

impl DimensionArgs {
    pub(crate) fn config(&self) -> DimensionConfig {
        DimensionConfig {
            min_height_m: self.min_height_mm / 1e3,
            cluster_radius_m: self.cluster_mm / 1e3,
            ..DimensionConfig::default()
        }
    }
}

/// Where the clouds come from.
#[derive(Debug, Clone)]
pub(crate) enum Source {
    /// One camera of a server.
    Camera(String),
    /// Every camera of a server, merged by the server.
    All,
    /// Every server of a multicast group.
    Group {
        /// The group's address and port.
        group: SocketAddr,
        /// Stop once this many servers answered.
        expect: Option<usize>,
        /// How long to collect answers.
        wait: Duration,
    },
}

/// The clouds of one measurement, merged, and where they came from.
#[derive(Debug)]
pub(crate) struct Grabbed {
    pub(crate) cloud: PointCloud,
    /// `(server, camera serial)` of every camera that contributed.
    pub(crate) cameras: Vec<(SocketAddr, String)>,
    /// Frame timestamps, microseconds since the UNIX epoch (one per cloud received).
    pub(crate) timestamps_us: Vec<u64>,
    /// Bytes of point-cloud representations received.
    pub(crate) bytes: usize,
}

/// One measurement with its provenance and timing.
#[derive(Debug)]
pub(crate) struct Measurement {
    pub(crate) dimensions: Dimensions,
    pub(crate) grabbed: Grabbed,
    /// From sending the first request until the dimensions were known.
    pub(crate) cycle: Duration,
    /// Of the cycle: until the last cloud arrived (the servers' grabs and the transfers).
    pub(crate) grab: Duration,
}

impl Measurement {
    /// length x width x height in cm³ over the divisor, kilograms.
    pub(crate) fn volumetric_weight_kg(&self) -> f64 {
        let d = &self.dimensions;
        (d.length_mm / 10.0) * (d.width_mm / 10.0) * (d.height_mm / 10.0)
            / VOLUMETRIC_DIVISOR_CM3_PER_KG
    }

    /// The JSON object of `measure --json` (DESIGN.md §6).
    pub(crate) fn to_json(&self) -> serde_json::Value {
        let d = &self.dimensions;
        let mm = |v: f64| (v * 10.0).round() / 10.0;
        serde_json::json!({
            "length_mm": mm(d.length_mm),
            "width_mm": mm(d.width_mm),
            "height_mm": mm(d.height_mm),
            "yaw_deg": (d.yaw_deg * 100.0).round() / 100.0,
            "corners_m": d.corners_m,
            "volume_l": (d.volume_l * 1000.0).round() / 1000.0,
            "volumetric_weight_kg": (self.volumetric_weight_kg() * 1000.0).round() / 1000.0,
            "points": d.points,
            "cloud_points": self.grabbed.cloud.len(),
            "cameras": self.grabbed.cameras.iter().map(|(_, sn)| sn).collect::<Vec<_>>(),
            "servers": self.grabbed.cameras.iter().map(|(s, _)| s.to_string()).collect::<Vec<_>>(),
            "timestamps_us": self.grabbed.timestamps_us,
            "cycle_ms": (self.cycle.as_secs_f64() * 1e4).round() / 10.0,
            "grab_ms": (self.grab.as_secs_f64() * 1e4).round() / 10.0,
            "bytes": self.grabbed.bytes,
        })
    }

    /// The text of `measure` without --json.
    pub(crate) fn to_text(&self) -> String {
        let d = &self.dimensions;
        let serials: Vec<&str> = self
            .grabbed
            .cameras
            .iter()
            .map(|(_, s)| s.as_str())
            .collect();
        let corners: Vec<String> = d
            .corners_m
            .iter()
            .map(|[x, y]| format!("({x:.3}, {y:.3})"))
            .collect();
        format!(
            "length {:.1} mm  width {:.1} mm  height {:.1} mm\n\
             yaw {:.1} deg  volume {:.2} l  volumetric weight {:.2} kg (divisor {} cm3/kg)\n\
             footprint corners (m): {}\n\
             {} points of {} from {} camera(s): {}\n\
             cycle {:.0} ms (grab and transfer {:.0} ms), {:.2} MB received",
            d.length_mm,
            d.width_mm,
            d.height_mm,
            d.yaw_deg,
            d.volume_l,
            self.volumetric_weight_kg(),
            VOLUMETRIC_DIVISOR_CM3_PER_KG,
            corners.join(" "),
            d.points,
            self.grabbed.cloud.len(),
            serials.len(),
            serials.join(", "),
            self.cycle.as_secs_f64() * 1e3,
            self.grab.as_secs_f64() * 1e3,
            self.grabbed.bytes as f64 / 1e6,
        )
    }
}

/// Grabs the clouds of `source` (`client` is the server's client; for a group, any
/// client) and merges them.
pub(crate) async fn grab_clouds(client: &CamClient, source: &Source) -> anyhow::Result<Grabbed> {
    let mut grabbed = Grabbed {
        cloud: PointCloud::default(),
        cameras: Vec::new(),
        timestamps_us: Vec::new(),
        bytes: 0,
    };
    // The CBOR map names the cameras that made each cloud and its time in microseconds.
    let accept = Some(ContentFormat::CBOR);
    let answers = match source {
        Source::Camera(sn) => vec![(
            client.server(),
            client.grab(sn, Stream::Pointcloud, accept).await?,
        )],
        Source::All => vec![(client.server(), client.grab_all(accept).await?)],
        Source::Group {
            group,
            expect,
            wait,
        } => {
            let mut request =
                client.request(Code::POST, "/cams/pointclouds", Bytes::new(), None, accept);
            request.timeout = Some(*wait);
            let answers = client
                .coap()
                .multicast_expecting(*group, request, *expect)
                .await
                .with_context(|| format!("POST /cams/pointclouds to the group {group}"))?;
            if answers.is_empty() {
                bail!("no server of the group {group} answered within {wait:?}");
            }
            answers
                .into_iter()
                .map(|(server, r)| {
                    Ok((
                        server,
                        check(&format!("POST /cams/pointclouds on {server}"), r)?,
                    ))
                })
                .collect::<anyhow::Result<_>>()?
        }
    };
    for (server, response) in answers {
        let c = cbor::Cloud::from_cbor(&response.payload)
            .with_context(|| format!("reading the point cloud of {server}"))?;
        grabbed.bytes += response.payload.len();
        grabbed.cloud.extend_from(&c.cloud);
        grabbed.timestamps_us.push(c.timestamp_us);
        grabbed
            .cameras
            .extend(c.serials.into_iter().map(|sn| (server, sn)));
    }
    Ok(grabbed)
}

/// Grabs and measures once.
pub(crate) async fn measure_once(
    client: &CamClient,
    source: &Source,
    config: &DimensionConfig,
) -> anyhow::Result<Measurement> {
    let started = Instant::now();
    let grabbed = grab_clouds(client, source).await?;
    let grab = started.elapsed();
    let (dimensions, grabbed) = tokio::task::spawn_blocking({
        let config = *config;
        move || (geometry::dimension(&grabbed.cloud, &config), grabbed)
    })
    .await
    .context("the measuring task failed")?;
    let dimensions = dimensions.context("measuring the point cloud")?;
    Ok(Measurement {
        dimensions,
        grabbed,
        cycle: started.elapsed(),
        grab,
    })
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
                crate::demo::prepare_cameras(&client, &serials, 1.0, args.codes).await?;
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
        let codes = crate::codes::read_cameras(&client, &m.grabbed.cameras).await?;
        Some((codes, started.elapsed()))
    } else {
        None
    };
    if args.json {
        let mut json = m.to_json();
        if let Some((codes, took)) = &codes {
            json["codes"] = codes.iter().map(crate::codes::Seen::to_json).collect();
            json["codes_ms"] = ((took.as_secs_f64() * 1e4).round() / 10.0).into();
        }
        println!("{json}");
    } else {
        println!("{}", m.to_text());
        if let Some((codes, took)) = &codes {
            println!(
                "codes: {} (grabbed and read in {:.0} ms)",
                crate::codes::describe(codes),
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
        crate::annotate::from_server(&one, sn, &m.dimensions, path).await?;
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
