//! `coapcam rd`: a resource directory (RFC 9176) until SIGINT, SIGTERM or `--duration`.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context as _;
use clap::Args;
use coap::EndpointConfig;
use coap_net::{Client, Router, Server, ServerConfig};
use coap_rd::Limits;
use coap_rd::service::{self, Service, Store};
use tokio::signal::unix::{SignalKind, signal};

/// Flags of `rd`.
#[derive(Debug, Args)]
pub(crate) struct RdArgs {
    /// Address to listen on; repeat for several (default 0.0.0.0:5683 and [::]:5683).
    #[arg(long, value_name = "ADDR:PORT")]
    bind: Vec<SocketAddr>,
    /// Where the registrations are kept, one file each under DIR/rd/, so they outlive a
    /// restart (default: $XDG_STATE_HOME/coapcam, ~/.local/state/coapcam, else
    /// ./coapcam-state).
    #[arg(long, value_name = "DIR")]
    state_dir: Option<PathBuf>,
    /// Keep the registrations in memory only: a restart forgets them.
    #[arg(long, conflicts_with = "state_dir")]
    no_state: bool,
    /// The most registrations held at once; past it a registration answers 5.03 with
    /// Max-Age 60.
    #[arg(long, value_name = "N", default_value_t = (Limits::default().max_registrations) as u64,
          value_parser = clap::value_parser!(u64).range(1..=10_000_000))]
    max_registrations: u64,
    /// The most memory the registrations may be counted for together, in MiB (each
    /// counts its text and a share for the structures holding it).
    #[arg(long, value_name = "MIB", default_value_t = (Limits::default().max_bytes >> 20) as u64,
          value_parser = clap::value_parser!(u64).range(1..=1_048_576))]
    max_mib: u64,
    /// The most registrations one client (an IPv4 address, an IPv6 /64) may hold; past
    /// it 4.03.
    #[arg(long, value_name = "N", default_value_t = (Limits::default().per_peer) as u64,
          value_parser = clap::value_parser!(u64).range(1..=10_000_000))]
    per_peer: u64,
    /// The most KiB one client's registrations (an IPv4 address, an IPv6 /64) may be
    /// counted for; past it 4.03.
    #[arg(long, value_name = "KIB", default_value_t = (Limits::default().per_peer_bytes >> 10) as u64,
          value_parser = clap::value_parser!(u64).range(1..=1_048_576))]
    per_peer_kib: u64,
    /// The largest link-format document one registration may carry, in KiB; a larger one
    /// answers 4.13.
    #[arg(long, value_name = "KIB", default_value_t = (Limits::default().max_document >> 10) as u64,
          value_parser = clap::value_parser!(u64).range(1..=1024))]
    max_document_kib: u64,
    /// Answer clients off this machine in full before their address is verified (RFC
    /// 9175 Echo), for lookup clients that do not implement Echo (aiocoap 0.4.17) on a
    /// network you trust; a lookup's answer can be far larger than its request.
    /// Registering, updating and removing still need a fresh Echo value.
    #[arg(long)]
    no_address_check: bool,
    /// Stop after this many seconds, above 0 (default: run until interrupted).
    #[arg(long, value_name = "SECONDS", value_parser = super::values::positive_seconds)]
    duration: Option<Duration>,
}

/// Runs `rd` until a signal or `--duration`.
pub(crate) async fn run(args: RdArgs) -> anyhow::Result<()> {
    let binds = super::binds_or_default(&args.bind);
    let limits = Limits {
        max_registrations: usize::try_from(args.max_registrations)?,
        max_bytes: usize::try_from(args.max_mib << 20)?,
        per_peer: usize::try_from(args.per_peer)?,
        per_peer_bytes: usize::try_from(args.per_peer_kib << 10)?,
        max_document: usize::try_from(args.max_document_kib << 10)?,
    };
    let store = if args.no_state {
        None
    } else {
        let dir = args
            .state_dir
            .clone()
            .unwrap_or_else(super::default_state_dir)
            .join("rd");
        Some(Store::open(&dir)?)
    };
    let endpoint = EndpointConfig {
        rng_seed: coap_net::fresh_seed(),
        verify_addresses: !args.no_address_check,
        limits: service::endpoint_limits(&limits),
        ..EndpointConfig::default()
    };
    // Simple registration asks the endpoints for their links from a client socket of
    // its own, one per address family in use.
    let fetcher = Client::bind(
        if binds.iter().all(SocketAddr::is_ipv4) {
            SocketAddr::from(([0, 0, 0, 0], 0))
        } else {
            SocketAddr::from(([0u16; 8], 0))
        },
        endpoint.clone(),
    )
    .context("binding the client of simple registration")?;
    let service = Service::new(limits, store, fetcher, !args.no_address_check)?;
    let held = service.directory().len();
    let router = Router::new();
    service.route(&router);
    let server = Server::bind(
        &binds,
        ServerConfig {
            endpoint,
            ..ServerConfig::default()
        },
        router,
    )
    .with_context(|| format!("binding {binds:?}"))?;
    let sweep = service::spawn_sweep(Arc::clone(&service));
    let mut terminate =
        signal(SignalKind::terminate()).context("installing the SIGTERM handler")?;
    let mut interrupt = signal(SignalKind::interrupt()).context("installing the SIGINT handler")?;
    if args.no_address_check {
        eprintln!(
            "coapcam: warning: clients are answered in full before their address is verified (--no-address-check)"
        );
    }
    if held > 0 {
        eprintln!("coapcam: {held} registrations kept from before");
    }
    for a in server.local_addrs() {
        eprintln!("coapcam: resource directory on {a}");
    }
    let duration = async {
        match args.duration {
            Some(d) => tokio::time::sleep(d).await,
            None => std::future::pending().await,
        }
    };
    tokio::select! {
        _ = interrupt.recv() => {}
        _ = terminate.recv() => {}
        () = duration => {}
    }
    sweep.abort();
    drop(server);
    Ok(())
}
