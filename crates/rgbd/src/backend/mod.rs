//! Camera backends.

pub(crate) mod label;
pub mod playback;
mod raycast;
pub mod realsense;
mod render;
pub mod synthetic;
