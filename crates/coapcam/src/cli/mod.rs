//! The commands: one file per subcommand, with its clap flags and its `run`. The
//! commands share only what this file holds: the flag groups (the server and its
//! cameras, transmission parameters, the measurement's thresholds), the value parsers
//! (`values`), the progress bars, `Deferred`, which builds a command's flags only when it
//! is the one given, how a command ends (`Exit`, `exit_status`, `error_text`, `Usage`),
//! and the output macros. None imports another, and what they do is the library's.
//! `config` and `log` are `main.rs`'s: `serve --config`'s keys as flags, and the log.

pub(crate) mod bench;
pub(crate) mod calibrate;
pub(crate) mod config;
pub(crate) mod demo;
pub(crate) mod grab;
pub(crate) mod log;
pub(crate) mod markers;
pub(crate) mod measure;
pub(crate) mod monitor;
pub(crate) mod netem;
pub(crate) mod part_file;
pub(crate) mod rd;
pub(crate) mod request;
pub(crate) mod results;
pub(crate) mod serve;
pub(crate) mod values;

use std::time::Duration;

use anyhow::Context as _;
use clap::Args;
use coap::EndpointConfig;
use geometry::DimensionConfig;

/// Transmission parameters (RFC 7252 §4.8). The defaults are the RFC's; on a link whose
/// round trip is known to be short (a LAN, loopback), a shorter ACK timeout recovers a
/// lost datagram in milliseconds instead of seconds.
#[derive(Debug, Clone, Args)]
pub(crate) struct TransmissionArgs {
    /// ACK_TIMEOUT in milliseconds: a CON is sent again after this times a random factor
    /// in [1, 1.5], doubling each time (RFC 7252 default 2000).
    #[arg(long, value_name = "MS", default_value_t = 2000, value_parser = clap::value_parser!(u64).range(1..=600_000))]
    ack_timeout_ms: u64,
    /// MAX_RETRANSMIT: how often a CON is sent again before the exchange fails (RFC 7252
    /// default 4).
    #[arg(long, value_name = "N", default_value_t = 4, value_parser = clap::value_parser!(u8).range(0..=10))]
    max_retransmit: u8,
    /// NSTART: requests outstanding at once per peer (RFC 7252 default 1).
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..=64))]
    nstart: u64,
    /// Give up on a request, with every block of its body, after this many seconds (the
    /// same default in every command: a few megabytes over a slow link take minutes
    /// block by block). A request that nothing acknowledges fails sooner, after
    /// MAX_RETRANSMIT retransmissions (45-93 s with the RFC 7252 defaults).
    #[arg(long, value_name = "SECONDS", default_value = "300", value_parser = values::positive_seconds)]
    timeout: Duration,
    /// How a body that comes in blocks is moved: `window` (many block requests in
    /// flight, paced by a congestion controller, lost blocks asked for again within about
    /// a round trip; falls back to stop-and-wait with servers that refuse),
    /// `stop-and-wait` (RFC 7959: one block per round trip) or `q-block` (RFC 9177
    /// Q-Block2 and Q-Block1: the sender sends MAX_PAYLOADS blocks at a time as NONs, the
    /// receiver confirms each set and asks for missing blocks; with servers that do not
    /// know Q-Block, as `window`). Uploads are windowed only with `q-block`.
    #[arg(long, value_name = "MODE", default_value = "window")]
    transfer: TransferMode,
    /// For coaps://, coaps+tcp:// and coaps+ws:// URIs: the pre-shared key identity to
    /// present (in DTLS or TLS).
    #[arg(long, value_name = "ID", requires = "psk_key")]
    psk_identity: Option<String>,
    /// For coaps://, coaps+tcp:// and coaps+ws:// URIs: the pre-shared key of --psk-identity (its text, as libcoap's
    /// coap-client -k takes it).
    #[arg(long, value_name = "KEY", requires = "psk_identity")]
    psk_key: Option<String>,
}

/// `--transfer`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum TransferMode {
    /// Many blocks in flight.
    Window,
    /// One block per round trip (RFC 7959).
    StopAndWait,
    /// RFC 9177 Q-Block2 and Q-Block1.
    QBlock,
}

