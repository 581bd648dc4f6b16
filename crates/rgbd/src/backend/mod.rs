//! Camera backends.

pub(crate) mod label;
mod raycast;
pub mod realsense;
mod render;
pub mod synthetic;
