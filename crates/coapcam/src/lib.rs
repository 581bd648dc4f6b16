//! coapcam: RGB-D cameras (Intel RealSense D400 and a synthetic D415) as CoAP resources,
//! and parcel measurement from their point clouds.
//!
//! The `coapcam` binary is a thin layer of commands over this library:
//! - [`repr`]: the wire formats, each encoder beside its decoder, and the one table of
//!   which stream is served in which content format;
//! - [`documents`]: the JSON documents of a camera's resources (application-config) as
//!   serde types, for the server and the client;
//! - [`server`]: the resource tree of a camera server (`/cams`, `/files`, `/coap-group`)
//!   and its assembly from a configuration;
//! - [`backends`]: where a server's cameras come from (a scene's synthetic cameras,
//!   recordings, librealsense), one file each, with their flags;
//! - [`client`]: the typed client of a camera server, measuring (with the cameras'
//!   preparation), the codes of the cameras and the annotated picture;
//! - [`station`]: what the server does by itself for a parcel lane: the results log;
//! - [`vision`]: pure image work: reading QR and Code 128 codes, pictures for people;
//! - [`stats`]: medians, percentiles and running moments of repeated measurements;
//! - [`timesync`]: the servers' clock offsets (NTP's four timestamps over CoAP) and the
//!   check that a measurement's frames belong together in time;
//! - [`bench`](mod@bench): the benchmarks, and [`process`]: the child processes and peer programs
//!   they and the integration tests run.
//!
//! The protocol lives in the `coap` and `coap-net` crates, the resource directory in
//! `coap-rd`, the cameras in `rgbd`, the point-cloud geometry in `geometry`, the link
//! emulator in `netem`.

#![forbid(unsafe_code)]

pub mod api;
pub mod backends;
pub mod bench;
pub mod client;
pub mod documents;
pub mod identity;
pub mod process;
pub mod report;
pub mod repr;
pub mod server;
pub mod station;
pub mod stats;
pub mod timesync;
pub mod vision;

/// An error and its causes, `: `-separated, each said once: many errors repeat their
/// cause's text in their own (`cannot read x: No such file (os error 2)`) and also
/// return it as their source, which `{:#}` would print twice. Any error: an
/// `anyhow::Error` is given as `e.as_ref()`.
pub fn error_text(error: &(dyn std::error::Error + 'static)) -> String {
    let mut out = String::new();
    let mut cause = Some(error);
    while let Some(e) = cause {
        let text = e.to_string();
        if !out.contains(&text) {
            if !out.is_empty() {
                out.push_str(": ");
            }
            out.push_str(&text);
        }
        cause = e.source();
    }
    out
}

/// A directory of a unit test's own under the system's temporary directory, removed on
/// drop.
#[cfg(test)]
pub(crate) struct ScratchDir(pub(crate) std::path::PathBuf);

#[cfg(test)]
impl ScratchDir {
    pub(crate) fn new(tag: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("coapcam-unit-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("scratch directory");
        Self(dir)
    }

    pub(crate) fn path(&self) -> &std::path::Path {
        &self.0
    }
}

#[cfg(test)]
impl Drop for ScratchDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

#[cfg(test)]
mod tests {
    use super::error_text;

    #[test]
    fn an_error_and_its_causes_are_said_once_each_whether_typed_or_anyhow() {
        let typed = crate::process::ProcError::FreePort(std::io::Error::other("no port"));
        assert_eq!(error_text(&typed), "finding a free UDP port: no port");
        let wrapped = anyhow::Error::new(typed).context("starting coap-server");
        assert_eq!(
            error_text(wrapped.as_ref()),
            "starting coap-server: finding a free UDP port: no port"
        );
        let repeated = anyhow::Error::new(std::io::Error::other("gone")).context("reading x: gone");
        assert_eq!(error_text(repeated.as_ref()), "reading x: gone");
    }
}
