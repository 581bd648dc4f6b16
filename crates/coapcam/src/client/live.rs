//! Following a camera's live stream (`/cams/<sn>/<stream>/live`, an Observe of frames at a
//! rate asked for): each frame as it arrives whole, with its capture-to-client latency
//! (the Capture-Time option, corrected by the server's clock offset when the client
//! knows it).

use std::time::{Duration, Instant};

use bytes::Bytes;
use coap::{Code, ContentFormat, OptionNumber};

use super::clocks::unix_now_us;
use super::timed::{TimedError, WatchError};
use super::{CamClient, check};
use crate::repr::Stream;
use crate::timesync::capture_time;

/// One frame of a live stream.
#[derive(Debug, Clone)]
pub struct LiveFrame {
    /// The body's bytes.
    pub bytes: usize,
    /// The time since the previous frame arrived (the first's: since the registration).
    pub gap: Duration,
    /// When the frame was captured, µs since the UNIX epoch on the client's clock (the
    /// server's corrected by its offset, when known).
    pub captured_unix_us: Option<i64>,
    /// From the capture to the whole body here; `None` without a capture time.
    pub latency: Option<Duration>,
    /// Frames skipped so far for a newer one that arrived meanwhile.
    pub skipped: u64,
}

/// The live resource of `serial`'s `stream`, with the query asking for `fps`.
pub fn path(serial: &str, stream: Stream) -> String {
    format!("{}/live", crate::api::paths::camera(serial, stream.name()))
}

/// Observes the live stream of `serial`'s `stream` (in the representation `accept`, the
/// compact one without; at `fps` frames a second, the camera's rate without), handing
/// each frame to `on_frame` until it says to stop (true) or the stream ends (an error).
/// A frame that arrives while `on_frame` is busy with an older one is skipped for the
/// newest ([`LiveFrame::skipped`] counts them). The first answer must come within
/// `timeout`.
pub async fn follow<E: From<TimedError>>(
    client: &CamClient,
    serial: &str,
    stream: Stream,
    accept: Option<ContentFormat>,
    fps: Option<u32>,
    timeout: Duration,
    mut on_frame: impl FnMut(Result<LiveFrame, TimedError>) -> Result<bool, E>,
) -> Result<(), E> {
    let path = path(serial, stream);
    let mut request = client.request(Code::GET, &path, Bytes::new(), None, accept);
    request.timeout = None;
    if let Some(fps) = fps {
        request
            .options
            .push(OptionNumber::URI_QUERY, format!("fps={fps}").as_bytes());
    }
    let server = client.server();
    let mut observation = client
        .coap()
        .observe(server, request)
        .await
        .map_err(|source| {
            TimedError::from(WatchError::Register {
                path: path.clone(),
                server,
                source,
            })
        })?;
    let mut previous = Instant::now();
    let mut first = true;
    loop {
        let next = if first {
            tokio::time::timeout(timeout, observation.newest())
                .await
                .map_err(|source| {
                    TimedError::from(WatchError::FirstAnswer {
                        path: path.clone(),
                        timeout,
                        source,
                    })
                })?
        } else {
            observation.newest().await
        };
        let arrived_us = unix_now_us();
        let gap = previous.elapsed();
        previous = Instant::now();
        let Some(next) = next else {
            return Err(TimedError::from(WatchError::Ended(path)).into());
        };
        let response = match next {
            Ok(response) => response,
            Err(source) if !first => {
                let failed = WatchError::Notification {
                    path: path.clone(),
                    source,
                };
                if on_frame(Err(failed.into()))? {
                    return Ok(());
                }
                continue;
            }
            Err(source) => {
                return Err(TimedError::from(WatchError::Notification { path, source }).into());
            }
        };
        let observing = response.options.contains(OptionNumber::OBSERVE);
        let offset_us = client
            .clocks()
            .offset(server)
            .map_or(0, |offset| offset.offset_us);
        let captured = capture_time(&response.options).map(|t| t - offset_us);
        let checked = check(&format!("GET {path}"), response);
        if first && let Err(refused) = checked {
            return Err(TimedError::from(refused).into());
        }
        let outcome = checked
            .map(|r| LiveFrame {
                bytes: r.payload.len(),
                gap,
                captured_unix_us: captured,
                latency: captured
                    .map(|t| Duration::from_micros(u64::try_from(arrived_us - t).unwrap_or(0))),
                skipped: observation.skipped(),
            })
            .map_err(TimedError::from);
        let stop = on_frame(outcome)?;
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
