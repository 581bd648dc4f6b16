//! `coapcam measure`: grab point clouds (one camera, every camera of a server, or every
//! server of a multicast group), merge them and measure the largest parcel on the floor
//! (docs/design.md §6).

use std::collections::BTreeSet;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use clap::Args;
use coap_net::Uri;
use coap_rd::registrant::{Endpoint, GROUP_ATTR, group_key, lookup_endpoints};

use coapcam::client::measure::{
    FLOOR_CUT_M, Source, calibration_of, color_for_codes, measure_checked, prepare_cameras,
};
use coapcam::client::{CamClient, annotate, codes};
use coapcam::report::{self, Billing, Division, EdgeQuery, Found, Measurement, Parcel};
use coapcam::timesync::Limits;

use super::{
    Bars, CameraArgs, DimensionArgs, Exit, TransmissionArgs, folder_exists, outln, usage, values,
};

/// Flags of `measure`.
#[derive(Debug, Args)]
pub(crate) struct MeasureArgs {
    // The server (not needed with --group) and its cameras. With every camera (--all,
    // the default) the server measures when it offers it (see --edge), else the client
    // measures its merged clouds (POST /cams/pointclouds).
    #[command(flatten)]
    cameras: CameraArgs,
    /// Ask every server of this multicast group (e.g. 224.0.1.187 or
    /// coap://[ff02::fd%eth0]:5683) and merge the clouds of all that answer.
    #[arg(long, value_name = "MCAST_ADDR", conflicts_with_all = ["server", "camera"],
          value_parser = values::group)]
    group: Option<String>,
    /// With --group: stop waiting once this many servers have answered (at least 1).
    #[arg(long, value_name = "N", requires = "group", conflicts_with = "rd",
          value_parser = clap::value_parser!(u64).range(1..=10_000))]
    expect: Option<u64>,
    /// With --group: ask this resource directory (RFC 9176) which servers joined the
    /// group (those registered with grp=ADDR:PORT, `serve --register`), wait exactly for
    /// them: stop as soon as each has answered (or at --wait), and name each that did not
    /// by its endpoint name and address (exit status 6).
    #[arg(long, value_name = "coap://HOST[:PORT]", requires = "group",
          value_parser = values::coap_uri)]
    rd: Option<String>,
    /// With --group: the local address to send from; by default the kernel chooses per
    /// destination (the servers accept the follow-ups of a group request from any of the
    /// client's addresses).
    #[arg(long, value_name = "ADDR", requires = "group")]
    bind: Option<std::net::IpAddr>,
    /// With --group: how long to collect answers, in seconds (above 0; 3 by default).
    #[arg(
        long,
        value_name = "SECONDS",
        requires = "group",
        value_parser = values::positive_seconds
    )]
    wait: Option<Duration>,
    /// First prepare the server's cameras as `demo` does (and the thesis's client
    /// expects): roi3d becomes the space above the floor within 1 m of the origin, so
    /// the floor is not sent, and the flying-pixel stage and the spatial filter run
    /// (the first drops the pixels that float beyond a parcel's edge); the rest of each
    /// camera's application-config stays. This changes the cameras' settings on the server, for
    /// every client and across restarts (the server persists them); what changed is
    /// printed on standard error. Not with --group.
    #[arg(long, conflicts_with = "group")]
    prepare: bool,
    /// Measure on the server (`POST /cams/dimensions`, an extension of coapcam): it
    /// grabs and merges its cameras, measures, and sends only the result, about a
    /// kilobyte instead of the point clouds. The default when the server offers it and
    /// neither --camera nor --group is given; with --edge a server without it is an
    /// error.
    #[arg(long, conflicts_with_all = ["camera", "group", "clouds"])]
    edge: bool,
    /// Grab the point clouds and measure here, even when the server could measure.
    #[arg(long)]
    clouds: bool,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
    /// Also read the codes on the parcel (QR, Code 128, Data Matrix, EAN-13, UPC-A,
    /// PDF417) from a new color image of each camera (`codes` in the JSON; at the edge the
    /// server reads them, while it grabs the clouds). The color stream first becomes
    /// 1920x1080 (on the server, for every client), where a code may be a third smaller
    /// than at 1280x720.
    #[arg(long)]
    codes: bool,
    /// Draw the measured box and its dimensions onto a new color image of the first
    /// camera and write it as PNG (the name must end in .png). A refused parcel is drawn
    /// as its footprint on the floor, with the reason. With nothing on the table nothing
    /// is drawn and no file written (said on standard error).
    #[arg(long, value_name = "FILE.png")]
    annotate: Option<PathBuf>,
    /// Divisor of the volumetric weight, cm³ per kg, 100 to 100000 (5000 is the common
    /// courier convention, 6000 is used too).
    #[arg(long, value_name = "CM3_PER_KG", default_value = "5000",
          value_parser = values::volumetric_divisor)]
    volumetric_divisor: f64,
    /// Round each dimension up to a multiple of this many millimetres, 0.1 to 1000 (a
    /// carrier's rule, e.g. 10), instead of to the nearest multiple of its division; the
    /// volume and volumetric weight follow the rounded dimensions.
    #[arg(long, value_name = "MM", value_parser = values::round_up_mm)]
    round_up_mm: Option<f64>,
    /// The accuracy division d, millimetres: each parcel's dimensions (the numbers to bill
    /// on) are rounded to the nearest multiple of d, or of 2 d above 200 d (1,000 mm at
    /// d = 5). Dimensions below 10 d (length, width) or 2 d (height), or above 300 d
    /// (length, width) or 200 d (height), are out of range, and the parcel is refused (exit
    /// status 10 when it is the largest).
    #[arg(long, value_name = "MM", default_value = "5", value_parser = values::division_mm)]
    division_mm: f64,
    /// The most the cameras' capture times may differ, in milliseconds, each corrected
    /// by its server's clock offset (estimated from the exchanges: the server's receive
    /// and transmit times ride in every answer); frames further apart are not merged
    /// (exit status 9, the camera named). By default one frame period at the slowest
    /// camera's rate (33.3 ms at 30 fps). A camera whose frame was captured more than
    /// this plus a frame period before the grab asked for it, or that serves the same
    /// frame again, is stale (exit status 9 too). From 0.001 to 10000.
    #[arg(long, value_name = "MS", value_parser = values::max_skew_ms)]
    max_skew_ms: Option<f64>,
    #[command(flatten)]
    dimension: DimensionArgs,
    #[command(flatten)]
    transmission: TransmissionArgs,
}

