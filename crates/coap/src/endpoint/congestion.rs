//! How many exchanges a peer may have outstanding: a controller per peer, asked before
//! each of its queued requests starts (quinn-proto's `congestion` module is the model).
//!
//! Today's one controller is RFC 7252's NSTART (§4.7): a fixed number, 1 by default, so a
//! block-wise transfer is stop-and-wait. The place for what windowed transfers need: a
//! per-peer round-trip estimate (SRTT and RTTVAR from unambiguous samples, so timers follow
//! the peer rather than ACK_TIMEOUT) and a delivery-rate-based controller that opens the
//! window beyond NSTART, which RFC 7252 §4.8.1 allows only together with congestion
//! control.

/// Says how many exchanges a peer may have outstanding.
pub(super) trait Controller: Send {
    /// Exchanges the peer may have outstanding now (at least 1).
    fn window(&self) -> usize;
}

/// RFC 7252's NSTART: a fixed window.
#[derive(Debug, Clone, Copy)]
pub(super) struct Nstart(usize);

impl Nstart {
    /// A window of `nstart` exchanges (at least 1).
    pub(super) fn new(nstart: usize) -> Self {
        Self(nstart.max(1))
    }
}

impl Controller for Nstart {
    fn window(&self) -> usize {
        self.0
    }
}
