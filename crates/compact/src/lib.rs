//! Compact representations of camera data, with decoders that take any bytes: a payload
//! that does not hold what it claims gives a typed error, never a panic (each decoder has
//! a fuzz target in `fuzz/`).
//!
//! - [`rvl`]: 16-bit depth images, lossless: RVL, and RVL in a zstd frame.

pub mod rvl;
