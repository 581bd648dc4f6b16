//! Where the peer programs are: libcoap 4.3.1 (Debian libcoap3-bin, on PATH), libcoap
//! 4.3.5 built from source (Q-Block, RFC 9177; and with OpenSSL, for TLS), aiocoap (PyPI) and `quic-bench` (this
//! workspace), Mosquitto and PostgreSQL (Debian). Each lookup says why a program cannot be used when it cannot: the
//! benchmarks report that mode as unavailable, the tests skip or (in CI) fail with it.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

/// libcoap 4.3.1's client without DTLS (Debian libcoap3-bin).
pub const LIBCOAP_CLIENT: &str = "coap-client-notls";
/// libcoap 4.3.1's server without DTLS.
pub const LIBCOAP_SERVER: &str = "coap-server-notls";
/// libcoap 4.3.1's client with DTLS (OpenSSL).
pub const LIBCOAP_DTLS_CLIENT: &str = "coap-client-openssl";
/// libcoap 4.3.1's client with DTLS through GnuTLS (the same package).
pub const LIBCOAP_GNUTLS_CLIENT: &str = "coap-client-gnutls";
/// libcoap 4.3.1's server with DTLS (OpenSSL).
pub const LIBCOAP_DTLS_SERVER: &str = "coap-server-openssl";
/// aiocoap's command-line client.
pub const AIOCOAP_CLIENT: &str = "aiocoap-client";

/// The first file called `name` in a folder of PATH.
pub fn on_path(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|dir| dir.join(name))
        .find(|p| p.is_file())
}

/// The first of `names` that is not on PATH, as the reason it cannot be used.
pub fn missing_on_path(names: &[&str]) -> Option<String> {
    names.iter().find(|b| on_path(b).is_none()).map(|b| {
        format!("{b} is not on PATH (Debian package libcoap3-bin: apt-get install libcoap3-bin)")
    })
}

/// libcoap 4.3.1's client and server (without DTLS).
pub fn libcoap431() -> Result<(PathBuf, PathBuf), String> {
    if let Some(why) = missing_on_path(&[LIBCOAP_CLIENT, LIBCOAP_SERVER]) {
        return Err(why);
    }
    match (on_path(LIBCOAP_CLIENT), on_path(LIBCOAP_SERVER)) {
        (Some(client), Some(server)) => Ok((client, server)),
        _ => Err(format!(
            "{LIBCOAP_CLIENT} or {LIBCOAP_SERVER} is not on PATH"
        )),
    }
}

/// The folder of libcoap 4.3.5's `coap-client` and `coap-server`: `COAPCAM_LIBCOAP435`,
/// or `~/.cache/coapcam-peers/libcoap-4.3.5/build`.
pub fn libcoap435_dir() -> PathBuf {
    std::env::var_os("COAPCAM_LIBCOAP435").map_or_else(
        || {
            let home = std::env::var_os("HOME").unwrap_or_default();
            PathBuf::from(home).join(".cache/coapcam-peers/libcoap-4.3.5/build")
        },
        PathBuf::from,
    )
}

/// libcoap 4.3.5's client and server.
pub fn libcoap435() -> Result<(PathBuf, PathBuf), String> {
    built_libcoap(
        &libcoap435_dir(),
        "../shared/peers/build-libcoap.sh builds libcoap 4.3.5 there; COAPCAM_LIBCOAP435 names another folder",
    )
}

/// The folder of libcoap 4.3.5's `coap-client` and `coap-server` built with OpenSSL
/// (DTLS and TLS, so also `coaps+tcp` and `coaps+ws`): `COAPCAM_LIBCOAP435_OPENSSL`, or
/// `~/.cache/coapcam-peers/libcoap-4.3.5-openssl/build`.
pub fn libcoap435_openssl_dir() -> PathBuf {
    std::env::var_os("COAPCAM_LIBCOAP435_OPENSSL").map_or_else(
        || {
            let home = std::env::var_os("HOME").unwrap_or_default();
            PathBuf::from(home).join(".cache/coapcam-peers/libcoap-4.3.5-openssl/build")
        },
        PathBuf::from,
    )
}

/// libcoap 4.3.5's client and server with OpenSSL.
pub fn libcoap435_openssl() -> Result<(PathBuf, PathBuf), String> {
    built_libcoap(
        &libcoap435_openssl_dir(),
        "scripts/build-libcoap-openssl.sh builds libcoap 4.3.5 with OpenSSL there; COAPCAM_LIBCOAP435_OPENSSL names another folder",
    )
}

