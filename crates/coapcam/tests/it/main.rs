//! Integration tests of the `coapcam` binary: one binary, one module per subcommand.

mod bag;
mod cams;
mod client;
mod formats;
mod get;
mod group;
mod interop;
mod netem;
mod realsense;
mod signals;
