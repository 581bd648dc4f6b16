//! `coapcam serve`: the station (the library's [`Station`]: a camera server, and with
//! cameras its results log and outputs) until SIGINT, SIGTERM or `--duration`.

use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context as _;
use clap::Args;
use coap::EndpointConfig;
use coap_rd::registrant::{Registrant, RegistrantConfig};
use coapcam::server::{self, Identities};
use coapcam::station::log::Retention;
use coapcam::station::watch::AutoConfig;
use coapcam::station::{self, Station};
use rgbd::Scene;
use tokio::signal::unix::{SignalKind, signal};

use super::{TransmissionArgs, usage, values};

/// Flags of `serve`.
#[derive(Debug, Args)]
pub(crate) struct ServeArgs {
    /// Take the flags from this TOML file: each key is a flag without its -- (`bind =
    /// ["0.0.0.0:5683"]`, `auto-measure = true`, `grab-memory = 512`); a flag given on
    /// the command line overrides its key. An unknown key or a bad value exits 2 naming
    /// it and its line (docs/station.md, "A configuration file").
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Print the configuration in effect (the flags given, with --config's keys) as a
    /// file for --config, and exit: passwords in URLs are masked, files of keys are
    /// named by their path.
    #[arg(long)]
    #[allow(dead_code, reason = "done by cli::config before serve is parsed")]
    print_config: bool,
    /// Address to listen on; repeat for several (default 0.0.0.0:5683 and [::]:5683).
    #[arg(long, value_name = "ADDR:PORT")]
    bind: Vec<SocketAddr>,
    /// Serve no cameras (a plain CoAP server, e.g. with --static).
    #[arg(long, conflicts_with = "scene")]
    no_cameras: bool,
    /// Synthetic cameras of this scene file (default: the built-in single-camera scene).
    #[arg(long, value_name = "FILE")]
    scene: Option<PathBuf>,
    #[command(flatten)]
    backends: coapcam::backends::Backends,
    /// Where camera configuration is persisted per serial (default:
    /// $XDG_STATE_HOME/coapcam, ~/.local/state/coapcam, else ./coapcam-state).
    #[arg(long, value_name = "DIR")]
    state_dir: Option<PathBuf>,
    /// Serve the regular files of DIR at /files/<name>, read-only unless --writable.
    /// The resources are observable: a changed file is notified to its observers.
    #[arg(long = "static", value_name = "DIR")]
    static_dir: Option<PathBuf>,
    /// Let clients change --static DIR: PUT /files/<name> creates or replaces a file
    /// (If-Match and If-None-Match honoured), POST /files creates one under a new name
    /// (2.01 with Location-Path), DELETE removes one.
    #[arg(long, requires = "static_dir")]
    writable: bool,
    /// With --writable: the most bytes the served files may take together; a PUT or POST
    /// that would go beyond it answers 4.13 and writes nothing. Each file counts what it
    /// takes: its bytes in whole 4 KiB blocks (at least one) and its link in discovery.
    #[arg(long, value_name = "BYTES", requires = "writable")]
    quota: Option<u64>,
    /// Join this multicast group on start (e.g. 224.0.1.187 or ff02::fd), on the server's
    /// port; repeatable. Listed in /coap-group, where clients add and remove memberships.
    #[arg(long, value_name = "MCAST_ADDR")]
    group: Vec<IpAddr>,
    /// IPv6 interface index for --group (0: the system's default).
    #[arg(long, value_name = "INDEX", default_value_t = 0)]
    group_interface: u32,
    /// Accept configuration changes (PUT and DELETE, and POST to /coap-group, /files and
    /// /cams/<name>) from any address. Without it they are accepted only from this
    /// machine (loopback) and answer 4.03 from elsewhere: coapcam has no authentication
    /// yet, so anyone who can reach the port could change the cameras.
    #[arg(long)]
    allow_unauthenticated_config: bool,
    /// Answer clients off this machine in full before their address is verified. By
    /// default (RFC 9175) a client whose address has not been proven gets an Echo
    /// challenge (4.01) before the server works on its request, and at most three times
    /// the bytes it sent; clients that implement Echo (coapcam, libcoap) repeat the
    /// request once and go on. For clients that do not (aiocoap 0.4.17) on a
    /// network you trust; it lets a forged source address turn the server into an
    /// amplifier.
    #[arg(long)]
    no_address_check: bool,
    /// Also answer coaps:// (DTLS 1.2 with pre-shared keys, RFC 7252 §9) on this address,
    /// e.g. 0.0.0.0:5684; repeatable. Needs --psk-file.
    #[arg(long, value_name = "ADDR:PORT", requires = "psk_file")]
    coaps: Vec<SocketAddr>,
    /// Also answer coap+tcp:// (CoAP over TCP, RFC 8323) on this address, e.g.
    /// 0.0.0.0:5683 (TCP's port, beside UDP's); repeatable. The same resources as over
    /// UDP; each answer goes whole in one message, up to the client's Max-Message-Size
    /// (no block-wise transfer or Observe over TCP yet), and requests may carry up to
    /// 1 MiB; at most 64 connections, each closed after 60 s idle. Configuration changes over TCP come from this machine only (TCP's handshake
    /// proves the client's address), unless --allow-unauthenticated-config.
    #[arg(long, value_name = "ADDR:PORT")]
    bind_tcp: Vec<SocketAddr>,
    /// Also answer coap+ws:// (CoAP over WebSockets, RFC 8323 §4) on this address, e.g.
    /// 0.0.0.0:80 (the scheme's default port) or 127.0.0.1:8080; repeatable. WebSocket
    /// clients connect to /.well-known/coap with the subprotocol "coap". The same
    /// resources and bounds as --bind-tcp (64 connections, 60 s idle, 1 MiB requests),
    /// and the same rule for configuration changes.
    #[arg(long, value_name = "ADDR:PORT")]
    bind_ws: Vec<SocketAddr>,
    /// Also answer coaps+tcp:// (CoAP over TLS, RFC 8323) on this address, e.g.
    /// 0.0.0.0:5684; repeatable. Needs --psk-file: a client must present one of its
    /// identities and keys (TLS 1.3 or 1.2 with a pre-shared key, no certificates), which
    /// then counts as over coaps://. Otherwise as --bind-tcp.
    #[arg(long, value_name = "ADDR:PORT", requires = "psk_file")]
    bind_tls: Vec<SocketAddr>,
    /// Also answer coaps+ws:// (CoAP over WebSockets over TLS, wss) on this address, e.g.
    /// 0.0.0.0:443 (the scheme's default port) or 127.0.0.1:8443; repeatable. Needs
    /// --psk-file, with the keys as --bind-tls; otherwise as --bind-ws.
    #[arg(long, value_name = "ADDR:PORT", requires = "psk_file")]
    bind_wss: Vec<SocketAddr>,
    /// The DTLS and TLS identities, one per line: `IDENTITY KEY ROLE`, ROLE `read` (GET, grabs,
    /// discovery, Observe) or `configure` (also PUT, DELETE, POST to /coap-group, /files
    /// and /cams/<name>). With it, configuration changes need a `configure` identity
    /// (4.03 for a `read` one, 4.01 over plain CoAP), except from this machine.
    #[arg(
        long,
        value_name = "FILE",
        conflicts_with = "allow_unauthenticated_config"
    )]
    psk_file: Option<PathBuf>,
    /// The memory grabs in progress may take together, in MiB. Each grab reserves its
    /// estimated peak (about 29 MiB for a 1280x720 point cloud) before it starts; one
    /// that would pass the budget answers 5.03 with Max-Age 1 (clients retry then).
    #[arg(long, value_name = "MIB", default_value_t = 256,
          value_parser = clap::value_parser!(u64).range(1..=1_048_576))]
    grab_memory: u64,
    /// Live streams (observations of /cams/<sn>/<stream>/live) a client address may have
    /// at once; the next answers 4.29 Too Many Requests.
    #[arg(long, value_name = "N", default_value_t = 4,
          value_parser = clap::value_parser!(u64).range(1..=1024))]
    live_streams_per_client: u64,
    /// Live streams in all; the next answers 5.03 with Max-Age 5. Each stream of another
    /// camera, stream or representation grabs and encodes its frames; observers of the
    /// same share them.
    #[arg(long, value_name = "N", default_value_t = 32,
          value_parser = clap::value_parser!(u64).range(1..=1024))]
    live_streams: u64,
    /// The station's name, in every record of the results log (default: the host name).
    /// With --mqtt it is one topic level, so no /, + or #.
    #[arg(long, value_name = "NAME")]
    station_name: Option<String>,
    /// The results log: every measurement is recorded in this SQLite file, append-only
    /// and hash-chained (`coapcam results verify FILE` checks it) and served at
    /// /station/measurements (default: results.sqlite in the state directory). With
    /// --no-cameras: an archived log (the file must exist), served to read as it is.
    #[arg(long, value_name = "FILE")]
    results: Option<PathBuf>,
    /// Keep the photo and annotated picture of the newest N records only; older ones are
    /// pruned (their SHA-256s stay in the records). Default: keep every picture.
    #[arg(long, value_name = "N", conflicts_with = "no_cameras")]
    results_keep_pictures: Option<u64>,
    /// Keep the results log's records and pictures within BYTES, pruning the oldest
    /// pictures first. Records are never dropped: past the limit with every picture
    /// pruned, recording goes on and the server warns. Default: no limit.
    #[arg(long, value_name = "BYTES", conflicts_with = "no_cameras")]
    results_max_bytes: Option<u64>,
    /// Sign every record of the results log with the station key in FILE (Ed25519; the
    /// key stays outside the log). The file must exist, readable by its owner only: make
    /// it once with `coapcam results keygen FILE`, which prints the public key. The
    /// public key is published at /api/station and CoAP /station, and
    /// `coapcam results verify LOG --public-key KEY` checks every signature.
    #[arg(long, value_name = "FILE", conflicts_with = "no_cameras")]
    signing_key: Option<PathBuf>,
    #[command(flatten)]
    outputs: station::Outputs,
    /// Serve the station's page and its HTTP API (docs/station.md "HTTP") on this
    /// address; a bare port means 127.0.0.1:PORT. Reading is open to every client;
    /// POST /api/measure only from this machine unless --allow-unauthenticated-config.
    /// Plain HTTP/1.1, no TLS: put a TLS proxy in front to reach it across networks.
    #[arg(long, value_name = "ADDR:PORT", value_parser = station::http::parse_listen, conflicts_with = "no_cameras")]
    http: Option<SocketAddr>,
    /// A CoAP server the HTTP-CoAP proxy (/hc/coap://...) may reach, besides this
    /// server's own addresses (the only ones by default); repeatable. HOST is an IP
    /// address or a name (resolved at each request); without PORT any port of it. The
    /// decision is made on the address the target resolves to: loopback addresses other
    /// than this server's own (another server of this machine) are refused unless named
    /// here, multicast and broadcast always.
    #[arg(long, value_name = "HOST[:PORT]", requires = "http")]
    proxy_allow: Vec<station::http::proxy::Allowed>,
    /// Measure by itself: watch the table through the calibrated cameras' depth (a few
    /// looks a second, every fourth pixel or so) and, when a parcel has arrived and stood
    /// still for --still-ms, measure it once (dimensions, the codes, a photo and the
    /// annotated picture) into the results log, recorded as triggered "auto". It is
    /// measured again only after the table was empty or the parcel moved; nothing is
    /// measured while it moves. Uncalibrated cameras are not watched (a warning names
    /// them). With real cameras, --realsense-streaming keeps looks cheap.
    #[arg(long, conflicts_with = "no_cameras")]
    auto_measure: bool,
    /// With --auto-measure: how long a parcel's height map must stay the same before it
    /// is measured, in milliseconds. 600 by default: a parcel let go of has settled and
    /// the hand is away by then, and it is measured within about a second of standing
    /// still; raise it where parcels are placed slowly or wobble.
    #[arg(long, value_name = "MS", requires = "auto_measure", value_parser = clap::value_parser!(u64).range(100..=60_000))]
    still_ms: Option<u64>,
    /// Shift this server's clock as its clients see it by this many milliseconds (may be
    /// negative): the receive and transmit times it stamps into its answers and its
    /// frames' capture times move together, as on a host whose clock is off. For
    /// testing clients' clock-offset estimation (`measure --max-skew-ms`); a real
    /// server's clock is its system's.
    #[arg(long, value_name = "MS", default_value_t = 0, allow_negative_numbers = true,
          value_parser = clap::value_parser!(i64).range(-86_400_000..=86_400_000))]
    clock_offset_ms: i64,
    /// Register with this resource directory (RFC 9176; `coapcam rd`, aiocoap-rd,
    /// libcoap's coap-rd): the server's typed resources (its cameras', /cams/pointclouds,
    /// /coap-group, ...) and the groups it joined (endpoint attribute grp=ADDR:PORT), sent
    /// from the server's own socket so the directory sees its address. Renewed at three
    /// quarters of --rd-lifetime, registered again when cameras come or go or a group is
    /// joined or left, removed at shutdown. Without a path the registration resource is
    /// discovered (/.well-known/core?rt=core.rd).
    #[arg(long, value_name = "coap://HOST[:PORT][/PATH]", value_parser = super::values::coap_uri)]
    register: Option<String>,
    /// With --register: the endpoint name, unique in the directory (at most 63 bytes;
    /// default: the station's name).
    #[arg(long, value_name = "NAME", requires = "register")]
    rd_ep: Option<String>,
    /// With --register: the sector (d) to register in.
    #[arg(long, value_name = "NAME", requires = "register")]
    rd_sector: Option<String>,
    /// With --register: the registration's lifetime in seconds. A server stopped without
    /// removing its registration (killed, cut off) is listed until it ends.
    #[arg(long, value_name = "SECONDS", default_value_t = 120, requires = "register",
          value_parser = clap::value_parser!(u32).range(1..))]
    rd_lifetime: u32,
    /// Stop after this many seconds, above 0 (default: run until interrupted).
    #[arg(long, value_name = "SECONDS", value_parser = values::positive_seconds)]
    duration: Option<Duration>,
    #[command(flatten)]
    transmission: TransmissionArgs,
}

