//! The JSON documents a camera's resources serve and take, as serde types with typed
//! errors, for the server that keeps them and the client that edits them:
//! `application-config` ([`AppConfig`], thesis Listing A.3); `color-settings` and
//! `depth-settings` are `rgbd`'s [`rgbd::ColorSettings`] and [`rgbd::DepthSettings`],
//! `3d-transformation` is `geometry`'s [`geometry::Transformation`], `advanced-config`
//! `rgbd`'s [`rgbd::AdvancedConfig`].

mod app_config;

pub use app_config::{AppConfig, AppConfigError};
