//! Integration tests of the rgbd crate.

mod hub;