impl TransmissionArgs {
    /// A client socket for `uri`'s server at `peer`: DTLS with `--psk-identity` and
    /// `--psk-key` for `coaps://`.
    pub(crate) fn client(
        &self,
        uri: &coap_net::Uri,
        peer: std::net::SocketAddr,
    ) -> anyhow::Result<coap_net::Client> {
        Ok(coapcam::client::secured_client(
            uri,
            peer,
            self.endpoint_config(),
            self.psk().as_ref(),
        )?)
    }

    /// The DTLS client key of `--psk-identity` and `--psk-key`, if given.
    pub(crate) fn psk(&self) -> Option<coap_net::Psk> {
        let (identity, key) = (self.psk_identity.as_ref()?, self.psk_key.as_ref()?);
        Some(coap_net::Psk::Client {
            identity: identity.as_bytes().to_vec(),
            key: key.as_bytes().to_vec(),
        })
    }

    /// `--timeout`.
    pub(crate) fn timeout(&self) -> Duration {
        self.timeout
    }

    /// The endpoint configuration, with message IDs and tokens of its own
    /// ([`coap_net::fresh_seed`]).
    pub(crate) fn endpoint_config(&self) -> EndpointConfig {
        EndpointConfig {
            rng_seed: coap_net::fresh_seed(),
            ack_timeout: Duration::from_millis(self.ack_timeout_ms),
            max_retransmit: self.max_retransmit,
            nstart: self.nstart as usize,
            transfer: match self.transfer {
                TransferMode::Window => coap::Transfer::Window,
                TransferMode::StopAndWait => coap::Transfer::StopAndWait,
                TransferMode::QBlock => coap::Transfer::QBlock,
            },
            ..EndpointConfig::default()
        }
    }
}

/// The server a command talks to and which of its cameras: `--server`, `--camera`,
/// `--all`.
#[derive(Debug, Clone, Args)]
pub(crate) struct CameraArgs {
    /// The server, coap://host[:port] (or coaps:// with --psk-identity and --psk-key,
    /// coap+tcp:// over TCP, coap+ws:// over WebSockets, or coaps+tcp:// and coaps+ws://
    /// over TLS with the same keys).
    /// `measure` takes it more than once: every camera of each server, merged.
    // Required, but an argument that conflicts with one given (measure's --group) is not.
    #[arg(long, value_name = "URI", required = true, value_parser = values::coap_uri)]
    server: Vec<String>,
    /// Only this camera (its serial: a D400's 12 digits). Without it, a command that grabs one frame
    /// takes the server's camera if it has only one; the others use every camera.
    #[arg(long, value_name = "SN", conflicts_with = "all", value_parser = values::serial)]
    pub(crate) camera: Option<String>,
    /// Every camera of the server: grab merges their point clouds (POST
    /// /cams/pointclouds); measure, calibrate and monitor do so by default.
    #[arg(long)]
    pub(crate) all: bool,
}

impl CameraArgs {
    /// `--server` (the first, when given more than once); `None` only where a flag that
    /// stands for it was given (`--group`).
    pub(crate) fn server(&self) -> Option<&str> {
        self.server.first().map(String::as_str)
    }

    /// Every `--server` given.
    pub(crate) fn servers(&self) -> &[String] {
        &self.server
    }

    /// A client of `--server`, with `transmission`'s parameters.
    pub(crate) async fn connect(
        &self,
        transmission: &TransmissionArgs,
    ) -> anyhow::Result<coapcam::client::CamClient> {
        let server = anyhow::Context::context(self.server(), "give --server URI")?;
        if self.server.len() > 1 {
            anyhow::bail!("give --server once (only measure merges several servers)");
        }
        Ok(coapcam::client::CamClient::connect(
            server,
            transmission.endpoint_config(),
            transmission.psk().as_ref(),
            transmission.timeout(),
        )
        .await?)
    }
}

