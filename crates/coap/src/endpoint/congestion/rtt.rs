//! A peer's round-trip estimate and how a CON's timeout backs off.
//!
//! [`RttEstimator`]: RFC 6298's SRTT and RTTVAR from unambiguous samples (Karn's rule),
//! with CoCoA's *weak* samples (from exchanges that needed a retransmission) used only
//! until a strong one exists. It ages back towards the RFC 7252 defaults while the peer is
//! idle. CON timers follow it; windowed transfers take their loss timers from it.

use std::time::{Duration, Instant};

/// Each this long without a sample, an estimate moves halfway back to the defaults.
const AGE_HALF_LIFE: Duration = Duration::from_secs(30);

/// The round-trip estimate of one peer.
#[derive(Debug, Clone)]
pub(crate) struct RttEstimator {
    srtt: Duration,
    rttvar: Duration,
    min: Duration,
    /// Samples so far (0: no estimate).
    samples: u64,
    /// The estimate comes from weak samples only.
    weak: bool,
    last_sample: Instant,
}

impl RttEstimator {
    pub(crate) fn new(now: Instant) -> Self {
        Self {
            srtt: Duration::ZERO,
            rttvar: Duration::ZERO,
            min: Duration::MAX,
            samples: 0,
            weak: false,
            last_sample: now,
        }
    }

    /// Takes a sample. `strong`: from an exchange sent once (Karn's rule); a weak one
    /// (CoCoA: the time from the first transmission of an exchange sent again) counts only
    /// while no strong one has been taken.
    pub(crate) fn on_sample(&mut self, now: Instant, rtt: Duration, strong: bool) {
        if !strong && self.samples > 0 && !self.weak {
            return;
        }
        if strong && self.weak {
            self.samples = 0;
        }
        self.weak = !strong;
        self.min = self.min.min(rtt);
        if self.samples == 0 {
            self.srtt = rtt;
            self.rttvar = rtt / 2;
        } else {
            // RFC 6298 §2.3: alpha 1/8, beta 1/4.
            let diff = self.srtt.abs_diff(rtt);
            self.rttvar = (self.rttvar * 3 + diff) / 4;
            self.srtt = (self.srtt * 7 + rtt) / 8;
        }
        self.samples += 1;
        self.last_sample = now;
    }

    /// A sample from an exchange that may have been answered by a message already on
    /// its way (a Q-Block set the server sent by timer just before a 'Continue' asked
    /// for it): taken as strong, unless it is shorter than half the smallest round trip
    /// seen, which no round trip can be.
    pub(crate) fn on_plausible_sample(&mut self, now: Instant, rtt: Duration) {
        if self.min().is_none_or(|min| rtt >= min / 2) {
            self.on_sample(now, rtt, true);
        }
    }

    /// The smoothed round trip, if there is an estimate.
    pub(crate) fn srtt(&self) -> Option<Duration> {
        (self.samples > 0).then_some(self.srtt)
    }

    /// The smoothed round-trip variation.
    pub(crate) fn rttvar(&self) -> Duration {
        self.rttvar
    }

    /// The smallest sample so far.
    pub(crate) fn min(&self) -> Option<Duration> {
        (self.samples > 0).then_some(self.min)
    }

    /// The base timeout of a CON at `now` (before ACK_RANDOM_FACTOR's jitter): CoCoA's
    /// RTO, `SRTT + max(4 RTTVAR, G)` with a granularity G of 100 ms (RFC 6298 (2.3);
    /// Californium's G) and without RFC 6298's 1 s floor, which CoCoA replaces with its
    /// variable backoff ([`Backoff::cocoa`]), at most 60 s, moving back towards `default`
    /// (ACK_TIMEOUT) by half every 30 s without a sample; `None` before any sample.
    pub(crate) fn con_timeout(&self, now: Instant, default: Duration) -> Option<Duration> {
        let srtt = self.srtt()?;
        let rto = (srtt + (self.rttvar * 4).max(CON_GRANULARITY)).min(Duration::from_secs(60));
        let idle = now.saturating_duration_since(self.last_sample);
        let kept = 0.5f64.powf(idle.as_secs_f64() / AGE_HALF_LIFE.as_secs_f64());
        let (rto, default) = (rto.as_secs_f64(), default.as_secs_f64());
        Some(Duration::from_secs_f64(default + (rto - default) * kept))
    }

    /// The probe timeout of a windowed transfer: `SRTT + max(4 RTTVAR, 1 ms)`; `default`
    /// before any sample.
    pub(crate) fn pto(&self, default: Duration) -> Duration {
        match self.srtt() {
            Some(srtt) => srtt + (self.rttvar * 4).max(Duration::from_millis(1)),
            None => default,
        }
    }
}

/// G of a CON's RTO ([`RttEstimator::con_timeout`]).
const CON_GRANULARITY: Duration = Duration::from_millis(100);

/// How a CON's timeout grows at each retransmission.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Backoff {
    factor: f64,
    cap: Duration,
}

impl Backoff {
    /// RFC 7252 §4.2: doubling, for a timeout from ACK_TIMEOUT.
    pub(crate) const DOUBLING: Self = Self {
        factor: 2.0,
        cap: Duration::MAX,
    };

    /// CoCoA's variable backoff for a timeout from a round-trip estimate `rto` (before
    /// the jitter): 3 times below 1 s (a short RTO backs off fast), 1.5 times above 3 s,
    /// else 2 times; no timeout beyond 32 s.
    pub(crate) fn cocoa(rto: Duration) -> Self {
        let factor = if rto < Duration::from_secs(1) {
            3.0
        } else if rto > Duration::from_secs(3) {
            1.5
        } else {
            2.0
        };
        Self {
            factor,
            cap: Duration::from_secs(32),
        }
    }

    /// The timeout after `timeout` at the next retransmission.
    pub(crate) fn next(self, timeout: Duration) -> Duration {
        timeout.mul_f64(self.factor).min(self.cap)
    }
}
