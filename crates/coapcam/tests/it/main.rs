//! Integration tests of the `coapcam` binary: one binary, one module per subcommand.

mod interop;
mod netem;
