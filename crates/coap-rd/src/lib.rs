//! A resource directory (RFC 9176) and the client side of one, over [`coap_net`].
//!
//! - [`directory`]: the directory itself, sans-IO: registrations, lookups, lifetimes and
//!   bounds, every call given the time;
//! - [`service`]: the directory over CoAP (`coapcam rd`): its resources on a
//!   `coap_net` server, simple registration's fetch, the registrations persisted one
//!   file each, the sweep of expired ones;
//! - [`freshness`]: the directory's own Echo values, which a request that changes a
//!   registration (or draws a large lookup) must carry: proof, per request, that the
//!   sender receives at its address;
//! - [`registrant`]: a server's registration kept alive (`serve --register`): registered,
//!   renewed before its lifetime ends, registered again when its links or groups
//!   change, removed at shutdown; and the lookups clients make (`discover --rd`,
//!   `measure --group --rd`).
//!
//! Group members (docs/fleet.md): each server registers the groups it joined as the
//! endpoint attribute `grp`, one per group (`grp=224.0.1.188:5683`); a client finds a
//! group's members with one endpoint lookup, `?grp=224.0.1.188:5683`.
//!
//! Uses `coap` (messages, link format) and `coap-net` (client, router), nothing of
//! coapcam: coapcam's `rd` command runs the service, its camera servers the registrant.

#![forbid(unsafe_code)]

pub mod directory;
pub mod freshness;
pub mod registrant;
pub mod service;

pub use directory::{Directory, Limits, LookupKind, Params, Query, RdError, Record};
