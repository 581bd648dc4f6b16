//! What the tests share: processes (our `coapcam serve` and `coapcam netem`, libcoap
//! 4.3.1's `coap-server-notls` and `coap-client-notls`, aiocoap's
//! `tests/peers/aiocoap_server.py` and `aiocoap-client`), a CoAP client and its requests,
//! scratch directories and bodies. Every process is killed and reaped on drop, every wait
//! is bounded, and every socket is on 127.0.0.1.

use std::io::{BufRead, BufReader, Read, Write as _};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, mpsc};
use std::thread;
use std::time::{Duration, Instant};

use coap::{Code, ContentFormat, EndpointConfig, OptionNumber, Request, Response};
use coap_net::Client;
use coapcam::process::{self, peers};

/// How long a server may take to start listening.
const STARTUP: Duration = Duration::from_secs(20);
/// Longest wait for a finished process's pipes to end (a child of its own may hold them).
const DRAIN: Duration = Duration::from_secs(5);

pub(crate) const COAPCAM: &str = env!("CARGO_BIN_EXE_coapcam");
pub(crate) use coapcam::process::peers::{
    AIOCOAP_CLIENT, LIBCOAP_CLIENT, LIBCOAP_DTLS_CLIENT, LIBCOAP_DTLS_SERVER,
    LIBCOAP_GNUTLS_CLIENT, LIBCOAP_SERVER, MOSQUITTO_SUB,
};

/// A peer program the tests need.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Peer {
    /// Debian libcoap3-bin: coap-server-notls and coap-client-notls, and the OpenSSL
    /// (DTLS) ones.
    Libcoap,
    /// PyPI aiocoap: the library (for the server script) and aiocoap-client.
    Aiocoap,
    /// [`Peer::Aiocoap`] with PyPI websockets, which aiocoap's CoAP over WebSockets needs.
    AiocoapWs,
    /// libcoap 4.3.5 built from source (Q-Block, RFC 9177) by
    /// `../shared/peers/build-libcoap.sh`: its folder in `COAPCAM_LIBCOAP435`, or the
    /// script's default.
    Libcoap435,
    /// libcoap 4.3.5 built with OpenSSL (DTLS, TLS and WebSockets over TLS) by
    /// `scripts/build-libcoap-openssl.sh`: its folder in `COAPCAM_LIBCOAP435_OPENSSL`, or
    /// the script's default.
    Libcoap435Openssl,
    /// Debian mosquitto (the broker) and mosquitto-clients (mosquitto_sub).
    Mosquitto,
    /// Debian chromium and chromium-driver (headless Chromium and chromedriver).
    Chromium,
    /// Debian poppler-utils: pdftoppm, a PDF renderer of its own (the printed sheet of
    /// markers).
    Poppler,
    /// Debian postgresql: initdb and postgres (on PATH or in /usr/lib/postgresql/*/bin).
    Postgres,
    /// PyPI asyncua, an OPC UA client library (`tests/peers/opcua_client.py` uses it).
    Asyncua,
}

/// The path of libcoap 4.3.5's `coap-client` or `coap-server`.
pub(crate) fn libcoap435(bin: &str) -> PathBuf {
    peers::libcoap435_dir().join(bin)
}

/// The path of `coap-client` or `coap-server` of libcoap 4.3.5 built with OpenSSL.
pub(crate) fn libcoap435_openssl(bin: &str) -> PathBuf {
    peers::libcoap435_openssl_dir().join(bin)
}

/// libcoap 4.3.5's server with Q-Block (`-L 5`) and dynamic resources (`-d 10`).
pub(crate) fn libcoap435_server() -> (Proc, SocketAddr) {
    let server = libcoap435("coap-server");
    let server = server.to_str().expect("UTF-8 path").to_string();
    start_on_free_port(
        |port| {
            Proc::spawn(
                &server,
                &[
                    "-A",
                    "127.0.0.1",
                    "-p",
                    &port.to_string(),
                    "-d",
                    "10",
                    "-L",
                    "5",
                ],
            )
        },
        "/.well-known/core",
    )
}

/// libcoap 4.3.5 built with OpenSSL: `coap-server -A 127.0.0.1 -p PORT -k KEY -d 10 -w
/// ,WSS`, with TLS (any identity, this pre-shared key) on TCP port PORT + 1 and
/// WebSockets over TLS on WSS; returns its `coaps+tcp` and `coaps+ws` addresses.
pub(crate) fn libcoap435_tls_server(key: &str) -> (Proc, SocketAddr, SocketAddr) {
    let server = peers::libcoap435_openssl_dir().join("coap-server");
    let server = server.to_str().expect("UTF-8 path").to_string();
    let mut wss = 0;
    let (p, plain) = start_on_free_port(
        |port| {
            wss = std::net::TcpListener::bind("127.0.0.1:0")
                .and_then(|l| l.local_addr())
                .expect("a free TCP port")
                .port();
            let (port, wss) = (port.to_string(), format!(",{wss}"));
            Proc::spawn(
                &server,
                &[
                    "-A",
                    "127.0.0.1",
                    "-p",
                    &port,
                    "-k",
                    key,
                    "-d",
                    "10",
                    "-w",
                    &wss,
                ],
            )
        },
        "/.well-known/core",
    );
    let tls = SocketAddr::new(plain.ip(), plain.port() + 1);
    (p, tls, SocketAddr::new(plain.ip(), wss))
}

