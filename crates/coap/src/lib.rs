//! The CoAP protocol, sans-IO.
//!
//! Owns: the wire format (RFC 7252 messages and options, RFC 7959 block options, RFC 7641
//! Observe, RFC 9175 Echo/Request-Tag, RFC 9177 Q-Block numbers, RFC 8323 stream framing
//! and signalling messages), the content-format registry, the endpoint state machine
//! (message IDs, tokens, retransmission, deduplication, block-wise transfer), both
//! sides of an RFC 8323 stream connection, RFC 6690 link-format and RFC 7390 group JSON.
//!
//! Must not: read a clock, sleep, draw from a thread RNG or touch a socket. Time enters as
//! `now` on every call, randomness comes from the endpoint's seeded generator, and bytes move
//! through `handle` / `poll_transmit`. `clippy.toml` in this crate enforces it.

#![forbid(unsafe_code)]

pub mod connection;
pub mod content_format;
pub mod group;
pub mod link_format;
pub mod msg;
mod peer_key;

mod block;
pub mod config;
mod dedup;
pub mod endpoint;

pub use block::{BlockSource, Source};
pub use config::{Congestion, EndpointConfig, Limits};
pub use content_format::ContentFormat;
pub use endpoint::{
    Endpoint, Event, IncomingId, IncomingRequest, ObservationId, PathStats, Request, RequestError,
    RequestId, Response, RoundTrace, ServerStats, Transfer, Transmit,
};
pub use msg::{BlockOpt, Code, Message, OptionNumber, Options, Token, Type};

/// A fixed instant for unit tests: the crate reads no clock, except this one place that
/// only tests compile.
#[cfg(test)]
#[expect(
    clippy::disallowed_methods,
    reason = "tests need one real Instant as an epoch"
)]
pub(crate) fn test_epoch() -> std::time::Instant {
    std::time::Instant::now()
}
