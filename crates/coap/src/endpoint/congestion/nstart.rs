//! RFC 7252's NSTART (§4.7): a fixed number of requests outstanding, sent as soon as
//! one may go. It admits each peer's requests; chosen for windowed transfers
//! ([`Congestion::Nstart`](crate::config::Congestion)), it keeps NSTART block requests
//! in flight, as the RFC's default congestion control allows.

use std::time::{Duration, Instant};

use super::controller::{Controller, SendState};

/// A fixed window of requests, unpaced.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Nstart {
    window: usize,
    in_flight: usize,
}

impl Nstart {
    /// A window of `nstart` requests (at least 1).
    pub(crate) fn new(nstart: usize) -> Self {
        Self {
            window: nstart.max(1),
            in_flight: 0,
        }
    }
}

impl Controller for Nstart {
    fn window(&self) -> usize {
        self.window
    }

    fn in_flight(&self) -> usize {
        self.in_flight
    }

    fn next_send(&self, _now: Instant) -> Option<Instant> {
        None
    }

    fn on_sent(&mut self, now: Instant) -> SendState {
        self.in_flight += 1;
        SendState::at(now)
    }

    fn on_delivered(&mut self, _now: Instant, _sent: &SendState, _rtt: Option<Duration>) {
        self.in_flight = self.in_flight.saturating_sub(1);
    }

    fn on_late_delivery(&mut self, _now: Instant) {}

    fn on_lost(&mut self, _now: Instant, n: usize) {
        self.in_flight = self.in_flight.saturating_sub(n);
    }

    fn on_abandoned(&mut self, n: usize) {
        self.in_flight = self.in_flight.saturating_sub(n);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn admits_nstart_requests_and_frees_a_place_per_answer_loss_or_abandonment() {
        let now = crate::test_epoch();
        let mut c = Nstart::new(2);
        assert_eq!((c.window(), c.in_flight()), (2, 0));
        let a = c.on_sent(now);
        c.on_sent(now);
        c.on_sent(now);
        assert_eq!(c.in_flight(), 3);
        assert_eq!(c.next_send(now), None, "never paced");
        c.on_delivered(now, &a, None);
        c.on_lost(now, 1);
        assert_eq!(c.in_flight(), 1);
        c.on_abandoned(5);
        assert_eq!(c.in_flight(), 0);
        assert_eq!(Nstart::new(0).window(), 1, "at least one");
    }
}