/// The broker program (checked by [`available`] with [`Peer::Mosquitto`]).
pub(crate) fn mosquitto_broker() -> Option<PathBuf> {
    peers::mosquitto().ok()
}

/// Why `peer` cannot be used here, if it cannot.
fn missing(peer: Peer) -> Option<String> {
    match peer {
        Peer::Libcoap => peers::missing_on_path(&[
            LIBCOAP_SERVER,
            LIBCOAP_CLIENT,
            LIBCOAP_DTLS_SERVER,
            LIBCOAP_DTLS_CLIENT,
            LIBCOAP_GNUTLS_CLIENT,
        ]),
        Peer::Mosquitto => peers::mosquitto().err(),
        Peer::Chromium => peers::missing_on_path(&["chromium", "chromedriver"]),
        Peer::Poppler => peers::on_path("pdftoppm").is_none().then(|| {
            "pdftoppm is not on PATH (Debian package poppler-utils: apt-get install poppler-utils)"
                .to_owned()
        }),
        Peer::Libcoap435 => peers::libcoap435().err(),
        Peer::Libcoap435Openssl => peers::libcoap435_openssl().err(),
        Peer::Aiocoap => peers::aiocoap().err(),
        Peer::AiocoapWs => peers::aiocoap_ws().err(),
        Peer::Postgres => peers::postgres_bin().err(),
        Peer::Asyncua => peers::asyncua().err(),
    }
}

/// Whether the peers are installed. Missing in CI (`CI=true`) fails the test; missing
/// locally skips it with a loud message on standard error.
pub(crate) fn available(test: &str, peers: &[Peer]) -> bool {
    let Some(why) = peers.iter().find_map(|p| missing(*p)) else {
        return true;
    };
    if std::env::var("CI").is_ok_and(|v| v == "true" || v == "1") {
        panic!("{test}: {why}; scripts/test.sh installs the interop peers");
    }
    // Written to the process's standard error directly, past libtest's capture of
    // eprintln!, so the skip shows in a plain `cargo test`.
    let message = format!(
        "\n!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!\n\
         !!! SKIPPED interop test {test}: {why}.\n\
         !!! Install the peers (scripts/test.sh does) to run it; in CI it fails.\n\
         !!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!\n"
    );
    let _ = std::io::Write::write_all(&mut std::io::stderr(), message.as_bytes());
    false
}

/// A fresh directory under the system's temporary directory, removed on drop.
pub(crate) struct TempDir(PathBuf);

