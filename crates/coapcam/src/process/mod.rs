//! Child processes for the benchmarks and the integration tests: started with standard
//! input closed, waited for within limits, killed and reaped on drop; servers started on
//! a free loopback port and waited for until they answer a CoAP ping. Where the peer
//! programs are (libcoap 4.3.1 and 4.3.5, aiocoap, `quic-bench`) is [`peers`].
//!
//! Nothing here talks to any address but 127.0.0.1.

pub mod peers;

use std::fs::File;
use std::net::{Ipv4Addr, SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::thread;
use std::time::{Duration, Instant};

/// How often a running child is checked for its exit: the resolution of the times.
pub const POLL: Duration = Duration::from_millis(1);

/// A child process that could not be started, waited for, or that failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ProcError {
    /// The program could not be started.
    #[error("starting {name}")]
    Spawn {
        /// The process's name.
        name: String,
        /// Why.
        source: std::io::Error,
    },
    /// Its state could not be read.
    #[error("waiting for {name}")]
    Wait {
        /// The process's name.
        name: String,
        /// Why.
        source: std::io::Error,
    },
    /// It exited while it should run.
    #[error("{name} exited ({status})")]
    Exited {
        /// The process's name.
        name: String,
        /// How it ended.
        status: ExitStatus,
    },
    /// It ended without success.
    #[error("{name} failed ({status}): {log_tail}")]
    Failed {
        /// The process's name.
        name: String,
        /// How it ended.
        status: ExitStatus,
        /// The last lines of its standard error ([`tail`]).
        log_tail: String,
    },
    /// It did not end in time (it was killed).
    #[error("{name} did not end within {limit_s} s")]
    TimedOut {
        /// The process's name.
        name: String,
        /// The time it had, seconds.
        limit_s: u64,
    },
    /// A server did not answer a CoAP ping in time.
    #[error("{name} did not answer on {addr} within {startup_s} s")]
    NoAnswer {
        /// The server's name.
        name: String,
        /// Where it should answer.
        addr: SocketAddr,
        /// The time it had, seconds.
        startup_s: u64,
    },
    /// A server did not start on any of the ports tried: the last lines of its
    /// standard error, and why the last try failed.
    #[error("{log_tail}")]
    Startup {
        /// The last lines of its standard error ([`tail`]).
        log_tail: String,
        /// Why the last try failed.
        source: Box<Self>,
    },
    /// The file for a standard error could not be created.
    #[error("creating {}", path.display())]
    Log {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// No UDP port of 127.0.0.1 could be had.
    #[error("finding a free UDP port")]
    FreePort(#[source] std::io::Error),
}

fn create_log(path: &Path) -> Result<File, ProcError> {
    File::create(path).map_err(|source| ProcError::Log {
        path: path.to_owned(),
        source,
    })
}

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
    pub fn spawn(mut command: Command, name: &str) -> Result<Self, ProcError> {
        let child = command
            .stdin(Stdio::null())
            .spawn()
            .map_err(|source| ProcError::Spawn {
                name: name.to_owned(),
                source,
            })?;
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
    pub fn try_status(&mut self) -> Result<Option<ExitStatus>, ProcError> {
        self.child
            .try_wait()
            .map_err(|source| self.wait_error(source))
    }

    fn wait_error(&self, source: std::io::Error) -> ProcError {
        ProcError::Wait {
            name: self.name.clone(),
            source,
        }
    }

    /// Whether it still runs.
    pub fn is_running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    /// An error if it has exited.
    pub fn check_running(&mut self) -> Result<(), ProcError> {
        match self.try_status()? {
            None => Ok(()),
            Some(status) => Err(ProcError::Exited {
                name: self.name.clone(),
                status,
            }),
        }
    }

    /// Waits at most `limit` for it to exit; `None` if it still runs then (it is not
    /// killed).
    pub fn wait_for(&mut self, limit: Duration) -> Result<Option<ExitStatus>, ProcError> {
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
    pub fn kill(&mut self) -> Result<ExitStatus, ProcError> {
        let _ = self.child.kill();
        self.child.wait().map_err(|source| self.wait_error(source))
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
) -> Result<Vec<(Option<ExitStatus>, Duration)>, ProcError> {
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
) -> Result<(Option<ExitStatus>, Duration), ProcError> {
    let ended = wait_all_capped(std::slice::from_mut(proc), cap, || {})?;
    Ok(ended[0])
}

/// Runs `command` to its end within `limit`, its standard error into `log`; an error says
/// why it failed (with the log's last lines).
pub fn run_to_end(
    command: Command,
    name: &str,
    log: &Path,
    limit: Duration,
) -> Result<(), ProcError> {
    let mut command = command;
    let stderr = create_log(log)?;
    command.stdout(Stdio::null()).stderr(stderr);
    let mut proc = Proc::spawn(command, name)?;
    let (status, _) = wait_capped(&mut proc, limit)?;
    match status {
        Some(s) if s.success() => Ok(()),
        Some(status) => Err(ProcError::Failed {
            name: name.to_owned(),
            status,
            log_tail: tail(log),
        }),
        None => Err(ProcError::TimedOut {
            name: name.to_owned(),
            limit_s: limit.as_secs(),
        }),
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
pub fn free_udp_port() -> Result<u16, ProcError> {
    let socket = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0)).map_err(ProcError::FreePort)?;
    Ok(socket.local_addr().map_err(ProcError::FreePort)?.port())
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
) -> Result<(Proc, SocketAddr), ProcError> {
    const TRIES: u32 = 3;
    let mut tried = 0;
    loop {
        tried += 1;
        let port = free_udp_port()?;
        let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
        let mut cmd = command(port);
        let stderr = create_log(log)?;
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
                break Err(ProcError::NoAnswer {
                    name: name.to_owned(),
                    addr,
                    startup_s: startup.as_secs(),
                });
            }
        };
        match up {
            Ok(()) => return Ok((server, addr)),
            Err(e) if tried >= TRIES => {
                return Err(ProcError::Startup {
                    log_tail: tail(log),
                    source: Box::new(e),
                });
            }
            Err(_) => {}
        }
    }
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
        assert!(
            matches!(&e, ProcError::Failed { name, status, .. } if name == "sh" && status.code() == Some(3)),
            "{e:?}"
        );
        let text = e.to_string();
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
