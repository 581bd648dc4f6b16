//! Release builds place the functions a server and a client run together at the front of
//! the binary's code, in the order of `link-order.txt` (made by `scripts/link-order.sh`).
//! The kernel maps code in 64 KiB runs around each page touched, so a server whose code
//! is spread over the whole binary has most of it resident; placed together, a few runs
//! hold it. Only with the default linker of x86_64 Linux (rust-lld, which knows
//! `--symbol-ordering-file`); `COAPCAM_LINK_ORDER=0` turns it off.

use std::env;
use std::path::Path;

fn main() {
    println!("cargo:rerun-if-changed=link-order.txt");
    println!("cargo:rerun-if-env-changed=COAPCAM_LINK_ORDER");
    let var = |name: &str| env::var(name).unwrap_or_default();
    let flags = var("CARGO_ENCODED_RUSTFLAGS");
    let default_linker = env::var_os("RUSTC_LINKER").is_none()
        && !flags.contains("linker")
        && !flags.contains("link-self-contained")
        && !flags.contains("fuse-ld");
    let order = Path::new(&var("CARGO_MANIFEST_DIR")).join("link-order.txt");
    if var("PROFILE") == "release"
        && var("TARGET") == "x86_64-unknown-linux-gnu"
        && default_linker
        && var("COAPCAM_LINK_ORDER") != "0"
        && order.exists()
    {
        println!(
            "cargo:rustc-link-arg-bin=coapcam=-Wl,--symbol-ordering-file={}",
            order.display()
        );
        // Names the binary no longer has (the list is older than the code) are skipped.
        println!("cargo:rustc-link-arg-bin=coapcam=-Wl,--no-warn-symbol-ordering");
    }
}
