//! Which software this is: the crate's version and the SHA-256 of its legally relevant
//! part (the code from frames to dimensions, [`sources`]), computed by the build script.

pub mod sources;

/// The coapcam version of this build.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// SHA-256 (hex) of the legally relevant sources this build was made from
/// ([`sources::legal_checksum`] at build time).
pub const SOFTWARE_SHA256: &str = env!("COAPCAM_SOFTWARE_SHA256");

/// `VERSION (software SHA-256 …)`: what `coapcam --version` prints after the name.
pub const VERSION_LINE: &str = concat!(
    env!("CARGO_PKG_VERSION"),
    " (legally relevant software SHA-256 ",
    env!("COAPCAM_SOFTWARE_SHA256"),
    ")"
);
