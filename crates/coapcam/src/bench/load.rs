//! `bench load`: many concurrent clients against one running server for a while,
//! each with its own socket, in four roles:
//! - discovery: `GET /.well-known/core?rt=rgbd*` again and again, timed, each answer
//!   compared with the first (the cameras' links do not change while the files do);
//! - uploads: `PUT /files/load-<n>.bin` of a seeded random body, then `GET` it back and
//!   compare (needs `serve --static DIR --writable`);
//! - grabs: by turns `POST /cams/<sn>/depth` (RVL+zstd, decoded to check it) and
//!   `POST /cams/dimensions` (parsed); a 5.03 with Max-Age (the server's grab memory
//!   budget) is waited out and asked again, and counted;
//! - observers of `/cams/dimensions`, each of whose notifications must parse; once the
//!   grabs have ended, each must receive the server's final measurement within 5 s.
//!
//! The command prints what they counted as one JSON object.

use std::net::SocketAddr;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use anyhow::Context as _;
use bytes::Bytes;
use coap::{Code, EndpointConfig, OptionNumber, Request, Response};
use coap_net::{Client, Uri};
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore as _, SeedableRng as _};

use crate::client::CamClient;
use crate::repr::{self, rvl};

/// What to run.
#[derive(Debug, Clone)]
pub struct Config {
    /// The server's URI (started with `--static DIR --writable`).
    pub server: String,
    /// Concurrent clients, each with its own socket, a quarter in each role.
    pub clients: usize,
    /// How long the clients keep going.
    pub duration: Duration,
    /// Pause of each client between two of its requests.
    pub pause: Duration,
    /// Per-request timeout.
    pub timeout: Duration,
}

/// What the discovery clients ask for: the cameras' links, which stay the same while the
/// uploads add files.
fn discovery() -> Request {
    let mut request = Request::new(Code::GET, "/.well-known/core");
    request.options.push(OptionNumber::URI_QUERY, "rt=rgbd*");
    request
}

/// What the clients counted.
#[derive(Debug, Default, Clone)]
pub struct Tally {
    /// Each discovery's time, milliseconds.
    pub discovery_ms: Vec<f64>,
    /// Discovery answers that differed from the first.
    pub discovery_mismatches: u64,
    /// Uploads read back.
    pub uploads: u64,
    /// Their bytes.
    pub upload_bytes: u64,
    /// Uploads read back otherwise than they were written.
    pub upload_mismatches: u64,
    /// Depth grabs.
    pub depth_grabs: u64,
    /// Measurements.
    pub measurements: u64,
    /// 5.03 answers waited out and asked again.
    pub busy: u64,
    /// Bodies that did not decode.
    pub undecodable: u64,
    /// Notifications the observers received.
    pub notifications: u64,
    /// Observers that had not received the final measurement 5 s after it was known.
    pub behind_at_end: u64,
    /// What failed, one line each.
    pub failures: Vec<String>,
}

impl Tally {
    /// Nothing failed, mismatched, did not decode or was lost.
    pub fn clean(&self) -> bool {
        self.failures.is_empty()
            && self.discovery_mismatches
                + self.upload_mismatches
                + self.undecodable
                + self.behind_at_end
                == 0
    }
}

type Shared = Arc<Mutex<Tally>>;

fn tally(t: &Shared) -> std::sync::MutexGuard<'_, Tally> {
    t.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Runs the clients against `config.server` for `config.duration`; what they counted.
