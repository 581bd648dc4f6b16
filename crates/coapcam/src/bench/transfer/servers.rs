//! The servers of `bench transfer` (our `coapcam serve`, libcoap's, `quic-bench serve`),
//! each holding every body, and the client command of a run of each mode.

use std::fs::File;
use std::io::{BufRead as _, BufReader};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::thread;
use std::time::Duration;

use anyhow::{Context as _, bail};

use super::body::{Body, difference};
use super::config::{Mode, SETUP_TRANSFER, STARTUP};
use crate::process::{Proc, peers, run_to_end, start_coap_server, tail};

/// Where the programs of the modes are.
pub(super) struct Programs {
    pub(super) coapcam: PathBuf,
    pub(super) libcoap431: Result<(PathBuf, PathBuf), String>,
    pub(super) libcoap435: Result<(PathBuf, PathBuf), String>,
    pub(super) quic: Result<PathBuf, String>,
}

impl Programs {
    /// The programs: `coapcam` (this executable, for our modes) and the peers,
    /// each with why it cannot be used if it cannot.
    pub(super) fn locate(coapcam: PathBuf) -> Self {
        let quic = peers::quic_bench(&coapcam);
        Self {
            coapcam,
            libcoap431: peers::libcoap431(),
            libcoap435: peers::libcoap435(),
            quic,
        }
    }

    /// Why `mode` cannot run here, if it cannot.
    pub(super) fn missing(&self, mode: Mode) -> Option<&str> {
        match mode {
            Mode::StopAndWait | Mode::Window | Mode::QBlock => None,
            Mode::Libcoap431 => self.libcoap431.as_ref().err().map(String::as_str),
            Mode::Libcoap435 => self.libcoap435.as_ref().err().map(String::as_str),
            Mode::Quic => self.quic.as_ref().err().map(String::as_str),
        }
    }
}

/// What a client of one mode fetches a body of one size from.
#[derive(Debug, Clone)]
pub(super) struct Target {
    pub(super) addr: SocketAddr,
    /// The URI path (CoAP modes) or the certificate (QUIC).
    pub(super) path: String,
}

/// Servers started for a mode, and where each size's body is.
type Started = (Vec<Proc>, Vec<(u64, Target)>);

/// The servers of the benchmark and, per (mode, size), where to fetch from or why it
/// cannot be.
pub(super) struct Servers {
    _procs: Vec<Proc>,
    targets: Vec<(Mode, u64, Result<Target, String>)>,
}

impl Servers {
    pub(super) fn target(&self, mode: Mode, size: u64) -> Result<&Target, &str> {
        self.targets
            .iter()
            .find(|(m, s, _)| *m == mode && *s == size)
            .map_or(Err("no server"), |(_, _, t)| {
                t.as_ref().map_err(String::as_str)
            })
    }

    /// Starts the servers that `modes` need, holding `bodies`. A server that does not
    /// start, or a body it does not give back, makes those cells' runs fail (reported);
    /// it does not stop the benchmark.
    pub(super) fn start(
        programs: &Programs,
        modes: &[Mode],
        bodies: &[Body],
        work: &Path,
        progress: &mut dyn FnMut(String),
    ) -> anyhow::Result<Self> {
        let mut procs = Vec::new();
        let mut targets = Vec::new();
        let mut record = |mode: Mode, result: anyhow::Result<Vec<(u64, Target)>>| match result {
            Ok(list) => {
                for (size, target) in list {
                    targets.push((mode, size, Ok(target)));
                }
            }
            Err(e) => {
                let why = crate::error_text(e.as_ref());
                progress(format!("coapcam: bench transfer: {}: {why}", mode.name()));
                for body in bodies {
                    targets.push((mode, body.size, Err(why.clone())));
                }
            }
        };
        let ours: Vec<Mode> = modes
            .iter()
            .copied()
            .filter(|m| matches!(m, Mode::StopAndWait | Mode::Window | Mode::QBlock))
            .collect();
        if !ours.is_empty() {
            let started =
                start_coap_server("coapcam serve", &work.join("serve.log"), STARTUP, |port| {
                    let mut cmd = Command::new(&programs.coapcam);
                    cmd.arg("serve")
                        .arg("--no-cameras")
                        .arg("--static")
                        .arg(work.join("files"))
                        .arg("--bind")
                        .arg(format!("127.0.0.1:{port}"));
                    cmd
                });
            let started = started.map(|(proc, addr)| {
                procs.push(proc);
                bodies
                    .iter()
                    .map(|b| {
                        let path = format!("/files/{}", b.file_name());
                        (b.size, Target { addr, path })
                    })
                    .collect::<Vec<_>>()
            });
            match started {
                Ok(list) => {
                    for mode in ours {
                        record(mode, Ok(list.clone()));
                    }
                }
                Err(e) => {
                    let why = format!("{e:#}");
                    for mode in ours {
                        record(mode, Err(anyhow::anyhow!("{why}")));
                    }
                }
            }
        }
        for mode in modes {
            let started = match mode {
                Mode::Libcoap431 => {
                    let Ok((client, server)) = &programs.libcoap431 else {
                        continue;
                    };
                    libcoap_server(*mode, client, server, false, bodies, work)
                }
                Mode::Libcoap435 => {
                    let Ok((client, server)) = &programs.libcoap435 else {
                        continue;
                    };
                    libcoap_server(*mode, client, server, true, bodies, work)
                }
                Mode::Quic => {
                    let Ok(quic) = &programs.quic else { continue };
                    quic_servers(quic, bodies, work)
                }
                _ => continue,
            };
            let list = started.map(|(mut started, list)| {
                procs.append(&mut started);
                list
            });
            record(*mode, list);
        }
        Ok(Self {
            _procs: procs,
            targets,
        })
    }
}

