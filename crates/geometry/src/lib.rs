//! Point-cloud geometry for coapcam.
//!
//! Owns: rigid transforms (thesis Listing A.4), regions of interest, registration and
//! dimensioning. Must not: know about CoAP or cameras; everything here is synchronous and
//! works in metres.

#![forbid(unsafe_code)]

/// A point in metres.
pub type Point3 = nalgebra::Point3<f32>;
