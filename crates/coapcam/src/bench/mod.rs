//! The benchmarks behind `coapcam bench`: what each runs and measures, returned as values
//! the command prints.
//!
//! - [`accuracy`]: seeded synthetic parcels measured end to end over CoAP, and their
//!   errors;
//! - [`codes`]: labels of every symbology at several module widths, read by our
//!   reader, rxing and both;
//! - [`load`]: many concurrent clients in four roles against a running server, every
//!   transfer checked;
//! - [`rd`]: a resource directory filled with registrations, its memory and its lookups'
//!   times;
//! - [`repr`]: the bytes and encode and decode times of every representation of a
//!   scene's frames and merged cloud;
//! - [`transfer`]: whole-body GETs of our client's transfer modes, libcoap and QUIC, each
//!   a child process, through emulated links.

pub mod accuracy;
pub mod codes;
pub mod load;
pub mod rd;
pub mod repr;
pub mod transfer;