/// Thresholds of the measurement.
#[derive(Debug, Clone, Args)]
pub(crate) struct DimensionArgs {
    /// Points lower than this above the floor are floor, in millimetres (0 to 1000).
    #[arg(long, value_name = "MM", default_value = "10", value_parser = values::min_height_mm)]
    min_height_mm: f32,
    /// Points closer than this belong to one object, in millimetres (5 to 500: below 5
    /// a D415's points at a metre or more lie too far apart and a parcel falls into
    /// pieces; above 500 it merges with whatever stands beside it).
    #[arg(long, value_name = "MM", default_value = "10", value_parser = values::cluster_mm)]
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

/// A subcommand's arguments, built by clap only when that subcommand is the one given
/// (`Command::defer`): `coapcam get` does not build the arguments of every other command
/// at each start.
#[derive(Debug)]
pub(crate) struct Deferred<T>(pub(crate) T);

impl<T: clap::FromArgMatches> clap::FromArgMatches for Deferred<T> {
    fn from_arg_matches(matches: &clap::ArgMatches) -> Result<Self, clap::Error> {
        T::from_arg_matches(matches).map(Self)
    }

    fn update_from_arg_matches(&mut self, matches: &clap::ArgMatches) -> Result<(), clap::Error> {
        self.0.update_from_arg_matches(matches)
    }
}

impl<T: Args> Args for Deferred<T> {
    fn augment_args(cmd: clap::Command) -> clap::Command {
        cmd.defer(|cmd| keep_about(cmd, T::augment_args))
    }

    fn augment_args_for_update(cmd: clap::Command) -> clap::Command {
        cmd.defer(|cmd| keep_about(cmd, T::augment_args_for_update))
    }

    fn group_id() -> Option<clap::Id> {
        T::group_id()
    }
}

/// Runs `augment` on a subcommand but keeps the subcommand's description: built late, the
/// arguments' own doc comment would otherwise replace it.
fn keep_about(cmd: clap::Command, augment: fn(clap::Command) -> clap::Command) -> clap::Command {
    use clap::builder::Resettable;
    let kept = |text: Option<&clap::builder::StyledStr>| {
        text.cloned().map_or(Resettable::Reset, Resettable::Value)
    };
    let (about, long_about) = (kept(cmd.get_about()), kept(cmd.get_long_about()));
    augment(cmd).about(about).long_about(long_about)
}

/// How a command ended, as its exit status; README.md's table lists them. A usage error
/// is 2 (clap's, or [`Usage`] for what clap cannot check alone); an error's status is
/// [`exit_status`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Exit {
    /// 0: done.
    Success,
    /// 1: failed: a network or file error, a malformed answer, a protocol violation.
    Failure,
    /// 2: usage: a bad flag or value; nothing was sent.
    Usage,
    /// 3: the server answered with an error response (4.xx, 5.xx) or refused what was
    /// asked (an observation it does not allow); the code and diagnostic were printed.
    Refused,
    /// 4: no answer: nothing listens at the address (ICMP port unreachable), nothing
    /// answered in time, no member of the group answered.
    NoAnswer,
    /// 5: `measure`: nothing is on the table (printed as a result).
    Empty,
    /// 6: fewer servers answered than `--expect` asked for; the answers that came were
    /// used and printed.
    Fewer,
    /// 7: `results verify`: the chain does not verify (a record was altered or is
    /// missing); the first such record was named.
    Altered,
    /// 8: `measure`: the station is not calibrated (a camera's 3d-transformation is the
    /// identity); no dimensions were given, the cameras were named.
    Uncalibrated,
    /// 10: `measure`: a parcel was found but the data cannot support a number (not seen
    /// whole, holes, side by side, out of the measurable range); the reason was printed.
    Unsupported,
    /// 9: `measure`: the frames do not belong together (capture times, corrected by
    /// each server's clock offset, further apart than `--max-skew-ms`, or a stale
    /// camera); nothing was measured, the camera was named.
    Unsynced,
    /// 128 + the signal's number (130 for SIGINT, 143 for SIGTERM): stopped by a signal
    /// after cleaning up (`get -o FILE` removes its temporary file).
    Interrupted(u8),
}

impl Exit {
    /// The process's exit status.
    pub(crate) fn code(self) -> u8 {
        match self {
            Self::Success => 0,
            Self::Failure => 1,
            Self::Usage => 2,
            Self::Refused => 3,
            Self::NoAnswer => 4,
            Self::Empty => 5,
            Self::Fewer => 6,
            Self::Altered => 7,
            Self::Uncalibrated => 8,
            Self::Unsupported => 10,
            Self::Unsynced => 9,
            Self::Interrupted(signal) => 128 + signal,
        }
    }
}