/// The environment variable that fixes glibc's mmap threshold, and its value (128 KiB).
const MALLOC_THRESHOLD: (&str, &str) = ("MALLOC_MMAP_THRESHOLD_", "131072");

/// Makes glibc's malloc give freed large buffers back: its mmap threshold otherwise rises
/// with each large block freed, later frames and clouds come from the heap, and what they
/// free stays resident, so the server grew to 1.7 times what its limits count
/// (docs/design.md, "Address verification, limits and the server under load"). glibc
/// reads the setting from the environment only at start, so when it is not set `serve`
/// sets it and runs itself again in the same process (`exec`, same process id). Nothing
/// happens when it is set already (an operator's own value stays), off glibc, or if the
/// exec fails.
pub(crate) fn fix_malloc_threshold() {
    use std::os::unix::process::CommandExt as _;
    let (name, value) = MALLOC_THRESHOLD;
    if !cfg!(all(target_os = "linux", target_env = "gnu")) || std::env::var_os(name).is_some() {
        return;
    }
    let Ok(exe) = std::env::current_exe() else {
        return;
    };
    let mut args = std::env::args_os();
    let arg0 = args.next().unwrap_or_else(|| exe.clone().into_os_string());
    let error = std::process::Command::new(&exe)
        .arg0(arg0)
        .args(args)
        .env(name, value)
        .exec();
    eprintln!(
        "coapcam: warning: not run again with {name}={value} ({error}); memory may grow past the limits"
    );
}

