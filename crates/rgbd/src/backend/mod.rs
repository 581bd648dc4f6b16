//! Camera backends.

pub(crate) mod label;
mod raycast;
mod render;
pub mod synthetic;
