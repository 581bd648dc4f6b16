//! Integration tests of the CoAP core: one binary, one module per area.

mod blockwise;
mod observe;
mod reliability;
mod sim;