/// Runs `serve` until a signal or `--duration`.
pub(crate) async fn run(args: ServeArgs) -> anyhow::Result<()> {
    let (server, config) = config(&args)?;
    let station = Station::start(server, config).await?;
    // The station reads codes by itself: their color mode is set now and said.
    if args.auto_measure {
        for c in station.color_for_codes() {
            let warning = if c.too_far() || c.failed.is_some() {
                "warning: "
            } else {
                ""
            };
            eprintln!("coapcam: {warning}{c}");
        }
    } else if !args.no_cameras {
        eprintln!(
            "coapcam: a measurement with the codes (?codes, the page's Measure now) sets each camera's color to its largest resolution first"
        );
    }
    if let Some(path) = &args.config {
        eprintln!(
            "coapcam: configuration from {} (the flags given override it)",
            path.display()
        );
    }
    warn_of_config(&args);
    // Both handlers are in place before the server announces itself: a signal sent as soon
    // as "serving on" appears stops the server cleanly instead of killing it.
    let mut terminate =
        signal(SignalKind::terminate()).context("installing the SIGTERM handler")?;
    let mut interrupt = signal(SignalKind::interrupt()).context("installing the SIGINT handler")?;
    announce(&args, &station);
    let registrant = register(&args, &station).await?;
    let duration = async {
        match args.duration {
            Some(d) => tokio::time::sleep(d).await,
            None => std::future::pending().await,
        }
    };
    let mut why = "";
    station
        .run(async {
            why = tokio::select! {
                _ = interrupt.recv() => "SIGINT",
                _ = terminate.recv() => "SIGTERM",
                () = duration => "--duration",
            };
            // Still serving: the directory's answer comes to the server's socket.
            if let Some(registrant) = registrant {
                registrant.remove().await;
            }
        })
        .await;
    // Said, so that a log shows a stop asked for apart from a crash.
    eprintln!("coapcam: stopped cleanly ({why})");
    Ok(())
}

