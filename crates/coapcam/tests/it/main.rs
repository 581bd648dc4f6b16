//! Integration tests of the `coapcam` binary: one binary, one module per subcommand.

mod cams;
mod interop;
mod netem;
