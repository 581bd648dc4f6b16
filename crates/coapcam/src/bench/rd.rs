//! `bench rd`: a `coapcam rd` child process filled with registrations over loopback
//! (until the number asked for, or until it answers 5.03 because its count reached
//! `--max-mib`, 128 MiB), then timed lookups: its resident memory before and after
//! beside the bytes it counts for them, and each kind of lookup's median, 95th
//! percentile and longest time over the client's round trip.
//!
//! Every registration is a station with one camera: the typed links `serve --register`
//! sends for the built-in scene (about 900 bytes), `et=coapcam.station`, one of eight
//! groups as `grp`, its own `base`.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use coap::{Code, ContentFormat, EndpointConfig, OptionNumber, Request};
use coap_net::Client;
use coap_rd::{Directory, Limits, LookupKind, Params, Query};
use serde::Serialize;

use crate::process::{self, Proc};
use crate::stats;

/// What `bench rd` is asked to do.
#[derive(Debug, Clone)]
pub struct Config {
    /// The `coapcam` executable to run as the directory.
    pub exe: PathBuf,
    /// Registrations to fill it with.
    pub registrations: usize,
    /// Lookups of each kind to time.
    pub lookups: usize,
    /// Registrations sent at once.
    pub concurrency: usize,
    /// Full lookups (`/rd-lookup/res`, no query: every link of every registration) after the timed ones,
    /// each from a client of its own (as many clients would: the directory keeps each
    /// answer for its block-wise transfer), four at a time.
    pub full_lookups: usize,
}

/// One kind of lookup's times, milliseconds.
#[derive(Debug, Clone, Serialize)]
pub struct LookupRow {
    /// What was looked up (the query, `N` standing for the varying part).
    pub lookup: String,
    /// Links in each answer (of the last one).
    pub links: usize,
    /// Median.
    pub median_ms: f64,
    /// Nearest-rank 95th percentile.
    pub p95_ms: f64,
    /// Longest.
    pub max_ms: f64,
    /// The directory's own work of the same lookups (`Directory::lookup` in this process,
    /// no network): median, milliseconds.
    pub work_median_ms: f64,
    /// Its 95th percentile.
    pub work_p95_ms: f64,
}

/// What `bench rd` measured.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// Registrations held.
    pub registrations: usize,
    /// Whether the directory was full before all asked for were registered (5.03).
    pub full: bool,
    /// The bytes the directory counts its registrations for (the same registrations in
    /// a `Directory` in this process), KiB.
    pub counted_kib: u64,
    /// The directory's resident memory before the first registration, KiB.
    pub rss_idle_kib: u64,
    /// And after the last.
    pub rss_filled_kib: u64,
    /// Its peak, KiB.
    pub rss_peak_kib: u64,
    /// Seconds to register them all.
    pub fill_s: f64,
    /// The lookups' times.
    pub lookups: Vec<LookupRow>,
    /// Full lookups made.
    pub full_lookups: usize,
    /// Bytes of each full lookup's answer (the last one's).
    pub full_lookup_bytes: usize,
    /// Seconds the full lookups took together.
    pub full_lookups_s: f64,
    /// The directory's resident memory after the timed lookups, before the full ones, KiB.
    pub rss_looked_up_kib: u64,
    /// And after the full lookups.
    pub rss_full_kib: u64,
}

/// The links of a one-camera station (what `serve --register` registers).
fn station_links(serial: &str) -> String {
    let mut links = vec![
        r#"</coap-group>;rt="core.gp";ct=256"#.to_owned(),
        r#"</cams/pointclouds>;rt="rgbd.pointcloud";ct="42 60 65100 65103 65104""#.to_owned(),
        r#"</cams/dimensions>;rt="coapcam.dimensions";ct="50 60";obs"#.to_owned(),
        format!(r#"</cams/{serial}/color>;rt="rgbd.color";if="core.p";ct="42 23 22 60";obs"#),
        format!(
            r#"</cams/{serial}/depth>;rt="rgbd.depth";if="core.p";ct="42 23 60 65101 65102";obs"#
        ),
        format!(
            r#"</cams/{serial}/pointcloud>;rt="rgbd.pointcloud";if="core.p";ct="42 60 65100 65103 65104";obs"#
        ),
    ];
    for doc in [
        "color-settings",
        "depth-settings",
        "application-config",
        "3d-transformation",
    ] {
        links.push(format!(
            r#"</cams/{serial}/{doc}>;rt="rgbd.config";if="core.p";ct=50"#
        ));
    }
    links.join(",")
}

/// The path and query of a kind's `k`th lookup.
type LookupOf = Box<dyn Fn(usize) -> (&'static str, Vec<String>)>;

/// The query of registration `i`.
fn registration_query(i: usize) -> Vec<String> {
    vec![
        format!("ep=station-{i}"),
        "et=coapcam.station".to_owned(),
        format!("grp=224.0.1.{}:5683", 180 + i % 8),
        format!("base=coap://10.{}.{}.1", i / 250, i % 250),
        "lt=86400".to_owned(),
    ]
}

/// Resident and peak memory of process `pid`, KiB (`/proc/PID/status`).
fn memory_kib(pid: u32) -> anyhow::Result<(u64, u64)> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))
        .with_context(|| format!("reading /proc/{pid}/status"))?;
    let field = |name: &str| {
        status
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse::<u64>().ok())
            .with_context(|| format!("{name} in /proc/{pid}/status"))
    };
    Ok((field("VmRSS:")?, field("VmHWM:")?))
}

