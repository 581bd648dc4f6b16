//! DTLS with pre-shared keys (`coaps://`) against Debian's libcoap (OpenSSL, and GnuTLS as
//! a client), both directions: libcoap's client against `coapcam serve --coaps
//! --psk-file`, where only an identity of the `configure` role changes anything; our
//! client against libcoap's
//! server. Bodies of several blocks, checked bit-exact.

use std::net::SocketAddr;

use crate::support::{
    self, COAPCAM, LIBCOAP_DTLS_CLIENT, LIBCOAP_GNUTLS_CLIENT, LIMIT, Peer, Proc, TempDir,
    assert_file_is, random_file,
};

const IDENTITIES: &str =
    "# coapcam test identities\nalice secret-of-alice configure\nbob secret-of-bob read\n";

/// `coapcam serve --no-cameras --static DIR --writable` with DTLS: its plain and its
/// DTLS address.
fn our_dtls_server(dir: &TempDir) -> (Proc, SocketAddr, SocketAddr) {
    let psk = dir.join("psk.txt");
    std::fs::write(&psk, IDENTITIES).expect("writing the identities");
    let files = dir.join("files");
    let mut p = Proc::spawn(
        COAPCAM,
        &[
            "serve",
            "--no-cameras",
            "--static",
            files.to_str().expect("UTF-8 path"),
            "--writable",
            "--bind",
            "127.0.0.1:0",
            "--coaps",
            "127.0.0.1:0",
            "--psk-file",
            psk.to_str().expect("UTF-8 path"),
            "--duration",
            "120",
        ],
    );
    let plain = p.stderr_line(LIMIT, |l| {
        l.strip_prefix("coapcam: serving on ")
            .and_then(|a| a.trim().parse().ok())
    });
    let secure = p.stderr_line(LIMIT, |l| {
        l.strip_prefix("coapcam: serving coaps on ")
            .and_then(|a| a.trim().parse().ok())
    });
    (p, plain, secure)
}

/// libcoap's DTLS client as `identity` with `key`.
fn libcoap(identity: &str, key: &str, args: &[&str]) -> support::Finished {
    let mut all = vec!["-u", identity, "-k", key];
    all.extend_from_slice(args);
    Proc::run(LIBCOAP_DTLS_CLIENT, &all, LIMIT)
}

#[test]
fn libcoap_over_dtls_reads_and_only_a_configure_identity_changes_files() {
    let test = "libcoap_over_dtls_reads_and_only_a_configure_identity_changes_files";
    if !support::available(test, &[Peer::Libcoap]) {
        return;
    }
    let dir = TempDir::new("dtls-ours");
    std::fs::create_dir(dir.join("files")).expect("mkdir");
    let body = random_file(&dir.join("files").join("big.bin"), 100_000, 5);
    let (_server, _plain, secure) = our_dtls_server(&dir);
    let uri = |name: &str| format!("coaps://{secure}/files/{name}");

    // A read identity fetches 100,000 bytes (98 blocks) bit-exact.
    let out = dir.join("got.bin");
    libcoap(
        "bob",
        "secret-of-bob",
        &["-o", out.to_str().expect("UTF-8"), &uri("big.bin")],
    )
    .expect_success("libcoap GET over DTLS");
    assert_file_is(&out, &body);
    // So does libcoap's GnuTLS client: both answer the server's cookie (RFC 6347 §4.2.1).
    let out = dir.join("got-gnutls.bin");
    Proc::run(
        LIBCOAP_GNUTLS_CLIENT,
        &[
            "-u",
            "bob",
            "-k",
            "secret-of-bob",
            "-o",
            out.to_str().expect("UTF-8"),
            &uri("big.bin"),
        ],
        LIMIT,
    )
    .expect_success("libcoap (GnuTLS) GET over DTLS");
    assert_file_is(&out, &body);

    // It may not write: 4.03, and no file.
    let upload = dir.join("upload.bin");
    let new = random_file(&upload, 3_000, 6);
    let up = upload.to_str().expect("UTF-8");
    let f = libcoap(
        "bob",
        "secret-of-bob",
        &["-m", "put", "-f", up, &uri("new.bin")],
    );
    let said = format!("{}{}", f.stdout_text(), f.stderr);
    assert!(said.contains("4.03"), "{said}");
    assert!(
        !dir.join("files").join("new.bin").exists(),
        "a read identity wrote"
    );
    // A wrong key gets no session, so nothing.
    let f = libcoap(
        "alice",
        "guessed",
        &["-B", "5", "-m", "put", "-f", up, &uri("new.bin")],
    );
    let said = format!("{}{}", f.stdout_text(), f.stderr);
    assert!(!said.contains("2.01"), "{said}");
    assert!(
        !dir.join("files").join("new.bin").exists(),
        "a wrong key wrote"
    );
    // The configure identity writes (three blocks).
    libcoap(
        "alice",
        "secret-of-alice",
        &["-m", "put", "-f", up, &uri("new.bin")],
    )
    .expect_success("libcoap PUT over DTLS");
    assert_file_is(&dir.join("files").join("new.bin"), &new);
}

#[test]
fn our_client_over_dtls_against_libcoap() {
    let test = "our_client_over_dtls_against_libcoap";
    if !support::available(test, &[Peer::Libcoap]) {
        return;
    }
    let dir = TempDir::new("dtls-theirs");
    let (_server, secure) = support::libcoap_dtls_server("shared-key");
    let uri = format!("coaps://{secure}/example_data");
    let psk = ["--psk-identity", "carol", "--psk-key", "shared-key"];
    let upload = dir.join("up.bin");
    let body = random_file(&upload, 5_000, 7);
    let mut put = vec![
        "put",
        uri.as_str(),
        "--file",
        upload.to_str().expect("UTF-8"),
    ];
    put.extend_from_slice(&psk);
    Proc::run(COAPCAM, &put, LIMIT).expect_success("coapcam put over DTLS");
    let out = dir.join("got.bin");
    let mut get = vec!["get", uri.as_str(), "-o", out.to_str().expect("UTF-8")];
    get.extend_from_slice(&psk);
    Proc::run(COAPCAM, &get, LIMIT).expect_success("coapcam get over DTLS");
    assert_file_is(&out, &body);

    // A wrong key: a clear failure, exit status 1.
    let f = Proc::run(
        COAPCAM,
        &["get", &uri, "--psk-identity", "carol", "--psk-key", "wrong"],
        LIMIT,
    );
    assert_eq!(f.status.code(), Some(1), "{}", f.stderr);
    assert!(f.stderr.contains("no DTLS session"), "{}", f.stderr);
}
