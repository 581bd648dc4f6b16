//! Drives the sans-IO [`coap`] core over UDP sockets, and its stream connections over TCP,
//! for async (tokio) callers.
//!
//! Owns: sockets (IPv4, IPv6, multicast membership, the destination address of each
//! datagram), DTLS sessions (OpenSSL's, [`dtls`]), the thread per socket that owns a
//! `coap::Endpoint`, the [`Client`], the [`Server`] and its [`Router`], the `coap+tcp`
//! and `coap+ws` [`TcpServer`] and [`TcpClient`] (a task per connection owning a
//! `coap::connection::Connection`; WebSockets through tokio-tungstenite) and their TLS
//! twins `coaps+tcp` and `coaps+ws` (OpenSSL's TLS with pre-shared keys, through
//! tokio-openssl), `coap://`, `coaps://`, `coap+tcp://`, `coaps+tcp://`, `coap+ws://` and
//! `coaps+ws://` URIs.
//! Must not: implement protocol rules (those live in `coap`), or read the clock anywhere
//! but [`clock::now`].

#![forbid(unsafe_code)]

pub mod client;
mod driver;
pub mod dtls;
mod link;
mod observers;
pub mod router;
pub mod server;
pub mod socket;
pub mod tcp;
mod tls;
pub mod uri;

pub use client::{BodyPart, BodyStream, Client, Observation, fresh_seed};
pub use coap;
pub use driver::{EndpointHandle, Progress};
pub use dtls::Psk;
pub use router::{Around, Ctx, ObservationEnd, Policy, Resource, Router, handler};
pub use server::{Server, ServerConfig};
pub use tcp::{TcpClient, TcpServer};
pub use uri::Uri;

/// The one clock of the network layer.
pub mod clock {
    /// Now, for the endpoint threads (their timeouts are the socket's read timeouts, so
    /// this is the system's monotonic clock, not tokio's).
    pub fn now() -> std::time::Instant {
        std::time::Instant::now()
    }
}

/// Errors of the network layer.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The request failed in the protocol (timeout, reset, too large ...).
    #[error(transparent)]
    Request(#[from] coap::RequestError),
    /// A socket operation failed.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// The endpoint task is gone.
    #[error("the endpoint has shut down")]
    Closed,
    /// What was asked is not done over this client's transport (multicast over TCP or
    /// WebSockets, with TLS or not).
    #[error("{0} is not supported over coap+tcp or coap+ws (nor coaps+tcp or coaps+ws)")]
    Unsupported(&'static str),
}
