//! The legally relevant part of coapcam, the code from frames to dimensions, and the
//! SHA-256 that identifies it (docs/station.md, "Software identity"). Used by the
//! library and, through `#[path]`, by the crate's build script, so the checksum a build
//! carries and the one the tests compute come from this one function. Only `std` and
//! `sha2` here: the build script has nothing else.

use std::io;
use std::path::{Path, PathBuf};

use sha2::{Digest as _, Sha256};

/// The folders of the legally relevant sources, from the workspace's root: every `.rs`
/// file in them and their subfolders counts.
pub const LEGAL_DIRS: [&str; 3] = [
    "crates/rgbd/src/filter",
    "crates/geometry/src",
    "crates/coapcam/src/report",
];

/// Single legally relevant files outside those folders, from the workspace's root: depth
/// to points (the deprojection and the intrinsics it uses), and how the server makes a
/// measurement of its cameras' depth: the grab's chain from depth to a cloud in the common
/// frame with the floor check (`grab.rs`, `clouds.rs`), the parts of the table without
/// depth that turn a measurement into a refusal (`no_depth.rs`), the merge of the clouds
/// and the table measured from it (`merge.rs`), and the check of the frames' times that
/// refuses frames too far apart (`timesync.rs`).
pub const LEGAL_FILES: [&str; 7] = [
    "crates/rgbd/src/deproject.rs",
    "crates/rgbd/src/intrinsics.rs",
    "crates/coapcam/src/server/cams/grab.rs",
    "crates/coapcam/src/repr/clouds.rs",
    "crates/coapcam/src/repr/no_depth.rs",
    "crates/coapcam/src/server/cams/merge.rs",
    "crates/coapcam/src/timesync.rs",
];

/// What the hashed bytes start with: the encoding's name and version.
const DOMAIN: &[u8] = b"coapcam-software-v1\n";

/// The legally relevant source files under `root` (a workspace's root), as paths from
/// `root` with `/` between their parts, sorted by their UTF-8 bytes.
pub fn legal_sources(root: &Path) -> io::Result<Vec<String>> {
    let mut out = Vec::new();
    for dir in LEGAL_DIRS {
        collect(root, &root.join(dir), &mut out)?;
    }
    for file in LEGAL_FILES {
        if !root.join(file).is_file() {
            return Err(io::Error::new(
                io::ErrorKind::NotFound,
                format!("{file}: a legally relevant source is missing"),
            ));
        }
        out.push(file.to_owned());
    }
    out.sort();
    out.dedup();
    Ok(out)
}

fn collect(root: &Path, dir: &Path, out: &mut Vec<String>) -> io::Result<()> {
    for entry in std::fs::read_dir(dir)? {
        let path: PathBuf = entry?.path();
        if path.is_dir() {
            collect(root, &path, out)?;
        } else if path.extension().is_some_and(|e| e == "rs") {
            let rel = path.strip_prefix(root).map_err(io::Error::other)?;
            let parts: Vec<String> = rel
                .components()
                .map(|c| c.as_os_str().to_string_lossy().into_owned())
                .collect();
            out.push(parts.join("/"));
        }
    }
    Ok(())
}

/// SHA-256 (lower-case hex) of the legally relevant sources under `root`, and their
/// paths: over `coapcam-software-v1` and a newline, then for each file in
/// [`legal_sources`]' order its path, a newline, its length in bytes as a decimal and a
/// newline, and its bytes.
pub fn legal_checksum(root: &Path) -> io::Result<(String, Vec<String>)> {
    let files = legal_sources(root)?;
    let mut h = Sha256::new();
    h.update(DOMAIN);
    for file in &files {
        let bytes = std::fs::read(root.join(file))?;
        h.update(file.as_bytes());
        h.update(b"\n");
        h.update(bytes.len().to_string().as_bytes());
        h.update(b"\n");
        h.update(&bytes);
    }
    let hex = h.finalize().iter().map(|b| format!("{b:02x}")).collect();
    Ok((hex, files))
}