pub async fn run(config: &Config) -> anyhow::Result<Tally> {
    let uri = Uri::parse(&config.server)?;
    if uri.secure || uri.tcp || uri.ws {
        anyhow::bail!("{}: bench load speaks coap:// only", config.server);
    }
    let server = uri.resolve().await.context("resolving the server")?;
    let (timeout, duration) = (config.timeout, config.duration);
    let cam = CamClient::connect(&config.server, EndpointConfig::default(), None, timeout).await?;
    let serial = cam.one_camera(None).await?;
    // A first measurement, so that observers of /cams/dimensions have one to register on.
    cam.call(Code::POST, "/cams/dimensions", Bytes::new(), None, None)
        .await
        .context("the first measurement")?;
    let mut first = discovery();
    first.timeout = Some(timeout);
    let reference = cam.coap().send(server, first).await?.payload;

    let shared: Shared = Arc::default();
    let stop = Instant::now() + duration;
    let pause = config.pause;
    let mut tasks = Vec::new();
    let mut observers = Vec::new();
    let (final_tx, final_rx) = tokio::sync::watch::channel(None);
    for n in 0..config.clients {
        let client = Client::for_peer(
            server,
            EndpointConfig {
                rng_seed: n as u64 + 1,
                ..EndpointConfig::default()
            },
        )
        .context("binding a client socket")?;
        let one = One {
            client,
            server,
            timeout,
            shared: shared.clone(),
        };
        match n % 4 {
            0 => tasks.push(tokio::spawn(one.discovery(reference.clone(), stop, pause))),
            1 => tasks.push(tokio::spawn(one.uploads(n, stop, pause))),
            2 => tasks.push(tokio::spawn(one.grabs(serial.clone(), stop, pause))),
            _ => observers.push(tokio::spawn(one.observe(final_rx.clone()))),
        }
    }
    for t in tasks {
        t.await.context("a client task")?;
    }
    // Every grab is done: the last measurement is what each observer must get.
    let last = cam
        .call(Code::GET, "/cams/dimensions", Bytes::new(), None, None)
        .await?
        .payload;
    let _ = final_tx.send(Some(last));
    let mut behind = 0u64;
    for o in observers {
        behind += u64::from(!o.await.context("an observer task")?);
    }
    let mut t = std::mem::take(&mut *tally(&shared));
    t.behind_at_end = behind;
    Ok(t)
}

/// One client.
struct One {
    client: Client,
    server: SocketAddr,
    timeout: Duration,
    shared: Shared,
}

impl One {
    /// Sends a request; a 5.03 with Max-Age is waited out and sent again (counted).
    async fn send(&self, request: Request) -> Option<Response> {
        loop {
            let mut r = request.clone();
            r.timeout = Some(self.timeout);
            match self.client.send(self.server, r).await {
                Ok(resp) if resp.code == Code::SERVICE_UNAVAILABLE => {
                    self.record(|t| t.busy += 1);
                    let secs = resp.options.uint(OptionNumber::MAX_AGE).unwrap_or(1);
                    tokio::time::sleep(Duration::from_secs(u64::from(secs.min(5)))).await;
                }
                Ok(resp) if resp.code.is_success() => return Some(resp),
                Ok(resp) => {
                    self.fail(format!("{}: {}", describe(&request), resp.code));
                    return None;
                }
                Err(e) => {
                    let path = self.client.path_stats(self.server).await.ok().flatten();
                    let local = self.client.local_addr();
                    self.fail(format!(
                        "{}: {e} (from {local}; {path:?})",
                        describe(&request)
                    ));
                    return None;
                }
            }
        }
    }

    fn fail(&self, what: String) {
        self.record(|t| t.failures.push(what));
    }

    fn record(&self, f: impl FnOnce(&mut Tally)) {
        f(&mut tally(&self.shared));
    }

    async fn discovery(self, reference: Bytes, stop: Instant, pause: Duration) {
        while Instant::now() < stop {
            let started = Instant::now();
            let Some(r) = self.send(discovery()).await else {
                return;
            };
            let ms = started.elapsed().as_secs_f64() * 1000.0;
            self.record(|t| {
                t.discovery_ms.push(ms);
                t.discovery_mismatches += u64::from(r.payload != reference);
            });
            tokio::time::sleep(pause).await;
        }
    }

