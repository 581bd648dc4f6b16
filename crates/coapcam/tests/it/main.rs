//! Integration tests of `coapcam`: the binary as a process (one module per subcommand, the
//! peers it interoperates with), and the library in process (`library`); `support` holds
//! what they share.

mod bag;
mod bench_transfer;
mod calibrated;
mod cams;
mod client;
mod config;
mod depth_pngs;
mod dtls;
mod exits;
mod files;
mod formats;
mod frames;
mod get;
mod group;
mod http;
mod identity;
mod interop;
mod lane;
mod library;
mod line;
mod live;
mod load;
mod logs;
mod markers;
mod mqtt;
mod netem;
mod observe;
mod offhost;
#[cfg(feature = "opcua")]
mod opcua;
mod postgres;
mod rd;
mod readme;
mod realsense;
mod results;
mod service;
mod signals;
mod support;
mod tcp;
mod tls;
mod usage;
mod webhook;
mod ws;
