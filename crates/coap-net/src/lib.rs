//! Drives the sans-IO [`coap`] core over tokio UDP sockets.
//!
//! Owns: sockets, timers, the task that owns each `coap::Endpoint`.
//! Must not: implement protocol rules; those live in `coap`.
//!
//! The network layer is its own issue ("The network layer"); this crate holds only what
//! the layers above need today.

#![forbid(unsafe_code)]

pub use coap;
