//! Computes the SHA-256 of the legally relevant sources (src/identity/sources.rs) into
//! `COAPCAM_SOFTWARE_SHA256`, and reruns when any of them changes.

#[path = "src/identity/sources.rs"]
#[allow(dead_code, unreachable_pub)]
mod sources;

use std::path::Path;

fn main() {
    let manifest = std::env::var("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR");
    let root = Path::new(&manifest).join("../..");
    let (sum, files) =
        sources::legal_checksum(&root).expect("reading the legally relevant sources");
    for dir in sources::LEGAL_DIRS {
        println!("cargo:rerun-if-changed={}", root.join(dir).display());
    }
    for file in &files {
        println!("cargo:rerun-if-changed={}", root.join(file).display());
    }
    println!("cargo:rerun-if-changed=src/identity/sources.rs");
    println!("cargo:rustc-env=COAPCAM_SOFTWARE_SHA256={sum}");
}