/// How a command that failed with `error` ends: [`Exit::Refused`] when a server's
/// error response caused it, [`Exit::NoAnswer`] when nothing answered in time, else
/// [`Exit::Failure`]. `None` when standard output was closed by its reader (`coapcam
/// discover | head`): not a failure, the command ends quietly.
pub(crate) fn exit_status(error: &anyhow::Error) -> Option<Exit> {
    for cause in error.chain() {
        if let Some(Interrupted(signal)) = cause.downcast_ref() {
            return Some(Exit::Interrupted(*signal));
        }
        if cause.is::<Usage>() {
            return Some(Exit::Usage);
        }
        if cause.is::<coapcam::client::ErrorResponse>() {
            return Some(Exit::Refused);
        }
        let silent = |e: &coap::RequestError| {
            matches!(
                e,
                coap::RequestError::Timeout | coap::RequestError::Unreachable
            )
        };
        if cause.is::<coapcam::client::NoAnswer>()
            || matches!(cause.downcast_ref(), Some(coap_net::Error::Request(e)) if silent(e))
            || cause.downcast_ref().is_some_and(silent)
        {
            return Some(Exit::NoAnswer);
        }
        if cause
            .downcast_ref::<std::io::Error>()
            .is_some_and(|e| e.kind() == std::io::ErrorKind::BrokenPipe)
        {
            return None;
        }
    }
    Some(Exit::Failure)
}

pub(crate) use coapcam::error_text;

/// A bad combination of flags or values that clap cannot see alone (a file name whose
/// extension does not suit the stream, a flag for another mode): the command ends with
/// status 2 before it sends anything. Checked first thing in each command's `run`.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub(crate) struct Usage(pub(crate) String);

/// The addresses `--bind` gave, or by default CoAP's port 5683 on every IPv4 and IPv6
/// address (`serve`, `rd`).
pub(crate) fn binds_or_default(bind: &[std::net::SocketAddr]) -> Vec<std::net::SocketAddr> {
    if bind.is_empty() {
        vec![
            std::net::SocketAddr::from(([0, 0, 0, 0], 5683)),
            std::net::SocketAddr::from(([0u16; 8], 5683)),
        ]
    } else {
        bind.to_vec()
    }
}

/// Fails when the folder `path` would be written into does not exist: checked before
/// anything is sent, so a picture that cannot be written does not cost a grab first.
pub(crate) fn folder_exists(path: &std::path::Path) -> anyhow::Result<()> {
    match path.parent().filter(|d| !d.as_os_str().is_empty()) {
        Some(dir) if !dir.is_dir() => {
            anyhow::bail!(
                "cannot write {}: {} is not a folder",
                path.display(),
                dir.display()
            )
        }
        _ => Ok(()),
    }
}

/// Returns a [`Usage`] error from the enclosing function.
macro_rules! usage {
    ($($arg:tt)*) => {
        return Err($crate::cli::Usage(format!($($arg)*)).into())
    };
}
pub(crate) use usage;

/// A command stopped by a signal (its number).
#[derive(Debug, thiserror::Error)]
#[error("interrupted by signal {0}")]
pub(crate) struct Interrupted(pub(crate) u8);

/// SIGINT and SIGTERM, caught.
pub(crate) struct Signals {
    interrupt: tokio::signal::unix::Signal,
    terminate: tokio::signal::unix::Signal,
}

impl Signals {
    pub(crate) fn install() -> anyhow::Result<Self> {
        use tokio::signal::unix::{SignalKind, signal};
        Ok(Self {
            interrupt: signal(SignalKind::interrupt()).context("installing the SIGINT handler")?,
            terminate: signal(SignalKind::terminate()).context("installing the SIGTERM handler")?,
        })
    }

    /// The next signal.
    pub(crate) async fn recv(&mut self) -> Interrupted {
        tokio::select! {
            _ = self.interrupt.recv() => Interrupted(2),
            _ = self.terminate.recv() => Interrupted(15),
        }
    }
}

/// Runs a command's `work` until it ends or SIGINT or SIGTERM comes: then `work` is
/// dropped (with whatever it holds: a temporary file is removed, a request forgotten) and
/// the command ends with [`Interrupted`] ("interrupted by signal 2", status 130), the same
/// in every command.
pub(crate) async fn interruptible(
    work: impl Future<Output = anyhow::Result<Exit>>,
) -> anyhow::Result<Exit> {
    let mut signals = Signals::install()?;
    tokio::select! {
        done = work => done,
        signal = signals.recv() => Err(signal.into()),
    }
}

