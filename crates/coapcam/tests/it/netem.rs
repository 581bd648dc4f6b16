//! `coapcam netem` as a process: real sockets on 127.0.0.1, the counters it prints.

use std::io::{BufRead, BufReader};
use std::net::{SocketAddr, UdpSocket};
use std::process::{Child, Command, Output, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::thread;
use std::time::{Duration, Instant};

/// How long any step may take before the test gives up.
const PATIENCE: Duration = Duration::from_secs(10);

/// An echo server on 127.0.0.1 in a thread, stopped on drop.
struct Echo {
    addr: SocketAddr,
    stop: Arc<AtomicBool>,
    thread: Option<thread::JoinHandle<()>>,
}

impl Echo {
    fn start() -> std::io::Result<Self> {
        let socket = UdpSocket::bind("127.0.0.1:0")?;
        socket.set_read_timeout(Some(Duration::from_millis(20)))?;
        let addr = socket.local_addr()?;
        let stop = Arc::new(AtomicBool::new(false));
        let stopping = Arc::clone(&stop);
        let thread = thread::spawn(move || {
            let mut buf = [0u8; 2048];
            while !stopping.load(Ordering::Relaxed) {
                if let Ok((len, peer)) = socket.recv_from(&mut buf) {
                    let _ = socket.send_to(&buf[..len], peer);
                }
            }
        });
        Ok(Self {
            addr,
            stop,
            thread: Some(thread),
        })
    }
}

impl Drop for Echo {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// A `coapcam netem` process, killed on drop if it is still running.
struct Netem {
    child: Child,
    listen: SocketAddr,
}

impl Netem {
    /// Starts `coapcam netem --listen 127.0.0.1:0 --forward FORWARD FLAGS` and reads the
    /// listen address it reports on standard error.
    fn start(forward: SocketAddr, flags: &[&str]) -> Self {
        let mut child = Command::new(env!("CARGO_BIN_EXE_coapcam"))
            .args([
                "netem",
                "--listen",
                "127.0.0.1:0",
                "--forward",
                &forward.to_string(),
            ])
            .args(flags)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("starting coapcam netem: {e}"));
        let Some(stderr) = child.stderr.take() else {
            panic!("coapcam netem has no standard error pipe")
        };
        let (tx, rx) = mpsc::channel();
        thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                let _ = tx.send(line);
            }
        });
        let line = rx
            .recv_timeout(PATIENCE)
            .unwrap_or_else(|e| panic!("no address reported by coapcam netem: {e}"));
        let listen = line
            .strip_prefix("netem: listening on ")
            .and_then(|rest| rest.split(',').next())
            .and_then(|addr| addr.parse().ok())
            .unwrap_or_else(|| panic!("unexpected first line {line:?}"));
        Self { child, listen }
    }

    /// Waits (bounded) for the process to end by itself and returns what it printed.
    fn wait(mut self) -> Output {
        let deadline = Instant::now() + PATIENCE;
        while Instant::now() < deadline {
            match self.child.try_wait() {
                Ok(Some(_)) => break,
                Ok(None) => thread::sleep(Duration::from_millis(10)),
                Err(e) => panic!("waiting for coapcam netem: {e}"),
            }
        }
        let _ = self.child.kill();
        let mut stdout = String::new();
        if let Some(mut pipe) = self.child.stdout.take() {
            let _ = std::io::Read::read_to_string(&mut pipe, &mut stdout);
        }
        let status = self
            .child
            .wait()
            .unwrap_or_else(|e| panic!("waiting for coapcam netem: {e}"));
        Output {
            status,
            stdout: stdout.into_bytes(),
            stderr: Vec::new(),
        }
    }
}

impl Drop for Netem {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[test]
fn relays_through_the_cli_and_prints_json_counters_on_ctrl_c() {
    let echo = Echo::start().unwrap_or_else(|e| panic!("echo server: {e}"));
    let netem = Netem::start(echo.addr, &["--delay-ms=10", "--duration=20", "--json"]);
    let client = UdpSocket::bind("127.0.0.1:0").unwrap_or_else(|e| panic!("client: {e}"));
    client
        .set_read_timeout(Some(PATIENCE))
        .unwrap_or_else(|e| panic!("client timeout: {e}"));
    let mut buf = [0u8; 64];
    for i in 0..8u8 {
        let sent = Instant::now();
        client
            .send_to(&[i; 32], netem.listen)
            .unwrap_or_else(|e| panic!("send: {e}"));
        let len = client
            .recv(&mut buf)
            .unwrap_or_else(|e| panic!("echo {i}: {e}"));
        assert_eq!(&buf[..len], &[i; 32]);
        assert!(
            sent.elapsed() >= Duration::from_millis(20),
            "{:?}",
            sent.elapsed()
        );
    }
    let interrupted = Command::new("kill")
        .args(["-INT", &netem.child.id().to_string()])
        .status()
        .unwrap_or_else(|e| panic!("kill -INT: {e}"));
    assert!(interrupted.success());
    let output = netem.wait();
    assert!(output.status.success(), "{:?}", output.status);
    let counters: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap_or_else(|e| {
        panic!(
            "JSON counters: {e}: {:?}",
            String::from_utf8_lossy(&output.stdout)
        )
    });
    assert_eq!(counters["clients"], 1);
    for dir in ["up", "down"] {
        assert_eq!(counters[dir]["received"], 8, "{counters}");
        assert_eq!(counters[dir]["forwarded"], 8, "{counters}");
        assert_eq!(counters[dir]["bytes_forwarded"], 256, "{counters}");
    }
}

#[test]
fn stops_after_the_duration_and_prints_a_table() {
    let echo = Echo::start().unwrap_or_else(|e| panic!("echo server: {e}"));
    let netem = Netem::start(echo.addr, &["--loss=1", "--duration=2", "--seed=3"]);
    let client = UdpSocket::bind("127.0.0.1:0").unwrap_or_else(|e| panic!("client: {e}"));
    for _ in 0..3 {
        client
            .send_to(b"lost", netem.listen)
            .unwrap_or_else(|e| panic!("send: {e}"));
    }
    let output = netem.wait();
    assert!(output.status.success(), "{:?}", output.status);
    let text = String::from_utf8_lossy(&output.stdout);
    assert!(text.starts_with("netem: ran "), "{text}");
    assert!(text.contains("seed 3"), "{text}");
    let up: Vec<&str> = text
        .lines()
        .find(|line| line.starts_with("up "))
        .map(|line| line.split_whitespace().collect())
        .unwrap_or_default();
    assert_eq!(up.get(1..4), Some(&["3", "3", "0"][..]), "{text}");
}

#[test]
fn refuses_a_loss_that_is_not_a_probability() {
    let output = Command::new(env!("CARGO_BIN_EXE_coapcam"))
        .args([
            "netem",
            "--listen=127.0.0.1:0",
            "--forward=127.0.0.1:9",
            "--loss=1.5",
        ])
        .output()
        .unwrap_or_else(|e| panic!("running coapcam: {e}"));
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("not a probability"));
}