/// Runs `measure`: [`Exit::Uncalibrated`] when a camera is not calibrated (no
/// dimensions), [`Exit::Empty`] when nothing is on the table, [`Exit::Fewer`] when fewer
/// servers of a group answered than `--expect`.
pub(crate) async fn run(args: MeasureArgs) -> anyhow::Result<Exit> {
    check_flags(&args)?;
    let billing = Billing {
        divisor_cm3_per_kg: args.volumetric_divisor,
        round_up_mm: args.round_up_mm,
        division: Division {
            d_mm: args.division_mm,
        },
    };
    let (client, source, members) = connect(&args).await?;
    let edge = match (&source, args.clouds) {
        (Source::All, false) => measure_edge(&client, &args, &billing).await?,
        _ => None,
    };
    // Servers of a group that failed: their cameras are missing (exit status 6).
    let (mut m, mut missing) = match edge {
        Some(m) => (m, false),
        None => measure_here(&client, &source, &args, &billing)
            .await
            .map_err(|e| loopback_hint(e, &args))?,
    };
    missing |= missing_servers(&mut m, &source, &members);
    for w in &m.warnings {
        eprintln!("coapcam: warning: {w}");
    }
    if args.json {
        outln!("{}", m.to_json()?);
    } else {
        outln!("{}", m.text());
    }
    let parcel = m.parcel();
    annotate_parcel(&client, &m, &parcel, &args).await?;
    Ok(if matches!(m.parcel, Found::Unsynced { .. }) {
        Exit::Unsynced
    } else if matches!(m.parcel, Found::Uncalibrated { .. }) {
        Exit::Uncalibrated
    } else if matches!(parcel, Parcel::Nothing { .. }) {
        Exit::Empty
    } else if matches!(parcel, Parcel::Refused { .. }) {
        Exit::Unsupported
    } else if missing && matches!(source, Source::Group { .. }) {
        Exit::Fewer
    } else {
        Exit::Success
    })
}

