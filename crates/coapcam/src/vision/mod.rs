//! Image work that needs no network: reading the codes on a parcel, a camera's pose from
//! markers, and the pictures for people (depth views, the top view of a cloud, the
//! measured box on a color image).

pub mod calibration;
pub mod codes;
pub mod picture;
