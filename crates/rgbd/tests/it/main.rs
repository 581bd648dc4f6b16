//! Integration tests of the rgbd crate: one binary, one module per topic.

mod advanced;
mod bag;
mod cert;
mod filters;
mod hub;
mod lane;
mod librealsense;
mod modes;
mod parcels;
mod realsense;
mod round;
mod scene;
mod support;
mod synthetic;
mod timeline;