/// What clap cannot check of the flags alone: a usage error (exit 2) before anything is
/// sent.
fn check_flags(args: &MeasureArgs) -> anyhow::Result<()> {
    if let Some(path) = &args.annotate
        && !path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("png"))
    {
        usage!(
            "--annotate writes PNG: give a file name ending in .png, not {}",
            path.display()
        );
    }
    // clap waives `requires = "group"` once --server, which conflicts with --group, is
    // given: checked here.
    if args.group.is_none() {
        for (given, flag) in [
            (args.expect.is_some(), "--expect"),
            (args.bind.is_some(), "--bind"),
            (args.wait.is_some(), "--wait"),
        ] {
            if given {
                usage!("{flag} is for --group MCAST_ADDR");
            }
        }
    }
    if let Some(path) = &args.annotate {
        folder_exists(path)?;
    }
    Ok(())
}

/// The client, what it measures, and the members of the group a directory lists (--rd).
async fn connect(args: &MeasureArgs) -> anyhow::Result<(CamClient, Source, Vec<Endpoint>)> {
    let timeout = args.transmission.timeout();
    let config = args.transmission.endpoint_config();
    // The members a directory lists (--rd).
    let mut members: Vec<Endpoint> = Vec::new();
    let (client, source) = match (&args.group, args.cameras.server()) {
        (Some(g), _) => {
            let group = group_address(g).await?;
            let wait = args.wait.unwrap_or(Duration::from_secs(3));
            let client = CamClient::for_group(group, args.bind, config, timeout)?
                .with_progress(Bars::shown());
            let expect = args.expect.map(|n| n as usize);
            if let Some(rd) = &args.rd {
                members = group_members(rd, group, &client, timeout).await?;
            }
            (
                client,
                Source::Group {
                    group,
                    expect,
                    wait,
                    members: members.iter().filter_map(|m| m.addr).collect(),
                },
            )
        }
        (None, Some(server)) if args.cameras.servers().len() > 1 => {
            if args.edge || args.prepare || args.cameras.camera.is_some() {
                bail!(
                    "with several --server the clouds of every camera are merged here: leave out --edge, --prepare and --camera"
                );
            }
            let psk = args.transmission.psk();
            let client = CamClient::connect(server, config, psk.as_ref(), timeout)
                .await?
                .with_progress(Bars::shown());
            let mut servers = vec![client.server()];
            let scheme = |uri: &Uri| (uri.secure, uri.tcp, uri.ws);
            let first = scheme(&Uri::parse(server)?);
            for uri in &args.cameras.servers()[1..] {
                let parsed = Uri::parse(uri)?;
                if scheme(&parsed) != first {
                    bail!(
                        "--server {uri}: give every --server the scheme of the first (one client reaches them all)"
                    );
                }
                let addr = parsed
                    .resolve()
                    .await
                    .with_context(|| format!("resolving {}", parsed.host))?;
                if servers.contains(&addr) {
                    bail!("--server {uri} is given twice");
                }
                servers.push(addr);
            }
            (client, Source::Servers(servers))
        }
        (None, Some(server)) => {
            let psk = args.transmission.psk();
            let client = CamClient::connect(server, config, psk.as_ref(), timeout)
                .await?
                .with_progress(Bars::shown());
            if args.prepare {
                let serials = match &args.cameras.camera {
                    Some(sn) => vec![sn.clone()],
                    None => client.cameras().await?,
                };
                prepare_cameras(&client, &serials, 1.0, args.codes).await?;
                eprintln!(
                    "coapcam: prepared camera(s) {} on the server, for every client: roi3d from {:.0} mm above the floor, flying-pixel stage and spatial filter on{}",
                    serials.join(", "),
                    FLOOR_CUT_M * 1e3,
                    if args.codes { ", color 1920x1080" } else { "" }
                );
            } else if args.codes && (args.cameras.camera.is_some() || args.clouds) {
                // This client reads the codes: their color mode first (at the edge the
                // server sets it itself).
                let serials = match &args.cameras.camera {
                    Some(sn) => vec![sn.clone()],
                    None => client.cameras().await?,
                };
                for (sn, (w, h)) in color_for_codes(&client, &serials).await? {
                    eprintln!(
                        "coapcam: camera {sn}: color set to 1920x1080 for the codes (was {w}x{h}), on the server, for every client"
                    );
                }
            }
            let source = match &args.cameras.camera {
                Some(sn) => Source::Camera(sn.clone()),
                None => Source::All,
            };
            (client, source)
        }
        (None, None) => bail!("give --server URI or --group MCAST_ADDR"),
    };
    Ok((client, source, members))
}

