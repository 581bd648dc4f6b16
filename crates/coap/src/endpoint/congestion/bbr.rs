//! BBR: the window and pacing of block requests from the delivery rate and the smallest
//! round trip seen (BBR v1's model). Random loss does not shrink it: a loss-based
//! controller (Reno, Cubic) falls to about 5 Mbit/s at 2 % loss and 20 ms (Mathis et
//! al.), while the delivery rate at 2 % loss is 98 % of the link's.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use super::controller::{Controller, SendState};

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

/// A delivery-rate-based controller (BBR v1's model without ProbeRTT: the min-RTT
/// filter simply takes a newer sample once its value is 10 s old). It sets a window
/// (`2 x` the bandwidth-delay product) and a pacing rate (`gain x` the largest delivery
/// rate of the last 10 rounds).
#[derive(Debug, Clone)]
pub(crate) struct Bbr {
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
    pub(crate) fn new(now: Instant) -> Self {
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
    fn max_bw(&self) -> Option<f64> {
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

    /// The time between two requests at the pacing rate; none before the first rate
    /// sample (the initial window goes at once, as TCP's and QUIC's do).
    fn interval(&self) -> Duration {
        match self.max_bw() {
            Some(bw) => Duration::from_secs_f64(1.0 / (bw * self.gains().0).max(1.0)),
            None => Duration::ZERO,
        }
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

impl Controller for Bbr {
    fn window(&self) -> usize {
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

    fn in_flight(&self) -> usize {
        self.in_flight
    }

    fn next_send(&self, now: Instant) -> Option<Instant> {
        (now < self.pace_at).then_some(self.pace_at)
    }

    fn on_sent(&mut self, now: Instant) -> SendState {
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

    fn on_delivered(&mut self, now: Instant, s: &SendState, rtt: Option<Duration>) {
        self.in_flight = self.in_flight.saturating_sub(1);
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

    fn on_late_delivery(&mut self, now: Instant) {
        self.delivered += 1;
        self.delivered_time = now;
    }

    /// The window stays (see the module documentation).
    fn on_lost(&mut self, _now: Instant, n: usize) {
        self.in_flight = self.in_flight.saturating_sub(n);
    }

    fn on_abandoned(&mut self, n: usize) {
        self.in_flight = self.in_flight.saturating_sub(n);
    }
}
