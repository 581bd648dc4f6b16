//! Child processes for the benchmarks and the integration tests: started with standard
//! input closed, waited for within limits, killed and reaped on drop; servers started on
//! a free loopback port and waited for until they answer a CoAP ping. Where the peer
//! programs are (libcoap 4.3.1 and 4.3.5, aiocoap, `quic-bench`) is [`peers`].
//!
//! Nothing here talks to any address but 127.0.0.1.

pub mod peers;

use std::fs::File;
use std::net::{Ipv4Addr, SocketAddr, UdpSocket};
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::thread;
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};

/// How often a running child is checked for its exit: the resolution of the times.
pub const POLL: Duration = Duration::from_millis(1);

/// A child process, killed and reaped on drop.
#[derive(Debug)]
pub struct Proc {
    child: Child,
    name: String,
    /// When it started (when the spawn returned): where its time counts from.
    started: Instant,
}

impl Proc {
    /// Starts `command` (standard input closed; its output goes where `command` says),
    /// named `name` in errors.
    pub fn spawn(mut command: Command, name: &str) -> anyhow::Result<Self> {
        let child = command
            .stdin(Stdio::null())
            .spawn()
            .with_context(|| format!("starting {name}"))?;
        Ok(Self {
            child,
            name: name.to_owned(),
            started: Instant::now(),
        })
    }

    /// Its name in errors.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The process id.
    pub fn id(&self) -> u32 {
        self.child.id()
    }

    /// The child itself, e.g. to take its pipes.
    pub fn child_mut(&mut self) -> &mut Child {
        &mut self.child
    }

    /// Its exit status if it has exited, without waiting.
    pub fn try_status(&mut self) -> anyhow::Result<Option<ExitStatus>> {
        self.child
            .try_wait()
            .with_context(|| format!("waiting for {}", self.name))
    }

    /// Whether it still runs.
    pub fn is_running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    /// An error if it has exited.
    pub fn check_running(&mut self) -> anyhow::Result<()> {
        match self.try_status()? {
            None => Ok(()),
            Some(status) => bail!("{} exited ({status})", self.name),
        }
    }

    /// Waits at most `limit` for it to exit; `None` if it still runs then (it is not
    /// killed).
    pub fn wait_for(&mut self, limit: Duration) -> anyhow::Result<Option<ExitStatus>> {
        let deadline = Instant::now() + limit;
        loop {
            if let Some(status) = self.try_status()? {
                return Ok(Some(status));
            }
            if Instant::now() >= deadline {
                return Ok(None);
            }
            thread::sleep(POLL);
        }
    }

    /// Kills it (if it still runs) and reaps it; its exit status.
    pub fn kill(&mut self) -> anyhow::Result<ExitStatus> {
        let _ = self.child.kill();
        self.child
            .wait()
            .with_context(|| format!("waiting for {}", self.name))
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.kill();
    }
}

/// Waits for every one of `procs` to exit, checking each every [`POLL`] and killing one
/// still running `cap` after its start. Per process, in order: its exit status (`None`:
/// killed) and the time from its start to when its end was seen. `on_first_end` is called
/// once, right after the check that first sees one of them end.
pub fn wait_all_capped(
    procs: &mut [Proc],
    cap: Duration,
    on_first_end: impl FnOnce(),
) -> anyhow::Result<Vec<(Option<ExitStatus>, Duration)>> {
    let mut ended: Vec<Option<(Option<ExitStatus>, Duration)>> = vec![None; procs.len()];
    let mut on_first_end = Some(on_first_end);
    loop {
        for (proc, end) in procs.iter_mut().zip(&mut ended) {
            if end.is_some() {
                continue;
            }
            let polled = proc.try_status();
            let elapsed = proc.started.elapsed();
            if let Some(status) = polled? {
                *end = Some((Some(status), elapsed));
            } else if elapsed >= cap {
                let _ = proc.kill();
                *end = Some((None, elapsed));
            }
        }
        if ended.iter().any(Option::is_some)
            && let Some(first) = on_first_end.take()
        {
            first();
        }
        if ended.iter().all(Option::is_some) {
            return Ok(ended.into_iter().flatten().collect());
        }
        thread::sleep(POLL);
    }
}

/// Waits for `proc` to exit, killing it `cap` after its start; its exit status (`None`:
/// killed) and the time from its start to when its exit was seen.
pub fn wait_capped(
    proc: &mut Proc,
    cap: Duration,
) -> anyhow::Result<(Option<ExitStatus>, Duration)> {
    let ended = wait_all_capped(std::slice::from_mut(proc), cap, || {})?;
    Ok(ended[0])
}