/// The server's own measurement of every camera (/cams/dimensions), or `None` when it
/// does not offer one.
async fn measure_edge(
    client: &CamClient,
    args: &MeasureArgs,
    billing: &Billing,
) -> anyhow::Result<Option<Measurement>> {
    let query = EdgeQuery {
        codes: args.codes,
        config: args.dimension.config(),
        billing: *billing,
    };
    let started = Instant::now();
    let measured = client.measure_edge(&query).await?;
    if measured.is_none() && args.edge {
        bail!(
            "{} does not offer /cams/dimensions (measurement at the edge); leave out --edge",
            client.server()
        );
    }
    Ok(measured.map(|(mut m, bytes)| {
        m.servers = vec![client.server(); m.cameras.len()];
        m.cycle_ms = Some(report::ms(started.elapsed()));
        m.received_bytes = Some(bytes as u64);
        m
    }))
}

/// Warns of the servers of a group that did not answer (fewer than --expect, or a member
/// the directory lists); whether any did not.
fn missing_servers(m: &mut Measurement, source: &Source, members: &[Endpoint]) -> bool {
    let mut missing = false;
    if let Source::Group {
        group,
        expect: Some(expected),
        ..
    } = source
    {
        let answered = m.servers.iter().collect::<BTreeSet<_>>().len();
        if answered < *expected {
            missing = true;
            m.warnings.push(format!(
                "{answered} of the {expected} expected servers of the group {group} answered"
            ));
        }
    }
    for member in members {
        if member.addr.is_none_or(|a| !m.servers.contains(&a)) {
            missing = true;
            m.warnings.push(format!(
                "{} ({}), a member of the group the directory lists, did not answer",
                member.ep, member.base
            ));
        }
    }
    missing
}

/// Draws the measured parcel onto a camera's color image (--annotate); a refused one as
/// its footprint, with why.
async fn annotate_parcel(
    client: &CamClient,
    m: &Measurement,
    parcel: &Parcel,
    args: &MeasureArgs,
) -> anyhow::Result<()> {
    let Some(path) = &args.annotate else {
        return Ok(());
    };
    if !matches!(parcel, Parcel::Measured(..) | Parcel::Refused { .. }) {
        eprintln!(
            "coapcam: no parcel was measured, so nothing to draw: {} not written",
            path.display()
        );
        return Ok(());
    }
    let (server, sn) = m
        .servers
        .first()
        .zip(m.cameras.first())
        .context("no camera to take the color image from")?;
    let one = CamClient::unicast(client, *server);
    match parcel {
        Parcel::Measured(dimensions, _) => {
            let division = m.reported().and_then(|r| r.division_mm);
            annotate::from_server(&one, sn, dimensions, division, m.codes.as_deref(), path).await?;
            eprintln!("coapcam: wrote {}", path.display());
        }
        Parcel::Refused { reason, .. } => {
            // The refused parcel is the largest, the first of the list.
            let corners = m.parcels.first().map(|p| &p.corners_m);
            annotate::refused_from_server(&one, sn, corners, reason, m.codes.as_deref(), path)
                .await?;
            eprintln!(
                "coapcam: wrote {}: the refused parcel and why",
                path.display()
            );
        }
        Parcel::Nothing { .. } => {}
    }
    Ok(())
}