/// The flags lowered, in this one place, to the camera server's and the station's
/// configuration.
fn config(args: &ServeArgs) -> anyhow::Result<(server::Config, station::Config)> {
    let binds = super::binds_or_default(&args.bind);
    let cameras = if args.no_cameras {
        if args.outputs.any() {
            usage!("--no-cameras keeps no results log for an output to follow");
        }
        Vec::new()
    } else {
        let scene = match &args.scene {
            Some(path) => {
                Scene::load(path).with_context(|| format!("loading scene {}", path.display()))?
            }
            None => Scene::default_single(),
        };
        if scene.cameras.is_empty() && !args.backends.any() {
            usage!(
                "the scene {} has no [[camera]]: nothing to serve (--no-cameras serves none on purpose)",
                args.scene
                    .as_deref()
                    .map_or_else(|| "built in".into(), |p| p.display().to_string())
            );
        }
        args.backends.chosen(scene)
    };
    let identities = match &args.psk_file {
        Some(path) => Some(Arc::new(Identities::load(path)?)),
        None => None,
    };
    let server = server::Config {
        binds,
        cameras,
        state_dir: args
            .state_dir
            .clone()
            .unwrap_or_else(super::default_state_dir),
        static_dir: args.static_dir.clone(),
        writable: args.writable,
        quota: args.quota,
        groups: args.group.clone(),
        group_interface: args.group_interface,
        endpoint: EndpointConfig {
            verify_addresses: !args.no_address_check,
            ..args.transmission.endpoint_config()
        },
        allow_unauthenticated_config: args.allow_unauthenticated_config,
        grab_memory: args.grab_memory.saturating_mul(1 << 20),
        secure_binds: args.coaps.clone(),
        tcp_binds: args.bind_tcp.clone(),
        ws_binds: args.bind_ws.clone(),
        tls_binds: args.bind_tls.clone(),
        wss_binds: args.bind_wss.clone(),
        identities,
        clock_offset_us: args.clock_offset_ms.saturating_mul(1000),
        live: server::LiveLimits {
            per_client: usize::try_from(args.live_streams_per_client).unwrap_or(usize::MAX),
            total: usize::try_from(args.live_streams).unwrap_or(usize::MAX),
        },
    };
    let name = args.station_name.clone().unwrap_or_else(station::host_name);
    if let Err(e) = args.outputs.check() {
        usage!("{e}");
    }
    if let Err(e) = args.outputs.check_station(&name) {
        usage!("--station-name with --mqtt: {e}");
    }
    let station = station::Config {
        name,
        results: args.results.clone(),
        retention: Retention {
            keep_pictures: args.results_keep_pictures,
            max_bytes: args.results_max_bytes,
        },
        signing_key: args.signing_key.clone(),
        outputs: args.outputs.clone(),
        http: args.http,
        proxy_allow: args.proxy_allow.clone(),
        auto_measure: args.auto_measure.then(|| {
            let mut auto = AutoConfig::default();
            if let Some(ms) = args.still_ms {
                auto.stillness.still = Duration::from_millis(ms);
            }
            auto
        }),
    };
    Ok((server, station))
}

