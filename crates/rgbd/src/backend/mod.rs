//! Camera backends.

pub(crate) mod label;
pub mod playback;
mod raycast;
mod render;
pub mod synthetic;
