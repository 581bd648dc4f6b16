//! The benchmarks behind `coapcam bench`: what each runs and measures, returned as values
//! the command prints.
//!
//! - [`transfer`]: whole-body GETs of our client's transfer modes, libcoap and QUIC, each
//!   a child process, through emulated links.

pub mod transfer;
