//! Requests timed as the thesis's test procedure (§3.4) times them: a grab or a
//! measurement repeated, or the notifications of an observed resource.

use std::time::{Duration, Instant};

use bytes::Bytes;
use coap::{Code, ContentFormat, OptionNumber, Response};
use geometry::DimensionConfig;

use super::measure::{self, CloudMeasurement, MeasureError, Source};
use super::{CallError, CamClient, DiscoveryError};
use crate::repr::Stream;

/// A timed request or an observation failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum TimedError {
    /// A request failed (transparent: the causes the command's exit status looks for
    /// are the [`CallError`]'s sources, not itself).
    #[error(transparent)]
    Call(#[from] CallError),
    /// A measurement failed (transparent, as `Call`).
    #[error(transparent)]
    Measure(#[from] MeasureError),
    /// The observation failed (transparent, as `Call`).
    #[error(transparent)]
    Watch(#[from] WatchError),
    /// The cameras could not be listed (transparent, as `Call`).
    #[error(transparent)]
    Discovery(#[from] DiscoveryError),
    /// The server answered without registering the observation.
    #[error("the server did not accept the observation of {0}")]
    NotAccepted(String),
    /// The server ended the observation.
    #[error("the server ended the observation of {0}")]
    Ended(String),
}

/// A request repeated every interval.
#[derive(Debug, Clone)]
pub enum Repeat {
    /// A grab of one camera's stream.
    Grab {
        /// The camera.
        serial: String,
        /// Its stream.
        stream: Stream,
    },
    /// Every camera's cloud, merged (`POST /cams/pointclouds`).
    All,
    /// A measurement.
    Measure(Source),
}

/// What one request brought.
#[derive(Debug)]
pub struct Timed {
    /// The body's bytes (a measurement's: those of its grabs).
    pub bytes: usize,
    /// The time the statistics count.
    pub time: Duration,
    /// The measurement, if it was one.
    pub measurement: Option<CloudMeasurement>,
}

/// One grab (in the representation `accept`, or the compact one) or measurement, timed:
/// a grab from its request to its whole body, a measurement by its grabs.
pub async fn once(
    client: &CamClient,
    what: &Repeat,
    accept: Option<ContentFormat>,
    config: &DimensionConfig,
) -> Result<Timed, TimedError> {
    let started = Instant::now();
    match what {
        Repeat::Grab { serial, stream } => {
            let r = match accept {
                Some(cf) => client.grab(serial, *stream, Some(cf)).await?,
                None => client.grab_compact(serial, *stream).await?,
            };
            Ok(Timed {
                bytes: r.payload.len(),
                time: started.elapsed(),
                measurement: None,
            })
        }
        Repeat::All => {
            let r = match accept {
                Some(cf) => client.grab_all(Some(cf)).await?,
                None => client.grab_cloud(None).await?,
            };
            Ok(Timed {
                bytes: r.payload.len(),
                time: started.elapsed(),
                measurement: None,
            })
        }
        Repeat::Measure(source) => {
            let m = measure::measure_once(client, source, config).await?;
            Ok(Timed {
                bytes: m.grabbed.bytes,
                time: m.grab,
                measurement: Some(m),
            })
        }
    }
}

/// How often [`observe`] asks again while the camera has no frame yet.
pub const FIRST_FRAME_POLL: Duration = Duration::from_millis(250);

/// Observes `/cams/<serial>/<stream>` (in the representation `accept`): each
/// notification, the first within `timeout`, is handed to `on_result` with the time since
/// the previous one (the first's since the request), until `on_result` says to stop
/// (true) or the observation ends (an error; an error of `on_result` ends it as that
/// error, untouched). While the camera (one the server lists)
/// has no frame yet (4.04: nobody grabbed one), it waits for the first frame anyone
/// grabs, asking again every [`FIRST_FRAME_POLL`]; `on_waiting` is called once when it
/// starts to wait.
pub async fn observe<E: From<TimedError>>(
    client: &CamClient,
    serial: &str,
    stream: Stream,
    accept: Option<ContentFormat>,
    timeout: Duration,
    mut on_waiting: impl FnMut(&str),
    mut on_result: impl FnMut(Result<Timed, TimedError>, Duration) -> Result<bool, E>,
) -> Result<(), E> {
    let path = crate::api::paths::camera(serial, stream.name());
    let mut previous = Instant::now();
    let mut watch = Watch::start(client, &path, accept, timeout)
        .await
        .map_err(TimedError::from)?;
    let mut first = true;
    // Whether the server lists the camera: asked at the first 4.04.
    let mut listed = None;
    loop {
        let next = watch.next().await;
        let elapsed = previous.elapsed();
        previous = Instant::now();
        let response = match next {
            Ok(response) => response,
            // A notification that could not be completed (its other blocks lost, or the
            // resource changing faster than it can be fetched) is a failed result, not
            // the end: the observation goes on, and its end comes as `Ended`.
            Err(e) if !first && !matches!(e, WatchError::Ended(_)) => {
                if on_result(Err(e.into()), elapsed)? {
                    return Ok(());
                }
                continue;
            }
            Err(e) => return Err(TimedError::from(e).into()),
        };
        let observing = response.options.contains(OptionNumber::OBSERVE);
        if first && !observing && response.code == Code::NOT_FOUND {
            if listed.is_none() {
                let serials = client.cameras().await.map_err(TimedError::from)?;
                let is_listed = serials.iter().any(|sn| sn == serial);
                if is_listed {
                    on_waiting(&path);
                }
                listed = Some(is_listed);
            }
            if listed == Some(true) {
                tokio::time::sleep(FIRST_FRAME_POLL).await;
                watch = Watch::start(client, &path, accept, timeout)
                    .await
                    .map_err(TimedError::from)?;
                previous = Instant::now();
                continue;
            }
        }
        let outcome = super::check(&format!("GET {path}"), response)
            .map(|r| Timed {
                bytes: r.payload.len(),
                time: elapsed,
                measurement: None,
            })
            .map_err(TimedError::from);
        let stop = on_result(outcome, elapsed)?;
        if !observing {
            return Err(if first {
                TimedError::NotAccepted(path)
            } else {
                TimedError::Ended(path)
            }
            .into());
        }
        if stop {
            return Ok(());
        }
        first = false;
    }
}

/// An observation that could not be registered, or did not go on.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum WatchError {
    /// The registration was not sent or not answered.
    #[error("observing {path} on {server}")]
    Register {
        /// The resource.
        path: String,
        /// The server.
        server: std::net::SocketAddr,
        /// Why.
        source: coap_net::Error,
    },
    /// The first answer did not come in time.
    #[error("no answer to the observation of {path} in {timeout:?}")]
    FirstAnswer {
        /// The resource.
        path: String,
        /// The time it had.
        timeout: Duration,
        /// The timeout's error.
        source: tokio::time::error::Elapsed,
    },
    /// The observation ended (the server or the path to it gave up).
    #[error("the observation of {0} ended")]
    Ended(String),
    /// A notification could not be completed (its other blocks lost, or the resource
    /// changing faster than it can be fetched).
    #[error("observing {path}")]
    Notification {
        /// The resource.
        path: String,
        /// Why.
        source: coap_net::Error,
    },
}

/// An observation whose first answer must come within a timeout, and whose end is an
/// error.
pub(super) struct Watch {
    observation: coap_net::Observation,
    path: String,
    /// For the first answer.
    timeout: Option<Duration>,
}

impl Watch {
    /// Registers as an observer of `path` (in the representation `accept`).
    pub(super) async fn start(
        client: &CamClient,
        path: &str,
        accept: Option<ContentFormat>,
        timeout: Duration,
    ) -> Result<Self, WatchError> {
        let mut request = client.request(Code::GET, path, Bytes::new(), None, accept);
        // The request's timeout would end the observation; only the first answer is
        // bounded.
        request.timeout = None;
        let observation = client
            .coap()
            .observe(client.server(), request)
            .await
            .map_err(|source| WatchError::Register {
                path: path.to_owned(),
                server: client.server(),
                source,
            })?;
        Ok(Self {
            observation,
            path: path.to_owned(),
            timeout: Some(timeout),
        })
    }

    /// The next answer or notification (not checked for success).
    pub(super) async fn next(&mut self) -> Result<Response, WatchError> {
        let path = &self.path;
        let next = match self.timeout.take() {
            Some(timeout) => tokio::time::timeout(timeout, self.observation.next())
                .await
                .map_err(|source| WatchError::FirstAnswer {
                    path: path.clone(),
                    timeout,
                    source,
                })?,
            None => self.observation.next().await,
        };
        let Some(next) = next else {
            return Err(WatchError::Ended(path.clone()));
        };
        next.map_err(|source| WatchError::Notification {
            path: path.clone(),
            source,
        })
    }
}