    async fn uploads(self, n: usize, stop: Instant, pause: Duration) {
        let mut rng = ChaCha8Rng::seed_from_u64(n as u64);
        let path = format!("/files/load-{n}.bin");
        while Instant::now() < stop {
            let mut body = vec![0u8; 10_000 + (rng.next_u32() % 90_000) as usize];
            rng.fill_bytes(&mut body);
            let put = Request::new(Code::PUT, &path).with_payload(body.clone());
            if self.send(put).await.is_none() {
                return;
            }
            let Some(r) = self.send(Request::new(Code::GET, &path)).await else {
                return;
            };
            self.record(|t| {
                t.uploads += 1;
                t.upload_bytes += body.len() as u64;
                t.upload_mismatches += u64::from(r.payload[..] != body[..]);
            });
            tokio::time::sleep(pause).await;
        }
    }

    async fn grabs(self, serial: String, stop: Instant, pause: Duration) {
        let mut turn = 0u64;
        while Instant::now() < stop {
            turn += 1;
            if turn.is_multiple_of(2) {
                let Some(r) = self
                    .send(Request::new(Code::POST, "/cams/dimensions"))
                    .await
                else {
                    return;
                };
                let parsed = serde_json::from_slice::<serde::de::IgnoredAny>(&r.payload).is_ok();
                self.record(|t| {
                    t.measurements += 1;
                    t.undecodable += u64::from(!parsed);
                });
            } else {
                let mut request = Request::new(Code::POST, &format!("/cams/{serial}/depth"));
                let cf = repr::RVL_ZSTD;
                request
                    .options
                    .set_uint(OptionNumber::ACCEPT, u32::from(cf.0));
                let Some(r) = self.send(request).await else {
                    return;
                };
                let decoded = rvl::depth_from_rvl_zstd(&r.payload).is_ok();
                self.record(|t| {
                    t.depth_grabs += 1;
                    t.undecodable += u64::from(!decoded);
                });
            }
            tokio::time::sleep(pause).await;
        }
    }

    /// Observes `/cams/dimensions` until the final measurement is known and has arrived
    /// (true), or 5 s after it is known (false).
    async fn observe(self, mut last: tokio::sync::watch::Receiver<Option<Bytes>>) -> bool {
        let mut request = Request::new(Code::GET, "/cams/dimensions");
        request.timeout = Some(self.timeout);
        let mut observation = match self.client.observe(self.server, request).await {
            Ok(o) => o,
            Err(e) => {
                self.fail(format!("observe /cams/dimensions: {e}"));
                return false;
            }
        };
        let mut seen = Bytes::new();
        let mut deadline = None;
        loop {
            if let Some(last) = last.borrow().as_ref() {
                if *last == seen {
                    return true;
                }
                deadline
                    .get_or_insert_with(|| tokio::time::Instant::now() + Duration::from_secs(5));
            }
            let wait = async {
                match deadline {
                    Some(d) => tokio::time::sleep_until(d).await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                _ = last.changed() => {}
                () = wait => return false,
                next = observation.next() => match next {
                    Some(Ok(r)) if r.code.is_success() => {
                        let parsed = serde_json::from_slice::<serde::de::IgnoredAny>(&r.payload).is_ok();
                        self.record(|t| {
                            t.notifications += 1;
                            t.undecodable += u64::from(!parsed);
                        });
                        seen = r.payload;
                    }
                    Some(Ok(r)) => {
                        self.fail(format!("a notification of /cams/dimensions: {}", r.code));
                        return false;
                    }
                    Some(Err(e)) => {
                        self.fail(format!("a notification of /cams/dimensions: {e}"));
                        return false;
                    }
                    None => {
                        self.fail("the observation of /cams/dimensions ended".into());
                        return false;
                    }
                },
            }
        }
    }
}

fn describe(request: &Request) -> String {
    format!(
        "{} {}",
        request.method.name().unwrap_or("request"),
        request.options.path_string()
    )
}
