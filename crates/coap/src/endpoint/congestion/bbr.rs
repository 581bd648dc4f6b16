//! BBR: the window and pacing of block requests from the delivery rate and the smallest
//! round trip seen (BBR v1's model). Random loss does not shrink it: a loss-based
//! controller (Reno, Cubic) falls to about 5 Mbit/s at 2 % loss and 20 ms (Mathis et
//! al.), while the delivery rate at 2 % loss is 98 % of the link's.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use super::controller::{Controller, RoundTrace, SendState};

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
/// The most wake-up lateness the pacer learns: beyond it a delay is a stall (the sender
/// idle or descheduled), not the driver's timer.
const MAX_WAKE_LATENESS: Duration = Duration::from_millis(20);
/// Rounds a trace keeps that nobody has taken yet (about 80 s of 20 ms rounds).
const TRACE_ROUNDS: usize = 4096;

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
    /// The delivery-rate draft's `C.app_limited`: while not zero, requests sent are
    /// marked app-limited, until more than this many have been delivered.
    app_limited: u64,
    /// Requests declared lost since the current ProbeBW phase began.
    lost_in_phase: bool,
    /// How late the sender was woken for a paced request, at worst per round, newest
    /// last ([`Bbr::learn_lateness`]).
    lateness: VecDeque<(u64, Duration)>,
    /// The round being recorded, and the rounds recorded (`None`: no trace).
    round_trace: RoundAcc,
    trace: Option<VecDeque<RoundTrace>>,
}

/// What the trace adds up over the current round.
#[derive(Debug, Clone, Copy, Default)]
struct RoundAcc {
    samples: u32,
    app_limited_samples: u32,
    max_sample: Option<(f64, bool)>,
    max_in_flight: usize,
    sent: u32,
    late_sends: u32,
    lateness: Duration,
    delivered: u32,
    lost: u32,
}

