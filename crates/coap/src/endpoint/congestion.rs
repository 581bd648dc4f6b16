//! Round-trip estimation and congestion control, per peer (quinn-proto's `congestion`
//! module is the model).
//!
//! - [`RttEstimator`]: RFC 6298's SRTT and RTTVAR from unambiguous samples (Karn's rule),
//!   with CoCoA's *weak* samples (from exchanges that needed a retransmission) used only
//!   until a strong one exists. It ages back towards the RFC 7252 defaults while the peer
//!   is idle. CON timers follow it; windowed transfers take their loss timers from it.
//! - [`Nstart`]: RFC 7252's NSTART (§4.7), how many requests a peer may have outstanding.
//! - [`Bbr`]: the window and pacing of a windowed transfer's block requests, from the
//!   delivery rate and the smallest round trip seen (BBR's model). Random loss does not
//!   shrink it: a loss-based controller (Reno, Cubic) falls to about 5 Mbit/s at 2 % loss
//!   and 20 ms (Mathis et al.), while the delivery rate at 2 % loss is 98 % of the link's.
//!
//! Units: one *block* is one block request and the response it brings back.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// Says how many requests a peer may have outstanding.
pub(super) trait Controller: Send {
    /// Requests the peer may have outstanding now (at least 1).
    fn window(&self) -> usize;
}

/// RFC 7252's NSTART: a fixed window.
#[derive(Debug, Clone, Copy)]
pub(super) struct Nstart(usize);

impl Nstart {
    /// A window of `nstart` requests (at least 1).
    pub(super) fn new(nstart: usize) -> Self {
        Self(nstart.max(1))
    }
}

impl Controller for Nstart {
    fn window(&self) -> usize {
        self.0
    }
}

/// Each this long without a sample, an estimate moves halfway back to the defaults.
const AGE_HALF_LIFE: Duration = Duration::from_secs(30);