/// `println!` for command output, returning from the enclosing function with an error
/// instead of panicking when standard output fails (a reader that went away).
macro_rules! outln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        anyhow::Context::context(
            writeln!(std::io::stdout(), $($arg)*),
            "writing standard output",
        )?
    }};
}
pub(crate) use outln;

/// `print!` as [`outln!`].
macro_rules! out {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        anyhow::Context::context(
            write!(std::io::stdout(), $($arg)*),
            "writing standard output",
        )?
    }};
}
pub(crate) use out;

/// A progress bar on standard error that appears once a transfer passes
/// [`Bar::SHOW_ABOVE`] bytes (indicatif draws nothing when standard error is not a
/// terminal); it goes when dropped.
pub(crate) struct Bar {
    enabled: bool,
    group: Option<indicatif::MultiProgress>,
    bar: Option<indicatif::ProgressBar>,
}

impl Bar {
    /// Transfers larger than this show a bar.
    pub(crate) const SHOW_ABOVE: usize = 1 << 20;

    /// A bar of its own (none when `enabled` is false).
    pub(crate) fn new(enabled: bool) -> Self {
        Self {
            enabled,
            group: None,
            bar: None,
        }
    }

    /// `done` bytes of `total` (if known) have arrived.
    pub(crate) fn show(&mut self, done: usize, total: Option<usize>) {
        if !self.enabled {
            return;
        }
        if self.bar.is_none() && total.unwrap_or(done).max(done) > Self::SHOW_ABOVE {
            let bar = indicatif::ProgressBar::new(total.unwrap_or(0) as u64);
            bar.set_style(
                indicatif::ProgressStyle::with_template(
                    "{bar:40} {bytes}/{total_bytes} {bytes_per_sec} {eta}",
                )
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
            );
            self.bar = Some(match &self.group {
                Some(group) => group.add(bar),
                None => bar,
            });
        }
        if let Some(bar) = &self.bar {
            bar.set_position(done as u64);
        }
    }

    /// The transfer ended: the bar goes.
    pub(crate) fn finish(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
            if let Some(group) = &self.group {
                group.remove(&bar);
            }
        }
    }

    /// Shows what arrives on `progress` until its sender is dropped, then finishes.
    pub(crate) async fn follow(
        mut self,
        mut progress: tokio::sync::mpsc::UnboundedReceiver<coap_net::Progress>,
    ) {
        while let Some(p) = progress.recv().await {
            self.show(p.done, p.total);
        }
        self.finish();
    }
}

impl Drop for Bar {
    fn drop(&mut self) {
        self.finish();
    }
}

impl coapcam::client::WatchProgress for Bar {
    fn show(&mut self, done: usize, total: Option<usize>) {
        Self::show(self, done, total);
    }
}

/// One bar per transfer of a client, one line each (transfers run at once):
/// [`coapcam::client::CamClient::with_progress`].
pub(crate) struct Bars(indicatif::MultiProgress);

impl Bars {
    /// A client's bars.
    pub(crate) fn shown() -> std::sync::Arc<Self> {
        std::sync::Arc::new(Self(indicatif::MultiProgress::new()))
    }
}

impl coapcam::client::ShowProgress for Bars {
    fn watch(&self) -> Box<dyn coapcam::client::WatchProgress> {
        Box::new(Bar {
            enabled: true,
            group: Some(self.0.clone()),
            bar: None,
        })
    }
}

/// The default state directory of `serve` and `rd`: $XDG_STATE_HOME/coapcam,
/// ~/.local/state/coapcam, else ./coapcam-state.
pub(crate) fn default_state_dir() -> std::path::PathBuf {
    let base = std::env::var_os("XDG_STATE_HOME")
        .filter(|v| !v.is_empty())
        .map(std::path::PathBuf::from)
        .or_else(|| {
            std::env::var_os("HOME")
                .filter(|v| !v.is_empty())
                .map(|h| std::path::PathBuf::from(h).join(".local").join("state"))
        });
    base.map_or_else(
        || std::path::PathBuf::from("coapcam-state"),
        |b| b.join("coapcam"),
    )
}
