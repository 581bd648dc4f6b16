//! Round-trip estimation and congestion control, per peer (quinn-proto's `congestion`
//! module is the model).
//!
//! - `rtt`: the round-trip estimate ([`RttEstimator`]) and the back-off of a CON's
//!   timeout ([`Backoff`]).
//! - `controller`: the [`Controller`] trait every controller implements: a window, a
//!   pacing time, and what it learns when a request is sent, delivered, lost or
//!   abandoned.
//! - `nstart`: RFC 7252's NSTART ([`Nstart`]), a fixed window: how many requests a peer
//!   may have outstanding, and a windowed transfer's controller when chosen.
//! - `bbr`: BBR, the window and pacing of a windowed transfer's block requests from the
//!   delivery rate and the smallest round trip (the default).
//!
//! [`EndpointConfig::congestion`] chooses the controller of windowed transfers
//! ([`for_path`]).

mod bbr;
mod controller;
mod nstart;
mod rtt;

use std::time::Instant;

pub use controller::RoundTrace;
pub(crate) use controller::{Controller, SendState};
pub(crate) use nstart::Nstart;
pub(crate) use rtt::{Backoff, RttEstimator};

use crate::config::{Congestion, EndpointConfig};

/// A new controller for the windowed transfers on one path, as `config` chooses.
pub(crate) fn for_path(config: &EndpointConfig, now: Instant) -> Box<dyn Controller> {
    match config.congestion {
        Congestion::Bbr => Box::new(bbr::Bbr::new(now, config.trace_congestion)),
        Congestion::Nstart => Box::new(Nstart::new(config.nstart)),
    }
}
