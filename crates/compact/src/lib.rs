//! Compact representations of camera data, with decoders that take any bytes: a payload
//! that does not hold what it claims gives a typed error, never a panic (each decoder has
//! a fuzz target in `fuzz/`).
//!
//! - [`rvl`]: 16-bit depth images, lossless: RVL, and RVL in a zstd frame.
//! - [`cloud`]: point clouds as the depth images they were computed from (RVL) with the
//!   numbers that turn them into points.
//! - [`mm`]: point clouds quantized to whole millimetres.

pub mod cloud;
pub mod mm;
pub mod rvl;
mod wire;

pub use wire::WireError;