fn request(method: Code, path: &str, query: &[String]) -> Request {
    let mut r = Request::new(method, path);
    for q in query {
        r.options.push(OptionNumber::URI_QUERY, q.as_bytes());
    }
    r.timeout = Some(Duration::from_secs(30));
    r
}

/// Starts the directory, fills it, times the lookups.
///
/// # Errors
///
/// When the directory does not start, or a registration or lookup fails.
pub async fn run(config: &Config) -> anyhow::Result<Report> {
    let port = process::free_udp_port()?;
    let rd = SocketAddr::from(([127, 0, 0, 1], port));
    let mut command = Command::new(&config.exe);
    command
        .args([
            "rd",
            "--bind",
            &rd.to_string(),
            "--no-state",
            "--max-registrations",
            &config.registrations.to_string(),
            "--per-peer",
            &config.registrations.to_string(),
            "--per-peer-kib",
            "1048576",
            "--duration",
            "3600",
        ])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null());
    let mut child = Proc::spawn(command, "coapcam rd")?;
    let client = Client::bind(
        SocketAddr::from(([127, 0, 0, 1], 0)),
        EndpointConfig::default(),
    )?;
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        child.check_running()?;
        if client.ping(rd).await.is_ok() {
            break;
        }
        if Instant::now() > deadline {
            bail!("coapcam rd did not answer within 20 s");
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let (rss_idle_kib, _) = memory_kib(child.id())?;
    let started = Instant::now();
    let mut next = 0usize;
    let mut held = 0usize;
    let mut full = false;
    let mut running = tokio::task::JoinSet::new();
    while (next < config.registrations && !full) || !running.is_empty() {
        while next < config.registrations && !full && running.len() < config.concurrency.max(1) {
            let i = next;
            next += 1;
            let client = client.clone();
            running.spawn(async move {
                let query = registration_query(i);
                let mut post = request(Code::POST, "/rd", &query);
                post.options.set_uint(
                    OptionNumber::CONTENT_FORMAT,
                    u32::from(ContentFormat::LINK_FORMAT.0),
                );
                post.payload = station_links(&format!("{:012}", i)).into();
                let r = client.send(rd, post).await?;
                if r.code == Code::SERVICE_UNAVAILABLE {
                    return Ok(false);
                }
                if r.code != Code::CREATED {
                    bail!(
                        "registration {i} answered {} {}",
                        r.code,
                        String::from_utf8_lossy(&r.payload)
                    );
                }
                Ok(true)
            });
        }
        if let Some(done) = running.join_next().await {
            if done.context("a registration task failed")?? {
                held += 1;
            } else {
                full = true;
            }
        }
    }
    let fill_s = started.elapsed().as_secs_f64();
    let (rss_filled_kib, _) = memory_kib(child.id())?;
    let n = held.max(1);
    let kinds: Vec<(String, LookupOf)> = vec![
        (
            "ep lookup ?ep=station-N".to_owned(),
            Box::new(move |k| {
                (
                    "/rd-lookup/ep",
                    vec![format!("ep=station-{}", (k * 7919) % n)],
                )
            }),
        ),
        (
            "ep lookup ?grp=224.0.1.N:5683&count=50 (a group's members, first page)".to_owned(),
            Box::new(|k| {
                (
                    "/rd-lookup/ep",
                    vec![
                        format!("grp=224.0.1.{}:5683", 180 + k % 8),
                        "count=50".to_owned(),
                    ],
                )
            }),
        ),
        (
            "res lookup ?ep=station-N&rt=rgbd.color".to_owned(),
            Box::new(move |k| {
                (
                    "/rd-lookup/res",
                    vec![
                        format!("ep=station-{}", (k * 7919) % n),
                        "rt=rgbd.color".to_owned(),
                    ],
                )
            }),
        ),
        (
            "ep lookup ?page=N&count=100".to_owned(),
            Box::new(move |k| {
                (
                    "/rd-lookup/ep",
                    vec![
                        format!("page={}", k % (n / 100).max(1)),
                        "count=100".to_owned(),
                    ],
                )
            }),
        ),
    ];
    // The same registrations in a directory here, for the lookups' own work.
    let now = coap_rd::service::now_ms();
    let mut here = Directory::new(Limits {
        max_registrations: n,
        per_peer: n,
        per_peer_bytes: usize::MAX,
        max_bytes: usize::MAX,
        ..Limits::default()
    });
    let peer = SocketAddr::from(([127, 0, 0, 1], 40_000));
    // Those the directory took (when it was full, the last ones sent may not be all of
    // them, but as many).
    for i in 0..n {
        let query = registration_query(i);
        let params = Params::parse(query.iter().map(String::as_str))?;
        here.register(now, peer, params, &station_links(&format!("{i:012}")))?;
    }
    let mut lookups = Vec::new();
    for (name, make) in &kinds {
        let mut times = Vec::with_capacity(config.lookups);
        let mut links = 0;
        for k in 0..config.lookups {
            let (path, query) = make(k);
            let started = Instant::now();
            let r = client.send(rd, request(Code::GET, path, &query)).await?;
            times.push(started.elapsed().as_secs_f64() * 1e3);
            if r.code != Code::CONTENT {
                bail!("{name}: {}", r.code);
            }
            let text = std::str::from_utf8(&r.payload).context("lookup not UTF-8")?;
            links = coap::link_format::parse(text)
                .context("parsing a lookup")?
                .len();
        }
        let mut work = Vec::with_capacity(config.lookups);
        for k in 0..config.lookups {
            let (path, query) = make(k);
            let kind = if path.ends_with("/res") {
                LookupKind::Resources
            } else {
                LookupKind::Endpoints
            };
            let query = Query::parse(query.iter().map(String::as_str))?;
            let started = Instant::now();
            let found = here.lookup(now, kind, &query);
            work.push(started.elapsed().as_secs_f64() * 1e3);
            if found.links != links {
                bail!(
                    "{name}: {} links here, {links} from the directory",
                    found.links
                );
            }
        }
        lookups.push(LookupRow {
            lookup: name.clone(),
            links,
            work_median_ms: stats::median(&work).unwrap_or(f64::NAN),
            work_p95_ms: stats::percentile(&work, 0.95).unwrap_or(f64::NAN),
            median_ms: stats::median(&times).unwrap_or(f64::NAN),
            p95_ms: stats::percentile(&times, 0.95).unwrap_or(f64::NAN),
            max_ms: times.iter().copied().fold(0.0, f64::max),
        });
    }
    let (rss_looked_up_kib, _) = memory_kib(child.id())?;
    let started = Instant::now();
    let mut full_lookup_bytes = 0;
    let mut next = 0;
    let mut running = tokio::task::JoinSet::new();
    while next < config.full_lookups || !running.is_empty() {
        while next < config.full_lookups && running.len() < 4 {
            next += 1;
            running.spawn(async move {
                let client = Client::bind(
                    SocketAddr::from(([127, 0, 0, 1], 0)),
                    EndpointConfig::default(),
                )?;
                let mut get = request(Code::GET, "/rd-lookup/res", &[]);
                get.timeout = Some(Duration::from_secs(600));
                let r = client.send(rd, get).await?;
                if r.code != Code::CONTENT {
                    bail!("full lookup: {}", r.code);
                }
                Ok(r.payload.len())
            });
        }
        if let Some(done) = running.join_next().await {
            full_lookup_bytes = done.context("a full lookup failed")??;
        }
    }
    let full_lookups_s = started.elapsed().as_secs_f64();
    let (rss_full_kib, rss_peak_kib) = memory_kib(child.id())?;
    let _ = child.kill();
    let counted_kib = u64::try_from(here.bytes() / 1024).unwrap_or(u64::MAX);
    Ok(Report {
        registrations: held,
        full,
        counted_kib,
        rss_idle_kib,
        rss_filled_kib,
        rss_peak_kib,
        fill_s,
        lookups,
        full_lookups: config.full_lookups,
        full_lookup_bytes,
        full_lookups_s,
        rss_looked_up_kib,
        rss_full_kib,
    })
}
