//! Integration tests of the CoAP core: one binary, one module per area.

mod amplification;
mod blockwise;
mod codec;
mod observe;
mod qblock;
mod reliability;
mod sim;
mod stream;
mod window;