/// A libcoap server (`-d`: a PUT creates a resource; `-L 5` for Q-Block) holding every
/// body, PUT on loopback with the same version's client and checked with a GET.
fn libcoap_server(
    mode: Mode,
    client: &Path,
    server: &Path,
    qblock: bool,
    bodies: &[Body],
    work: &Path,
) -> anyhow::Result<Started> {
    let tag = mode.name();
    let resources = (bodies.len() + 2).max(10).to_string();
    let (proc, addr) = start_coap_server(
        &server.display().to_string(),
        &work.join(format!("{tag}-server.log")),
        STARTUP,
        |port| {
            let mut cmd = Command::new(server);
            cmd.args(["-A", "127.0.0.1", "-p", &port.to_string(), "-d", &resources]);
            if qblock {
                cmd.args(["-L", "5"]);
            }
            cmd
        },
    )?;
    let wait = SETUP_TRANSFER.as_secs().to_string();
    let mut list = Vec::new();
    for body in bodies {
        let path = format!("/body-{}", body.size);
        let uri = format!("coap://{addr}{path}");
        let log = work.join(format!("{tag}-setup.log"));
        let mut put = Command::new(client);
        put.args(["-m", "put", "-b", "1024", "-B", &wait, "-f"])
            .arg(&body.path)
            .arg(&uri);
        run_to_end(
            put,
            &format!("{} -m put {uri}", client.display()),
            &log,
            SETUP_TRANSFER,
        )?;
        let check = work.join(format!("{tag}-check"));
        let mut get = Command::new(client);
        get.args(["-b", "1024", "-B", &wait, "-o"])
            .arg(&check)
            .arg(&uri);
        run_to_end(
            get,
            &format!("{} {uri}", client.display()),
            &log,
            SETUP_TRANSFER,
        )?;
        if let Some(diff) = difference(&check, &body.bytes) {
            bail!("the server gave back another body than was PUT to {uri}: {diff}");
        }
        let _ = std::fs::remove_file(&check);
        list.push((body.size, Target { addr, path }));
    }
    Ok((vec![proc], list))
}

/// One `quic-bench serve` per body (it serves one file), each on a port of its choice.
fn quic_servers(quic: &Path, bodies: &[Body], work: &Path) -> anyhow::Result<Started> {
    let mut procs = Vec::new();
    let mut list = Vec::new();
    for body in bodies {
        let cert = work.join(format!("quic-{}.der", body.size));
        let log = work.join(format!("quic-{}.log", body.size));
        let mut cmd = Command::new(quic);
        cmd.arg("serve")
            .arg("127.0.0.1:0")
            .arg(&body.path)
            .arg(&cert)
            .stdout(Stdio::piped())
            .stderr(File::create(&log).with_context(|| format!("creating {}", log.display()))?);
        let mut proc = Proc::spawn(cmd, "quic-bench serve")?;
        let stdout = proc
            .child_mut()
            .stdout
            .take()
            .context("quic-bench serve's output")?;
        // It prints "ready ADDR" once bound; the thread reads on to the end so a later
        // line never blocks it.
        let (tx, rx) = mpsc::channel();
        thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if let Some(addr) = line.strip_prefix("ready ") {
                    let _ = tx.send(addr.trim().parse::<SocketAddr>());
                }
            }
        });
        let addr = match rx.recv_timeout(STARTUP) {
            Ok(Ok(addr)) => addr,
            Ok(Err(e)) => bail!("quic-bench serve printed a bad address: {e}"),
            Err(_) => {
                let _ = proc.check_running();
                bail!("quic-bench serve did not start: {}", tail(&log));
            }
        };
        procs.push(proc);
        let path = cert
            .to_str()
            .context("the certificate's path is not UTF-8")?;
        list.push((
            body.size,
            Target {
                addr,
                path: path.to_owned(),
            },
        ));
    }
    Ok((procs, list))
}

/// The client command of one run of `mode` fetching from `addr` into `out`.
pub(super) fn client_command(
    programs: &Programs,
    mode: Mode,
    addr: SocketAddr,
    target: &Target,
    out: &Path,
    cap: Duration,
) -> anyhow::Result<Command> {
    let uri = format!("coap://{addr}{}", target.path);
    // libcoap gives up by itself after -B seconds, exit status 0; past the cap, so that
    // the cap is what stops it.
    let wait = (cap.as_secs() + 10).to_string();
    let mut cmd;
    match mode {
        Mode::StopAndWait | Mode::Window | Mode::QBlock => {
            let transfer = match mode {
                Mode::StopAndWait => "stop-and-wait",
                Mode::Window => "window",
                _ => "q-block",
            };
            cmd = Command::new(&programs.coapcam);
            cmd.arg("get")
                .arg(&uri)
                .arg("-o")
                .arg(out)
                .args(["--transfer", transfer]);
        }
        Mode::Libcoap431 => {
            let (client, _) = programs
                .libcoap431
                .as_ref()
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            cmd = Command::new(client);
            cmd.args(["-b", "1024", "-B", &wait, "-o"])
                .arg(out)
                .arg(&uri);
        }
        Mode::Libcoap435 => {
            let (client, _) = programs
                .libcoap435
                .as_ref()
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            cmd = Command::new(client);
            cmd.args(["-L", "5", "-N", "-b", "1024", "-B", &wait, "-o"])
                .arg(out)
                .arg(&uri);
        }
        Mode::Quic => {
            let quic = programs.quic.as_ref().map_err(|e| anyhow::anyhow!("{e}"))?;
            cmd = Command::new(quic);
            cmd.arg("get")
                .arg(addr.to_string())
                .arg(&target.path)
                .arg(out);
        }
    }
    Ok(cmd)
}