/// Who may change the configuration, and what is unusual.
fn warn_of_config(args: &ServeArgs) {
    if args.no_address_check {
        eprintln!(
            "coapcam: warning: clients are answered in full before their address is verified (--no-address-check)"
        );
    }
    if args.psk_file.is_some() {
        eprintln!(
            "coapcam: configuration changes need a DTLS or TLS identity of the configure role (or this machine)"
        );
    } else if args.allow_unauthenticated_config {
        eprintln!(
            "coapcam: warning: anyone who can reach this server may change its configuration (--allow-unauthenticated-config)"
        );
    } else {
        eprintln!(
            "coapcam: configuration changes are accepted only from this machine (--allow-unauthenticated-config accepts them from anywhere)"
        );
    }
}

/// Where the server and its outputs are.
fn announce(args: &ServeArgs, station: &Station) {
    for output in station.outputs() {
        eprintln!("coapcam: {output}");
    }
    if let Some(a) = station.http_addr() {
        let who = if args.allow_unauthenticated_config {
            "anyone may measure"
        } else {
            "measuring from this machine only"
        };
        eprintln!("coapcam: HTTP on http://{a}/ ({who})");
    }
    // The DTLS addresses come last.
    let addrs = station.local_addrs();
    let plain = addrs.len() - args.coaps.len();
    for (i, a) in addrs.iter().enumerate() {
        if i < plain {
            eprintln!("coapcam: serving on {a}");
        } else {
            eprintln!("coapcam: serving coaps on {a}");
        }
    }
    for a in station.tcp_addrs() {
        eprintln!("coapcam: serving coap+tcp on {a}");
    }
    for a in station.ws_addrs() {
        eprintln!("coapcam: serving coap+ws on {a}");
    }
    for a in station.tls_addrs() {
        eprintln!("coapcam: serving coaps+tcp on {a}");
    }
    for a in station.wss_addrs() {
        eprintln!("coapcam: serving coaps+ws on {a}");
    }
}

/// Registers with the directory of --register.
async fn register(args: &ServeArgs, station: &Station) -> anyhow::Result<Option<Registrant>> {
    Ok(match &args.register {
        Some(uri) => {
            let ep = args
                .rd_ep
                .clone()
                .unwrap_or_else(|| args.station_name.clone().unwrap_or_else(station::host_name));
            let config = RegistrantConfig::from_uri(
                uri,
                ep.clone(),
                args.rd_sector.clone(),
                args.rd_lifetime,
            )
            .await
            .context("--register")?;
            eprintln!(
                "coapcam: registering with {uri} as {ep} (lifetime {} s)",
                args.rd_lifetime
            );
            Some(station.register_with(config)?)
        }
        None => None,
    })
}
