//! What every congestion controller is told and what it answers ([`Controller`]).

use std::time::{Duration, Instant};

/// A congestion controller of one path: it admits requests (the window), spaces them
/// (pacing) and learns from what becomes of each: sent, delivered (with its round trip),
/// declared lost, or abandoned with its transfer.
///
/// The unit is one *request*: a block request and the block it brings back (every block
/// of a transfer has one size). The caller keeps the [`SendState`] that
/// [`Controller::on_sent`] returns with its request and hands it back on delivery.
pub(crate) trait Controller: Send {
    /// Requests that may be in flight now (at least 1). Checked against
    /// [`Controller::in_flight`] by the caller.
    fn window(&self) -> usize;

    /// Requests sent and not yet delivered, declared lost or abandoned.
    fn in_flight(&self) -> usize;

    /// When pacing lets the next request leave, if later than `now`.
    fn next_send(&self, now: Instant) -> Option<Instant>;

    /// A request left at `now`; what is returned comes back with its delivery.
    fn on_sent(&mut self, now: Instant) -> SendState;

    /// The answer to a request sent as `sent` arrived at `now`; `rtt` is its round trip
    /// when unambiguous (it was sent once).
    fn on_delivered(&mut self, now: Instant, sent: &SendState, rtt: Option<Duration>);

    /// An answer arrived whose request had been declared lost: delivered, though its
    /// send state is gone (no rate or round-trip sample).
    fn on_late_delivery(&mut self, now: Instant);

    /// `n` requests were declared lost at `now`: no longer in flight.
    fn on_lost(&mut self, now: Instant, n: usize);

    /// `n` requests in flight will never be answered (their transfer ended): no longer in
    /// flight, and no loss.
    fn on_abandoned(&mut self, n: usize);

    /// The sender had nothing to ask for at `now` although the window and pacing would
    /// have let a request go (the transfer's tail, or no message ID free): the delivery
    /// rate measured over the requests in flight says what the sender offered, not what
    /// the path carries (draft-cheng-iccrg-delivery-rate-estimation §3.4).
    fn on_app_limited(&mut self, _now: Instant) {}

    /// The next round the controller recorded, oldest first, when its trace is on
    /// ([`EndpointConfig::trace_congestion`](crate::EndpointConfig::trace_congestion)).
    fn poll_round(&mut self) -> Option<RoundTrace> {
        None
    }
}

/// One round trip of a controller as its trace records it (one per round: from the
/// delivery that starts a round to the next such delivery). Rates are in requests (one
/// block each) per second.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct RoundTrace {
    /// When the round ended (the delivery that started the next one).
    pub at: Instant,
    /// The round's number on its path, from 1.
    pub round: u64,
    /// The controller's state: `startup`, `drain`, or `probe_bw` with its pacing gain.
    pub mode: &'static str,
    /// The pacing gain during the round.
    pub pacing_gain: f64,
    /// Delivery-rate samples taken in the round.
    pub samples: u32,
    /// Of `samples`, those taken over requests sent while the sender was app-limited or
    /// behind its pacing schedule.
    pub app_limited_samples: u32,
    /// The round's largest delivery-rate sample, and whether it was app-limited.
    pub max_sample: Option<(f64, bool)>,
    /// The bandwidth estimate (the windowed maximum) at the round's end.
    pub bw: Option<f64>,
    /// The pacing rate at the round's end (`None`: unpaced).
    pub pacing_rate: Option<f64>,
    /// The window at the round's end.
    pub window: usize,
    /// Requests in flight at the round's end.
    pub in_flight: usize,
    /// The most requests in flight during the round.
    pub max_in_flight: usize,
    /// The smallest round trip seen.
    pub min_rtt: Option<Duration>,
    /// Requests sent during the round.
    pub sent: u32,
    /// Of `sent`, those that left later than the pacing schedule allowed (the sender
    /// woke late: a coarse timer, a busy CPU), and by how long in total.
    pub late_sends: u32,
    /// The total lateness of `late_sends`.
    pub lateness: Duration,
    /// Requests delivered during the round.
    pub delivered: u32,
    /// Requests declared lost during the round.
    pub lost: u32,
}

/// What a controller recorded of a request when it left: the state of a delivery-rate
/// sample (draft-cheng-iccrg-delivery-rate-estimation's per-packet state).
#[derive(Debug, Clone, Copy)]
pub(crate) struct SendState {
    /// When the request went out.
    pub(crate) sent: Instant,
    /// Requests delivered on the path before it went.
    pub(crate) delivered: u64,
    /// When the last of those was delivered.
    pub(crate) delivered_time: Instant,
    /// When the first request of the flight it went in was sent.
    pub(crate) first_sent_time: Instant,
    /// Sent while the sender was app-limited (or behind its pacing schedule): a rate
    /// sample over it says what was offered, not what the path carries.
    pub(crate) app_limited: bool,
}

impl SendState {
    /// The state of a request sent at `now` by a controller that samples no rate.
    pub(crate) fn at(now: Instant) -> Self {
        Self {
            sent: now,
            delivered: 0,
            delivered_time: now,
            first_sent_time: now,
            app_limited: false,
        }
    }

    /// When the request went out.
    pub(crate) fn sent(&self) -> Instant {
        self.sent
    }
}