impl TempDir {
    pub(crate) fn new(tag: &str) -> Self {
        static NEXT: AtomicU64 = AtomicU64::new(0);
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let dir =
            std::env::temp_dir().join(format!("coapcam-interop-{tag}-{}-{n}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("creating {}: {e}", dir.display()));
        Self(dir)
    }

    pub(crate) fn path(&self) -> &Path {
        &self.0
    }

    pub(crate) fn join(&self, name: &str) -> PathBuf {
        self.0.join(name)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// `len` pseudo-random bytes (SplitMix64 from `seed`): incompressible, never all zero.
pub(crate) fn random_bytes(len: usize, seed: u64) -> Vec<u8> {
    let mut state = seed;
    let mut out = Vec::with_capacity(len + 8);
    while out.len() < len {
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        out.extend_from_slice(&(z ^ (z >> 31)).to_le_bytes());
    }
    out.truncate(len);
    out
}

/// Writes `random_bytes(len, seed)` to `path` and returns them.
pub(crate) fn random_file(path: &Path, len: usize, seed: u64) -> Vec<u8> {
    let body = random_bytes(len, seed);
    std::fs::write(path, &body).unwrap_or_else(|e| panic!("writing {}: {e}", path.display()));
    body
}

/// Asserts that `path` holds exactly `want`, naming the first differing byte if not.
pub(crate) fn assert_file_is(path: &Path, want: &[u8]) {
    let got = std::fs::read(path).unwrap_or_else(|e| panic!("reading {}: {e}", path.display()));
    assert_same(&got, want, &path.display().to_string());
}

/// Asserts that two bodies are identical, naming the first differing byte if not.
pub(crate) fn assert_same(got: &[u8], want: &[u8], what: &str) {
    if got != want {
        let first = got.iter().zip(want).position(|(a, b)| a != b);
        panic!(
            "{what}: {} bytes, {} expected; first difference at byte {:?}",
            got.len(),
            want.len(),
            first.unwrap_or_else(|| got.len().min(want.len()))
        );
    }
}

/// A port that was free on 127.0.0.1 a moment ago (for peers that cannot bind port 0
/// and report it). Servers started on it are checked, and restarted on another port if
/// they could not bind it.
pub(crate) fn free_port() -> u16 {
    process::free_udp_port().expect("binding 127.0.0.1:0")
}

/// Lines a child printed, collected by a thread per pipe.
#[derive(Clone, Default)]
struct Lines {
    bytes: Arc<Mutex<Vec<u8>>>,
    /// Set once the pipe reached its end (every process holding it is gone).
    ended: Arc<AtomicBool>,
}

impl Lines {
    fn follow(pipe: impl Read + Send + 'static, lines: Option<mpsc::Sender<String>>) -> Self {
        let me = Self::default();
        let (buf, ended) = (Arc::clone(&me.bytes), Arc::clone(&me.ended));
        thread::spawn(move || {
            let mut reader = BufReader::new(pipe);
            let mut line = Vec::new();
            loop {
                line.clear();
                match reader.read_until(b'\n', &mut line) {
                    Ok(0) | Err(_) => break,
                    Ok(_) => {
                        buf.lock()
                            .unwrap_or_else(std::sync::PoisonError::into_inner)
                            .extend_from_slice(&line);
                        if let Some(tx) = &lines {
                            let _ = tx.send(String::from_utf8_lossy(&line).trim_end().to_string());
                        }
                    }
                }
            }
            ended.store(true, Ordering::Release);
        });
        me
    }

    /// Everything read so far, once the pipe ended or `limit` passed (a grandchild may
    /// still hold the pipe open).
    fn bytes(&self, limit: Duration) -> Vec<u8> {
        let deadline = Instant::now() + limit;
        while !self.ended.load(Ordering::Acquire) && Instant::now() < deadline {
            thread::sleep(Duration::from_millis(2));
        }
        self.bytes
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone()
    }
}

/// A running child process (the library's, killed and reaped on drop) and what it
/// prints.
pub(crate) struct Proc {
    name: String,
    child: process::Proc,
    stdout: Lines,
    stderr: Lines,
    /// Standard error, line by line, as it is printed.
    stderr_lines: mpsc::Receiver<String>,
    /// Standard output, line by line, as it is printed.
    stdout_lines: mpsc::Receiver<String>,
}

/// What a finished process printed.
#[derive(Debug)]
pub(crate) struct Finished {
    pub(crate) status: ExitStatus,
    pub(crate) stdout: Vec<u8>,
    pub(crate) stderr: String,
}

impl Finished {
    pub(crate) fn stdout_text(&self) -> String {
        String::from_utf8_lossy(&self.stdout).into_owned()
    }

    /// Standard output as one JSON value (`--json`).
    pub(crate) fn json(&self) -> serde_json::Value {
        let text = self.stdout_text();
        serde_json::from_str(text.trim()).unwrap_or_else(|e| panic!("{text:?}: {e}"))
    }

    /// Standard output as one JSON value per line.
    pub(crate) fn json_lines(&self) -> Vec<serde_json::Value> {
        self.stdout_text()
            .lines()
            .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{l:?}: {e}")))
            .collect()
    }

    /// Panics with everything the process printed unless it exited 0.
    pub(crate) fn expect_success(self, what: &str) -> Self {
        self.expect_status(0, what)
    }

    /// Panics with everything the process printed unless it exited with `code`.
    pub(crate) fn expect_status(self, code: i32, what: &str) -> Self {
        assert_eq!(
            self.status.code(),
            Some(code),
            "{what}: {}\nstdout: {}\nstderr: {}",
            self.status,
            self.stdout_text(),
            self.stderr
        );
        self
    }
}

impl Proc {
    pub(crate) fn spawn(program: &str, args: &[&str]) -> Self {
        Self::spawn_with_env(program, args, &[])
    }

    /// As [`Proc::spawn`], with more environment variables.
    pub(crate) fn spawn_with_env(program: &str, args: &[&str], env: &[(&str, &str)]) -> Self {
        let name = format!("{program} {}", args.join(" "));
        let mut command = Command::new(program);
        // Round trips remembered between processes (client::rtt_cache) stay out of the
        // tests, unless one asks for them.
        command
            .args(args)
            .env("COAPCAM_RTT_CACHE", "off")
            .envs(env.iter().copied());
        Self::spawn_command(command, &name)
    }

    /// Starts `command` as it is set up (another user, a working directory), its output
    /// piped and collected as [`Proc::spawn`]'s.
    pub(crate) fn spawn_command(mut command: Command, name: &str) -> Self {
        let name = name.to_owned();
        command.stdout(Stdio::piped()).stderr(Stdio::piped());
        let mut child = process::Proc::spawn(command, &name).unwrap_or_else(|e| panic!("{e:#}"));
        let (out_tx, stdout_lines) = mpsc::channel();
        let (err_tx, stderr_lines) = mpsc::channel();
        let pipes = child.child_mut();
        let stdout = Lines::follow(pipes.stdout.take().expect("stdout pipe"), Some(out_tx));
        let stderr = Lines::follow(pipes.stderr.take().expect("stderr pipe"), Some(err_tx));
        Self {
            name,
            child,
            stdout,
            stderr,
            stderr_lines,
            stdout_lines,
        }
    }

    /// Runs a program to its end, killing it (and failing) after `limit`.
    pub(crate) fn run(program: &str, args: &[&str], limit: Duration) -> Finished {
        let mut p = Self::spawn(program, args);
        match p.wait(limit) {
            Some(f) => f,
            None => {
                let f = p.kill();
                panic!(
                    "{} did not finish within {limit:?}\nstdout: {}\nstderr: {}",
                    p.name,
                    f.stdout_text(),
                    f.stderr
                );
            }
        }
    }

    /// Waits for the process to end, at most `limit`; `None` if it is still running.
    pub(crate) fn wait(&mut self, limit: Duration) -> Option<Finished> {
        let status = self
            .child
            .wait_for(limit)
            .unwrap_or_else(|e| panic!("{e:#}"))?;
        Some(self.finished(status))
    }

    /// Kills the process and returns what it printed.
    pub(crate) fn kill(&mut self) -> Finished {
        let status = self.child.kill().unwrap_or_else(|e| panic!("{e:#}"));
        self.finished(status)
    }

    fn finished(&mut self, status: ExitStatus) -> Finished {
        // The reader threads see end-of-file once the process (and its children) are
        // gone, and have read everything by then.
        Finished {
            status,
            stdout: self.stdout.bytes(DRAIN),
            stderr: String::from_utf8_lossy(&self.stderr.bytes(DRAIN)).into_owned(),
        }
    }

    /// Waits (bounded) for a line of standard error that `pick` accepts.
    pub(crate) fn stderr_line<T>(
        &mut self,
        limit: Duration,
        pick: impl Fn(&str) -> Option<T>,
    ) -> T {
        Self::line(
            &self.stderr_lines,
            &self.name,
            "standard error",
            limit,
            pick,
        )
    }

    /// Waits (bounded) for a line of standard output that `pick` accepts.
    pub(crate) fn stdout_line<T>(
        &mut self,
        limit: Duration,
        pick: impl Fn(&str) -> Option<T>,
    ) -> T {
        Self::line(
            &self.stdout_lines,
            &self.name,
            "standard output",
            limit,
            pick,
        )
    }

    fn line<T>(
        rx: &mpsc::Receiver<String>,
        name: &str,
        pipe: &str,
        limit: Duration,
        pick: impl Fn(&str) -> Option<T>,
    ) -> T {
        let deadline = Instant::now() + limit;
        let mut seen = Vec::new();
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match rx.recv_timeout(left) {
                Ok(line) => {
                    if let Some(t) = pick(&line) {
                        return t;
                    }
                    seen.push(line);
                }
                Err(e) => panic!("{name}: no expected line on {pipe} ({e}); saw {seen:?}"),
            }
        }
    }

    /// Interrupts the process (SIGINT, as Ctrl-C) and waits for it, at most [`STARTUP`].
    /// The process id.
    pub(crate) fn pid(&self) -> u32 {
        self.child.id()
    }

    pub(crate) fn interrupt(&mut self) -> Finished {
        let pid = self.child.id().to_string();
        let sent = Command::new("kill").args(["-INT", &pid]).status();
        assert!(sent.is_ok_and(|s| s.success()), "kill -INT {pid}");
        self.wait(STARTUP)
            .unwrap_or_else(|| panic!("{} still runs {STARTUP:?} after SIGINT", self.name))
    }

    /// Interrupts the process and parses the JSON object it printed last on standard
    /// output (`coapcam netem --json`).
    pub(crate) fn interrupt_json(&mut self) -> serde_json::Value {
        let f = self.interrupt();
        let text = f.stdout_text();
        let last = text.lines().last().unwrap_or_default();
        serde_json::from_str(last).unwrap_or_else(|e| panic!("{}: {last:?}: {e}", self.name))
    }

    pub(crate) fn is_running(&mut self) -> bool {
        self.child.is_running()
    }
}

/// Polls `addr` with `coapcam get coap://ADDR/PATH` until it answers with a success,
/// while `server` runs. Returns false if the server exited.
fn wait_until_serving(server: &mut Proc, addr: SocketAddr, path: &str) -> bool {
    let deadline = Instant::now() + STARTUP;
    let uri = format!("coap://{addr}{path}");
    while Instant::now() < deadline {
        if !server.is_running() {
            return false;
        }
        let probe = Proc::run(
            COAPCAM,
            &["get", &uri, "--timeout", "1", "--json"],
            Duration::from_secs(10),
        );
        if probe.status.success() {
            return true;
        }
        thread::sleep(Duration::from_millis(50));
    }
    panic!("no answer from {uri} within {STARTUP:?}");
}

/// Starts a server on a free port of 127.0.0.1 and waits until it answers `probe`;
/// tries another port if the first was taken meanwhile.
fn start_on_free_port(mut start: impl FnMut(u16) -> Proc, probe: &str) -> (Proc, SocketAddr) {
    for _ in 0..5 {
        let port = free_port();
        let addr = SocketAddr::from(([127, 0, 0, 1], port));
        let mut p = start(port);
        if wait_until_serving(&mut p, addr, probe) {
            return (p, addr);
        }
        let f = p.kill();
        eprintln!("server on port {port} exited: {}\n{}", f.status, f.stderr);
    }
    panic!("no server could be started");
}

/// `coap-server-notls -A 127.0.0.1 -p PORT -d 10`: libcoap's example server, where a PUT
/// creates a resource (at most 10).
pub(crate) fn libcoap_server() -> (Proc, SocketAddr) {
    start_on_free_port(
        |port| {
            Proc::spawn(
                LIBCOAP_SERVER,
                &["-A", "127.0.0.1", "-p", &port.to_string(), "-d", "10"],
            )
        },
        "/.well-known/core",
    )
}

/// `coap-server-openssl -A 127.0.0.1 -p PORT -k KEY -d 10`: libcoap's example server
/// with DTLS (any identity, this pre-shared key) on PORT + 1; returns its DTLS address.
pub(crate) fn libcoap_dtls_server(key: &str) -> (Proc, SocketAddr) {
    let (p, plain) = start_on_free_port(
        |port| {
            Proc::spawn(
                LIBCOAP_DTLS_SERVER,
                &[
                    "-A",
                    "127.0.0.1",
                    "-p",
                    &port.to_string(),
                    "-k",
                    key,
                    "-d",
                    "10",
                ],
            )
        },
        "/.well-known/core",
    );
    (p, SocketAddr::new(plain.ip(), plain.port() + 1))
}

/// The path of a script of `tests/peers/`.
pub(crate) fn script(name: &str) -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/peers")
        .join(name);
    path.to_str().expect("UTF-8 path").to_string()
}

/// `tests/peers/aiocoap_server.py [BIG_FILE]` on the port it picked and printed ("ready PORT ..."):
/// its UDP address.
pub(crate) fn aiocoap_server(big: Option<&Path>) -> (Proc, SocketAddr) {
    let (p, ports) = aiocoap_server_on_all(big);
    (p, ports.udp)
}

/// The addresses `tests/peers/aiocoap_server.py` listens on.
pub(crate) struct AiocoapAddrs {
    pub(crate) udp: SocketAddr,
    /// CoAP over TCP (RFC 8323).
    pub(crate) tcp: SocketAddr,
    /// CoAP over WebSockets, when Python's `websockets` package is there.
    pub(crate) ws: Option<SocketAddr>,
}

/// `tests/peers/aiocoap_server.py [BIG_FILE]` with every address it listens on, as it
/// printed them ("ready UDP TCP WS", WS "-" without WebSockets).
pub(crate) fn aiocoap_server_on_all(big: Option<&Path>) -> (Proc, AiocoapAddrs) {
    let script = script("aiocoap_server.py");
    let big = big.map(|p| p.to_str().expect("UTF-8 path").to_string());
    let mut args = vec![script.as_str()];
    args.extend(big.as_deref());
    let mut p = Proc::spawn("python3", &args);
    let (udp, tcp, ws) = p.stdout_line(STARTUP, |l| {
        let mut ports = l.strip_prefix("ready ")?.split(' ');
        let udp = ports.next()?.parse::<u16>().ok()?;
        let tcp = ports.next()?.parse::<u16>().ok()?;
        let ws = match ports.next()? {
            "-" => None,
            port => Some(port.parse::<u16>().ok()?),
        };
        Some((udp, tcp, ws))
    });
    let at = |port| SocketAddr::from(([127, 0, 0, 1], port));
    let addrs = AiocoapAddrs {
        udp: at(udp),
        tcp: at(tcp),
        ws: ws.map(at),
    };
    assert!(
        wait_until_serving(&mut p, addrs.udp, "/.well-known/core"),
        "the aiocoap server exited"
    );
    (p, addrs)
}

/// `coapcam serve --no-cameras --static DIR [--writable] --bind 127.0.0.1:0`, with the
/// address it reports.
pub(crate) fn our_server(dir: &Path, writable: bool) -> (Proc, SocketAddr) {
    our_server_with(dir, if writable { &["--writable"] } else { &[] })
}

/// [`our_server`] with other flags (`--writable`, `--quota N`, ...).
pub(crate) fn our_server_with(dir: &Path, flags: &[&str]) -> (Proc, SocketAddr) {
    let dir = dir.to_str().expect("UTF-8 path");
    let mut args = vec![
        "serve",
        "--no-cameras",
        "--static",
        dir,
        "--bind",
        "127.0.0.1:0",
    ];
    args.extend_from_slice(flags);
    let mut p = Proc::spawn(COAPCAM, &args);
    let addr = p.stderr_line(STARTUP, |l| {
        l.strip_prefix("coapcam: serving on ")
            .and_then(|a| a.trim().parse::<SocketAddr>().ok())
    });
    assert!(
        wait_until_serving(&mut p, addr, "/.well-known/core"),
        "coapcam serve exited"
    );
    (p, addr)
}

/// `coapcam netem --listen 127.0.0.1:0 --forward FORWARD --loss LOSS --seed SEED --json`,
/// with the address it listens on.
pub(crate) fn netem(forward: SocketAddr, loss: f64, seed: u64) -> (Proc, SocketAddr) {
    let mut p = Proc::spawn(
        COAPCAM,
        &[
            "netem",
            "--listen",
            "127.0.0.1:0",
            "--forward",
            &forward.to_string(),
            "--loss",
            &loss.to_string(),
            "--seed",
            &seed.to_string(),
            "--json",
        ],
    );
    let addr = p.stderr_line(STARTUP, |l| {
        l.strip_prefix("netem: listening on ")
            .and_then(|rest| rest.split(',').next())
            .and_then(|a| a.parse::<SocketAddr>().ok())
    });
    (p, addr)
}

/// A running `coapcam serve`, killed on drop.
pub(crate) struct Server(process::Proc);

impl Server {
    /// The server's process.
    pub(crate) fn process(&mut self) -> &mut Child {
        self.0.child_mut()
    }
}

pub(crate) const SN: &str = "840412060746";
pub(crate) const LIMIT: Duration = Duration::from_secs(60);

/// A server on an ephemeral port of 127.0.0.1 with its state in `state`.
pub(crate) fn serve(state: &Path) -> (Server, SocketAddr) {
    serve_with(state, &[])
}

/// As [`serve`], with more flags.
pub(crate) fn serve_with(state: &Path, extra: &[&str]) -> (Server, SocketAddr) {
    serve_at("127.0.0.1:0", state, extra)
}

/// A server bound to `bind` with its state in `state` and more flags.
pub(crate) fn serve_at(bind: &str, state: &Path, extra: &[&str]) -> (Server, SocketAddr) {
    serve_at_with_env(bind, state, extra, &[])
}

/// [`serve_with`] with the variables `env` set for the server.
pub(crate) fn serve_with_env(
    state: &Path,
    extra: &[&str],
    env: &[(&str, &Path)],
) -> (Server, SocketAddr) {
    serve_at_with_env("127.0.0.1:0", state, extra, env)
}

fn serve_at_with_env(
    bind: &str,
    state: &Path,
    extra: &[&str],
    env: &[(&str, &Path)],
) -> (Server, SocketAddr) {
    let dir = state.to_string_lossy().into_owned();
    let mut command = Command::new(COAPCAM);
    command.envs(env.iter().copied());
    command
        .args([
            "serve",
            "--bind",
            bind,
            "--state-dir",
            &dir,
            "--duration",
            "120",
        ])
        .args(extra)
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let mut child =
        process::Proc::spawn(command, "coapcam serve").unwrap_or_else(|e| panic!("{e:#}"));
    let stderr = child.child_mut().stderr.take().expect("stderr pipe");
    let server = Server(child);
    // The server stops by itself after --duration, which bounds this read.
    let mut lines = BufReader::new(stderr).lines();
    let addr = lines
        .by_ref()
        .map_while(Result::ok)
        .find_map(|l| {
            l.strip_prefix("coapcam: serving on ")
                .and_then(|a| a.trim().parse().ok())
        })
        .expect("coapcam serve printed no address");
    thread::spawn(move || lines.for_each(drop));
    (server, addr)
}

/// A running `coapcam serve` (a [`Proc`]: its standard error can still be read) and the
/// addresses it announced.
pub(crate) struct Station {
    pub(crate) process: Proc,
    /// Its (first) CoAP address.
    pub(crate) coap: SocketAddr,
    /// Its HTTP address, when the flags have `--http`.
    pub(crate) http: Option<SocketAddr>,
    /// Its line output's address, when the flags have `--line-output`.
    pub(crate) line: Option<SocketAddr>,
    /// Every line output's address, in the order they were announced (a configuration
    /// file's `[[output]]` tables may give more).
    pub(crate) lines: Vec<SocketAddr>,
    /// Its OPC UA server's address, when the flags have `--opcua`.
    pub(crate) opcua: Option<SocketAddr>,
}

/// `coapcam serve --bind 127.0.0.1:0 --state-dir STATE --duration 600` and `flags`, once
/// it announced where it is: the outputs, then HTTP, then the CoAP address, in that order.
/// Without `--scene` or `--no-cameras` in `flags` it serves the default scene.
pub(crate) fn station(state: &Path, flags: &[&str]) -> Station {
    station_under(&[COAPCAM], &[], state, flags)
}

/// [`station`] run as `command` (a program and its first arguments, ending in the
/// coapcam binary: `["prlimit", "--nofile=128:128", "--", COAPCAM]`), with the
/// environment variables `env`.
pub(crate) fn station_under(
    command: &[&str],
    env: &[(&str, &str)],
    state: &Path,
    flags: &[&str],
) -> Station {
    let (program, first) = command.split_first().expect("a program");
    let dir = state.to_string_lossy().into_owned();
    let mut args = first.to_vec();
    args.extend_from_slice(&[
        "serve",
        "--bind",
        "127.0.0.1:0",
        "--state-dir",
        &dir,
        "--duration",
        "600",
    ]);
    args.extend_from_slice(flags);
    let mut process = Proc::spawn_with_env(program, &args, env);
    let (mut http, mut opcua, mut lines) = (None, None, Vec::new());
    let coap = loop {
        let (what, addr) = process.stderr_line(LIMIT, |l| {
            let l = l.strip_prefix("coapcam: ")?;
            let (what, rest) = [
                ("line", "line output on "),
                ("opcua", "OPC UA server on opc.tcp://"),
                ("http", "HTTP on http://"),
                ("coap", "serving on "),
            ]
            .into_iter()
            .find_map(|(what, prefix)| Some((what, l.strip_prefix(prefix)?)))?;
            let addr = rest.split('/').next()?.trim().parse::<SocketAddr>().ok()?;
            Some((what, addr))
        });
        match what {
            "line" => lines.push(addr),
            "opcua" => opcua = Some(addr),
            "http" => http = Some(addr),
            _ => break addr,
        }
    };
    Station {
        process,
        coap,
        http,
        line: lines.first().copied(),
        lines,
        opcua,
    }
}

/// [`station`] with `--http 127.0.0.1:0`: the process, its CoAP and its HTTP address.
pub(crate) fn station_with_http(state: &Path, flags: &[&str]) -> (Proc, SocketAddr, SocketAddr) {
    let s = station(state, &[&["--http", "127.0.0.1:0"], flags].concat());
    let http = s.http.expect("an HTTP address");
    (s.process, s.coap, http)
}

/// Two servers of the default scene on ephemeral ports of 127.0.0.1, their state in
/// `state`'s folders `a` and `b`, `b` started with the further flags `b_extra`: for
/// measuring with several servers at once. Both are killed on drop.
pub(crate) struct TwoServers {
    _servers: [Server; 2],
    pub(crate) a: SocketAddr,
    pub(crate) b: SocketAddr,
}

impl TwoServers {
    pub(crate) fn start(state: &Path, b_extra: &[&str]) -> Self {
        let (server_a, a) = serve_with(&state.join("a"), &[]);
        let (server_b, b) = serve_with(&state.join("b"), b_extra);
        Self {
            _servers: [server_a, server_b],
            a,
            b,
        }
    }

    /// `coapcam measure --server A --server B` and then `args`.
    pub(crate) fn measure(&self, args: &[&str]) -> Finished {
        let (a, b) = (format!("coap://{}", self.a), format!("coap://{}", self.b));
        let mut all = vec!["measure", "--server", &a, "--server", &b];
        all.extend_from_slice(args);
        Proc::run(COAPCAM, &all, LIMIT)
    }
}

pub(crate) fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime")
}

pub(crate) async fn send(
    client: &Client,
    addr: SocketAddr,
    method: Code,
    path: &str,
    payload: &[u8],
    accept: Option<u16>,
) -> Response {
    let mut request = Request::new(method, path).with_payload(payload.to_vec());
    request.timeout = Some(LIMIT);
    if let Some(cf) = accept {
        request
            .options
            .set_uint(OptionNumber::ACCEPT, u32::from(cf));
    }
    client
        .send(addr, request)
        .await
        .unwrap_or_else(|e| panic!("{method:?} {path}: {e}"))
}

/// A client on a free port of 127.0.0.1 with a seed of its own ([`coap_net::fresh_seed`]):
/// with the default seed every new client sends the same message IDs and tokens, and one
/// given the port of an earlier one within EXCHANGE_LIFETIME is answered from the server's
/// deduplication store with that one's answer (a directory's endpoint list for its
/// /.well-known/core, seen in CI).
pub(crate) fn client() -> Client {
    Client::bind(
        SocketAddr::from(([127, 0, 0, 1], 0)),
        EndpointConfig {
            rng_seed: coap_net::fresh_seed(),
            ..EndpointConfig::default()
        },
    )
    .expect("client socket")
}

pub(crate) const COLOR_640: &str = r#"{"format": "BGR8", "fps": 30, "width": 640, "height": 480}"#;
pub(crate) const DEPTH_640: &str = r#"{"format": "Z16", "fps": 30, "width": 640, "height": 480}"#;

/// Where [`tilted_uncalibrated_scene`]'s camera stands, world metres.
pub(crate) const TILTED_CAMERA: [f64; 3] = [0.45, -0.35, 1.05];
/// Where its origin marker (tag36h11 id 0) lies: centre and yaw in degrees.
pub(crate) const ORIGIN_MARKER: ([f64; 2], f64) = ([-0.30, -0.30], 20.0);

/// A scene file in `dir`: one uncalibrated D415 (noise on) 1.05 m above the floor, 0.57 m
/// aside of a 400 x 300 x 200 mm box (yaw 15 degrees), so tilted 28.5 degrees; two
/// tag36h11 markers on the floor beside the box, 0 at [`ORIGIN_MARKER`] and 3.
pub(crate) fn tilted_uncalibrated_scene(dir: &Path) -> PathBuf {
    let scene = dir.join("tilted.toml");
    let ([x, y], yaw) = ORIGIN_MARKER;
    std::fs::write(
        &scene,
        format!(
            "seed = 5\n[[camera]]\nserial = \"{SN}\"\nposition = {TILTED_CAMERA:?}\n\
             look_at = [0.0, 0.0, 0.0]\nnoise = \"d415\"\ncalibrated = false\n\
             [[box]]\nsize = [0.40, 0.30, 0.20]\ncenter = [0.0, 0.0]\nyaw_deg = 15.0\n\
             [[marker]]\nfamily = \"tag36h11\"\nid = 0\nsize = 0.14\ncenter = [{x}, {y}]\nyaw_deg = {yaw}\n\
             [[marker]]\nfamily = \"tag36h11\"\nid = 3\nsize = 0.14\ncenter = [0.30, 0.25]\nyaw_deg = -10.0\n"
        ),
    )
    .expect("writing the scene");
    scene
}

/// Asserts that a `measure --json` document has the box of
/// [`tilted_uncalibrated_scene`] within 5 mm and no warning.
pub(crate) fn assert_box_within_5_mm(m: &serde_json::Value) {
    for (key, truth) in [
        ("length_mm", 400.0),
        ("width_mm", 300.0),
        ("height_mm", 200.0),
    ] {
        let got = m[key].as_f64().expect("a dimension");
        assert!((got - truth).abs() <= 5.0, "{key} {got}: {m}");
    }
    assert_eq!(m["warnings"], serde_json::json!([]), "{m}");
}

/// A scene with the demo's camera and nothing on the table.
pub(crate) fn empty_table(state: &TempDir) -> String {
    let path = state.path().join("empty.toml");
    let mut f = std::fs::File::create(&path).expect("a scene file");
    writeln!(
        f,
        "[[camera]]\nserial = \"{SN}\"\nposition = [0.0, 0.0, 1.0]\nlook_at = [0.0, 0.0, 0.0]\ncalibrated = true"
    )
    .expect("writing the scene");
    path.to_str().expect("UTF-8 path").to_owned()
}

/// Issue 51, item 4: a measured parcel's document gives the numbers to bill on at its top
/// level, the same as its `parcels[0]`, and names the division they were rounded to
/// (the station's default, 5 mm). The numbers of those as an output writes them (their
/// division's decimals: none at 5 mm).
pub(crate) fn billed_numbers(m: &serde_json::Value) -> [String; 3] {
    assert_eq!(m["parcel"], "measured", "{m}");
    assert_eq!(m["division_mm"], 5.0, "the division at the top level: {m}");
    ["length_mm", "width_mm", "height_mm"].map(|key| {
        assert_eq!(m[key], m["parcels"][0][key], "{key}: {m}");
        let mm = m[key].as_f64().unwrap_or_else(|| panic!("{key}: {m}"));
        assert_eq!(mm % 5.0, 0.0, "{key} is not a multiple of 5 mm: {m}");
        format!("{mm:.0}")
    })
}

/// `POST /cams/dimensions` (CBOR), the measurement it answered.
pub(crate) async fn measure(c: &Client, addr: SocketAddr) -> coapcam::report::Measurement {
    let mut request = Request::new(Code::POST, "/cams/dimensions");
    request.timeout = Some(LIMIT);
    request.options.push(OptionNumber::URI_QUERY, b"codes");
    request
        .options
        .set_uint(OptionNumber::ACCEPT, u32::from(ContentFormat::CBOR.0));
    let r = c.send(addr, request).await.expect("an answer");
    assert_eq!(
        r.code,
        Code::CONTENT,
        "{}",
        String::from_utf8_lossy(&r.payload)
    );
    coapcam::report::Measurement::from_cbor(&r.payload).expect("a measurement")
}