/// Grabs the clouds, measures them here, and reads the codes if asked: the measurement,
/// and whether servers of a group failed (their cameras are missing).
async fn measure_here(
    client: &CamClient,
    source: &Source,
    args: &MeasureArgs,
    billing: &Billing,
) -> anyhow::Result<(Measurement, bool)> {
    let limits = Limits {
        max_skew_us: args.max_skew_ms.map(|ms| (ms * 1e3).round() as i64),
        skew: true,
    };
    let here = measure_checked(client, source, &args.dimension.config(), &limits).await?;
    let calibration = calibration_of(client, &here.grabbed.cameras).await;
    let mut m = here.report_with(billing, &calibration);
    let missing = !here.grabbed.failed.is_empty();
    if args.codes && here.unsynced.is_empty() {
        let started = Instant::now();
        let codes = codes::read_cameras(client, &here.grabbed.cameras).await?;
        m.set_codes(codes, started.elapsed());
    }
    Ok((m, missing))
}

/// Where Linux shows the loopback interface's flags (hexadecimal).
const LOOPBACK_FLAGS: &str = "/sys/class/net/lo/flags";

/// A group that no server answered, sent without --bind from a machine whose loopback
/// interface has no MULTICAST flag (the kernel's default for `lo`): servers on this
/// machine's loopback addresses are not reached that way, but are from 127.0.0.1. The
/// error says so; any other error is returned as it is.
fn loopback_hint(e: anyhow::Error, args: &MeasureArgs) -> anyhow::Error {
    if args.group.is_none() || args.bind.is_some() {
        return e;
    }
    let flags = std::fs::read_to_string(LOOPBACK_FLAGS).unwrap_or_default();
    with_loopback_hint(e, lacks_multicast(&flags))
}

/// Whether interface flags as Linux writes them (`0x9`) lack IFF_MULTICAST; `false` when
/// they do not read as flags.
fn lacks_multicast(flags: &str) -> bool {
    /// IFF_MULTICAST of <linux/if.h>.
    const IFF_MULTICAST: u32 = 0x1000;
    let hex = flags.trim().trim_start_matches("0x");
    u32::from_str_radix(hex, 16).is_ok_and(|f| f & IFF_MULTICAST == 0)
}

/// `e` with the --bind advice when no member answered and the loopback interface `lacks`
/// MULTICAST; still a [`NoAnswer`](coapcam::client::NoAnswer) (exit status 4). Its text
/// is said once, though the measurement's error and its [`NoAnswer`] source say the same.
///
/// [`NoAnswer`]: coapcam::client::NoAnswer
fn with_loopback_hint(e: anyhow::Error, lacks: bool) -> anyhow::Error {
    if !lacks || !e.chain().any(|c| c.is::<coapcam::client::NoAnswer>()) {
        return e;
    }
    coapcam::client::NoAnswer(format!(
        "{}; the loopback interface lo has no MULTICAST flag, so servers on this machine's loopback addresses do not get a group request sent this way: add --bind 127.0.0.1 to reach them",
        super::error_text(e.as_ref())
    ))
    .into()
}

