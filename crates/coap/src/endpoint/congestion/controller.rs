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
}

impl SendState {
    /// The state of a request sent at `now` by a controller that samples no rate.
    pub(crate) fn at(now: Instant) -> Self {
        Self {
            sent: now,
            delivered: 0,
            delivered_time: now,
            first_sent_time: now,
        }
    }

    /// When the request went out.
    pub(crate) fn sent(&self) -> Instant {
        self.sent
    }
}