/// `coap-client` and `coap-server` in `dir`, or which is missing and `how` to build it.
fn built_libcoap(dir: &Path, how: &str) -> Result<(PathBuf, PathBuf), String> {
    let (client, server) = (dir.join("coap-client"), dir.join("coap-server"));
    let missing = [&client, &server]
        .into_iter()
        .find(|p| !p.is_file())
        .cloned();
    match missing {
        None => Ok((client, server)),
        Some(missing) => Err(format!("{} is missing ({how})", missing.display())),
    }
}

/// Whether aiocoap is installed: `aiocoap-client` on PATH and the library importable by
/// `python3` (the tests' server script uses it).
pub fn aiocoap() -> Result<(), String> {
    if on_path(AIOCOAP_CLIENT).is_none() {
        return Err(format!("{AIOCOAP_CLIENT} is not on PATH (PyPI aiocoap)"));
    }
    python_imports("aiocoap")
}

/// Whether aiocoap can speak CoAP over WebSockets: [`aiocoap`], and `python3` imports
/// websockets (PyPI), which aiocoap's `ws` transport needs.
pub fn aiocoap_ws() -> Result<(), String> {
    aiocoap()?;
    python_imports("websockets")
}

/// Whether asyncua (PyPI), the OPC UA client library of `tests/peers/opcua_client.py`,
/// is importable by `python3`.
pub fn asyncua() -> Result<(), String> {
    python_imports("asyncua")
}

/// Whether `python3` imports `module`, a PyPI package of the same name.
fn python_imports(module: &str) -> Result<(), String> {
    let import = Command::new("python3")
        .args(["-c", &format!("import {module}")])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status();
    match import {
        Ok(s) if s.success() => Ok(()),
        _ => Err(format!("python3 cannot import {module} (PyPI {module})")),
    }
}

/// `quic-bench`: `COAPCAM_QUIC_BENCH`, or the file next to `coapcam` (the coapcam
/// executable, where cargo builds it).
pub fn quic_bench(coapcam: &Path) -> Result<PathBuf, String> {
    let quic = std::env::var_os("COAPCAM_QUIC_BENCH").map_or_else(
        || {
            coapcam
                .parent()
                .map_or_else(|| PathBuf::from("quic-bench"), |d| d.join("quic-bench"))
        },
        PathBuf::from,
    );
    if quic.is_file() {
        Ok(quic)
    } else {
        Err(format!(
            "{} is missing (cargo build --release -p quic-bench builds it next to coapcam; \
             COAPCAM_QUIC_BENCH names another path)",
            quic.display()
        ))
    }
}

/// Mosquitto's subscriber (Debian mosquitto-clients).
pub const MOSQUITTO_SUB: &str = "mosquitto_sub";

/// Mosquitto's broker: on PATH, else where Debian puts it (/usr/sbin is not on a user's
/// PATH); `mosquitto_sub` must be on PATH too.
pub fn mosquitto() -> Result<PathBuf, String> {
    let broker = on_path("mosquitto").or_else(|| {
        let sbin = PathBuf::from("/usr/sbin/mosquitto");
        sbin.is_file().then_some(sbin)
    });
    let Some(broker) = broker else {
        return Err("mosquitto is not installed (Debian package mosquitto)".into());
    };
    match on_path(MOSQUITTO_SUB) {
        Some(_) => Ok(broker),
        None => Err(format!(
            "{MOSQUITTO_SUB} is not on PATH (Debian package mosquitto-clients)"
        )),
    }
}

/// The folder of PostgreSQL's server programs (Debian postgresql): `initdb`, `postgres`,
/// `pg_ctl`. The folder of PATH's `initdb` when `postgres` is beside it, else Debian's
/// `/usr/lib/postgresql/<version>/bin` of the newest version (not on PATH there).
pub fn postgres_bin() -> Result<PathBuf, String> {
    let complete = |dir: &Path| ["initdb", "postgres"].iter().all(|p| dir.join(p).is_file());
    if let Some(dir) = on_path("initdb").and_then(|p| p.parent().map(Path::to_path_buf))
        && complete(&dir)
    {
        return Ok(dir);
    }
    let mut versions: Vec<(u32, PathBuf)> = std::fs::read_dir("/usr/lib/postgresql")
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let version = e.file_name().to_str()?.parse().ok()?;
            Some((version, e.path().join("bin")))
        })
        .filter(|(_, bin)| complete(bin))
        .collect();
    versions.sort();
    versions.pop().map(|(_, bin)| bin).ok_or_else(|| {
        "initdb and postgres are neither on PATH nor in /usr/lib/postgresql/<version>/bin \
         (Debian package postgresql)"
            .into()
    })
}