/// The servers the directory `rd` lists as members of `group` (endpoint lookup with
/// `grp=ADDR:PORT`).
async fn group_members(
    rd: &str,
    group: SocketAddr,
    client: &CamClient,
    timeout: Duration,
) -> anyhow::Result<Vec<Endpoint>> {
    let uri = Uri::parse(rd).context("--rd")?;
    let rd_addr = uri
        .resolve()
        .await
        .with_context(|| format!("resolving {rd}"))?;
    let query = [format!("{GROUP_ATTR}={}", group_key(group))];
    let members = lookup_endpoints(client.coap(), rd_addr, &query, timeout)
        .await
        .with_context(|| format!("asking {rd} for the members of {group}"))?;
    if members.is_empty() {
        bail!(
            "the directory {rd} lists no member of the group {}",
            group_key(group)
        );
    }
    for m in &members {
        if m.addr.is_none() {
            eprintln!(
                "coapcam: warning: {} registered the base {:?}, not a coap:// address: its answer cannot be recognized",
                m.ep, m.base
            );
        }
    }
    eprintln!(
        "coapcam: {} lists {} member(s) of {}: {}",
        rd,
        members.len(),
        group_key(group),
        members
            .iter()
            .map(|m| format!("{} ({})", m.ep, m.base))
            .collect::<Vec<_>>()
            .join(", ")
    );
    Ok(members)
}

/// The group of `--group`, as [`values::group`] wrote it (a `coap://` URI; port 5683 by
/// default), resolved.
async fn group_address(uri: &str) -> anyhow::Result<SocketAddr> {
    let text = uri;
    let addr = Uri::parse(uri)?
        .resolve()
        .await
        .with_context(|| format!("resolving {text}"))?;
    if !addr.ip().is_multicast() {
        bail!("{} is not a multicast address", addr.ip());
    }
    Ok(addr)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn no_answer_with_a_loopback_without_multicast_advises_bind() {
        assert!(lacks_multicast("0x9\n"));
        assert!(!lacks_multicast("0x1009\n"));
        assert!(!lacks_multicast(""));
        let none = || -> anyhow::Error {
            coapcam::client::NoAnswer(
                "no server of the group 224.0.1.187:5683 answered within 1s".to_owned(),
            )
            .into()
        };
        let hinted = with_loopback_hint(none(), true);
        let text = format!("{hinted:#}");
        assert!(
            text.starts_with("no server of the group 224.0.1.187:5683 answered within 1s; ")
                && text.contains("lo has no MULTICAST flag")
                && text.contains("--bind 127.0.0.1"),
            "{text}"
        );
        assert!(
            hinted.is::<coapcam::client::NoAnswer>(),
            "still exit status 4"
        );
        assert!(!format!("{:#}", with_loopback_hint(none(), false)).contains("--bind"));
        let other = with_loopback_hint(anyhow::anyhow!("a file error"), true);
        assert_eq!(format!("{other:#}"), "a file error");
    }

    /// A group that nobody answered, as the measurement returns it (a [`MeasureError`]
    /// whose source is the [`NoAnswer`]): exit status 4, and the hint says it once.
    ///
    /// [`MeasureError`]: coapcam::client::measure::MeasureError
    /// [`NoAnswer`]: coapcam::client::NoAnswer
    #[test]
    fn a_measurement_nobody_answered_is_exit_4_said_once() {
        let said = "no server of the group 224.0.1.187:5683 answered within 1s";
        let none = || -> anyhow::Error {
            coapcam::client::measure::MeasureError::NoAnswer(coapcam::client::NoAnswer(
                said.to_owned(),
            ))
            .into()
        };
        assert_eq!(super::super::exit_status(&none()), Some(Exit::NoAnswer));
        assert_eq!(super::super::error_text(none().as_ref()), said);
        let hinted = with_loopback_hint(none(), true);
        assert_eq!(super::super::exit_status(&hinted), Some(Exit::NoAnswer));
        let text = format!("{hinted:#}");
        assert!(
            text.starts_with(&format!("{said}; the loopback interface")),
            "{text}"
        );
    }
}
