//! The frames of one measurement checked ([`crate::timesync`]), with the exchanges that
//! check needs and nothing more: a camera's rate once, the `/time` resource only while a
//! server's offset is not known well enough.

use std::net::SocketAddr;

use bytes::Bytes;
use coap::Code;
use rgbd::DepthSettings;

use super::CamClient;
use crate::timesync::{FrameTime, Limits, Problem};

/// At most this many `/time` exchanges per server and measurement while its offset is
/// not known to a quarter of the allowed skew.
pub const TIME_EXCHANGES: usize = 3;

/// What [`check_frames`] found.
#[derive(Debug, Default)]
pub struct FramesChecked {
    /// Why the frames do not belong together (stale cameras first); empty when they do.
    pub problems: Vec<Problem>,
    /// What could not be checked (a server that does not tell its time).
    pub unchecked: Vec<String>,
}

/// Checks `frames` (each camera's frame of one measurement, on its server's clock) as
/// `limits` say, first filling in what they need: each camera's rate (its
/// depth-settings, asked once per client) and, when the frames come from several
/// servers, each server's clock offset, asked of its `/time` resource only while it is
/// not known to a quarter of the allowed skew (once known, every grab's answer keeps it
/// current and no exchange is added).
pub async fn check_frames(
    client: &CamClient,
    frames: &mut [FrameTime],
    limits: &Limits,
) -> FramesChecked {
    let clocks = client.clocks();
    let mut out = FramesChecked::default();
    for f in frames.iter_mut() {
        let Some(server) = f.server else { continue };
        if clocks.rate(server, &f.camera).is_none() {
            let one = CamClient::unicast(client, server);
            match one
                .get_json::<DepthSettings>(&f.camera, "depth-settings")
                .await
            {
                Ok(s) => clocks.set_rate(server, &f.camera, s.fps),
                Err(e) => tracing::debug!(
                    %server,
                    camera = %f.camera,
                    "no frame rate: {}",
                    crate::error_text(&e)
                ),
            }
        }
        f.fps = clocks.rate(server, &f.camera);
    }
    let mut servers: Vec<SocketAddr> = frames.iter().filter_map(|f| f.server).collect();
    servers.sort();
    servers.dedup();
    let mut limits = *limits;
    limits.skew &= servers.len() > 1;
    if limits.skew {
        let good_enough = limits.skew_us(frames) / 4;
        for &server in &servers {
            let one = CamClient::unicast(client, server);
            for _ in 0..TIME_EXCHANGES {
                if clocks
                    .offset(server)
                    .is_some_and(|o| o.error_us <= good_enough)
                {
                    break;
                }
                let asked = one
                    .call(Code::GET, crate::api::paths::TIME, Bytes::new(), None, None)
                    .await;
                if let Err(e) = asked {
                    tracing::debug!(%server, "no time: {}", crate::error_text(&e));
                    break;
                }
            }
            match clocks.offset(server) {
                Some(o) => {
                    for f in frames.iter_mut().filter(|f| f.server == Some(server)) {
                        f.clock = Some(o);
                    }
                }
                None => out.unchecked.push(format!(
                    "the clock of {server} is not known (it does not tell its time): the capture times of its cameras were not compared with the others'"
                )),
            }
        }
        if !out.unchecked.is_empty() {
            // Frames of a server whose clock is unknown cannot be compared.
            let known: Vec<FrameTime> = frames
                .iter()
                .filter(|f| f.clock.is_some())
                .cloned()
                .collect();
            let stale_only = Limits {
                skew: false,
                ..limits
            };
            let unknown: Vec<FrameTime> = frames
                .iter()
                .filter(|f| f.clock.is_none())
                .cloned()
                .collect();
            out.problems = clocks.check(&unknown, &stale_only);
            out.problems.extend(clocks.check(&known, &limits));
            return out;
        }
    }
    out.problems = clocks.check(frames, &limits);
    out
}