impl Bbr {
    /// A controller at `now`; `trace`: it records every round ([`Controller::poll_round`]).
    pub(crate) fn new(now: Instant, trace: bool) -> Self {
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
            app_limited: 0,
            lost_in_phase: false,
            lateness: VecDeque::new(),
            round_trace: RoundAcc::default(),
            trace: trace.then(VecDeque::new),
        }
    }

    /// Takes a delivery-rate sample into the windowed maximum of the last rounds.
    fn take_bw(&mut self, rate: f64) {
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

    /// How far behind its schedule the pacer may fall and catch up with a burst: two
    /// requests, 2 ms of them, or as long as the driver's wake-ups have lately been late
    /// (a receive timeout counted in 4 ms jiffies wakes 4-8 ms late), at most half the
    /// smallest round trip. So a driver whose timer is coarser than the interval still
    /// keeps the rate, sending several requests per wake-up.
    fn credit(&self, interval: Duration) -> Duration {
        let credit = (interval * 2)
            .max(Duration::from_millis(2))
            .max(self.wake_lateness());
        match self.min_rtt {
            Some((min_rtt, _)) => credit.min((min_rtt / 2).max(Duration::from_millis(2))),
            None => credit,
        }
    }

    /// Learns how late the sender woke for a request due `late` ago: the largest
    /// lateness of each of the last [`BW_ROUNDS`] rounds is kept.
    fn learn_lateness(&mut self, late: Duration) {
        match self.lateness.back_mut() {
            Some((round, worst)) if *round == self.round => *worst = (*worst).max(late),
            _ => self.lateness.push_back((self.round, late)),
        }
        while self
            .lateness
            .front()
            .is_some_and(|(r, _)| r + BW_ROUNDS <= self.round)
        {
            self.lateness.pop_front();
        }
    }

    /// How late the sender was woken at worst over the last rounds.
    fn wake_lateness(&self) -> Duration {
        self.lateness
            .iter()
            .map(|l| l.1)
            .max()
            .unwrap_or(Duration::ZERO)
    }

    /// The pacing rate in requests per second, once there is a rate sample.
    fn pacing_rate(&self) -> Option<f64> {
        self.max_bw().map(|bw| (bw * self.gains().0).max(1.0))
    }

    /// The window was `full` before a request left it at `now`: pacing starts again from
    /// now. Time spent with a full window is no credit for a burst, and a request that
    /// leaves as soon as the window opens is not late.
    fn reopened(&mut self, now: Instant, full: bool) {
        if full && self.in_flight < self.window() {
            self.pace_at = self.pace_at.max(now);
        }
    }

    /// The round that just ended goes into the trace.
    fn record_round(&mut self, now: Instant) {
        let acc = std::mem::take(&mut self.round_trace);
        let mode = match self.mode {
            Mode::Startup => "startup",
            Mode::Drain => "drain",
            Mode::ProbeBw { .. } => "probe_bw",
        };
        let round = RoundTrace {
            at: now,
            round: self.round,
            mode,
            pacing_gain: self.gains().0,
            samples: acc.samples,
            app_limited_samples: acc.app_limited_samples,
            max_sample: acc.max_sample,
            bw: self.max_bw(),
            pacing_rate: self.pacing_rate(),
            window: self.window(),
            in_flight: self.in_flight,
            max_in_flight: acc.max_in_flight,
            min_rtt: self.min_rtt.map(|m| m.0),
            sent: acc.sent,
            late_sends: acc.late_sends,
            lateness: acc.lateness,
            delivered: acc.delivered,
            lost: acc.lost,
        };
        if let Some(trace) = &mut self.trace {
            if trace.len() >= TRACE_ROUNDS {
                trace.pop_front();
            }
            trace.push_back(round);
        }
    }

    /// Moves between startup, drain and ProbeBW's phases after a delivery; `round_start`:
    /// it began a round; `app_limited`: its rate sample (if any) was app-limited.
    fn advance(&mut self, now: Instant, round_start: bool, app_limited: bool) {
        let Some(bw) = self.max_bw() else { return };
        match self.mode {
            // A round whose sample was app-limited says nothing of whether the rate
            // still grows (a hiccup of the sender's, or the end of its data): it neither
            // counts towards leaving startup nor resets the count.
            Mode::Startup if round_start && app_limited => {}
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
                let gain = PROBE_GAINS[phase];
                let bdp = self.bdp();
                let drained = gain < 1.0 && bdp.is_some_and(|bdp| self.in_flight as f64 <= bdp);
                let full_length = now.duration_since(since) >= min_rtt;
                // A probing phase lasts until the requests in flight reached its gain
                // times the bandwidth-delay product, or some were lost: a sender that
                // could not keep up with its pacing rate probes on (BBR v1).
                let probed = gain <= 1.0
                    || self.lost_in_phase
                    || bdp.is_some_and(|bdp| self.in_flight as f64 >= gain * bdp);
                if (full_length && probed) || drained {
                    self.lost_in_phase = false;
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
        let interval = self.interval();
        let credit = self.credit(interval);
        if self.in_flight == 0 {
            self.first_sent_time = now;
            self.delivered_time = now;
        }
        // The sender is behind its schedule by more than the burst it may catch up with:
        // it woke late (a coarse timer, a busy CPU) or had been idle, and offered less
        // than the pacing rate meanwhile. What is sent from here until those requests
        // are delivered measures the sender, not the path.
        let late = now.saturating_duration_since(self.pace_at);
        if self.in_flight > 0 && !interval.is_zero() && late < MAX_WAKE_LATENESS {
            self.learn_lateness(late);
        }
        if !interval.is_zero() && late > credit {
            self.app_limited = (self.delivered + self.in_flight as u64).max(1);
            if self.in_flight > 0 {
                self.round_trace.late_sends += 1;
                self.round_trace.lateness += late - credit;
            }
        }
        self.in_flight += 1;
        let base = self.pace_at.max(now.checked_sub(credit).unwrap_or(now));
        self.pace_at = base + interval;
        let acc = &mut self.round_trace;
        acc.sent += 1;
        acc.max_in_flight = acc.max_in_flight.max(self.in_flight);
        SendState {
            sent: now,
            delivered: self.delivered,
            delivered_time: self.delivered_time,
            first_sent_time: self.first_sent_time,
            app_limited: self.app_limited != 0,
        }
    }

    fn on_delivered(&mut self, now: Instant, s: &SendState, rtt: Option<Duration>) {
        let full = self.in_flight >= self.window();
        self.in_flight = self.in_flight.saturating_sub(1);
        self.delivered += 1;
        self.delivered_time = now;
        self.round_trace.delivered += 1;
        if self.app_limited != 0 && self.delivered > self.app_limited {
            self.app_limited = 0;
        }
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
            if self.trace.is_some() && self.round > 0 {
                self.record_round(now);
            }
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
            let acc = &mut self.round_trace;
            acc.samples += 1;
            acc.app_limited_samples += u32::from(s.app_limited);
            if acc.max_sample.is_none_or(|(best, _)| rate > best) {
                acc.max_sample = Some((rate, s.app_limited));
            }
            // An app-limited sample counts only when it shows more than the estimate
            // (the draft's §3.4; BBR's bandwidth filter): a sender that offered less
            // than the path carries must not lower what it believes the path carries.
            if !s.app_limited || self.max_bw().is_none_or(|bw| rate >= bw) {
                self.take_bw(rate);
            }
        }
        self.advance(now, round_start, s.app_limited);
        self.reopened(now, full);
    }

    fn on_late_delivery(&mut self, now: Instant) {
        self.delivered += 1;
        self.delivered_time = now;
        self.round_trace.delivered += 1;
    }

    /// The window stays (see the module documentation).
    fn on_lost(&mut self, now: Instant, n: usize) {
        let full = self.in_flight >= self.window();
        self.in_flight = self.in_flight.saturating_sub(n);
        if n > 0 {
            self.lost_in_phase = true;
            self.round_trace.lost += n as u32;
        }
        self.reopened(now, full);
    }

    fn on_abandoned(&mut self, n: usize) {
        self.in_flight = self.in_flight.saturating_sub(n);
    }

    fn on_app_limited(&mut self, _now: Instant) {
        self.app_limited = (self.delivered + self.in_flight as u64).max(1);
    }

    fn poll_round(&mut self) -> Option<RoundTrace> {
        self.trace.as_mut()?.pop_front()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A path of 20 ms round trip carrying at most `rate` requests a second, driven
    /// from `start` to `end`: the sender sends whenever the window and pacing let it
    /// (checking every `wake`, as a driver's timer would), unless `offer` (requests a
    /// second) limits it, when it says it is app-limited. Returns when it ended.
    fn drive(
        c: &mut Bbr,
        start: Instant,
        end: Duration,
        rate: f64,
        wake: Duration,
        offer: Option<f64>,
    ) -> Instant {
        let rtt = Duration::from_millis(20);
        let gap = Duration::from_secs_f64(1.0 / rate);
        let mut pending: VecDeque<(Instant, SendState)> = VecDeque::new();
        let mut link_free = start;
        let mut offered = 0.0;
        let mut now = start;
        while now < start + end {
            while pending.front().is_some_and(|p| p.0 <= now) {
                let (at, s) = pending.pop_front().unwrap_or_else(|| unreachable!());
                c.on_delivered(at, &s, Some(at - s.sent));
            }
            let budget = offer.map(|o| (now - start).as_secs_f64() * o);
            while c.in_flight() < c.window() && c.next_send(now).is_none() {
                if budget.is_some_and(|b| offered >= b) {
                    c.on_app_limited(now);
                    break;
                }
                offered += 1.0;
                let s = c.on_sent(now);
                // Served at the path's rate, answered a round trip later.
                link_free = link_free.max(now) + gap;
                pending.push_back((link_free + rtt, s));
            }
            now += wake;
        }
        now
    }

    #[test]
    fn an_app_limited_stretch_does_not_lower_the_rate_it_measured() {
        let start = crate::test_epoch();
        let mut c = Bbr::new(start, false);
        let tick = Duration::from_micros(100);
        let t = drive(&mut c, start, Duration::from_secs(1), 5000.0, tick, None);
        let bw = c.max_bw().unwrap_or(0.0);
        assert!((4500.0..=5600.0).contains(&bw), "{bw}");
        // A second of offering 1,000 a second: 50 rounds, far more than the filter's 10.
        drive(
            &mut c,
            t,
            Duration::from_secs(1),
            5000.0,
            tick,
            Some(1000.0),
        );
        let after = c.max_bw().unwrap_or(0.0);
        assert!(after >= bw * 0.9, "{after} after {bw}");
    }

    #[test]
    fn a_coarse_timer_still_keeps_the_rate() {
        // Wake-ups every 4 ms while requests are due every 0.2 ms: several go per
        // wake-up, and the path's rate is found all the same.
        let start = crate::test_epoch();
        let mut c = Bbr::new(start, true);
        drive(
            &mut c,
            start,
            Duration::from_secs(1),
            5000.0,
            Duration::from_millis(4),
            None,
        );
        let bw = c.max_bw().unwrap_or(0.0);
        assert!(bw >= 4500.0, "{bw}");
        assert!(c.wake_lateness() >= Duration::from_millis(3));
        let rounds: Vec<RoundTrace> = std::iter::from_fn(|| c.poll_round()).collect();
        assert!(rounds.len() >= 20, "{}", rounds.len());
        assert!(rounds.iter().any(|r| r.mode == "probe_bw"));
    }
}
