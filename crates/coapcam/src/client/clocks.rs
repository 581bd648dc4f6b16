//! The client's side of frames that belong together ([`crate::timesync`]): what it knows
//! of each server's clock (a [`ClockEstimator`] fed by every exchange whose answer
//! carries the Server-Time option), each camera's frame rate and last frame. The check
//! that asks servers for what it lacks is [`super::frames`].

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Mutex, PoisonError};
use std::time::{SystemTime, UNIX_EPOCH};

use coap::Options;

use crate::timesync::{
    self, ClockEstimator, FrameHistory, FrameTime, Limits, Offset, Problem, Sample, ServerTimes,
};

/// Now on the client's clock, µs since the UNIX epoch.
pub fn unix_now_us() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_micros()).unwrap_or(i64::MAX))
}

/// What a client knows of its servers' clocks and cameras (shared by the clients of one
/// socket, `CamClient::unicast`).
#[derive(Debug, Default)]
pub struct Clocks {
    state: Mutex<State>,
}

#[derive(Debug, Default)]
struct State {
    servers: HashMap<SocketAddr, ClockEstimator>,
    rates: HashMap<(SocketAddr, String), u32>,
    history: FrameHistory,
}

impl Clocks {
    fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Notes an exchange with `server` that left at `sent_us` and was answered at
    /// `received_us` (client clock) with `options`: a sample when they carry the
    /// server's times.
    pub fn exchanged(&self, server: SocketAddr, sent_us: i64, options: &Options, received_us: i64) {
        let sample = match ServerTimes::of(options) {
            None => return,
            Some(times) => times.and_then(|t| Sample::new(sent_us, t, received_us)),
        };
        match sample {
            Ok(s) if s.offset_us().abs() > timesync::MAX_BELIEVED_APART_US => {
                tracing::debug!(%server, offset_us = s.offset_us(), "a clock sample too far off to believe");
            }
            Ok(s) => self.state().servers.entry(server).or_default().add(s),
            Err(e) => tracing::debug!(%server, "not a clock sample: {e}"),
        }
    }

    /// The estimate of `server`'s clock offset now.
    pub fn offset(&self, server: SocketAddr) -> Option<Offset> {
        self.state()
            .servers
            .get(&server)
            .and_then(|e| e.estimate(unix_now_us()))
    }

    /// Samples kept of `server`'s clock.
    pub fn samples(&self, server: SocketAddr) -> usize {
        self.state()
            .servers
            .get(&server)
            .map_or(0, ClockEstimator::len)
    }

    pub(super) fn rate(&self, server: SocketAddr, camera: &str) -> Option<u32> {
        self.state()
            .rates
            .get(&(server, camera.to_owned()))
            .copied()
    }

    pub(super) fn set_rate(&self, server: SocketAddr, camera: &str, fps: u32) {
        self.state().rates.insert((server, camera.to_owned()), fps);
    }

    pub(super) fn check(&self, frames: &[FrameTime], limits: &Limits) -> Vec<Problem> {
        timesync::check_frames(frames, limits, &mut self.state().history)
    }
}