/// Runs `command` to its end within `limit`, its standard error into `log`; an error says
/// why it failed (with the log's last lines).
pub fn run_to_end(command: Command, name: &str, log: &Path, limit: Duration) -> anyhow::Result<()> {
    let mut command = command;
    let stderr = File::create(log).with_context(|| format!("creating {}", log.display()))?;
    command.stdout(Stdio::null()).stderr(stderr);
    let mut proc = Proc::spawn(command, name)?;
    let (status, _) = wait_capped(&mut proc, limit)?;
    match status {
        Some(s) if s.success() => Ok(()),
        Some(s) => bail!("{name} failed ({s}): {}", tail(log)),
        None => bail!("{name} did not end within {} s", limit.as_secs()),
    }
}

/// The last lines of a log file, for an error message.
pub fn tail(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let lines: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
    let start = lines.len().saturating_sub(4);
    let mut out = lines[start..].join(" | ");
    if out.len() > 600 {
        let cut = (0..=out.len() - 600)
            .rev()
            .find(|&i| out.is_char_boundary(i))
            .unwrap_or(0);
        out = format!("...{}", &out[cut..]);
    }
    if out.is_empty() {
        "(nothing on standard error)".into()
    } else {
        out
    }
}

/// A UDP port that was free on 127.0.0.1 a moment ago (for programs that cannot bind
/// port 0 and report it; a server started on it may still lose it to another program,
/// which [`start_coap_server`] retries).
pub fn free_udp_port() -> anyhow::Result<u16> {
    let socket = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0)).context("finding a free UDP port")?;
    Ok(socket
        .local_addr()
        .context("finding a free UDP port")?
        .port())
}

/// Whether a CoAP server answers at `addr` within 100 ms: an empty CON (a CoAP ping,
/// RFC 7252 §4.3) that every server answers with a RST.
pub fn coap_answers(addr: SocketAddr) -> bool {
    let Ok(socket) = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0)) else {
        return false;
    };
    let ping = [0x40, 0x00, 0x7a, 0x5e];
    let mut buf = [0u8; 64];
    socket
        .set_read_timeout(Some(Duration::from_millis(100)))
        .is_ok()
        && socket.send_to(&ping, addr).is_ok()
        && matches!(socket.recv_from(&mut buf), Ok((n, from)) if n >= 4 && from == addr)
}

/// Starts a CoAP server with `command(port)` on a free port of 127.0.0.1 and waits, at
/// most `startup`, until it answers a ping; its standard error goes to `log`. Tries three
/// ports.
pub fn start_coap_server(
    name: &str,
    log: &Path,
    startup: Duration,
    command: impl Fn(u16) -> Command,
) -> anyhow::Result<(Proc, SocketAddr)> {
    let mut last = None;
    for _ in 0..3 {
        let port = free_udp_port()?;
        let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
        let mut cmd = command(port);
        let stderr = File::create(log).with_context(|| format!("creating {}", log.display()))?;
        cmd.stdout(Stdio::null()).stderr(stderr);
        let mut server = Proc::spawn(cmd, name)?;
        let started = Instant::now();
        let up = loop {
            if let Err(e) = server.check_running() {
                break Err(e);
            }
            if coap_answers(addr) {
                break Ok(());
            }
            if started.elapsed() > startup {
                break Err(anyhow::anyhow!(
                    "{name} did not answer on {addr} within {} s",
                    startup.as_secs()
                ));
            }
        };
        match up {
            Ok(()) => return Ok((server, addr)),
            Err(e) => last = Some(e.context(tail(log))),
        }
    }
    Err(last.unwrap_or_else(|| anyhow::anyhow!("{name} did not start")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_child_past_its_cap_is_killed_and_one_that_ends_is_seen() {
        let mut sleeper = Command::new("sleep");
        sleeper.arg("30");
        let mut slow = Proc::spawn(sleeper, "sleep 30").unwrap();
        let (status, _) = wait_capped(&mut slow, Duration::from_millis(50)).unwrap();
        assert_eq!(status, None);
        assert!(!slow.is_running());
        let mut quick = Proc::spawn(Command::new("true"), "true").unwrap();
        let status = quick.wait_for(Duration::from_secs(30)).unwrap();
        assert!(status.is_some_and(|s| s.success()));
    }

    #[test]
    fn a_failing_program_is_reported_with_its_log() {
        let dir = crate::ScratchDir::new("process-log");
        let log = dir.path().join("log");
        let mut cmd = Command::new("sh");
        cmd.args(["-c", "echo first >&2; echo the reason >&2; exit 3"]);
        let e = run_to_end(cmd, "sh", &log, Duration::from_secs(30)).unwrap_err();
        let text = format!("{e:#}");
        assert!(
            text.contains("the reason") && text.contains("first"),
            "{text}"
        );
        assert_eq!(
            tail(&dir.path().join("none")),
            "(nothing on standard error)"
        );
    }
}