/// The round-trip estimate of one peer.
#[derive(Debug, Clone)]
pub(super) struct RttEstimator {
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
    pub(super) fn new(now: Instant) -> Self {
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
    pub(super) fn on_sample(&mut self, now: Instant, rtt: Duration, strong: bool) {
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
    pub(super) fn on_plausible_sample(&mut self, now: Instant, rtt: Duration) {
        if self.min().is_none_or(|min| rtt >= min / 2) {
            self.on_sample(now, rtt, true);
        }
    }

    /// The smoothed round trip, if there is an estimate.
    pub(super) fn srtt(&self) -> Option<Duration> {
        (self.samples > 0).then_some(self.srtt)
    }

    /// The smoothed round-trip variation.
    pub(super) fn rttvar(&self) -> Duration {
        self.rttvar
    }

    /// The smallest sample so far.
    pub(super) fn min(&self) -> Option<Duration> {
        (self.samples > 0).then_some(self.min)
    }

    /// The base timeout of a CON at `now` (before ACK_RANDOM_FACTOR's jitter): CoCoA's
    /// RTO, `SRTT + max(4 RTTVAR, G)` with a granularity G of 100 ms (RFC 6298 (2.3);
    /// Californium's G) and without RFC 6298's 1 s floor, which CoCoA replaces with its
    /// variable backoff ([`Backoff::cocoa`]), at most 60 s, moving back towards `default`
    /// (ACK_TIMEOUT) by half every 30 s without a sample; `None` before any sample.
    pub(super) fn con_timeout(&self, now: Instant, default: Duration) -> Option<Duration> {
        let srtt = self.srtt()?;
        let rto = (srtt + (self.rttvar * 4).max(CON_GRANULARITY)).min(Duration::from_secs(60));
        let idle = now.saturating_duration_since(self.last_sample);
        let kept = 0.5f64.powf(idle.as_secs_f64() / AGE_HALF_LIFE.as_secs_f64());
        let (rto, default) = (rto.as_secs_f64(), default.as_secs_f64());
        Some(Duration::from_secs_f64(default + (rto - default) * kept))
    }

    /// The probe timeout of a windowed transfer: `SRTT + max(4 RTTVAR, 1 ms)`; `default`
    /// before any sample.
    pub(super) fn pto(&self, default: Duration) -> Duration {
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
pub(super) struct Backoff {
    factor: f64,
    cap: Duration,
}

impl Backoff {
    /// RFC 7252 §4.2: doubling, for a timeout from ACK_TIMEOUT.
    pub(super) const DOUBLING: Self = Self {
        factor: 2.0,
        cap: Duration::MAX,
    };

    /// CoCoA's variable backoff for a timeout from a round-trip estimate `rto` (before
    /// the jitter): 3 times below 1 s (a short RTO backs off fast), 1.5 times above 3 s,
    /// else 2 times; no timeout beyond 32 s.
    pub(super) fn cocoa(rto: Duration) -> Self {
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
    pub(super) fn next(self, timeout: Duration) -> Duration {
        timeout.mul_f64(self.factor).min(self.cap)
    }
}

/// BBR's gains: startup doubles the delivery rate every round trip.
const STARTUP_GAIN: f64 = 2.885;
/// The pacing gains of ProbeBW, one phase of a smallest round trip each.
const PROBE_GAINS: [f64; 8] = [1.25, 0.75, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0];
/// Rounds over which the largest delivery rate is kept.
const BW_ROUNDS: u64 = 10;
/// How long the smallest round trip is kept before a newer, larger one replaces it.
const MIN_RTT_LIFETIME: Duration = Duration::from_secs(10);
/// The window before the first delivery-rate sample, and its floor after.
const INITIAL_WINDOW: usize = 10;
const MIN_WINDOW: usize = 4;

#[derive(Debug, Clone, Copy, PartialEq)]
enum Mode {
    /// Doubling the rate each round until it stops growing.
    Startup,
    /// Emptying the queue startup built.
    Drain,
    /// Cycling the pacing gain around the measured rate.
    ProbeBw { phase: usize, since: Instant },
}

/// What [`Bbr::on_send`] records of a block request, for its delivery-rate sample.
#[derive(Debug, Clone, Copy)]
pub(super) struct SendState {
    sent: Instant,
    delivered: u64,
    delivered_time: Instant,
    first_sent_time: Instant,
}

impl SendState {
    /// When the request went out.
    pub(super) fn sent(&self) -> Instant {
        self.sent
    }
}

/// A delivery-rate-based controller (BBR v1's model without ProbeRTT: the min-RTT
/// filter simply takes a newer sample once its value is 10 s old). It sets a window
/// (`2 x` the bandwidth-delay product) and a pacing rate (`gain x` the largest delivery
/// rate of the last 10 rounds).
#[derive(Debug, Clone)]
pub(super) struct Bbr {
    mode: Mode,
    /// The largest delivery rate per round, blocks per second, newest last.
    bw: VecDeque<(u64, f64)>,
    min_rtt: Option<(Duration, Instant)>,
    round: u64,
    next_round_delivered: u64,
    full_bw: f64,
    full_bw_rounds: u32,
    delivered: u64,
    delivered_time: Instant,
    first_sent_time: Instant,
    in_flight: usize,
    /// The earliest instant the next request may leave (pacing).
    pace_at: Instant,
}

impl Bbr {
    pub(super) fn new(now: Instant) -> Self {
        Self {
            mode: Mode::Startup,
            bw: VecDeque::new(),
            min_rtt: None,
            round: 0,
            next_round_delivered: 0,
            full_bw: 0.0,
            full_bw_rounds: 0,
            delivered: 0,
            delivered_time: now,
            first_sent_time: now,
            in_flight: 0,
            pace_at: now,
        }
    }

    /// The largest delivery rate of the last rounds, blocks per second.
    pub(super) fn max_bw(&self) -> Option<f64> {
        self.bw.iter().map(|b| b.1).reduce(f64::max)
    }

    fn gains(&self) -> (f64, f64) {
        match self.mode {
            Mode::Startup => (STARTUP_GAIN, STARTUP_GAIN),
            Mode::Drain => (1.0 / STARTUP_GAIN, STARTUP_GAIN),
            Mode::ProbeBw { phase, .. } => (PROBE_GAINS[phase], 2.0),
        }
    }

    /// The bandwidth-delay product in blocks, once both are measured.
    fn bdp(&self) -> Option<f64> {
        Some(self.max_bw()? * self.min_rtt?.0.as_secs_f64())
    }

    /// Blocks that may be in flight.
    pub(super) fn window(&self) -> usize {
        match self.bdp() {
            None => INITIAL_WINDOW,
            Some(bdp) => {
                let floor = if self.mode == Mode::Startup {
                    INITIAL_WINDOW
                } else {
                    MIN_WINDOW
                };
                ((self.gains().1 * bdp).ceil() as usize).max(floor)
            }
        }
    }

    /// Blocks in flight.
    pub(super) fn in_flight(&self) -> usize {
        self.in_flight
    }

    /// The time between two requests at the pacing rate; none before the first rate
    /// sample (the initial window goes at once, as TCP's and QUIC's do).
    fn interval(&self) -> Duration {
        match self.max_bw() {
            Some(bw) => Duration::from_secs_f64(1.0 / (bw * self.gains().0).max(1.0)),
            None => Duration::ZERO,
        }
    }

    /// Whether a request may leave at `now`: `Ok`, or the instant pacing allows it.
    /// The window is the caller's to check against [`Bbr::in_flight`].
    pub(super) fn pace(&self, now: Instant) -> Result<(), Instant> {
        if now >= self.pace_at {
            Ok(())
        } else {
            Err(self.pace_at)
        }
    }

    /// Records a request sent at `now`.
    pub(super) fn on_send(&mut self, now: Instant) -> SendState {
        if self.in_flight == 0 {
            self.first_sent_time = now;
            self.delivered_time = now;
        }
        self.in_flight += 1;
        // Up to 2 ms (or two requests) of credit carries over from a late wake-up, so a
        // driver whose timers have millisecond granularity still keeps the rate.
        let interval = self.interval();
        let credit = (interval * 2).max(Duration::from_millis(2));
        let base = self.pace_at.max(now.checked_sub(credit).unwrap_or(now));
        self.pace_at = base + interval;
        SendState {
            sent: now,
            delivered: self.delivered,
            delivered_time: self.delivered_time,
            first_sent_time: self.first_sent_time,
        }
    }

    /// A request's block arrived. `in_flight`: the request still counted as in flight
    /// (not declared lost before); `rtt`: its round trip if unambiguous.
    pub(super) fn on_delivered(
        &mut self,
        now: Instant,
        s: SendState,
        in_flight: bool,
        rtt: Option<Duration>,
    ) {
        if in_flight {
            self.in_flight = self.in_flight.saturating_sub(1);
        }
        self.delivered += 1;
        self.delivered_time = now;
        if let Some(rtt) = rtt {
            let expired = self
                .min_rtt
                .is_none_or(|(min, at)| rtt <= min || now.duration_since(at) > MIN_RTT_LIFETIME);
            if expired {
                self.min_rtt = Some((rtt, now));
            }
        }
        let round_start = s.delivered >= self.next_round_delivered;
        if round_start {
            self.round += 1;
            self.next_round_delivered = self.delivered;
        }
        // The delivery rate over the longer of the send and the acknowledgement
        // intervals (a burst sent or acknowledged at once does not inflate it).
        let interval = s
            .sent
            .saturating_duration_since(s.first_sent_time)
            .max(now.saturating_duration_since(s.delivered_time));
        self.first_sent_time = self.first_sent_time.max(s.sent);
        let long_enough = self.min_rtt.is_none_or(|(min, _)| interval >= min);
        if !interval.is_zero() && long_enough {
            let rate = (self.delivered - s.delivered) as f64 / interval.as_secs_f64();
            match self.bw.back_mut() {
                Some((round, best)) if *round == self.round => *best = best.max(rate),
                _ => self.bw.push_back((self.round, rate)),
            }
            while self
                .bw
                .front()
                .is_some_and(|(r, _)| r + BW_ROUNDS <= self.round)
            {
                self.bw.pop_front();
            }
        }
        self.advance(now, round_start);
    }

    /// A block arrived whose request had been declared lost: delivered, but without a
    /// rate sample (its request's send state is gone).
    pub(super) fn on_late_delivery(&mut self, now: Instant) {
        self.delivered += 1;
        self.delivered_time = now;
    }

    /// A request declared lost: no longer in flight. The window stays (see the module
    /// documentation).
    pub(super) fn on_lost(&mut self) {
        self.in_flight = self.in_flight.saturating_sub(1);
    }

    /// Requests that will never be answered (their transfer ended).
    pub(super) fn forget(&mut self, n: usize) {
        self.in_flight = self.in_flight.saturating_sub(n);
    }

    fn advance(&mut self, now: Instant, round_start: bool) {
        let Some(bw) = self.max_bw() else { return };
        match self.mode {
            Mode::Startup if round_start => {
                if bw >= self.full_bw * 1.25 {
                    self.full_bw = bw;
                    self.full_bw_rounds = 0;
                } else {
                    self.full_bw_rounds += 1;
                    if self.full_bw_rounds >= 3 {
                        self.mode = Mode::Drain;
                    }
                }
            }
            Mode::Startup => {}
            Mode::Drain => {
                if self.bdp().is_some_and(|bdp| self.in_flight as f64 <= bdp) {
                    self.mode = Mode::ProbeBw {
                        phase: 2,
                        since: now,
                    };
                }
            }
            Mode::ProbeBw { phase, since } => {
                let Some((min_rtt, _)) = self.min_rtt else {
                    return;
                };
                let drained = PROBE_GAINS[phase] < 1.0
                    && self.bdp().is_some_and(|bdp| self.in_flight as f64 <= bdp);
                if now.duration_since(since) >= min_rtt || drained {
                    self.mode = Mode::ProbeBw {
                        phase: (phase + 1) % PROBE_GAINS.len(),
                        since: now,
                    };
                }
            }
        }
    }
}
